"""The target's integer path in C on a model given at run time: the fixed column.

:class:`NativeTarget` runs the C that ``canrls export-c`` writes (``canrls_target.c``,
``canrls_fixed.c``, built into the extension ``canrls._target``) on the integers of a
:class:`~canrls.firmware.target_model.TargetModel`, handed to it as data (:func:`pack`: the
tables of ``canrls_model.c``, nothing compiled for a model). :class:`TargetFeed` is the
one loop that takes a stream's frame blocks to it (``canrls fit``:
:mod:`canrls.firmware.target_fit`; the daemon: :mod:`canrls.firmware.target_live`), or to the Python
specification :class:`~canrls.firmware.spec.TargetEstimator` against which the C is
tested bit for bit.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls import _target
from canrls.can.frameblock import FrameBlock
from canrls.core.samples import ROLES
from canrls.estimation.fixed import SaturationCounts
from canrls.firmware.qmath import dyadic
from canrls.firmware.spec import PUBLISH, REJECTS, TargetEstimator
from canrls.firmware.target_model import Column, EquationSpec, Field, TargetError, TargetModel
from canrls.firmware.vectors import block_frames, block_ticks, state_record
from canrls.processor import TargetRun

__all__ = ["STATE_BYTES", "NativeTarget", "TargetFeed", "TargetSnapshot", "pack",
           "state_layout"]

_U64 = 1 << 64
#: the estimator frames in the order of the C's model (estimate, info, status, health)
_OUT = ("RlsEstimate", "RlsParamInfo", "RlsStatus", "RlsHealth")


def _s64(v: int) -> int:
    """An unsigned 64-bit value as the int64 of its bits."""
    return v - _U64 if v >= 1 << 63 else v


def _put(out: list[int], section: str, values: Mapping[str, int | Sequence[int]]) -> None:
    """The values of one section of the C's layout (``canrls._target.LAYOUT``), by name,
    each with as many words as the layout gives it."""
    for name, count in _target.LAYOUT[section]:
        v = values[name]
        words = [v] if isinstance(v, int) else list(v)
        if len(words) != count:
            raise TargetError(f"the target's layout: {section}.{name} has {count} words, "
                              f"{len(words)} given")
        out.extend(words)


def _field(f: Field | None) -> dict[str, int]:
    if f is None:
        return dict.fromkeys(("msg", "length", "is_float", "frac", "is_signed", "biased",
                              "big_endian", "shift", "lo", "hi"), 0)
    return {"msg": f.msg, "length": f.length, "is_float": int(f.is_float), "frac": f.frac,
            "is_signed": int(f.signed), "biased": int(f.biased),
            "big_endian": int(f.big_endian), "shift": f.shift, "lo": f.lo, "hi": f.hi}


def _column(c: Column) -> dict[str, int]:
    return {"offset": c.offset, "m": c.m, "sh": c.sh, "exponent": c.exponent,
            "filter": c.filter, "derivative": int(c.derivative), "adaptive": int(c.adaptive),
            "pending": int(c.pending)}


def _equation(out: list[int], e: EquationSpec) -> None:
    s = e.selection
    _put(out, "equation", {
        "n": e.n, "index": e.index, "cross": int(s.cross), "trace_follows": int(e.trace_follows),
        "warmup": s.warmup, "min_w": s.min_w, "max_w": s.max_w, "e0": e.e0, "f_phi": e.f_phi,
        "f_y": e.f_y, "f_theta": e.f_theta, "f_eps": e.f_eps,
        "theta_h": e.theta_half.bit_length() - 1, "rms_shift": e.rms_shift,
        "trace_cap": e.trace_cap, "floor_term": e.floor_term, "first_term": e.first_term})
    (fm, fe), (im, ie) = dyadic(e.prior_floor), dyadic(e.first_ridge)
    _put(out, "priors", {"floor_m": _s64(fm), "floor_e": fe, "first_m": _s64(im),
                         "first_e": ie})
    _put(out, "plan", e.plan)
    _put(out, "column", _column(e.output))
    for c, p0, term, ridge in zip(e.columns, e.p0, e.trace_terms, e.ridge, strict=True):
        m, x = dyadic(ridge)
        _put(out, "column", _column(c))
        _put(out, "prior", {"p0": p0, "term": term, "ridge_m": _s64(m), "ridge_e": x})


def pack(tm: TargetModel) -> npt.NDArray[np.int64]:
    """The integers of ``tm`` as the vector ``canrls._target.Target`` reads: what
    :func:`canrls.firmware.cgen.model_files` writes as ``canrls_model.c``, in the order
    of the C's sections."""
    out: list[int] = []
    ta = tm.tanh_arg or (0, 0, 0)
    sa = tm.stribeck_arg or (0, 0, 0)
    pm, po = tm.phase or (0, 0)
    _put(out, "model", {
        "nmsg": len(tm.messages), "nfilters": len(tm.filters), "neq": len(tm.equations),
        "nparams": tm.n_params, "match_counters": int(tm.match_counters),
        "dt_ticks": tm.dt_ticks, "gap_ticks": tm.gap_ticks, "tol_ticks": tm.tol_ticks,
        "tanh_m": ta[0], "tanh_sh": ta[2], "tanh_b": ta[1], "strib_m": sa[0],
        "strib_sh": sa[2], "strib_b": sa[1], "phase_m": _s64(pm), "phase_o": _s64(po),
        "w_offset": tm.w_offset, "A": list(tm.A), "G": [v for row in tm.G for v in row],
        "publish_every": tm.publish_every, "active_effects": tm.active_effects,
        "has_frames": int(tm.out is not None)})
    for role in ROLES:
        _put(out, "field", _field(tm.roles.get(role)))
    for name in _OUT:
        f = None if tm.out is None else tm.out[name]
        spans = [] if f is None else [f.fields[s] for s in f.fields]
        spans += [(0, 0)] * (8 - len(spans))
        _put(out, "out", {"id": 0 if f is None else f.id, "start": [s for s, _ in spans],
                          "length": [n for _, n in spans]})
    for i, m in enumerate(tm.messages):
        roles = [k for k, r in enumerate(ROLES) if r in tm.roles and tm.roles[r].msg == i]
        _put(out, "message", {"id": m.id, "extended": int(m.extended), "dlc": m.dlc,
                              "crc": int(m.crc), "has_counter": int(m.counter is not None),
                              "nroles": len(roles), "roles": roles + [0] * (5 - len(roles))})
        _put(out, "field", _field(m.counter))
    for flt in tm.filters:
        _put(out, "filter", {"kind": flt.kind, "role": ROLES.index(flt.role) if flt.role else 0,
                             "order": flt.order, "hold": flt.hold, "fx": flt.fx})
    for e in tm.equations:
        _equation(out, e)
    for eff, comp, order, eq in tm.param_info:
        _put(out, "param", {"effect": eff, "component": comp, "equation": eq, "order": order})
    return np.array(out, np.int64)


