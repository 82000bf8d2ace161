"""canrls._can, the C loops of the CAN layer: the same samples as before, and safe calls.

Strict decoding and pairing of seeded streams with every kind of fault give the samples,
counts and rejection examples the numba kernels gave (a digest), and a wrong array is an
error, never a stray memory access.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from canrls import _can

# -- the same samples as the numba kernels gave -------------------------------------------

#: a DBC beyond the default's layout: an extended ID, a float32 and a float64 signal, big
#: endian, a 13-bit signed field, a counter without CRC, a message of 6 bytes
ODD_DBC = """VERSION ""

NS_ :

BS_:

BU_: Drive Canrls

BO_ 2147484160 FbA: 8 Drive
 SG_ Cnt : 0|8@1+ (1,0) [0|255] "" Canrls
 SG_ Cur : 8|32@1- (1,0) [-1000|1000] "A" Canrls
 SG_ Volt : 47|16@0+ (0.01,-300) [-300|300] "V" Canrls

BO_ 300 FbB: 8 Drive
 SG_ Spd : 0|64@1- (1,0) [-900|900] "rad/s" Canrls

BO_ 301 FbC: 6 Drive
 SG_ Pos : 7|13@0- (0.001,0) [-4|4] "rad" Canrls
 SG_ Cnt2 : 44|4@1+ (1,0) [0|15] "" Canrls

