"""``canrls fit``'s fixed-point column from the target's integers.

``canrls fit``'s fixed column (and the daemon's, :mod:`canrls.firmware.target_live`) is the
target's C (:class:`~canrls.firmware.native.TargetFeed`) run over the same logs' frames
with the fit's own calibration (its exponents, column energies,
pending columns and period; :func:`canrls.firmware.target_model.build`): the frames decoded,
paired, filtered, selected and rescaled in integers, as the C of ``canrls export-c``
runs them. A model saved by that fit (``--save-model``) exports to C that reproduces
these fixed values and every parameter frame bit for bit from the same frames
(``canrls export-c --model M --vectors LOG``; ``tests/firmware/test_target_fit.py``).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence

from canrls.can.protocol import Protocol
from canrls.estimation.settings import EstimatorSettings
from canrls.firmware.native import TargetFeed
from canrls.firmware.target_model import TargetModel, build
from canrls.firmware.vectors import log_blocks
from canrls.processor import FitResult
from canrls.processor.period import control_period

__all__ = ["fit_model", "target_fixed"]


def fit_model(res: FitResult, protocol: Protocol, settings: EstimatorSettings, *,
              frames: bool = True) -> TargetModel:
    """The target's integers for the model and calibration of a fit (what ``canrls
    export-c`` builds from the model that fit saves; ``frames``: with canrls' estimator
    frames, as the daemon sends them, or without, ``export-c --frames none``)."""
    model = res.model
    cal = res.calibration
    energy = pending = None
    if cal is not None:
        model = model.with_scaling(cal.scaling)
        energy = {k: list(v) for k, v in cal.energy.items()}
        pending = {k: list(v) for k, v in cal.pending.items()}
    period = control_period(measured=res.period.value, dbc=protocol.period).value
    return build(model, protocol, settings, period, energy=energy, pending=pending,
                 frames=frames, source="canrls fit")


def target_fixed(res: FitResult, paths: Sequence[str | os.PathLike[str]],
                 protocol: Protocol, settings: EstimatorSettings, *,
                 skip_bad_lines: bool = False) -> FitResult:
    """``res`` with every parameter's ``fixed`` from the target's integer path (the C of
    ``canrls export-c``, :class:`~canrls.firmware.native.TargetFeed`) over the frames of
    ``paths``; each equation's ``divergence`` and ``saturations`` are then the target's,
    and ``fixed`` (a :class:`~canrls.processor.TargetRun`) says what it ran (samples,
    updates, rescales, the frames it rejected or dropped and why).

    :raises canrls.firmware.target_model.TargetError: the model cannot run on the target (a user
        term).
    """
    # without canrls' frames: a fit keeps the estimate, never the frames, and a
    # publication only reads the estimate (the same integers as with them), so the fit
    # need not read canrls' DBC for their layout (about 0.1 s)
    tm = fit_model(res, protocol, settings, frames=False)
    feed = TargetFeed(tm)
    for block in log_blocks(paths, skip_bad_lines=skip_bad_lines):
        feed.feed(block)
    fixed = {name: v for name, (v, _) in feed.fixed().items()}
    estimates = res.estimates.with_fixed(fixed, feed.saturations())
    return dataclasses.replace(res, estimates=estimates, fixed=feed.run_info())