#: the bytes of a C state (:meth:`NativeTarget.state`) in this build
STATE_BYTES: int = _target.STATE_BYTES


def state_layout() -> str:
    """What the bytes of a C state (:meth:`NativeTarget.state`) mean: the SHA-256 of
    the headers that declare ``canrls_target`` (a state of other headers is not taken)."""
    c = resources.files("canrls") / "c" / "firmware"
    h = hashlib.sha256()
    for name in ("canrls_target.h", "canrls_fixed.h", "canrls_bounds.h"):
        h.update((c / name).read_bytes())
    return h.hexdigest()


class NativeTarget:
    """The target's estimator in C (``canrls_target``) on ``model``'s integers."""

    def __init__(self, model: TargetModel) -> None:
        self.m = model
        try:
            self._c = _target.Target(pack(model))
        except ValueError as e:
            raise TargetError(f"the target's C does not take this model: {e}") from e

    def run(self, ticks: npt.NDArray[np.uint32], block: FrameBlock,
            publications: list[Any] | None = None) -> int:
        """Every frame of ``block`` (receive times ``ticks``) through
        ``canrls_target_frame``, publishing where due; the samples it completed."""
        c = np.ascontiguousarray
        skip = block.is_error | block.is_remote
        return int(self._c.run(c(ticks, np.uint32), c(block.arbitration_id, np.uint32),
                               c(block.is_extended, np.bool_), c(skip, np.bool_),
                               c(block.dlc, np.uint8), c(block.data, np.uint8), publications))

    def theta_si(self) -> list[float]:
        """Every parameter in SI (``theta 2^(s_y - s_j - f_theta)``)."""
        return list(self._c.theta())

    def freeze(self, on: bool) -> None:
        """Every equation's kernel frozen (the estimate kept, ``eps`` computed) or not."""
        self._c.freeze(on)

    def state_record(self) -> list[int]:
        """The integer state as :func:`canrls.firmware.vectors.state_record` lays it out."""
        return list(self._c.record())

    def state(self) -> bytes:
        """The whole integer state (``canrls_target``) as its bytes, for :meth:`set_state`."""
        return bytes(self._c.state())

    def set_state(self, state: bytes) -> None:
        """Continue from a :meth:`state` of the same model's C in the same build
        (:class:`TargetError` for a state of another size, or one with a field
        ``canrls_target_check_state`` refuses: docs/target.md, "Restoring a state")."""
        try:
            self._c.set_state(state)
        except ValueError as e:
            raise TargetError(f"the target's C does not take this state: {e}") from e

    def counts(self) -> tuple[int, dict[str, int], list[int], list[int], list[SaturationCounts]]:
        """Samples, rejections by reason, and per equation updates, rescales and the
        kernel's saturations."""
        samples, rej, upd, res, sat = self._c.counts()
        return (samples, dict(zip(REJECTS, rej, strict=True)), list(upd), list(res),
                [SaturationCounts(list(s)) for s in sat])


