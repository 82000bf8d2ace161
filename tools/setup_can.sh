#!/bin/sh
# Bring up a SocketCAN interface for canrls (docs/daemon.md, "SocketCAN").
#
#   sudo tools/setup_can.sh vcan0              # virtual CAN (kernel module vcan), no hardware
#   sudo tools/setup_can.sh can0 1000000       # a real controller at 1 Mbit/s
#   sudo tools/setup_can.sh can0 500000 100    # ... restarting 100 ms after a bus-off
#   sudo tools/setup_can.sh down can0          # take it down again
#
# A real interface gets its bitrate, automatic restart after bus-off (restart-ms, so
# the daemon's transmission pause ends by itself), berr-reporting (error frames reach
# canrls and set its BusFault flag) and a transmit queue of 1000 frames (txqueuelen;
# when it is full canrls drops a frame and counts it in TxDropped rather than block).
set -eu

usage() {
    echo "usage: $0 IFACE [BITRATE [RESTART_MS]] | $0 down IFACE" >&2
    exit 2
}

[ $# -ge 1 ] || usage
if [ "$1" = "down" ]; then
    [ $# -eq 2 ] || usage
    ip link set "$2" down
    case "$2" in vcan*) ip link delete "$2" 2>/dev/null || true ;; esac
    exit 0
fi

IFACE=$1
BITRATE=${2:-1000000}
RESTART_MS=${3:-100}

case "$IFACE" in
vcan*)
    modprobe vcan 2>/dev/null || true
    ip link show "$IFACE" >/dev/null 2>&1 || ip link add dev "$IFACE" type vcan
    ip link set "$IFACE" up
    ;;
*)
    ip link set "$IFACE" down 2>/dev/null || true
    ip link set "$IFACE" type can bitrate "$BITRATE" restart-ms "$RESTART_MS" berr-reporting on
    ip link set "$IFACE" txqueuelen 1000
    ip link set "$IFACE" up
    ;;
esac
ip -details link show "$IFACE"
