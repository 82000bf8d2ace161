"""Fault injection on frame streams: drop, duplicate, reorder, corrupt, silence.

A :class:`FaultSpec` says what to inject; it parses from a short string::

    drop=0.01,dup=0.005,reorder=0.01,corrupt=0.001,silence=0.5s@10s

=================  ==========================================================================
``drop=P``         each frame is lost with probability P
``dup=P``          each frame is delivered twice (back to back) with probability P
``reorder=P``      each frame swaps places with the next frame of the same ID with
                   probability P (that ID's alive counter then runs backwards once)
``corrupt=P``      one random bit of each frame's payload is flipped with probability P
                   (CRC-8 detects every single-bit error, so the frame fails its CRC)
``silence=D@T``    no frame at all for D seconds from T seconds after the stream's start;
                   ``silence=D@T/E`` repeats every E seconds; the key may be given again
                   (``silence=0.5s@10s,silence=2s@30s``) or joined with ``+``
=================  ==========================================================================

Probabilities are in [0, 1]. Times take ``s``, ``ms`` or no suffix (seconds).
``none`` or an empty string means no faults. A malformed spec is a
:class:`~canrls.errors.ConfigError` naming the field and the value.

Faults apply in this order: silence, drop, corrupt, reorder, duplicate. Each frame
is affected by a given fault at most once; a corrupted frame that is then
duplicated is delivered twice, corrupted. :class:`FaultInjector` applies a spec
block after block with one ``numpy.random.default_rng(seed)`` and keeps a
:class:`FaultLog` of what it injected, so tests can check a decoder's counters.
Frame timestamps keep their order: reordering swaps the contents of two frames,
not their receive times; a duplicate has its original's timestamp.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from canrls.can.frameblock import FrameBlock
from canrls.errors import ConfigError

__all__ = ["Silence", "FaultSpec", "FaultLog", "FaultInjector", "inject"]

_KINDS = ("silenced", "dropped", "corrupted", "reordered", "duplicated")


@dataclass(frozen=True)
class Silence:
    """No frames during ``[start + j*every, start + j*every + duration)``.

    ``j`` counts 0, 1, 2, ... (only 0 when ``every`` is None).
    """

    duration: float
    start: float
    every: float | None = None

    def mask(self, t: npt.NDArray[np.float64]) -> npt.NDArray[np.bool_]:
        """True for the times (relative to the stream start) that fall in a silent window."""
        if self.every is None:
            return (t >= self.start) & (t < self.start + self.duration)
        rel = t - self.start
        return (rel >= 0) & (np.mod(rel, self.every) < self.duration)

    def __str__(self) -> str:
        s = f"{self.duration:g}s@{self.start:g}s"
        return s + (f"/{self.every:g}s" if self.every is not None else "")


def _seconds(text: str, key: str, spec: str) -> float:
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(ms|s)?\s*", text)
    if not m:
        raise ConfigError(f"fault spec {spec!r}: {key}: {text!r} is not a time (e.g. 0.5s, 500ms)")
    v = float(m.group(1)) * (1e-3 if m.group(2) == "ms" else 1.0)
    if not math.isfinite(v):
        raise ConfigError(f"fault spec {spec!r}: {key}: {text!r} is not finite")
    return v


@dataclass(frozen=True)
class FaultSpec:
    """What faults to inject (see the module docstring for the string syntax)."""

    drop: float = 0.0
    dup: float = 0.0
    reorder: float = 0.0
    corrupt: float = 0.0
    silence: tuple[Silence, ...] = ()

    def __post_init__(self) -> None:
        for key in ("drop", "dup", "reorder", "corrupt"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0.0 <= v <= 1.0):
                raise ConfigError(f"fault spec: {key}: probability {v!r} is not in [0, 1]")
        for s in self.silence:
            if not (s.duration > 0 and s.start >= 0 and (s.every is None or s.every > s.duration)):
                raise ConfigError(f"fault spec: silence: {s} needs duration > 0, start >= 0 "
                                  "and a repetition longer than the duration")

    @staticmethod
    def parse(spec: str | FaultSpec | None) -> FaultSpec:
        """Parse ``"drop=0.01,dup=0.005,reorder=0.01,corrupt=0.001,silence=0.5s@10s"``."""
        if isinstance(spec, FaultSpec):
            return spec
        if spec is None:
            return FaultSpec()
        text = str(spec).strip()
        if text.lower() in ("", "none", "off"):
            return FaultSpec()
        values: dict[str, float] = {}
        silences: list[Silence] = []
        for item in text.split(","):
            item = item.strip()
            if not item:
                continue
            key, eq, val = item.partition("=")
            key, val = key.strip(), val.strip()
            if not eq:
                raise ConfigError(f"fault spec {text!r}: {item!r} is not KEY=VALUE")
            if key in ("drop", "dup", "reorder", "corrupt"):
                if key in values:
                    raise ConfigError(f"fault spec {text!r}: {key} given twice")
                try:
                    p = float(val)
                except ValueError as e:
                    raise ConfigError(f"fault spec {text!r}: {key}: {val!r} is not a "
                                      "probability") from e
                if not (math.isfinite(p) and 0.0 <= p <= 1.0):
                    raise ConfigError(f"fault spec {text!r}: {key}: probability {val} is not "
                                      "in [0, 1]")
                values[key] = p
            elif key == "silence":
                for part in val.split("+"):
                    m = re.fullmatch(r"([^@/]+)@([^@/]+)(?:/([^@/]+))?", part.strip())
                    if not m:
                        raise ConfigError(f"fault spec {text!r}: silence: {part!r} is not "
                                          "DURATION@START[/EVERY] (e.g. 0.5s@10s)")
                    d = _seconds(m.group(1), "silence", text)
                    s = _seconds(m.group(2), "silence", text)
                    e = _seconds(m.group(3), "silence", text) if m.group(3) else None
                    if d <= 0 or (e is not None and e <= d):
                        raise ConfigError(f"fault spec {text!r}: silence: {part!r} needs a "
                                          "duration > 0 (and EVERY longer than it)")
                    silences.append(Silence(d, s, e))
            else:
                raise ConfigError(f"fault spec {text!r}: unknown fault {key!r}; known: drop, dup, "
                                  "reorder, corrupt, silence")
        return FaultSpec(silence=tuple(silences), **values)

    @property
    def active(self) -> bool:
        return bool(self.drop or self.dup or self.reorder or self.corrupt or self.silence)

    def __str__(self) -> str:
        parts = [f"{k}={getattr(self, k):g}" for k in ("drop", "dup", "reorder", "corrupt")
                 if getattr(self, k)]
        parts += [f"silence={s}" for s in self.silence]
        return ",".join(parts) or "none"


@dataclass
class FaultLog:
    """What an injector did: frames in and out, and the count of each fault.

    ``per_id[kind][arbitration_id]`` splits each count by frame ID. Frames lost to the
    receiver are ``dropped + silenced``; ``frames_out = frames_in - lost + duplicated``.
    """

    frames_in: int = 0
    frames_out: int = 0
    silenced: int = 0
    dropped: int = 0
    corrupted: int = 0
    reordered: int = 0  # swaps (each moves two frames)
    duplicated: int = 0
    per_id: dict[str, dict[int, int]] = field(default_factory=lambda: {k: {} for k in _KINDS})

    @property
    def lost(self) -> int:
        return self.dropped + self.silenced

    def _count(self, kind: str, ids: npt.NDArray[np.uint32]) -> None:
        setattr(self, kind, getattr(self, kind) + len(ids))
        d = self.per_id[kind]
        for i, c in zip(*np.unique(ids, return_counts=True), strict=True):
            d[int(i)] = d.get(int(i), 0) + int(c)

    def merge(self, other: FaultLog) -> None:
        for k in ("frames_in", "frames_out", *_KINDS):
            setattr(self, k, getattr(self, k) + getattr(other, k))
        for kind in _KINDS:
            for i, c in other.per_id[kind].items():
                self.per_id[kind][i] = self.per_id[kind].get(i, 0) + c

    def summary(self) -> str:
        return (f"{self.frames_in} frames in, {self.frames_out} out: {self.dropped} dropped, "
                f"{self.silenced} silenced, {self.corrupted} corrupted, {self.reordered} "
                f"reordered, {self.duplicated} duplicated")


class FaultInjector:
    """Apply a :class:`FaultSpec` to a stream of blocks with a seeded generator.

    ``t0`` is the stream's start for silence windows (default: the first frame's time).
    Reordering pairs frames within a block (the last frame of an ID in a block is never
    swapped with one of the next block).
    """

    def __init__(self, spec: FaultSpec | str | None, seed: int | None = 0,
                 t0: float | None = None) -> None:
        self.spec = FaultSpec.parse(spec)
        self.rng = np.random.default_rng(seed)
        self.t0 = t0
        self.log = FaultLog()

    def apply(self, block: FrameBlock) -> FrameBlock:
        """The faulted block (the input is not modified); counts go to :attr:`log`."""
        spec, rng, log = self.spec, self.rng, self.log
        n = len(block)
        log.frames_in += n
        if n and self.t0 is None:
            self.t0 = float(block.t[0])
        if not spec.active or n == 0:
            log.frames_out += n
            return block
        # silence: remove frames in the silent windows
        if spec.silence:
            rel = block.t - (self.t0 or 0.0)
            quiet = np.zeros(n, np.bool_)
            for s in spec.silence:
                quiet |= s.mask(rel)
            log._count("silenced", block.arbitration_id[quiet])
            block = block.take(~quiet)
        # drop: Bernoulli(drop) per frame
        if spec.drop:
            lost = rng.random(len(block)) < spec.drop
            log._count("dropped", block.arbitration_id[lost])
            block = block.take(~lost)
        block = FrameBlock(block.t.copy(), block.arbitration_id.copy(), block.is_extended.copy(),
                           block.is_remote.copy(), block.is_error.copy(), block.dlc.copy(),
                           block.data.copy())
        # corrupt: flip one payload bit of a frame (only frames carrying data)
        if spec.corrupt:
            hit = np.flatnonzero((rng.random(len(block)) < spec.corrupt) & (block.dlc > 0)
                                 & ~block.is_remote & ~block.is_error)
            bits = rng.integers(0, 1 << 30, size=len(hit))
            for k, b in zip(hit, bits, strict=True):
                nbits = 8 * int(block.dlc[k])
                bit = int(b) % nbits
                block.data[k, bit // 8] ^= np.uint8(1 << (bit % 8))
            log._count("corrupted", block.arbitration_id[hit])
        # reorder: swap a frame with the next frame of the same ID
        if spec.reorder:
            pick = rng.random(len(block)) < spec.reorder
            swapped: list[int] = []
            for fid in np.unique(block.arbitration_id[pick]):
                rows = np.flatnonzero(block.arbitration_id == fid)
                used = np.zeros(len(rows), np.bool_)
                for j in np.flatnonzero(pick[rows]):
                    if j + 1 >= len(rows) or used[j] or used[j + 1]:
                        continue
                    a, b = rows[j], rows[j + 1]
                    for arr in (block.is_extended, block.is_remote, block.is_error, block.dlc,
                                block.data):
                        arr[[a, b]] = arr[[b, a]]
                    used[j] = used[j + 1] = True
                    swapped.append(a)
            log._count("reordered", block.arbitration_id[np.array(swapped, np.intp)])
        # duplicate: deliver twice, back to back
        if spec.dup:
            twice = rng.random(len(block)) < spec.dup
            log._count("duplicated", block.arbitration_id[twice])
            block = block.take(np.repeat(np.arange(len(block)), 1 + twice.astype(np.intp)))
        log.frames_out += len(block)
        return block


def inject(block: FrameBlock, spec: FaultSpec | str | None, seed: int | None = 0,
           t0: float | None = None) -> tuple[FrameBlock, FaultLog]:
    """Apply ``spec`` to one block; returns the faulted block and the :class:`FaultLog`."""
    inj = FaultInjector(spec, seed, t0)
    out = inj.apply(block)
    return out, inj.log