def _spec_counts(est: TargetEstimator) -> tuple[int, dict[str, int], list[int], list[int],
                                                list[SaturationCounts]]:
    return (est.samples, dict(est.rejects), [es.updates for es in est.eqs],
            [es.rescales for es in est.eqs], [es.rls.saturations for es in est.eqs])


@dataclass(frozen=True)
class TargetSnapshot:
    """A :class:`TargetFeed` at one moment: ``model`` the integers of its target model
    (:func:`pack`), ``state`` the C's bytes, ``t0`` the stream's first receive time [s]
    (None: no frame yet), ``frozen`` whether its kernels were frozen."""

    model: npt.NDArray[np.int64]
    state: bytes
    t0: float | None
    frozen: bool


class TargetFeed:
    """A stream's frame blocks into the target's estimator: times in ticks from the
    stream's first frame (:func:`~canrls.firmware.vectors.block_ticks`), error and
    remote frames left out, a publication made where one is due.

    :param model: the target's integers.
    :param native: the C (``canrls._target``); False: the Python specification.
    """

    def __init__(self, model: TargetModel, native: bool = True) -> None:
        self.model = model
        self._t0: list[float] = []
        #: the kernels frozen (:meth:`freeze`)
        self.frozen = False
        self.estimator: NativeTarget | TargetEstimator = (
            NativeTarget(model) if native else TargetEstimator(model))

    def feed(self, block: FrameBlock) -> None:
        """The frames of one block, in order."""
        if not len(block):
            return
        est = self.estimator
        if isinstance(est, NativeTarget):
            est.run(block_ticks(block, self._t0, self.model.tick_s), block)
            return
        for t, fid, ext, data in block_frames(block, self._t0, self.model.tick_s):
            if est.frame(fid, ext, data, t) & PUBLISH:
                est.publish()

    def theta_si(self) -> list[float]:
        return self.estimator.theta_si()

    def freeze(self, on: bool) -> None:
        """Every equation's kernel frozen (as the command ``freeze`` freezes the daemon's
        estimators: the estimate kept) or running again."""
        self.frozen = on
        est = self.estimator
        if isinstance(est, NativeTarget):
            est.freeze(on)
            return
        for es in est.eqs:
            if on:
                es.rls.freeze()
            else:
                es.rls.resume()

    def snapshot(self) -> TargetSnapshot:
        """Everything the path needs to continue later on the same stream (a daemon's
        checkpoint): the model's integers, the C's state, the stream's first time.
        Only the C's state can be taken (:class:`TargetError` on the specification)."""
        est = self.estimator
        if not isinstance(est, NativeTarget):
            raise TargetError("the specification's state is not kept: only the C's is")
        return TargetSnapshot(model=pack(self.model), state=est.state(),
                              t0=self._t0[0] if self._t0 else None, frozen=self.frozen)

    def restore(self, snap: TargetSnapshot) -> None:
        """Continue from :meth:`snapshot` (:class:`TargetError`: taken on another model)."""
        est = self.estimator
        if not isinstance(est, NativeTarget):
            raise TargetError("the specification's state is not kept: only the C's is")
        if not np.array_equal(snap.model, pack(self.model)):
            raise TargetError("the state was taken on another target model")
        est.set_state(snap.state)
        self._t0 = [] if snap.t0 is None else [snap.t0]
        self.frozen = snap.frozen

    def state_record(self) -> list[int]:
        """The integer state (the test vectors' record)."""
        est = self.estimator
        return est.state_record() if isinstance(est, NativeTarget) else state_record(est)

    def fixed(self) -> dict[str, tuple[float, bool]]:
        """Every parameter's value in SI and whether its equation has updated."""
        updates = self._counts()[2]
        theta: Iterator[float] = iter(self.theta_si())
        return {p.name: (next(theta), n > 0)
                for e, n in zip(self.model.equations, updates, strict=True)
                for p in e.parameters}

    def saturations(self) -> dict[str, dict[str, int]]:
        """The kernel's saturations of each equation, the sites that counted."""
        sat = self._counts()[4]
        return {e.name: s.nonzero() for e, s in zip(self.model.equations, sat, strict=True)}

    def run_info(self) -> TargetRun:
        """What the path ran: samples, updates and rescales per equation, the frames it
        rejected or dropped by reason."""
        samples, rej, upd, res, _ = self._counts()
        names = [e.name for e in self.model.equations]
        return TargetRun(samples=samples, updates=dict(zip(names, upd, strict=True)),
                         rescales=dict(zip(names, res, strict=True)),
                         rejected={k: v for k, v in rej.items() if v})

    def _counts(self) -> tuple[int, dict[str, int], list[int], list[int],
                               list[SaturationCounts]]:
        est = self.estimator
        return est.counts() if isinstance(est, NativeTarget) else _spec_counts(est)

