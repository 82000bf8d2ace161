"""canrls.processor.pairing: frames of one period -> one sample; faults counted; chunk-invariant."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canrls.can.decoder import DecodedFrames, Decoder, MessageFrames
from canrls.can.encoder import FeedbackEncoder
from canrls.can.frameblock import FrameBlock
from canrls.can.protocol import Protocol
from canrls.core.errors import ConfigError
from canrls.core.samples import Signals
from canrls.processor.pairing import PAIRING_KINDS, Pairer

DATA = Path(__file__).resolve().parents[1] / "data"
USER_DBC = DATA / "proto_user.dbc"
USER_MAPPING = {
    "current": {"signal": "InverterFb1.Iq", "counter": "Alive", "crc": "Chk"},
    "voltage": "InverterFb1.Uq",
    "speed": {"signal": "InverterFb2.MotorSpeed", "counter": "Alive", "crc": "Chk"},
    "position": "InverterFb3.Angle",
}

PROTOCOLS = {
    "default": lambda: Protocol.load(),
    "no-counter-check": lambda: Protocol.load(check_counter=False),
    "user-3-messages": lambda: Protocol.load(USER_DBC, USER_MAPPING),
}
_cache: dict[str, Protocol] = {}


def protocol(name: str) -> Protocol:
    if name not in _cache:
        _cache[name] = PROTOCOLS[name]()
    return _cache[name]


def clean(p: Protocol, n: int, stagger: float = 1e-4) -> FrameBlock:
    """n periods; period k: current = k/100 A, speed = k/50 rad/s, position = voltage = k/10."""
    T = p.period
    k = np.arange(n, dtype=np.float64)
    return FeedbackEncoder(p, stagger=stagger).encode(k * T, k / 100, k / 50, k / 10, k / 10)


def run(p: Protocol, block: FrameBlock, cuts: list[int], **kw) -> tuple[Signals, Pairer, object]:
    dec = Decoder(p)
    pr = Pairer(p, **kw)
    bounds = list(zip([0, *cuts], [*cuts, len(block)], strict=True))
    out = [pr.push(dec.decode(block.take(slice(a, b)))) for a, b in bounds]
    out.append(pr.flush())
    return Signals.concat(out), pr, dec


# ---------------------------------------------------------------------------
# Rules, one at a time
# ---------------------------------------------------------------------------


def test_clean_stream_pairs_every_period() -> None:
    p = protocol("default")
    s, pr, _ = run(p, clean(p, 20), [])
    assert len(s) == 20
    assert np.allclose(s.current, np.arange(20) / 100)
    assert np.allclose(s.speed, np.arange(20) / 50)
    assert np.allclose(s.position, np.arange(20) / 10, atol=1e-4)
    assert np.allclose(s.voltage, np.arange(20) / 10, atol=5e-3)
    # timestamp = the later partner (DriveSpeed, sent 0.1 ms after DriveCurrent)
    assert np.allclose(s.t, np.arange(20) * 1e-3 + 1e-4)
    assert pr.counts.as_dict() == {"samples": 20, "unpaired": 0, "lost": 0, "duplicated": 0,
                                   "reordered": 0, "late": 0,
                                   "step_back": 0, "step_forward": 0, "gap": 0}
    assert pr.pending == 0


def test_sample_emitted_as_soon_as_complete() -> None:
    p = protocol("default")
    b = clean(p, 3)
    dec, pr = Decoder(p), Pairer(p)
    assert len(pr.push(dec.decode(b.take(slice(0, 1))))) == 0
    assert pr.pending == 1
    assert pr.push(dec.decode(b.take(slice(1, 2)))).current.tolist() == [0.0]
    assert pr.pending == 0


def test_missing_partner_drops_half_and_never_uses_stale_data() -> None:
    p = protocol("default")
    b = clean(p, 6)
    keep = np.array([0, 1, 2, 5, 6, 7, 10, 11])  # S1, C2, C4 and S4 dropped (rows 3, 4, 8, 9)
    s, pr, _ = run(p, b.take(keep), [])
    assert np.allclose(s.current * 100, [0, 3, 5]) and np.allclose(s.speed * 50, [0, 3, 5])
    c = pr.counts
    assert c.per_message["DriveCurrent"]["unpaired"] == 1  # C1
    assert c.per_message["DriveSpeed"]["unpaired"] == 1    # S2
    assert c.per_message["DriveSpeed"]["lost"] == 1 + 1    # S1, S4 (period 4 wholly missing)
    assert c.per_message["DriveCurrent"]["lost"] == 1 + 1  # C2, C4


def test_swap_across_periods_is_reordered_not_lost() -> None:
    p = protocol("default")
    b = clean(p, 4)
    s, pr, _ = run(p, b.take(np.array([0, 2, 1, 3, 4, 6, 5, 7])), [])
    assert len(s) == 4 and np.all(np.diff(s.t) > 0)
    assert pr.counts.reordered == 2 and pr.counts.unpaired == 0


def test_complete_period_waits_behind_an_older_open_one() -> None:
    p = protocol("no-counter-check")  # with counter checks S0 after S1 is stale
    b = clean(p, 3)
    dec, pr = Decoder(p), Pairer(p)
    assert len(pr.push(dec.decode(b.take(np.array([0, 2, 3]))))) == 0  # C0 open, period 1 done
    s = pr.push(dec.decode(b.take(np.array([1]))))  # S0 arrives: both periods out, in order
    assert s.current.tolist() == [0.0, 0.01]


def test_late_frame_dropped() -> None:
    order = np.array([0, 2, 3, 4, 5, 6, 1, 7, 8, 9, 10, 11])  # S0 arrives 3 periods late
    p = protocol("default")
    _, pr, dec = run(p, clean(p, 6).take(order), [])
    assert dec.rejected["stale"] == 1 and pr.counts.unpaired == 1  # the decoder catches it
    p = protocol("no-counter-check")
    s, pr, _ = run(p, clean(p, 6).take(order), [])
    assert pr.counts.per_message["DriveSpeed"]["late"] == 1
    assert pr.counts.per_message["DriveCurrent"]["unpaired"] == 1
    assert np.allclose(s.current * 100, [1, 2, 3, 4, 5])


def test_duplicates_without_counter_checks() -> None:
    p = protocol("no-counter-check")
    b = clean(p, 3)
    s, pr, dec = run(p, b.take(np.array([0, 0, 1, 2, 3, 3, 4, 5])), [])
    assert dec.rejected.total == 0
    assert len(s) == 3 and pr.counts.duplicated == 2


def test_time_only_pairing() -> None:
    p = protocol("default")
    b = clean(p, 5)
    s, pr, _ = run(p, b.take(np.array([0, 1, 3, 2, 4, 5, 6, 7, 8])), [], match_counters=False)
    assert not pr.match_counters
    assert np.allclose(s.current * 100, [0, 1, 2, 3]) and pr.counts.unpaired == 1


def test_counter_mismatch_never_pairs() -> None:
    p = protocol("default")
    b = clean(p, 2)
    b.data[1, 1] = (b.data[1, 1] & 0xF0) | 7  # S0 claims counter 7 (CRC then fails)
    p2 = Protocol.load(check_crc=False, check_counter=False)
    s, pr, _ = run(p2, b, [])
    assert s.current.tolist() == [0.01]
    assert pr.counts.unpaired == 2  # C0 and the S "0" with counter 7 each stay alone


def test_three_messages_need_all_partners() -> None:
    p = protocol("user-3-messages")
    b = clean(p, 4)
    assert [m.name for m in p.messages] == ["InverterFb1", "InverterFb2", "InverterFb3"]
    s, pr, _ = run(p, b.take(np.array([0, 1, 2, 3, 4, 6, 7, 8, 9, 10, 11])), [])
    assert np.allclose(s.current * 100, [0, 2, 3], atol=1e-3)
    assert np.allclose(s.position, np.radians(np.array([0, 2, 3]) / 10 * 180 / np.pi), rtol=1e-6)
    assert pr.counts.unpaired == 2 and pr.counts.lost == 1
    assert not pr.match_counters  # InverterFb3 has no counter


def test_configuration() -> None:
    p = protocol("default")
    pr = Pairer(p)
    assert pr.period == pytest.approx(1e-3) and pr.tolerance == pytest.approx(0.5e-3)
    assert Pairer(p, period=2e-3, tolerance=0.3e-3).tolerance == 0.3e-3
    with pytest.raises(ConfigError, match="tolerance"):
        Pairer(p, tolerance=2e-3)
    nocycle = Protocol.load(USER_DBC, ["current=InverterFb1.Iq", "speed=InverterFb2.MotorSpeed"],
                            period=None)
    assert Pairer(nocycle).period == pytest.approx(2e-3)


def test_no_cycle_time_needs_period(tmp_path: Path) -> None:
    text = USER_DBC.read_text()
    text = "\n".join(ln for ln in text.splitlines() if not ln.startswith('BA_ "GenMsgCycleTime"'))
    f = tmp_path / "nocycle.dbc"
    f.write_text(text)
    p = Protocol.load(f, ["current=InverterFb1.Iq", "speed=InverterFb2.MotorSpeed"])
    with pytest.raises(ConfigError, match=r"nocycle\.dbc gives no GenMsgCycleTime .*InverterFb1"):
        Pairer(p)
    assert Pairer(p, period=1e-3).period == 1e-3
    assert Pairer(Protocol.load(f, ["current=InverterFb1.Iq", "speed=InverterFb2.MotorSpeed"],
                                period=5e-3)).period == 5e-3


# ---------------------------------------------------------------------------
# Properties over fault patterns and split points
# ---------------------------------------------------------------------------


@st.composite
def faults(draw: st.DrawFn, n_frames: int) -> tuple[list[int], set[int], list[int]]:
    """Row order after faults (drop, duplicate, reorder by one, late), the rows touched, cuts."""
    order = list(range(n_frames))
    out: list[int] = []
    touched: set[int] = set()
    k = 0
    while k < len(order):
        f = draw(st.sampled_from(["ok"] * 8 + ["drop", "dup", "swap", "late"]))
        row = order[k]
        if f == "drop":
            touched.add(row)
        elif f == "dup":
            out += [row, row]
            touched.add(row)
        elif f == "swap" and k + 1 < len(order):
            out += [order[k + 1], row]
            touched |= {row, order[k + 1]}
            k += 1
        elif f == "late" and k + 8 < len(order):
            order.insert(k + draw(st.integers(6, 8)), row)
            touched.add(row)
        else:
            out.append(row)
        k += 1
    cuts = sorted(draw(st.lists(st.integers(0, len(out)), max_size=6)))
    return out, touched, cuts


@settings(max_examples=120, deadline=None)
@given(st.sampled_from(sorted(PROTOCOLS)), st.booleans(), st.data())
def test_chunk_invariant_and_sound(name: str, time_only: bool, data: st.DataObject) -> None:
    p = protocol(name)
    K = len(p.messages)
    n = 30
    base = clean(p, n)
    order, touched, cuts = data.draw(faults(n * K))
    block = base.take(np.array(order, dtype=np.intp))
    kw = {"match_counters": not time_only}
    whole, pr_w, dec_w = run(p, block, [], **kw)
    split, pr_s, _ = run(p, block, cuts, **kw)
    # chunk invariance
    for attr in ("t", "current", "speed", "position", "voltage"):
        assert np.array_equal(getattr(whole, attr), getattr(split, attr))
    assert pr_w.counts == pr_s.counts
    # every sample is one period's data, stamped with its later partner, in time order
    period = np.rint(whole.current * 100).astype(int)
    assert np.allclose(whole.current * 100, period, atol=0.1)  # quantisation << 1 period
    assert np.allclose(whole.speed * 50, period, atol=0.1)
    if whole.position is not None:
        assert np.allclose(whole.position * 10, period, atol=1e-2)
    assert np.allclose(whole.t, period * p.period + (K - 1) * 1e-4)
    assert np.all(np.diff(whole.t) > 0)
    # every period none of whose frames was touched is emitted
    untouched = [k for k in range(n) if not touched & set(range(k * K, k * K + K))]
    assert set(untouched) <= set(period.tolist())
    # conservation: every accepted frame is in a sample or counted as dropped
    c = pr_w.counts
    assert pr_w.pending == 0
    assert sum(dec_w.accepted.values()) == K * c.samples + c.unpaired + c.duplicated + c.late
    assert set(c.per_message["DriveCurrent" if name != "user-3-messages" else "InverterFb1"]) \
        == set(PAIRING_KINDS)


# ---------------------------------------------------------------------------
# Input the decoder does not produce: frames out of stream order, strided arrays
# ---------------------------------------------------------------------------


def rebuilt(d: DecodedFrames, order: dict[str, np.ndarray], strided: set[str]) -> DecodedFrames:
    """``d`` with each message's frames in ``order[name]`` and, for the messages in
    ``strided``, every array a non-contiguous view."""
    msgs = {}
    for name, m in d.messages.items():
        o = order[name]

        def arr(x: np.ndarray, o: np.ndarray = o, name: str = name) -> np.ndarray:
            return np.repeat(x[o], 2)[::2] if name in strided else x[o]

        msgs[name] = MessageFrames(name, arr(m.t), arr(m.index), arr(m.counter),
                                   {r: arr(v) for r, v in m.values.items()}, m.counter_modulo)
    return DecodedFrames(msgs, d.rejected, d.lost, d.foreign)


def pair_all(p: Protocol, blocks: list[DecodedFrames]) -> tuple[Signals, Pairer]:
    pr = Pairer(p)
    out = [pr.push(d) for d in blocks]
    return Signals.concat([*out, pr.flush()]), pr


@pytest.mark.parametrize("name", sorted(PROTOCOLS))
def test_frames_out_of_stream_order_or_strided_pair_as_sorted(name: str) -> None:
    """A message's frames out of stream order pair as a stable sort by stream index puts
    them; arrays may be strided views, some messages' and not others'."""
    p = protocol(name)
    rng = np.random.default_rng(1)
    order = np.array([0, 2, 1, 3, 4, 5, 7, 6] + list(range(8, 3 * 20)))[:len(p.messages) * 20]
    decoded = [Decoder(p).decode(clean(p, 20).take(order))]
    ref, pr_ref = pair_all(p, decoded)
    assert len(ref) > 10
    names = [m.name for m in p.messages]
    cases = [
        ({n: rng.permutation(len(decoded[0][n])) for n in names}, set()),
        ({n: np.arange(len(decoded[0][n])) for n in names}, {names[0]}),
        ({n: rng.permutation(len(decoded[0][n])) for n in names}, set(names)),
    ]
    for perm, strided in cases:
        got, pr = pair_all(p, [rebuilt(d, perm, strided) for d in decoded])
        for attr in ("t", "current", "speed", "position", "voltage"):
            a, b = getattr(ref, attr), getattr(got, attr)
            assert (a is None and b is None) or a.tobytes() == b.tobytes()
        assert pr.counts == pr_ref.counts
