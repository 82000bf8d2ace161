"""Test vectors of the target from any log: the frames in, the integers out.

:func:`record` runs a log's frames through the specification
(:class:`~canrls.firmware.spec.TargetEstimator`) and keeps what the C must reproduce: the
frames (receive time in ticks, ID, payload), the whole integer state every ``every``
samples and at the end (:func:`state_record`), and every frame of every publication.
:func:`vectors_header` writes them as ``canrls_vectors.h``, which ``canrls_replay.c``
replays through ``canrls_target_frame`` and compares word for word: the host test
(``canrls_test.c``) and the Cortex-M4 example (``src/canrls/c/firmware/example``) both run it.
"""

from __future__ import annotations

import collections
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from canrls.can.frameblock import FrameBlock
from canrls.core.errors import DecodeError
from canrls.firmware.spec import PUBLISH, SAMPLE, TargetEstimator
from canrls.firmware.target_model import TargetModel

__all__ = ["Frame", "Vectors", "block_frames", "block_ticks", "log_blocks", "log_frames",
           "record", "state_record", "vectors_header"]

#: a frame in: (receive time in ticks mod 2^32, id, extended, payload)
Frame = tuple[int, int, bool, bytes]


@dataclass
class Vectors:
    """What :func:`record` kept."""

    frames: list[Frame] = field(default_factory=list)
    #: (frame index after which it holds, the state record)
    checkpoints: list[tuple[int, list[int]]] = field(default_factory=list)
    #: (frame index, [(id, payload)])
    publications: list[tuple[int, list[tuple[int, bytes]]]] = field(default_factory=list)
    samples: int = 0
    source: str = ""
    #: samples between state records
    every: int = 1000
    #: the estimate at the end, SI (for people)
    theta: list[float] = field(default_factory=list)


def log_frames(paths: Iterable[str | Path], tick_s: float = 1e-6) -> Iterator[Frame]:
    """The frames of logs, times in ticks from the first frame (:func:`block_frames`); a
    log without a frame is refused as ``canrls fit`` refuses it."""
    t0: list[float] = []
    for b in log_blocks(paths):
        yield from block_frames(b, t0, tick_s)


def log_blocks(paths: Iterable[str | os.PathLike[str]], *, skip_bad_lines: bool = False
               ) -> Iterator[FrameBlock]:
    """The frame blocks of logs, one after the other; a log without a frame is refused
    as ``canrls fit`` refuses it."""
    from canrls.can.logs import LogReadStats, empty_log_error, read_frames

    for path in paths:
        read = 0
        stats = LogReadStats()
        for b in read_frames(path, skip_bad_lines=skip_bad_lines, stats=stats):
            read += len(b)
            yield b
        if not read:  # refused as canrls fit refuses it
            raise empty_log_error(path, stats.bad_lines)


def block_frames(b: FrameBlock, t0: list[float], tick_s: float = 1e-6) -> Iterator[Frame]:
    """The frames of one block as the target receives them: times in ticks from the
    first frame of the stream (``round((t - t0) / tick_s)`` modulo 2^32; ``t0`` holds it
    once known); error and remote frames are not passed on (the target never sees them:
    its CAN controller filters them)."""
    if not len(b):
        return
    ticks = block_ticks(b, t0, tick_s).tolist()
    for k in range(len(b)):
        if b.is_error[k] or b.is_remote[k]:
            continue
        yield (ticks[k], int(b.arbitration_id[k]), bool(b.is_extended[k]),
               bytes(b.data[k, :b.dlc[k]]))


def block_ticks(b: FrameBlock, t0: list[float], tick_s: float = 1e-6) -> npt.NDArray[np.uint32]:
    """The receive times of a block's frames in ticks from the first frame of the stream,
    ``round((t - t0) / tick_s)`` (half to even) modulo 2^32 (``t0`` holds the first
    frame's time once known)."""
    if not t0:
        t0.append(float(b.t[0]))
    x = np.rint((b.t - t0[0]) / tick_s)
    if not np.isfinite(x).all():
        k = int(np.flatnonzero(~np.isfinite(x))[0])
        raise DecodeError(f"frame {k} of a block: receive time {float(b.t[k])!r} s has no "
                          f"tick", reason="time")
    # modulo 2^32, exactly (fmod of a whole double is exact)
    x = np.fmod(x, 4294967296.0)
    return np.where(x < 0, x + 4294967296.0, x).astype(np.uint32)


def state_record(est: TargetEstimator) -> list[int]:
    """The integer state as the C's ``record()`` lays it out: samples, the rejection
    counters, the filters' states, then per equation theta, its fractions, the upper
    triangle of P, its fractions, e, c, the kernel's counters, the shifts (columns,
    output), updates, the residual's mean square and the rescales."""
    s = est.snapshot()
    out = [s["samples"], *s["rejects"], *s["x1"], *s["x2"]]
    for e in s["equations"]:
        out += [*e["theta"], *e["theta_frac"], *e["P"], *e["P_frac"], e["e"], e["c"],
                *e["counts"], *e["sh"], e["updates"], e["ms"], e["rescales"]]
    return out


