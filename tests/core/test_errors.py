"""canrls.core.errors: one root, and the builtin each error is."""

from __future__ import annotations

import numpy as np
import pytest

from canrls.core import errors
from canrls.core.errors import (
    BusError,
    CanrlsError,
    CheckpointError,
    CommandError,
    ConfigError,
    DecodeError,
    EstimatorError,
    FixedPointError,
    LogFormatError,
)
from canrls.estimation.fixed.formats import QFormat
from canrls.estimation.rls import RLS


def test_every_error_derives_from_the_root_and_a_builtin() -> None:
    for name in errors.__all__:
        cls = getattr(errors, name)
        assert issubclass(cls, CanrlsError), name
        assert cls is CanrlsError or any(
            issubclass(cls, b) for b in (ValueError, ArithmeticError, OSError)), name
    for cls in (ConfigError, DecodeError, LogFormatError, EstimatorError, CommandError,
                CheckpointError):
        assert issubclass(cls, ValueError)
    assert issubclass(FixedPointError, ArithmeticError) and issubclass(BusError, OSError)


def test_estimator_misuse_is_a_value_error() -> None:
    with pytest.raises(ValueError, match="alpha"):
        RLS(2, alpha=-1.0)
    with pytest.raises(ArithmeticError, match="NaN"):
        QFormat(32, 16).quantize(np.array([np.nan]))
