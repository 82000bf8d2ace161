"""The daemon (``canrls run``): the estimator on a live bus, and the monitor that reads it.

Small classes, each one job: the wiring (``daemon``), the bus link and frame queue
(``bus_link``; SocketCAN's bulk receive in ``socketcan``), the publisher of parameter and
status frames, the command handler, checkpoints, the daemon's settings, live tuning,
systemd notification (``sdnotify``), the ``[history]`` hook, the recorder, and the live
monitor (``monitor_listener``). Frames go through the same processor as the offline replay.
"""