def record(model: TargetModel, frames: Iterable[Frame], every: int = 1000,
           source: str = "") -> Vectors:
    """Run ``frames`` through the specification; a state record every ``every`` samples
    and after the last frame, every publication's frames."""
    est = TargetEstimator(model)
    v = Vectors(source=source, every=every)
    mapped = {(m.id, m.extended) for m in model.messages}
    seen: collections.Counter[int] = collections.Counter()
    for k, (t, fid, ext, data) in enumerate(frames):
        if not mapped.isdisjoint(((fid, ext),)):
            mapped = set()  # one mapped frame came: no more counting
        elif mapped:
            seen[fid] += 1
        v.frames.append((t, fid, ext, data))
        r = est.frame(fid, ext, data, t)
        if r & PUBLISH:
            v.publications.append((k, est.publish()))
        if r & SAMPLE and est.samples % every == 0:
            v.checkpoints.append((k, state_record(est)))
    if mapped:  # none of the frames is a mapped message: refused as canrls fit refuses it
        from canrls.processor.frames import unmapped_error

        raise unmapped_error(model.protocol, len(v.frames), seen.most_common(8),
                             source=source or None)
    if v.frames and (not v.checkpoints or v.checkpoints[-1][0] != len(v.frames) - 1):
        v.checkpoints.append((len(v.frames) - 1, state_record(est)))
    v.samples = est.samples
    v.theta = est.theta_si()
    return v


def _rows(values: Iterable[str], per: int = 8, empty: str = "0") -> str:
    """Rows of an initialiser (``empty``: the one element of an array with none: C has
    no empty initialiser)."""
    vals = list(values) or [empty]
    return ",\n".join("    " + ", ".join(vals[i:i + per]) for i in range(0, len(vals), per))


def vectors_header(v: Vectors) -> str:
    """``canrls_vectors.h``: the frames, the state records and the publications (numbers
    only: nothing of the user's text)."""
    nf = len(v.frames)
    rec = len(v.checkpoints[0][1]) if v.checkpoints else 0
    lines = ["/* canrls_vectors.h -- generated by `canrls export-c --vectors`: the frames of",
             " * a log and the integers the specification (canrls.firmware.spec) computes from",
             " * them, for canrls_replay.c. Do not edit. */",
             "#ifndef CANRLS_VECTORS_H", "#define CANRLS_VECTORS_H", "",
             "#include <stdint.h>", "",
             f"#define VEC_FRAMES {nf}u", f"#define VEC_SAMPLES {v.samples}u",
             f"#define VEC_CHECKPOINTS {len(v.checkpoints)}u", f"#define VEC_RECORD {rec}u",
             f"#define VEC_PUBLICATIONS {len(v.publications)}u", ""]
    lines.append("/* receive time (ticks), id (bit 31: 29-bit), length, payload */")
    lines.append(f"static const uint32_t vec_t[{max(nf, 1)}] = {{\n"
                 + _rows(f"{t}u" for t, _, _, _ in v.frames) + "\n};")
    lines.append(f"static const uint32_t vec_id[{max(nf, 1)}] = {{\n"
                 + _rows(f"0x{fid | (0x80000000 if ext else 0):08X}u"
                         for _, fid, ext, _ in v.frames) + "\n};")
    lines.append(f"static const uint8_t vec_len[{max(nf, 1)}] = {{\n"
                 + _rows((f"{len(d)}u" for _, _, _, d in v.frames), 16) + "\n};")
    lines.append(f"static const uint8_t vec_data[{max(nf, 1)}][8] = {{\n"
                 + _rows(("{" + ", ".join(str(b) for b in (d + bytes(8))[:8]) + "}"
                          for _, _, _, d in v.frames), 4, "{0}") + "\n};")
    lines.append("/* state records: the frame index after which each holds, then the record */")
    lines.append(f"static const uint32_t vec_cp_frame[{max(len(v.checkpoints), 1)}] = {{\n"
                 + _rows(f"{k}u" for k, _ in v.checkpoints) + "\n};")
    lines.append(f"static const int64_t vec_cp[{max(len(v.checkpoints) * rec, 1)}] = {{\n"
                 + _rows((f"{x}LL" if x != -(1 << 63) else "(-9223372036854775807LL - 1)"
                          for _, r in v.checkpoints for x in r), 4) + "\n};")
    pub_frames = [(k, fr) for k, frames in v.publications for fr in frames]
    lines.append("/* publications: the frame index, the number of frames; then each frame's "
                 "id and payload */")
    lines.append(f"static const uint32_t vec_pub_frame[{max(len(v.publications), 1)}] = {{\n"
                 + _rows(f"{k}u" for k, _ in v.publications) + "\n};")
    lines.append(f"static const uint8_t vec_pub_count[{max(len(v.publications), 1)}] = {{\n"
                 + _rows((f"{len(f)}u" for _, f in v.publications), 16) + "\n};")
    lines.append(f"static const uint32_t vec_pub_id[{max(len(pub_frames), 1)}] = {{\n"
                 + _rows(f"0x{fid:X}u" for _, (fid, _) in pub_frames) + "\n};")
    lines.append(f"static const uint8_t vec_pub_data[{max(len(pub_frames), 1)}][8] = {{\n"
                 + _rows(("{" + ", ".join(str(b) for b in d) + "}" for _, (_, d) in pub_frames),
                         4, "{0}") + "\n};")
    lines += ["", "#endif /* CANRLS_VECTORS_H */", ""]
    return "\n".join(lines)