BA_DEF_ BO_ "GenMsgCycleTime" INT 0 10000;
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_ "GenMsgCycleTime" BO_ 2147484160 1;
BA_ "GenMsgCycleTime" BO_ 300 1;
BA_ "GenMsgCycleTime" BO_ 301 1;
SIG_VALTYPE_ 2147484160 Cur : 1;
SIG_VALTYPE_ 300 Spd : 2;
"""
ODD_MAPPING = {"current": "FbA.Cur", "voltage": "FbA.Volt", "speed": "FbB.Spd",
               "position": {"signal": "FbC.Pos", "counter": "Cnt2"},
               "messages": {"FbA": {"counter": "Cnt"}}}


def _stream_digest(protocol: Any, seed: int, level: float) -> str:
    """SHA-256 of everything decoding and pairing give for a seeded stream with faults
    (drops, duplicates, swaps, jitter, corrupted bytes, remote and error frames, wrong
    lengths, foreign IDs), cut into blocks of random sizes."""
    from canrls.can.decoder import Decoder
    from canrls.can.encoder import FeedbackEncoder
    from canrls.can.frameblock import FrameBlock
    from canrls.processor.pairing import Pairer

    rng = np.random.default_rng(seed)
    n = 2000
    enc = FeedbackEncoder(protocol, clip=True, stagger=2e-4 if seed % 2 else 0.0)
    sig = {"current": rng.uniform(-10, 10, n), "speed": rng.uniform(-100, 100, n),
           "position": rng.uniform(-3, 3, n), "voltage": rng.uniform(-100, 100, n)}
    b = enc.encode(np.arange(n) * 1e-3, **{r: v for r, v in sig.items() if protocol.has(r)})
    keep = np.flatnonzero(rng.random(len(b)) > level / 2)
    idx = np.sort(np.concatenate([keep, keep[rng.choice(len(keep), len(keep) // 50 + 1)]]))
    for a in rng.integers(0, len(idx) - 1, int(level * len(idx) / 4)):
        idx[a], idx[a + 1] = idx[a + 1], idx[a]
    m = len(idx)
    data = b.data[idx].copy()
    flip = np.flatnonzero(rng.random(m) < level * 0.3)
    data[flip, rng.integers(0, 8, len(flip))] ^= rng.integers(1, 256, len(flip)).astype(np.uint8)
    dlc = b.dlc[idx].copy()
    short = rng.random(m) < level * 0.02
    dlc[short] = rng.integers(0, 9, int(short.sum()))
    aid = b.arbitration_id[idx].copy()
    foreign = rng.random(m) < level * 0.1
    aid[foreign] = rng.integers(0, 0x7FF, int(foreign.sum()))
    block = FrameBlock(b.t[idx] + rng.normal(0, 1e-4, m) * (rng.random(m) < level), aid,
                       b.is_extended[idx], b.is_remote[idx] | (rng.random(m) < level * 0.02),
                       b.is_error[idx] | (rng.random(m) < level * 0.02), dlc, data)
    dec = Decoder(protocol)
    pairer = Pairer(protocol, hold=seed % 3, match_counters=seed % 4 != 3)
    h = hashlib.sha256()
    i = 0
    while i < len(block):
        size = int(rng.integers(1, 300))
        d = dec.decode(block.take(slice(i, i + size)))
        i += size
        for name, f in d.messages.items():
            h.update(name.encode() + f.t.tobytes() + f.index.tobytes() + f.counter.tobytes())
            for v in f.values.values():
                h.update(v.tobytes())
        h.update(repr((dict(d.rejected), d.rejected.examples, d.lost, d.foreign)).encode())
        for s in (pairer.push(d), pairer.flush()) if i >= len(block) else (pairer.push(d),):
            for v in (s.t, s.current, s.speed, s.position, s.voltage):
                h.update(b"-" if v is None else v.tobytes())
        h.update(repr(pairer.pending).encode())
    h.update(repr((pairer.counts.per_message, dec.accepted, dec.lost)).encode())
    return h.hexdigest()[:16]


#: :func:`_stream_digest` as the numba kernels (main at 19b846f) computed it: the C loops
#: give the same frames, samples and counts, bit for bit. A deliberate change of the
#: decoding or pairing rules changes these (and says so in its commit). Changed twice
#: since: a counter ahead of its time is rejected (``sequence``) and a frame received but
#: rejected is no longer counted lost (the reason ``sequence`` in every repr; a copy
#: delivered with its frame is no frame received); then the reason ``time`` joined the
#: counts (frames rejected for their receive time, ``canrls.processor.times``: 0 here, the
#: frames and samples unchanged).
NUMBA_DIGESTS = {
    ('default', 0, 0.0): '98dae17cc24c0812',
    ('default', 1, 0.02): '07d682784978aa87',
    ('default', 2, 0.1): '63c9f85e914816a8',
    ('default', 3, 0.3): '708f1ee324911404',
    ('odd', 0, 0.0): '3cc0e69e05046c48',
    ('odd', 1, 0.02): 'e8e9fefac900376e',
    ('odd', 2, 0.1): '187a6135b4ef2ca8',
    ('odd', 3, 0.3): 'cb4321012d5e9b81',
}


@pytest.mark.parametrize("dbc", ["default", "odd"])
@pytest.mark.parametrize("seed,level", [(0, 0.0), (1, 0.02), (2, 0.1), (3, 0.3)])
def test_decoding_and_pairing_give_what_the_numba_kernels_gave(tmp_path: Path, dbc: str,
                                                               seed: int, level: float) -> None:
    from canrls.can.protocol import Protocol

    if dbc == "default":
        protocol = Protocol.load()
    else:
        (tmp_path / "odd.dbc").write_text(ODD_DBC)
        protocol = Protocol.load(tmp_path / "odd.dbc", ODD_MAPPING)
    assert _stream_digest(protocol, seed, level) == NUMBA_DIGESTS[dbc, seed, level]


# -- the C module's guard rails: a wrong array is an error, never a stray memory access --


def test_c_module_rejects_wrong_dtypes_and_short_arrays() -> None:
    table = np.zeros((8, 256), np.uint8)
    data = np.zeros((4, 8), np.uint8)
    with pytest.raises(TypeError, match="dtype"):
        _can.crc8(0x100, data.astype(np.int64), 8, 8, table, np.empty(4, np.uint8))
    with pytest.raises(ValueError, match="too small"):
        _can.crc8(0x100, data, 8, 8, table, np.empty(5, np.uint8))
    with pytest.raises(ValueError, match="needs"):
        _can.counters(np.zeros(3, np.int64), np.zeros(2), 16, 7, 0.001,
                      np.zeros(3, np.int64), np.zeros(1), np.empty(3, np.uint8),
                      np.empty(3, np.int64))
    with pytest.raises(IndexError):
        _can.gather_check(data, 8, np.array([4], np.int64), 8, np.zeros(4, np.bool_),
                          np.full(4, 8, np.uint8), True, 0x100, table,
                          np.empty((1, 8), np.uint8), np.empty(1, np.uint8))
    with pytest.raises(ValueError, match="read-only"):
        out = np.empty(4, np.uint8)
        out.flags.writeable = False
        _can.crc8(0x100, data, 8, 8, table, out)
