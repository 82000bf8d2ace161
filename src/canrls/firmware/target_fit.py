"""``canrls fit``'s fixed-point column from the target's integers.

``canrls fit``'s fixed column (and the daemon's, :mod:`canrls.firmware.target_live`) is
:class:`~canrls.firmware.spec.TargetEstimator` run over
the same logs' frames with the fit's own calibration (its exponents, column energies,
pending columns and period; :func:`canrls.firmware.target_model.build`): the frames decoded,
paired, filtered, selected and rescaled in integers, as the C of ``canrls export-c``
runs them. A model saved by that fit (``--save-model``) exports to C that reproduces
these fixed values and every parameter frame bit for bit from the same frames
(``canrls export-c --model M --vectors LOG``; ``tests/firmware/test_target_fit.py``).
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence

from canrls.can.protocol import Protocol
from canrls.estimation.estimates import divergence
from canrls.estimation.settings import EstimatorSettings
from canrls.firmware.spec import PUBLISH, TargetEstimator
from canrls.firmware.target_model import TargetModel, build
from canrls.firmware.vectors import log_frames
from canrls.processor import FitResult, TargetRun
from canrls.processor.period import control_period

__all__ = ["fit_model", "target_fixed"]


def fit_model(res: FitResult, protocol: Protocol, settings: EstimatorSettings) -> TargetModel:
    """The target's integers for the model and calibration of a fit (what ``canrls
    export-c`` builds from the model that fit saves)."""
    model = res.model
    cal = res.calibration
    energy = pending = None
    if cal is not None:
        model = model.with_scaling(cal.scaling)
        energy = {k: list(v) for k, v in cal.energy.items()}
        pending = {k: list(v) for k, v in cal.pending.items()}
    period = control_period(measured=res.period.value, dbc=protocol.period).value
    return build(model, protocol, settings, period, energy=energy, pending=pending,
                 source="canrls fit")


def target_fixed(res: FitResult, paths: Sequence[str | os.PathLike[str]],
                 protocol: Protocol, settings: EstimatorSettings) -> FitResult:
    """``res`` with every parameter's ``fixed`` from the target's integer path over the
    frames of ``paths``; each equation's ``divergence`` and ``saturations`` are then the
    target's, and ``fixed`` (a :class:`~canrls.processor.TargetRun`) says what it ran
    (samples, updates, rescales, the frames it rejected or dropped and why).

    :raises canrls.firmware.target_model.TargetError: the model cannot run on the target (a user
        term).
    """
    tm = fit_model(res, protocol, settings)
    est = TargetEstimator(tm)
    for t, fid, ext, data in log_frames(paths, tm.tick_s):
        if est.frame(fid, ext, data, t) & PUBLISH:
            est.publish()
    theta = iter(est.theta_si())
    fixed = {p.name: next(theta) for e in tm.equations for p in e.parameters}
    params = tuple(dataclasses.replace(p, fixed=fixed[p.name]) if p.name in fixed else p
                   for p in res.estimates.parameters)
    fits = []
    for fit in res.estimates.equations:
        es = next((x for x in est.eqs if x.spec.name == fit.equation), None)
        if es is None:  # pragma: no cover - every equation of the model is the target's
            fits.append(fit)
            continue
        mine = [p for p in params if p.equation == fit.equation]
        div = divergence([p.value for p in mine], [p.fixed for p in mine],
                         [p.sigma if math.isfinite(p.sigma) else 0.0 for p in mine])
        fits.append(dataclasses.replace(fit, divergence=div,
                                        saturations=es.rls.saturations.nonzero()))
    estimates = dataclasses.replace(res.estimates, parameters=params, equations=tuple(fits))
    info = TargetRun(samples=est.samples,
                     updates={es.spec.name: es.updates for es in est.eqs},
                     rescales={es.spec.name: es.rescales for es in est.eqs},
                     rejected={k: v for k, v in est.rejects.items() if v})
    return dataclasses.replace(res, estimates=estimates, fixed=info)
