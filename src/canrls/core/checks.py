"""The one check of each kind of value a user hands canrls: a finite number, a range, a
receive time, an epoch date, a control period, a forgetting factor, a number for JSON.
Every layer asks here, so a value is refused by the same rule and in the same words
wherever it enters."""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from canrls.core.errors import ConfigError

if TYPE_CHECKING:  # numpy loads with the first array: the command line's --help needs none
    import numpy as np
    import numpy.typing as npt

__all__ = ["EPOCH_WINDOW", "LAMBDA_MIN", "MAX_TIMESTAMP", "check_lambda", "describe_time",
           "finite_or_none", "in_range", "is_epoch", "is_positive", "is_real", "is_time",
           "json_safe", "not_times", "positive_period", "real_value"]


def real_value(value: object) -> float | None:
    """``value`` as a float when it is a finite real number: an int or a float (numpy's
    too), not a bool, not NaN nor infinite; else None. The one definition of "a number"
    of every check that asks."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return None
    try:
        v = float(value)
    except OverflowError:  # an integer beyond a double (a JSON 10**400)
        return None
    return v if math.isfinite(v) else None


def is_real(value: object) -> bool:
    """``value`` is a finite real number (:func:`real_value`)."""
    return real_value(value) is not None


def is_positive(value: object) -> bool:
    """``value`` is a finite real number above zero (:func:`real_value`)."""
    v = real_value(value)
    return v is not None and v > 0


def finite_or_none(x: float | None) -> float | None:
    """``x`` as a float for JSON, None where it is None or not finite: JSON has no NaN nor
    infinity, and canrls writes ``null`` for them."""
    return None if x is None or not math.isfinite(x) else float(x)


def json_safe(x: Any) -> Any:
    """``x`` for JSON: floats that are not finite as None (:func:`finite_or_none`), tuples
    as lists and mapping keys as strings, all the way down."""
    if isinstance(x, float):
        return finite_or_none(x)
    if isinstance(x, Mapping):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [json_safe(v) for v in x]
    return x


def in_range(value: object, lo: float, hi: float, *, lo_open: bool = False,
             hi_open: bool = False) -> bool:
    """``value`` is a finite real number (:func:`is_real`) from ``lo`` to ``hi``, each end
    included unless said open: the one range check of a number a user gives (``hi`` may
    be ``math.inf``, open: any finite number above ``lo``)."""
    v = real_value(value)
    if v is None:
        return False
    return (lo < v if lo_open else lo <= v) and (v < hi if hi_open else v <= hi)


#: Times in this open window [s] are epoch seconds (1973 to 5138: a date); others are a
#: log's own clock (a timestamp from zero)
EPOCH_WINDOW = (1e8, 1e11)


def is_epoch(t: object) -> bool:
    """``t`` is an epoch time, a date (within :data:`EPOCH_WINDOW`), not a log's own clock."""
    return in_range(t, *EPOCH_WINDOW, lo_open=True, hi_open=True)


#: Largest receive time [s] a frame may carry (about the year 2286): beyond it (or not
#: finite) a timestamp is no time of a frame.
MAX_TIMESTAMP = 1e10


def is_time(t: float) -> bool:
    """``t`` is a receive time: finite and at most :data:`MAX_TIMESTAMP` from zero."""
    return bool(abs(t) <= MAX_TIMESTAMP)  # False for NaN


def not_times(t: npt.NDArray[np.float64]) -> npt.NDArray[np.bool_]:
    """Mask of the entries of ``t`` that are not receive times (:func:`is_time`)."""
    import numpy as np

    with np.errstate(invalid="ignore"):
        return ~(np.abs(t) <= MAX_TIMESTAMP)


def describe_time(t: float) -> str:
    """Why ``t`` is not a receive time, for an error or a log line."""
    return f"timestamp {t!r} is not a time (finite, at most {MAX_TIMESTAMP:g} s)"


def positive_period(value: object, where: str) -> float:
    """``value`` as a control period [s]; a :class:`ConfigError` naming ``where`` (the
    flag, key or file that stated it) unless it is a finite positive number, at most
    :data:`MAX_TIMESTAMP` (no stream of receive times has a longer one). The one check of
    a period's value: a stated period (:meth:`Protocol.load
    <canrls.can.protocol.Protocol.load>`) and the processor's go through it."""
    v = real_value(value)
    if v is None or not in_range(v, 0.0, MAX_TIMESTAMP, lo_open=True):
        raise ConfigError(f"{where}: the control period must be a positive number of "
                          f"seconds, at most {MAX_TIMESTAMP:g}, got {value!r}")
    return v


#: The forgetting factor of canrls's estimators lies in (LAMBDA_MIN, 1]: the fixed-point
#: estimator stores 1/lambda as a Q1 word, and the float one runs beside it on the same
#: rows (docs/fixed_point.md), so the configuration, the command line, the monitor's
#: command, the command frame and both estimators take this one range.
LAMBDA_MIN = 0.5


def check_lambda(value: object, where: str, error: type[Exception] = ConfigError) -> float:
    """``value`` as the forgetting factor, or ``error`` naming ``where`` (the key, flag,
    command or class) unless it is a real number in (:data:`LAMBDA_MIN`, 1]."""
    v = real_value(value)
    if v is None or not LAMBDA_MIN < v <= 1.0:
        raise error(f"{where} = {value!r}: must be in ({LAMBDA_MIN:g}, 1]")
    return v
