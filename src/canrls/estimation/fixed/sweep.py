r"""Fixed-point parameter error against word length: :func:`sweep` runs
:class:`~canrls.estimation.fixed.estimator.FixedRLS` for several configurations against a
float reference (``canrls fixed-sweep``)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.core.checks import finite_or_none
from canrls.core.errors import EstimatorError, FixedPointError
from canrls.estimation.fixed.estimator import FixedRLS
from canrls.estimation.fixed.formats import FixedConfig, SaturationCounts

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

__all__ = ["SweepRow", "SweepResult", "sweep"]


# -------------------------------------------------------------------- sweep
@dataclass(frozen=True)
class SweepRow:
    """One configuration of a :func:`sweep`.

    Attributes
    ----------
    label : str
        ``W{word}/A{acc}/I{input}`` or the name given with the config.
    config : FixedConfig or None
        ``None`` when the word lengths cannot represent the problem (see ``error``).
    max_rel_error : float
        Largest relative parameter error against ``theta_ref`` (``inf`` if not run).
    rel_errors : tuple of float
        Relative error per parameter.
    theta : tuple of float
        Final fixed-point estimate (float, normalised units).
    saturations : SaturationCounts
        Saturations over the run (inputs included).
    ok : bool
        ``max_rel_error <= tol``.
    error : str or None
        Why the configuration could not be run.
    """

    label: str
    config: FixedConfig | None
    max_rel_error: float
    rel_errors: tuple[float, ...]
    theta: tuple[float, ...]
    saturations: SaturationCounts
    ok: bool
    error: str | None = None

    @property
    def cost(self) -> tuple[int, int, int]:
        """Sort key of "smallest": (state word, accumulator, input word)."""
        c = self.config
        return (c.word_bits, c.acc_bits, c.input_bits) if c is not None else (99, 99, 99)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (``inf``/``nan`` as ``None``)."""


        return {
            "label": self.label,
            "word_bits": self.config.word_bits if self.config else None,
            "acc_bits": self.config.acc_bits if self.config else None,
            "input_bits": self.config.input_bits if self.config else None,
            "max_rel_error": finite_or_none(self.max_rel_error),
            "rel_errors": [finite_or_none(x) for x in self.rel_errors],
            "theta": [finite_or_none(x) for x in self.theta],
            "saturations": dict(self.saturations),
            "ok": self.ok,
            "error": self.error,
            "config": self.config.to_dict() if self.config else None,
        }


