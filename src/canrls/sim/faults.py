"""Fault injection on frame streams: drop, duplicate, reorder, corrupt, silence, and the
hostile rest of a bus: bad counters and DLCs, clock steps, command floods, error frames.

A :class:`FaultSpec` parses from a short string (``drop=0.01,silence=0.5s@10s``);
:class:`FaultInjector` applies it block after block with one seeded generator and keeps
a :class:`FaultLog` of what it injected. Every key, the order the faults apply in and
what the decoder counts for each: docs/simulator.md, "Faults".
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.can.e2e import CRC8_TABLE
from canrls.can.frameblock import FrameBlock
from canrls.core.checks import in_range, is_positive
from canrls.core.errors import ConfigError

__all__ = ["Silence", "FaultSpec", "FaultLog", "FaultInjector", "inject", "ERROR_CLASSES",
           "HARMLESS_COMMANDS"]

_KINDS = ("silenced", "dropped", "corrupted", "reordered", "duplicated", "miscounted",
          "resized", "clock_steps", "commands", "error_frames")
_PROBS = ("drop", "dup", "reorder", "corrupt", "counter", "dlc", "tstep", "cmd", "errframe")

#: E2E-protected frames of the default DBC (DriveCurrent, DriveSpeed)
DEFAULT_PROTECTED = frozenset({0x101, 0x102})
#: RlsCommand in the default DBC
DEFAULT_COMMAND_ID = 0x320
#: SocketCAN error classes (linux/can/error.h) of injected error frames: lost
#: arbitration, controller problems, protocol violation, transceiver status, no ACK,
#: bus-off, bus error, controller restarted
ERROR_CLASSES = (0x002, 0x004, 0x008, 0x010, 0x020, 0x040, 0x080, 0x100)
#: Valid command frames (8 bytes: code, effect id, order (u16 LE), lambda (f32 LE)) that
#: leave the estimates as they were: freeze then resume at once (both ok), resume while
#: running (not_applicable), a lambda outside (0.5, 1] or NaN (bad_value), an unknown
#: effect id (unknown_effect), cogging without an order and viscous with one (bad_value)
HARMLESS_COMMANDS: tuple[tuple[bytes, ...], ...] = (
    (bytes((2, 0, 0, 0)) + np.float32(0).tobytes(),
     bytes((3, 0, 0, 0)) + np.float32(0).tobytes()),
    (bytes((3, 0, 0, 0)) + np.float32(0).tobytes(),),
    (bytes((6, 0, 0, 0)) + np.float32(0.3).tobytes(),),
    (bytes((6, 0, 0, 0)) + np.float32(np.nan).tobytes(),),
    (bytes((4, 0, 0, 0)) + np.float32(0).tobytes(),),
    (bytes((4, 200, 0, 0)) + np.float32(0).tobytes(),),
    (bytes((4, 7, 0, 0)) + np.float32(0).tobytes(),),
    (bytes((5, 2, 3, 0)) + np.float32(0).tobytes(),),
)


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
    """What faults to inject (the string syntax: docs/simulator.md, "Faults")."""

    drop: float = 0.0
    dup: float = 0.0
    reorder: float = 0.0
    corrupt: float = 0.0
    silence: tuple[Silence, ...] = ()
    counter: float = 0.0
    dlc: float = 0.0
    tstep: float = 0.0
    tstep_max: float = 0.5
    cmd: float = 0.0
    cmd_burst: int = 16
    errframe: float = 0.0

    def __post_init__(self) -> None:
        for key in _PROBS:
            v = getattr(self, key)
            if not in_range(v, 0.0, 1.0):
                raise ConfigError(f"fault spec: {key}: probability {v!r} is not in [0, 1]")
        if not is_positive(self.tstep_max):
            raise ConfigError(f"fault spec: tstep_max: {self.tstep_max!r} is not a time > 0")
        if isinstance(self.cmd_burst, bool) or not isinstance(self.cmd_burst, int) \
                or self.cmd_burst < 1:
            raise ConfigError(f"fault spec: cmd_burst: {self.cmd_burst!r} is not a whole "
                              "number >= 1")
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
        values: dict[str, Any] = {}
        silences: list[Silence] = []
        for item in text.split(","):
            item = item.strip()
            if not item:
                continue
            key, eq, val = item.partition("=")
            key, val = key.strip(), val.strip()
            if not eq:
                raise ConfigError(f"fault spec {text!r}: {item!r} is not KEY=VALUE")
            if key in values:
                raise ConfigError(f"fault spec {text!r}: {key} given twice")
            if key == "tstep_max":
                values[key] = _seconds(val, key, text)
                if values[key] <= 0:
                    raise ConfigError(f"fault spec {text!r}: tstep_max: {val!r} is not > 0")
            elif key == "cmd_burst":
                if not re.fullmatch(r"[0-9]+", val) or int(val) < 1:
                    raise ConfigError(f"fault spec {text!r}: cmd_burst: {val!r} is not a whole "
                                      "number >= 1")
                values[key] = int(val)
            elif key in _PROBS:
                try:
                    p = float(val)
                except ValueError as e:
                    raise ConfigError(f"fault spec {text!r}: {key}: {val!r} is not a "
                                      "probability") from e
                if not in_range(p, 0.0, 1.0):
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
                    every = _seconds(m.group(3), "silence", text) if m.group(3) else None
                    if d <= 0 or (every is not None and every <= d):
                        raise ConfigError(f"fault spec {text!r}: silence: {part!r} needs a "
                                          "duration > 0 (and EVERY longer than it)")
                    silences.append(Silence(d, s, every))
            else:
                raise ConfigError(f"fault spec {text!r}: unknown fault {key!r}; known: "
                                  f"{', '.join(_PROBS)}, silence, tstep_max, cmd_burst")
        return FaultSpec(silence=tuple(silences), **values)

    @property
    def active(self) -> bool:
        return bool(self.silence) or any(getattr(self, k) for k in _PROBS)

    def __str__(self) -> str:
        parts = [f"{k}={getattr(self, k):g}" for k in ("drop", "dup", "reorder", "corrupt")
                 if getattr(self, k)]
        parts += [f"silence={s}" for s in self.silence]
        parts += [f"{k}={getattr(self, k):g}" for k in _PROBS[4:] if getattr(self, k)]
        if self.tstep and self.tstep_max != 0.5:
            parts.append(f"tstep_max={self.tstep_max:g}s")
        if self.cmd and self.cmd_burst != 16:
            parts.append(f"cmd_burst={self.cmd_burst}")
        return ",".join(parts) or "none"


@dataclass
class FaultLog:
    """What an injector did: frames in and out, and the count of each fault.

    ``per_id[kind][arbitration_id]`` splits each count by frame ID. Frames lost to the
    receiver are ``dropped + silenced``; ``frames_out = frames_in - lost + duplicated +
    inserted`` (``inserted``: the command and error frames). ``commands`` counts command
    frames, ``command_bursts`` the bursts they came in; ``clock_steps`` the steps,
    ``clock_offset`` the sum of the steps so far [s].
    """

    frames_in: int = 0
    frames_out: int = 0
    silenced: int = 0
    dropped: int = 0
    corrupted: int = 0
    reordered: int = 0  # swaps (each moves two frames)
    duplicated: int = 0
    miscounted: int = 0
    resized: int = 0
    clock_steps: int = 0
    commands: int = 0
    error_frames: int = 0
    command_bursts: int = 0
    clock_offset: float = 0.0
    per_id: dict[str, dict[int, int]] = field(default_factory=lambda: {k: {} for k in _KINDS})

    @property
    def lost(self) -> int:
        return self.dropped + self.silenced

    @property
    def inserted(self) -> int:
        """Frames the injector added: commands and error frames."""
        return self.commands + self.error_frames

    def counts(self) -> dict[str, int]:
        """Each kind of fault and its count (``reordered``: swaps; ``commands``: frames)."""
        return {k: int(getattr(self, k)) for k in _KINDS}

    def _count(self, kind: str, ids: npt.NDArray[np.uint32]) -> None:
        setattr(self, kind, getattr(self, kind) + len(ids))
        d = self.per_id[kind]
        for i, c in zip(*np.unique(ids, return_counts=True), strict=True):
            d[int(i)] = d.get(int(i), 0) + int(c)

    def merge(self, other: FaultLog) -> None:
        for k in ("frames_in", "frames_out", *_KINDS, "command_bursts", "clock_offset"):
            setattr(self, k, getattr(self, k) + getattr(other, k))
        for kind in _KINDS:
            for i, c in other.per_id[kind].items():
                self.per_id[kind][i] = self.per_id[kind].get(i, 0) + c

    def summary(self) -> str:
        text = (f"{self.frames_in} frames in, {self.frames_out} out: {self.dropped} dropped, "
                f"{self.silenced} silenced, {self.corrupted} corrupted, {self.reordered} "
                f"reordered, {self.duplicated} duplicated")
        extra = [f"{getattr(self, k)} {k.replace('_', ' ')}" for k in _KINDS[5:]
                 if getattr(self, k)]
        return text + "".join(", " + e for e in extra)


class FaultInjector:
    """Apply a :class:`FaultSpec` to a stream of blocks with a seeded generator.

    ``t0`` is the stream's start for silence windows (default: the first frame's time).
    Reordering pairs frames within a block (the last frame of an ID in a block is never
    swapped with one of the next block). ``protected``: the IDs whose byte 0 is the
    E2E CRC and byte 1's low nibble the alive counter (``counter`` faults);
    ``command_id``: the ID of the inserted command frames.
    """

    def __init__(self, spec: FaultSpec | str | None, seed: int | tuple[int, ...] | None = 0,
                 t0: float | None = None, *,
                 protected: frozenset[int] = DEFAULT_PROTECTED,
                 command_id: int = DEFAULT_COMMAND_ID) -> None:
        self.spec = FaultSpec.parse(spec)
        self.rng = np.random.default_rng(seed)
        self.t0 = t0
        self.protected = frozenset(int(i) for i in protected)
        self.command_id = int(command_id)
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
        if spec.counter:
            self._miscount(block)
        if spec.dlc:
            self._resize(block)
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
        if spec.tstep or log.clock_offset:
            block = self._clock_steps(block)
        if spec.cmd or spec.errframe:
            block = self._insert(block)
        log.frames_out += len(block)
        return block

    def _data_rows(self, block: FrameBlock, p: float) -> npt.NDArray[np.intp]:
        """Rows of data frames (not remote, not error) hit with probability ``p``."""
        return np.flatnonzero((self.rng.random(len(block)) < p) & ~block.is_remote
                              & ~block.is_error)

    def _miscount(self, block: FrameBlock) -> None:
        """Move the alive counter of protected frames by 1..15; the CRC stays valid."""
        hit = self._data_rows(block, self.spec.counter)
        ok = np.isin(block.arbitration_id[hit], np.array(sorted(self.protected), np.uint32)) \
            & (block.dlc[hit] >= 2)
        hit = hit[ok]
        moves = self.rng.integers(1, 16, size=len(hit))
        for k, mv in zip(hit, moves, strict=True):
            d = block.data[k]
            d[1] = (d[1] & 0xF0) | ((int(d[1]) + int(mv)) & 0x0F)
            # crc = CRC8_0x1D(id_lo, id_hi, d_1 .. d_{n-1}), init 0xFF, xorout 0xFF
            fid = int(block.arbitration_id[k])
            c = 0xFF
            for b in (fid & 0xFF, (fid >> 8) & 0xFF, *d[1:int(block.dlc[k])].tolist()):
                c = int(CRC8_TABLE[c ^ b])
            d[0] = c ^ 0xFF
        self.log._count("miscounted", block.arbitration_id[hit])

    def _resize(self, block: FrameBlock) -> None:
        """Give frames another DLC in 0..8; bytes beyond it read as zeros."""
        hit = self._data_rows(block, self.spec.dlc)
        shift = self.rng.integers(1, 9, size=len(hit))
        for k, sh in zip(hit, shift, strict=True):
            new = (int(block.dlc[k]) + int(sh)) % 9  # never the old DLC (if it was <= 8)
            block.dlc[k] = new
            block.data[k, new:] = 0
        self.log._count("resized", block.arbitration_id[hit])

    def _clock_steps(self, block: FrameBlock) -> FrameBlock:
        """Shift the receive times by the steps so far, and by this block's steps."""
        spec, log = self.spec, self.log
        n = len(block)
        steps = np.zeros(n, np.float64)
        if spec.tstep:
            hit = np.flatnonzero(self.rng.random(n) < spec.tstep)
            size = self.rng.uniform(0.0, spec.tstep_max, size=len(hit))
            sign = np.where(self.rng.random(len(hit)) < 0.5, -1.0, 1.0)
            steps[hit] = sign * np.maximum(size, 1e-6)
            log._count("clock_steps", block.arbitration_id[hit])
        # t_k <- t_k + offset + sum_{j <= k} step_j
        shift = log.clock_offset + np.cumsum(steps)
        if n:
            log.clock_offset = float(shift[-1])
        return FrameBlock(block.t + shift, block.arbitration_id, block.is_extended,
                          block.is_remote, block.is_error, block.dlc, block.data)

    def _insert(self, block: FrameBlock) -> FrameBlock:
        """Command bursts and error frames after randomly chosen frames."""
        spec, rng, log = self.spec, self.rng, self.log
        n = len(block)
        after: list[int] = []  # the row each new frame follows
        new: list[tuple[int, bool, bool, bytes]] = []  # id, remote, error, payload
        if spec.cmd:
            for k in np.flatnonzero(rng.random(n) < spec.cmd):
                log.command_bursts += 1
                for _ in range(int(rng.integers(1, spec.cmd_burst + 1))):
                    for frame in self._command(rng):
                        after.append(int(k))
                        new.append((self.command_id, frame is None, False, frame or b""))
        if spec.errframe:
            for k in np.flatnonzero(rng.random(n) < spec.errframe):
                after.append(int(k))
                cls = ERROR_CLASSES[int(rng.integers(0, len(ERROR_CLASSES)))]
                new.append((cls, False, True, bytes(8)))
        if not new:
            return block
        m = len(new)
        extra = FrameBlock.allocate(m, block.data.shape[1])
        for j, (fid, remote, err, payload) in enumerate(new):
            extra.arbitration_id[j] = fid
            extra.is_remote[j] = remote
            extra.is_error[j] = err
            extra.dlc[j] = 8 if remote else len(payload)
            extra.data[j, :len(payload)] = np.frombuffer(payload, np.uint8)
        pos = np.array(after, np.intp)
        extra.t[:] = block.t[pos]
        ids = extra.arbitration_id
        log._count("commands", ids[~extra.is_error])
        log._count("error_frames", ids[extra.is_error])
        # stable merge: each new frame right after the frame it follows, in order
        key = np.concatenate([np.arange(n, dtype=np.float64),
                              pos + 0.5 + np.arange(m) / (2.0 * (m + 1))])
        order = np.argsort(key, kind="stable")
        return FrameBlock.concat([block, extra]).take(order)

    @staticmethod
    def _command(rng: np.random.Generator) -> tuple[bytes | None, ...]:
        """One command: random (unknown code, DLC not 8, or remote: None) or harmless."""
        kind = int(rng.integers(0, 4))
        if kind == 0:  # unknown command code, 8 bytes
            return (bytes((int(rng.integers(7, 256)),)) + rng.bytes(7),)
        if kind == 1:  # a DLC other than 8, any bytes
            return (rng.bytes(int(rng.integers(0, 8))),)
        if kind == 2 and rng.random() < 0.25:
            return (None,)  # a remote frame
        return HARMLESS_COMMANDS[int(rng.integers(0, len(HARMLESS_COMMANDS)))]


def inject(block: FrameBlock, spec: FaultSpec | str | None, seed: int | None = 0,
           t0: float | None = None) -> tuple[FrameBlock, FaultLog]:
    """Apply ``spec`` to one block; returns the faulted block and the :class:`FaultLog`."""
    inj = FaultInjector(spec, seed, t0)
    out = inj.apply(block)
    return out, inj.log
