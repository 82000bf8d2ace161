"""The canrls exception tree.

Every error canrls raises derives from :class:`CanrlsError`, and each leaf also
derives from the builtin that describes it best, so ``except ValueError`` keeps
working for callers who do not know canrls::

    CanrlsError
    ├── ConfigError (ValueError)        a configuration file, key or value is wrong
    │   ├── EffectError                 unknown effect name or bad effect parameter
    │   ├── ExpressionError             a user-defined term does not parse or uses
    │   │                               a name or function outside the whitelist
    │   └── SignalError                 a DBC mapping names a message or signal that
    │                                   is missing, or a unit that cannot convert
    ├── DecodeError (ValueError)        a CAN frame is rejected (``reason`` says why)
    │   └── protocol.EncodeError        a value cannot be encoded into its DBC signal
    ├── LogFormatError (ValueError)     a log file cannot be read (names file and line)
    ├── EstimatorError (ValueError)     an estimator is configured or used inconsistently
    │   └── FixedPointError             a fixed-point configuration cannot represent
    │       (also ArithmeticError)      the problem (names the quantity and Q format)
    ├── CommandError (ValueError)       a command frame is unknown or malformed
    │   └── frames.CommandFrameError    carries the CommandResult code for the ack
    ├── CheckpointError (ValueError)    a checkpoint is corrupted or does not match
    │   ├── live.checkpoint.CheckpointPathError   its name or directory cannot be
    │   │                               used (a link, FIFO, device, directory, no writes)
    │   └── live.checkpoint.CheckpointInUseError  another daemon holds its lock
    ├── BusError (OSError)              the CAN interface failed or vanished
    └── StallError (TimeoutError)       a Dask scheduler or its workers stopped
                                        answering: no result within the stall limit

Messages name what failed: the file, key, message, signal, limit and value.
Internal errors are turned into these with ``raise ... from e``.
"""

from __future__ import annotations

__all__ = [
    "CanrlsError",
    "ConfigError",
    "EffectError",
    "ExpressionError",
    "SignalError",
    "DecodeError",
    "LogFormatError",
    "EstimatorError",
    "FixedPointError",
    "CommandError",
    "CheckpointError",
    "BusError",
    "StallError",
]


class CanrlsError(Exception):
    """Root of every error raised by canrls."""


class ConfigError(CanrlsError, ValueError):
    """A configuration file, key or value is wrong."""


class EffectError(ConfigError):
    """An effect name is unknown or one of its parameters is invalid."""


class ExpressionError(ConfigError):
    """A user-defined term's expression does not parse or is not allowed."""


class SignalError(ConfigError):
    """A signal mapping cannot be satisfied by the DBC (missing message/signal, bad unit)."""


class DecodeError(CanrlsError, ValueError):
    """A CAN frame was rejected by strict decoding.

    ``reason`` is a short machine-readable key (``"length"``, ``"range"``,
    ``"crc"``, ``"counter"``, ``"nan"``, ...) used to count rejections.
    """

    def __init__(self, message: str, reason: str = "invalid") -> None:
        super().__init__(message)
        self.reason = reason


class LogFormatError(CanrlsError, ValueError):
    """A log file cannot be read."""


class EstimatorError(CanrlsError, ValueError):
    """An estimator was configured or used inconsistently."""


class FixedPointError(EstimatorError, ArithmeticError):
    """A fixed-point configuration cannot represent the problem."""


class CommandError(CanrlsError, ValueError):
    """A command frame is unknown or malformed."""


class CheckpointError(CanrlsError, ValueError):
    """A checkpoint file is corrupted or does not match the running model."""


class BusError(CanrlsError, OSError):
    """The CAN interface failed, went bus-off or vanished."""


class StallError(CanrlsError, TimeoutError):
    """A Dask scheduler (or its workers) stopped answering: nothing finished in time."""