@dataclass(frozen=True)
class SweepResult:
    """The outcome of :func:`sweep`: one row per configuration and a recommendation.

    ``str(result)`` is a text table; :meth:`to_dict` is JSON-able.

    Attributes
    ----------
    rows : tuple of SweepRow
        In the order run.
    tol : float
        Relative tolerance on every parameter.
    floor : float
        Parameters smaller than this are measured against it instead.
    theta_ref : tuple of float
        The float reference.
    sigma_ref : tuple of float
        Its standard deviations (empty when not given): a parameter is measured against
        ``max(|theta_ref|, 3 sigma_ref, floor)``.
    recommended : SweepRow or None
        The smallest configuration (by :attr:`SweepRow.cost`) within ``tol``.
    """

    rows: tuple[SweepRow, ...]
    tol: float
    floor: float
    theta_ref: tuple[float, ...]
    recommended: SweepRow | None
    sigma_ref: tuple[float, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict."""
        return {
            "tol": self.tol,
            "floor": self.floor,
            "theta_ref": list(self.theta_ref),
            "sigma_ref": list(self.sigma_ref),
            "recommended": self.recommended.label if self.recommended else None,
            "rows": [r.to_dict() for r in self.rows],
        }

    def __str__(self) -> str:
        head = (
            f"{'config':<16} {'word':>4} {'acc':>4} {'input':>5} {'max rel err':>12}  "
            f"{'ok':<3} saturations"
        )
        lines = [head, "-" * len(head)]
        for r in self.rows:
            c = r.config
            if c is None:
                blank = f"{'':>4} {'':>4} {'':>5}"
                lines.append(f"{r.label:<16} {blank} {'n/a':>12}  {'no':<3} {r.error}")
                continue
            sat = ", ".join(f"{k}={v}" for k, v in r.saturations.nonzero().items()) or "-"
            lines.append(
                f"{r.label:<16} {c.word_bits:>4} {c.acc_bits:>4} {c.input_bits:>5} "
                f"{r.max_rel_error:>12.3e}  {'yes' if r.ok else 'no':<3} {sat}"
            )
        if self.recommended is not None:
            lines.append(
                f"recommended: {self.recommended.label} (max relative error "
                f"{self.recommended.max_rel_error:.3e} <= {self.tol:.3g})"
            )
        else:
            lines.append(f"recommended: none meets the tolerance {self.tol:.3g}")
        return "\n".join(lines)


def sweep(
    Phi: npt.ArrayLike,
    Y: npt.ArrayLike,
    theta_ref: npt.ArrayLike,
    configs: Sequence[FixedConfig] | Mapping[str, FixedConfig] | None = None,
    *,
    lam: float = 1.0,
    alpha: float | npt.ArrayLike = 1e-2,
    trace_max: float | None = None,
    word_bits: Sequence[int] = (16, 24, 32),
    acc_bits: Sequence[int] = (32, 48, 64),
    input_bits: Sequence[int] = (16, 32),
    phi_max: float | Sequence[float] = 1.0,
    y_max: float = 1.0,
    theta_max: float | None = None,
    tol: float = 1e-3,
    floor: float | None = None,
    update: str = "symmetric",
    sigma: npt.ArrayLike | None = None,
) -> SweepResult:
    r"""Run the fixed-point RLS for several word lengths and compare with a float reference.

    Parameters
    ----------
    Phi : array_like, shape (N, n)
        Normalised regressors (float).
    Y : array_like, shape (N,)
        Normalised targets (float).
    theta_ref : array_like, shape (n,)
        Float reference estimate on the same data (e.g. ``canrls.estimation.rls.RLS`` with the
        same ``lam``, ``alpha``, ``trace_max``).
    configs : sequence or mapping of FixedConfig, optional
        Explicit configurations (a mapping gives them labels). Default: every
        combination of ``word_bits`` x ``acc_bits`` x ``input_bits`` through
        :meth:`FixedConfig.auto`.
    lam, alpha, trace_max : float
        Estimator settings (as for :class:`FixedRLS`).
    word_bits, acc_bits, input_bits : sequences of int
        The grid of word lengths (when ``configs`` is not given).
    phi_max, y_max, theta_max : float
        Ranges for :meth:`FixedConfig.auto`.
    tol : float, default 1e-3
        Tolerance on every parameter's relative error (0.1 %).
    floor : float or None
        A parameter smaller than this is measured against ``floor`` instead of its
        own size (so a zero parameter does not fail everything); ``None``: 1 % of
        the largest :math:`|\theta_{ref}|` without ``sigma``, none with it.
    update : {"symmetric", "literal", "naive"}
    sigma : array_like, shape (n,), optional
        Standard deviations of ``theta_ref``: each parameter is then measured against
        ``max(|theta_ref_j|, 3 sigma_j)``, as ``canrls fit`` measures the fixed point
        (:func:`canrls.estimation.pipeline.divergence`); a NaN counts as 0.

    Returns
    -------
    SweepResult
        Per configuration: relative errors and saturations; the recommended (smallest
        by state word, then accumulator, then input word) configuration within ``tol``.
    """
    Phi_a = np.asarray(Phi, dtype=np.float64)
    Y_a = np.asarray(Y, dtype=np.float64)
    ref = np.asarray(theta_ref, dtype=np.float64)
    if Phi_a.ndim != 2:
        raise EstimatorError(f"sweep Phi must have shape (N, n), got {Phi_a.shape}")
    N, n = Phi_a.shape
    if Y_a.shape != (N,) or ref.shape != (n,):
        raise EstimatorError(
            f"sweep Y must have shape ({N},) and theta_ref ({n},), got {Y_a.shape}, {ref.shape}"
        )
    sd = np.zeros(n) if sigma is None else np.asarray(sigma, dtype=np.float64)
    if sd.shape != (n,):
        raise EstimatorError(f"sweep sigma must have shape ({n},), got {sd.shape}")
    if floor is not None:
        fl = float(floor)
    else:
        fl = 0.01 * float(np.max(np.abs(ref))) if sigma is None else 0.0
    if not fl > 0:
        fl = np.finfo(np.float64).tiny
    # scale_j = max(|theta_ref_j|, 3 sigma_j, floor)
    scale = np.maximum(np.maximum(np.abs(ref), 3.0 * np.nan_to_num(sd, nan=0.0)), fl)

    todo: list[tuple[str, FixedConfig | None, str | None]] = []
    if configs is None:
        for W in word_bits:
            for A in acc_bits:
                for In in input_bits:
                    label = f"W{W}/A{A}/I{In}"
                    try:
                        auto = FixedConfig.auto(
                            n, alpha, lam, phi_max=phi_max, y_max=y_max, theta_max=theta_max,
                            word_bits=W, acc_bits=A, input_bits=In, trace_max=trace_max,
                        )  # fmt: skip
                        todo.append((label, auto, None))
                    except FixedPointError as e:
                        todo.append((label, None, str(e)))
    elif isinstance(configs, Mapping):
        todo = [(str(k), v, None) for k, v in configs.items()]
    else:
        todo = [(c.label, c, None) for c in configs]

    rows: list[SweepRow] = []
    zero = SaturationCounts.of({})
    for label, cfg, err in todo:
        if cfg is not None:
            try:
                est = FixedRLS(cfg, n, lam, alpha, trace_max=trace_max, update=update)
            except FixedPointError as e:
                cfg, err = None, str(e)
        if cfg is None:
            rows.append(SweepRow(label, None, math.inf, (), (), zero, False, err))
            continue
        Pq, Yq, _ = est.quantize_inputs(Phi_a, Y_a)
        est.run(Pq, Yq, record=False)
        th = est.theta_float
        rel = np.abs(th - ref) / scale
        mx = float(rel.max())
        rows.append(
            SweepRow(label, cfg, mx, tuple(float(x) for x in rel), tuple(float(x) for x in th),
                     est.saturations, bool(mx <= tol))
        )  # fmt: skip
    ok = [r for r in rows if r.ok]
    rec = min(ok, key=lambda r: r.cost) if ok else None
    return SweepResult(tuple(rows), float(tol), fl, tuple(float(x) for x in ref), rec,
                       () if sigma is None else tuple(float(x) for x in sd))
