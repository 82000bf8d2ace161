"""The ``[daemon]`` table of the configuration, validated once (``docs/daemon.md``)."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from canrls.core.checks import is_positive
from canrls.core.errors import ConfigError

if TYPE_CHECKING:
    from canrls.processor.config import AppConfig

__all__ = ["DaemonSettings", "DAEMON_KEYS", "FIXED_PATHS", "FRAME_PARAMETERS", "OBSOLETE_KEYS",
           "RX_BUFFER", "RX_INTERVAL", "resolve_path"]

log = logging.getLogger(__name__)

#: the most parameters the frames carry: RlsParamInfo's Index (0..255) and Count
#: (at most 255) are 8-bit fields of dbc/canrls.dbc
FRAME_PARAMETERS = 255
#: the bus reader's default sleep between takings [s] (:attr:`DaemonSettings.rx_s`)
RX_INTERVAL = 0.005
#: the receive buffer the daemon asks for on a SocketCAN socket [bytes]
#: (:attr:`DaemonSettings.rx_buffer`; docs/daemon.md, "The receive buffer")
RX_BUFFER = 1 << 20

DAEMON_KEYS: dict[str, str] = {
    "publish_interval": "seconds between parameter/status publications (0: after every block)",
    "info_interval": "seconds between RlsParamInfo, RlsCounters and RlsRejects",
    "block_interval": "seconds the estimator lets frames gather before processing them "
                      "(default: publish_interval; a command frame or a whole block of "
                      "max_block frames waiting is taken at once)",
    "commands": "accept RlsCommand frames (default false: every command is answered "
                "'disabled')",
    "max_parameters": "most parameters the running model may have; a command or reload "
                      "beyond is refused (at most 255, what the parameter frames carry)",
    "command_rate": "commands accepted per second on average (token bucket; freeze and "
                    "resume need no token); beyond, answered 'rate_limited'",
    "command_burst": "commands accepted at once (the token bucket's depth)",
    "checkpoint": "checkpoint file ('' or absent: none)",
    "checkpoint_interval": "seconds between checkpoints",
    "rx_interval": "seconds the bus reader sleeps after taking every frame waiting, so "
                   "that one wake-up serves several frames (default: 5 ms, at most a "
                   "quarter of block_interval; 0: wake for each frame)",
    "rx_bulk": "read a SocketCAN bus in blocks (recvmmsg on python-can's socket, no "
               "can.Message per frame; default true; false: through python-can's recv, "
               "for diagnosis)",
    "rx_buffer": "bytes of receive buffer asked for on a SocketCAN socket at start "
                 "(default 1 MiB; the kernel caps it at net.core.rmem_max without "
                 "CAP_NET_ADMIN; 0: the kernel's default)",
    "queue_size": "frames held between the bus and the estimator; beyond, dropped and counted",
    "max_block": "most frames processed in one block",
    "send_timeout": "seconds a transmission may wait (0: never block)",
    "fault_hold_s": "seconds transmission stays paused after the last error frame",
    "reopen_min_s": "first delay before reopening a vanished bus",
    "reopen_max_s": "longest delay between reopening attempts",
    "divergence_limit": "float-vs-fixed divergence above which the Diverged flag is set",
    "record": "log file of every frame received (python-can writer by suffix: .log, .asc, .blf)",
    "model_file": "TOML file whose [model] replaces the configuration's (re-read on SIGHUP)",
    "saved_model": "file the command save_model writes the running model to, as canrls fit "
                   "--save-model does (canrls tune --model reads it; '' or absent: none)",
    "switch_interval": "Python's thread switch interval while running, seconds (0: leave it)",
    "fixed": "the published fixed-point column: 'kernel' (default: the fixed-point kernel "
             "on the float front end) or 'target' (the target's whole integer path from the "
             "frames, bit for bit with export-c's C and canrls fit --fixed target; about "
             "25 us of CPU a frame more, docs/daemon.md)",
    "own_ids": "canrls' own frames (parameters, status, command, ack) moved by \"offset:N\" "
               "from the shipped DBC's IDs (default: none; an axis of [[axes]]: its own, "
               "by default its index x 0x40)",
}

#: the values of ``[daemon] fixed``: where the published fixed column comes from
FIXED_PATHS = ("kernel", "target")

#: keys of earlier versions that are accepted, ignored and warned about: why each is gone
OBSOLETE_KEYS: dict[str, str] = {
    "cache_dir": "canrls compiles nothing at run time any more, so it keeps no cache of "
                 "compiled kernels",
}


@dataclass(frozen=True)
class DaemonSettings:
    """The ``[daemon]`` table (see :data:`DAEMON_KEYS` and ``docs/daemon.md``)."""

    publish_interval: float = 0.1
    info_interval: float = 1.0
    #: ``None``: the publish interval (see :attr:`block_s`)
    block_interval: float | None = None
    #: ``None``: 5 ms, at most a quarter of the block interval (see :attr:`rx_s`)
    rx_interval: float | None = None
    commands: bool = False
    max_parameters: int = 32
    command_rate: float = 2.0
    command_burst: int = 10
    checkpoint: Path | None = None
    checkpoint_interval: float = 60.0
    rx_bulk: bool = True
    rx_buffer: int = RX_BUFFER
    queue_size: int = 1_000_000
    max_block: int = 65536
    send_timeout: float = 0.0
    fault_hold_s: float = 1.0
    reopen_min_s: float = 0.5
    reopen_max_s: float = 30.0
    divergence_limit: float = 0.1
    record: Path | None = None
    model_file: Path | None = None
    saved_model: Path | None = None
    switch_interval: float = 0.001
    fixed: str = "kernel"
    #: ``own_ids``: what canrls' own frames are moved by on the bus
    own_offset: int = 0
    #: take only the axis's feedback and command frames (the bus's filters): an axis of
    #: a machine's daemon, never a table key
    rx_filter: bool = False

    def __post_init__(self) -> None:
        src = "daemon"
        for k in ("publish_interval", "block_interval", "rx_interval", "send_timeout",
                  "switch_interval"):
            v = getattr(self, k)
            if k in ("block_interval", "rx_interval") and v is None:
                continue
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"{src}.{k} = {v!r}: must be >= 0 seconds")
        for k in ("info_interval", "checkpoint_interval", "fault_hold_s", "reopen_min_s",
                  "reopen_max_s", "divergence_limit"):
            v = getattr(self, k)
            if not is_positive(v):
                raise ConfigError(f"{src}.{k} = {v!r}: must be > 0")
        if self.reopen_max_s < self.reopen_min_s:
            raise ConfigError(f"{src}.reopen_max_s = {self.reopen_max_s!r}: must be >= "
                              f"reopen_min_s ({self.reopen_min_s!r})")
        if self.rx_buffer < 0:
            raise ConfigError(f"{src}.rx_buffer = {self.rx_buffer!r}: must be >= 0 bytes")
        for k in ("queue_size", "max_block", "command_burst"):
            if getattr(self, k) < 1:
                raise ConfigError(f"{src}.{k} = {getattr(self, k)!r}: must be >= 1")
        if not 1 <= self.max_parameters <= FRAME_PARAMETERS:
            raise ConfigError(f"{src}.max_parameters = {self.max_parameters!r}: must be in "
                              f"1..{FRAME_PARAMETERS} (RlsParamInfo's Index and Count are "
                              f"8-bit fields)")
        if not is_positive(self.command_rate):
            raise ConfigError(f"{src}.command_rate = {self.command_rate!r}: must be > 0 "
                              f"commands per second")

    @property
    def block_s(self) -> float:
        """Seconds the estimator lets frames gather: ``block_interval``, by default the
        publish interval (each block has a fixed cost of its own, so blocks more
        frequent than publications cost CPU without fresher parameter frames)."""
        return self.publish_interval if self.block_interval is None else self.block_interval

    @property
    def rx_s(self) -> float:
        """Seconds the bus reader sleeps once it has taken every frame waiting:
        ``rx_interval``, by default :data:`RX_INTERVAL` but at most a quarter of
        :attr:`block_s` (0 with blocks after every frame: the reader wakes for each).
        The frames wait for the block anyway, so the reader need not wake for each;
        the interface buffers them meanwhile."""
        if self.rx_interval is not None:
            return self.rx_interval
        return min(RX_INTERVAL, self.block_s / 4.0)

    @classmethod
    def from_table(cls, table: Mapping[str, Any], source: str = "<config>",
                   base_dir: Path | None = None) -> DaemonSettings:
        """Validate a ``[daemon]`` table; errors name the file, the key and the value."""
        kw: dict[str, Any] = {}
        for k, v in table.items():
            key = f"{source}: daemon.{k}"
            if k in OBSOLETE_KEYS:
                log.warning("%s is obsolete and ignored (%s): remove it", key, OBSOLETE_KEYS[k])
                continue
            if k not in DAEMON_KEYS:
                raise ConfigError(f"{key} = {v!r}: unknown key (valid: "
                                  f"{', '.join(DAEMON_KEYS)})")
            if k == "fixed":
                if v not in FIXED_PATHS:
                    raise ConfigError(f"{key} = {v!r}: must be one of "
                                      f"{', '.join(map(repr, FIXED_PATHS))}")
                kw[k] = v
            elif k == "own_ids":
                from canrls.processor.axes import own_offset

                kw["own_offset"] = own_offset(v, key)
            elif k in ("commands", "rx_bulk"):
                if not isinstance(v, bool):
                    raise ConfigError(f"{key} = {v!r}: must be true or false")
                kw[k] = v
            elif k in ("queue_size", "max_block", "command_burst", "max_parameters"):
                if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                    raise ConfigError(f"{key} = {v!r}: must be an integer >= 1")
                kw[k] = v
            elif k == "rx_buffer":
                if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                    raise ConfigError(f"{key} = {v!r}: must be an integer >= 0 (bytes)")
                kw[k] = v
            elif k in _PATH_KEYS:
                if not isinstance(v, str) or "\0" in v:
                    raise ConfigError(f"{key} = {v!r}: must be a file path"
                                      + (" (no NUL byte)" if isinstance(v, str) else ""))
                if v:
                    kw[k] = resolve_path(v, base_dir)
                    if k == "record":  # its format and place, before the daemon starts
                        from canrls.can.writers import check_record_path

                        check_record_path(kw[k], f"{key} = {v}")
            else:
                if isinstance(v, bool) or not isinstance(v, int | float):
                    unit = "commands per second" if k == "command_rate" else "seconds"
                    raise ConfigError(f"{key} = {v!r}: must be a number of {unit}")
                kw[k] = float(v)
        try:
            return cls(**kw)
        except ConfigError as e:
            raise ConfigError(f"{source}: {e}") from e

    @classmethod
    def from_config(cls, cfg: AppConfig) -> DaemonSettings:
        return cls.from_table(cfg.daemon, cfg.source, cfg.base_dir)


_PATH_KEYS = ("checkpoint", "record", "model_file", "saved_model")


def resolve_path(value: str, base_dir: Path | None) -> Path:
    """A path of the ``[daemon]`` table: ``~`` expanded, relative to the configuration's
    directory (``base_dir``; None: as given)."""
    p = Path(value).expanduser()
    return p if p.is_absolute() or base_dir is None else base_dir / p
