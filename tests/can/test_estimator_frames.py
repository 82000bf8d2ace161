"""canrls.can.estimator_frames: estimator, status and command frames through cantools."""

from __future__ import annotations

import dataclasses
import math
import struct
from pathlib import Path
from typing import Any

import can
import cantools
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canrls.can.codec import EncodeError
from canrls.can.estimator_frames import (
    COMPONENTS,
    FLAG_NAMES,
    REJECT_FIELDS,
    REJECT_WRAP,
    Command,
    CommandAck,
    CommandCode,
    CommandFrameError,
    CommandResult,
    FrameDecoder,
    ParameterReport,
    StatusReport,
    _codec,
    decode_command,
    encode_ack,
    encode_command,
    encode_param_info,
    encode_parameters,
    encode_status,
    frame_ids,
    parameter_name,
    parse_effect,
)
from canrls.core.effect_names import EffectId, EquationId
from canrls.core.errors import CommandError

REPO_DBC = Path(__file__).resolve().parents[2] / "dbc" / "canrls.dbc"
#: the frame IDs, read from the DBC (tests/can/test_dbc.py pins them to docs/protocol.md)
IDS = frame_ids()


@pytest.fixture(scope="module")
def db() -> cantools.database.can.Database:
    """The repository's DBC, loaded by cantools independently of canrls."""
    return cantools.database.load_file(str(REPO_DBC))


def f32(x: float) -> float:
    return float(np.float32(x))


def test_enums_match_the_dbc_value_tables(db) -> None:
    def table(msg: str, sig: str) -> dict[int, str]:
        return {int(k): str(v) for k, v in
                db.get_message_by_name(msg).get_signal_by_name(sig).choices.items()}

    effects = {int(e): e.effect_name for e in EffectId}
    assert table("RlsParamInfo", "EffectId") == effects
    assert table("RlsCommand", "EffectId") == effects
    assert table("RlsCommand", "Command") == {int(c): c.name.lower() for c in CommandCode}
    assert table("RlsCommandAck", "Command") == {int(c): c.name.lower() for c in CommandCode}
    assert table("RlsCommandAck", "Result") == {int(c): c.name.lower() for c in CommandResult}
    assert table("RlsParamInfo", "Equation") == {int(e): e.name.lower() for e in EquationId}
    assert (EffectId.INERTIA, EffectId.ELECTRICAL, EffectId.USER) == (1, 8, 9)


def test_parameter_names() -> None:
    assert parameter_name(EffectId.INERTIA, 0) == "inertia.J"
    assert parameter_name(EffectId.ELECTRICAL, 2) == "electrical.Ke"
    assert parameter_name(EffectId.COGGING, 0, 24) == "cogging:24.sin"
    assert parameter_name(EffectId.UNBALANCE, 1) == "unbalance.cos"
    assert parameter_name(EffectId.USER, 0, 2, ["a", "gear"]) == "user:gear.c"
    assert parameter_name(EffectId.USER, 0, 3) == "user:3.c"
    assert set(COMPONENTS) == {e for e in EffectId if e}


def test_parse_effect() -> None:
    assert parse_effect("viscous") == (EffectId.VISCOUS, 0)
    assert parse_effect("cogging:24") == (EffectId.COGGING, 24)
    with pytest.raises(CommandFrameError) as e:
        parse_effect("cogging")
    assert e.value.result is CommandResult.BAD_VALUE
    with pytest.raises(CommandFrameError) as e:
        parse_effect("gravity")
    assert e.value.result is CommandResult.UNKNOWN_EFFECT
    with pytest.raises(CommandError):
        parse_effect("inertia:2")


REPORTS = [
    ParameterReport(0, "inertia.J", EffectId.INERTIA, 0, 0, EquationId.MECHANICAL,
                    1.25e-3, 2e-6, 1.2501e-3, "kg·m²"),
    ParameterReport(1, "cogging:24.sin", EffectId.COGGING, 0, 24, EquationId.MECHANICAL,
                    -0.03, 1e-4, -0.0301, "N·m"),
    ParameterReport(2, "electrical.Ke", EffectId.ELECTRICAL, 2, 0, EquationId.ELECTRICAL,
                    0.12, None, 0.1201, "V·s/rad"),
]


def test_parameter_frames_round_trip(db) -> None:
    msgs = encode_parameters(REPORTS, counter=21) + encode_param_info(REPORTS)
    assert [m.arbitration_id for m in msgs] == (
        [IDS.estimate, IDS.sigma, IDS.reference] * 3 + [IDS.param_info] * 3)
    for m in msgs:  # cantools decodes every frame we produce
        d = db.decode_message(m.arbitration_id, m.data)
        if "Counter" in d:
            assert d["Counter"] == 21 % 16
        assert m.dlc == 8 and not m.is_extended_id
    fd = FrameDecoder(units={r.name: r.unit for r in REPORTS})
    fd.feed_all(msgs)
    assert fd.count == 3
    for got, want in zip(fd.table(), REPORTS, strict=True):
        assert got == ParameterReport(
            want.index, want.name, want.effect_id, want.component, want.order, want.equation,
            f32(want.fixed_value), None if want.sigma is None else f32(want.sigma),
            f32(want.float_value), want.unit)


def test_invalid_estimates() -> None:
    r = [ParameterReport(4, fixed_value=math.nan, sigma=math.inf, float_value=1e39),
         ParameterReport(5, fixed_value=2.0, valid=False)]
    fd = FrameDecoder()
    fd.feed_all(encode_parameters(r, 0))
    a, b = fd.table()
    assert a.fixed_value is None and not a.valid
    assert a.sigma == f32(3.4e38) and a.float_value == f32(3.4e38)  # saturated
    assert b.fixed_value is None and not b.valid
    with pytest.raises(EncodeError, match="index 256 outside 0..255"):
        encode_parameters([ParameterReport(256, fixed_value=1.0)], 0)


@settings(max_examples=100, deadline=None)
@given(st.builds(
    StatusReport,
    residual_rms=st.floats(0, 2.0**100, width=32), update_count=st.integers(0, 2**40),
    windup=st.booleans(), low_excitation=st.booleans(), saturation=st.booleans(),
    frame_loss=st.booleans(), frozen=st.booleans(), diverged=st.booleans(),
    bus_fault=st.booleans(), clock_fault=st.booleans(), active_effects=st.integers(0, 511),
    divergence=st.floats(0, 2.0**20, width=32), frames_rejected=st.integers(0, 10**6),
    frames_lost=st.integers(0, 10**6), saturations=st.integers(0, 10**6),
    tx_dropped=st.integers(0, 10**6),
    rejects=st.fixed_dictionaries({k: st.integers(0, 10**6) for k in REJECT_FIELDS})),
    st.integers(0, 1000))
def test_status_round_trip(db: cantools.database.can.Database, status: StatusReport,
                           counter: int) -> None:
    msgs = encode_status(status, counter)
    assert [m.arbitration_id for m in msgs] == [IDS.status, IDS.health, IDS.counters,
                                                IDS.rejects]
    for m in msgs:
        db.decode_message(m.arbitration_id, m.data)
    assert db.decode_message(IDS.health, msgs[1].data)["Counter"] == counter % 16
    fd = FrameDecoder()
    fd.feed_all(msgs)
    s = fd.status
    assert s.update_count == status.update_count % 2**32
    for k in ("frames_rejected", "frames_lost", "saturations", "tx_dropped"):
        assert getattr(s, k) == getattr(status, k) % 65536
    for k in FLAG_NAMES:
        assert getattr(s, k) == getattr(status, k)
    assert s.rejects == {k: v % REJECT_WRAP[k] for k, v in status.rejects.items()}
    assert s.active_effects == status.active_effects
    assert s.residual_rms == status.residual_rms and s.divergence == status.divergence


def test_status_effect_mask() -> None:
    mask = StatusReport.effect_mask([EffectId.INERTIA, EffectId.COGGING, EffectId.USER])
    assert mask == 0b1_0100_0001
    s = StatusReport(active_effects=mask, frozen=True, frame_loss=True)
    assert s.effects() == {EffectId.INERTIA, EffectId.COGGING, EffectId.USER}
    assert s.flags == ("frame_loss", "frozen")


# ---------------------------------------------------------------------------
# Commands
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("cmd", [
    Command(CommandCode.RESET), Command(CommandCode.FREEZE), Command(CommandCode.RESUME),
    Command(CommandCode.ADD_EFFECT, EffectId.COGGING, 24),
    Command(CommandCode.REMOVE_EFFECT, EffectId.VISCOUS),
    Command(CommandCode.ADD_EFFECT, EffectId.USER, 2),
    Command(CommandCode.SET_LAMBDA, lam=f32(0.999)), Command(CommandCode.SET_LAMBDA, lam=1.0),
])
def test_command_round_trip(db, cmd: Command) -> None:
    m = encode_command(cmd)
    assert m.arbitration_id == IDS.command
    d = db.decode_message(m.arbitration_id, m.data, decode_choices=True)
    assert str(d["Command"]) == cmd.code.name.lower()
    assert decode_command(m) == cmd
    assert FrameDecoder().feed(m) == cmd


def test_command_str() -> None:
    assert str(Command(CommandCode.ADD_EFFECT, EffectId.COGGING, 24)) == "add_effect cogging:24"
    assert str(Command(CommandCode.SET_LAMBDA, lam=0.5)) == "set_lambda 0.5"


def raw_command(code: int, effect: int = 0, order: int = 0, lam: float = 0.0,
                dlc: int = 8) -> can.Message:
    data = bytes([code, effect]) + order.to_bytes(2, "little") + np.float32(lam).tobytes()
    return can.Message(arbitration_id=IDS.command, is_extended_id=False, data=data[:dlc], dlc=dlc)


@pytest.mark.parametrize("msg, result, match", [
    (raw_command(9), CommandResult.UNKNOWN_COMMAND, "unknown command code 9"),
    (raw_command(0), CommandResult.UNKNOWN_COMMAND, "unknown command code 0"),
    (raw_command(1, dlc=6), CommandResult.MALFORMED, "DLC 6, expected 8"),
    (raw_command(6, lam=0.0), CommandResult.BAD_VALUE, r"lambda = 0\.0: must be in \(0\.5, 1\]"),
    (raw_command(6, lam=0.25), CommandResult.BAD_VALUE, r"lambda = 0\.25: must be in"),
    (raw_command(6, lam=1.5), CommandResult.BAD_VALUE, "lambda = 1.5"),
    (raw_command(6, lam=-0.5), CommandResult.BAD_VALUE, "lambda = -0.5"),
    (raw_command(6, lam=math.nan), CommandResult.BAD_VALUE, "lambda = nan"),
    (raw_command(4, effect=0), CommandResult.UNKNOWN_EFFECT, "unknown effect id 0"),
    (raw_command(5, effect=10), CommandResult.UNKNOWN_EFFECT, "unknown effect id 10"),
    (raw_command(4, effect=7), CommandResult.BAD_VALUE, "cogging needs an order"),
    (raw_command(4, effect=1, order=3), CommandResult.BAD_VALUE, "order 3, inertia takes none"),
    (can.Message(arbitration_id=IDS.ack, data=bytes(8)), CommandResult.MALFORMED,
     "not RlsCommand"),
    (can.Message(arbitration_id=IDS.command, is_extended_id=True, data=bytes(8)),
     CommandResult.MALFORMED, "not RlsCommand"),
    (can.Message(arbitration_id=IDS.command, is_extended_id=False, is_remote_frame=True, dlc=8),
     CommandResult.MALFORMED, "remote"),
])
def test_decode_command_rejects(msg: can.Message, result: CommandResult, match: str) -> None:
    with pytest.raises(CommandError, match=match) as e:
        decode_command(msg)
    assert e.value.result is result
    assert isinstance(e.value, ValueError)
    fd = FrameDecoder()
    assert fd.feed(msg) is None
    assert fd.malformed + fd.ignored == 1


def test_rejected_command_keeps_code_for_the_ack() -> None:
    with pytest.raises(CommandFrameError) as e:
        decode_command(raw_command(9))
    ack = encode_ack(e.value.code, e.value.result, counter=18)
    fd = FrameDecoder()
    assert fd.feed(ack) == CommandAck(9, CommandResult.UNKNOWN_COMMAND, 2)
    assert fd.acks == [CommandAck(9, CommandResult.UNKNOWN_COMMAND, 2)]


def test_ack_round_trip(db) -> None:
    for res in CommandResult:
        m = encode_ack(CommandCode.SET_LAMBDA, res, counter=5)
        d = db.decode_message(m.arbitration_id, m.data, decode_choices=True)
        assert str(d["Result"]) == res.name.lower() and d["Counter"] == 5
        assert FrameDecoder().feed(m) == CommandAck(6, res, 5)


def test_frame_decoder_ignores_and_counts() -> None:
    fd = FrameDecoder()
    assert fd.feed(can.Message(arbitration_id=IDS.feedback[0], data=bytes(8))) is None
    assert fd.feed(can.Message(arbitration_id=IDS.estimate, is_extended_id=False,
                               data=bytes(3))) is None
    assert (fd.ignored, fd.malformed) == (1, 1)


def test_encode_out_of_range_names_frame() -> None:
    with pytest.raises(EncodeError, match="RlsCommand"):
        encode_command(CommandCode.SET_LAMBDA, lam=2.0)


# ---------------------------------------------------------------------------
# Compiled encoders: byte for byte what cantools' strict encode gives
# ---------------------------------------------------------------------------

F32_MAX = 3.4e38
MESSAGES = [m.name for m in cantools.database.load_file(str(REPO_DBC)).messages]
HYPOTHESIS = settings(max_examples=200, deadline=None, derandomize=True, database=None)


def cantools_encode(msg: Any, values: dict[str, Any]) -> bytes | None:
    """``Message.encode(values, scaling=True, strict=True)``; None where it refuses them."""
    try:
        return bytes(msg.encode(values, scaling=True, strict=True))
    except (cantools.database.EncodeError, OverflowError, ValueError):
        return None


def f32_of_bits(bits: int) -> float:
    return float(struct.unpack("<f", struct.pack("<I", bits))[0])


def identity(s: Any) -> bool:
    return s.conversion.scale == 1 and s.conversion.offset == 0


def signal_values(s: Any) -> st.SearchStrategy[Any]:
    """Values of signal ``s``: inside its range, its limits, beyond them, NaN and inf."""
    lo, hi = s.minimum, s.maximum
    special = [math.nan, -math.nan, math.inf, -math.inf]
    if s.is_float:
        return st.one_of(st.floats(lo, hi),
                         st.sampled_from([float(lo), float(hi), -0.0, *special]),
                         st.integers(0, 2**32 - 1).map(f32_of_bits),  # every float32, NaN payloads
                         st.floats())
    if identity(s):
        return st.one_of(st.integers(lo, hi), st.sampled_from([lo, hi]),
                         st.integers(lo - 2, hi + 2), st.sampled_from(special))
    return st.one_of(st.floats(lo, hi), st.sampled_from([float(lo), float(hi), *special]),
                     st.floats(lo - 1.0, hi + 1.0))


def natural(s: Any, v: Any) -> bool:
    """Whether ``v`` has the type the fast path takes for ``s``."""
    if s.is_float:
        return type(v) is float
    return type(v) is int or not identity(s) and type(v) is float


def first_refused(msg: Any, values: dict[str, Any]) -> Any:
    """The first signal (in message order) whose value cantools refuses on its own."""
    ok = {s.name: float(s.minimum) if s.is_float or not identity(s) else s.minimum
          for s in msg.signals}
    return next(s for s in msg.signals
                if cantools_encode(msg, {**ok, s.name: values[s.name]}) is None)


def test_every_shipped_message_takes_the_fast_path() -> None:
    assert len(MESSAGES) == 12
    assert all(_codec(None, name).fast for name in MESSAGES)


@pytest.mark.parametrize("name", MESSAGES)
@HYPOTHESIS
@given(data=st.data())
def test_codec_encodes_like_cantools(db, name: str, data: st.DataObject) -> None:
    msg = db.get_message_by_name(name)
    codec = _codec(None, name)
    values = {s.name: data.draw(signal_values(s), label=s.name) for s in msg.signals}
    want = cantools_encode(msg, values)
    if want is not None:
        assert codec.encode(values) == want
        if all(natural(s, values[s.name]) for s in msg.signals):
            assert codec._pack(values) == want  # the fast path itself, not the fallback
        return
    with pytest.raises(EncodeError) as e:
        codec.encode(values)
    bad = first_refused(msg, values)
    v = values[bad.name]
    assert f"cannot encode {name}.{bad.name} = {v!r}: " in str(e.value)
    nan = not bad.is_float and isinstance(v, float) and not math.isfinite(v)
    assert e.value.reason == ("nan" if nan else "range")


def test_codec_errors_name_signal_value_and_limits() -> None:
    sigma = _codec(None, "RlsSigma")
    with pytest.raises(EncodeError, match=r"RlsSigma\.Sigma = -1\.0: outside \[0, 3\.4e\+38\]"):
        sigma.encode({"Index": 1, "Counter": 0, "Sigma": -1.0})
    with pytest.raises(EncodeError, match=r"RlsSigma\.Index = 256: outside \[0, 255\]") as e:
        sigma.encode({"Index": 256, "Counter": 0, "Sigma": 1.0})
    assert e.value.reason == "range"
    with pytest.raises(EncodeError, match=r"RlsSigma\.Counter = nan: .*finite") as e:
        sigma.encode({"Index": 1, "Counter": math.nan, "Sigma": 1.0})
    assert e.value.reason == "nan"
    with pytest.raises(EncodeError, match=r"RlsCommand\.Lambda = 2\.0: outside \[0, 1\]"):
        encode_command(CommandCode.SET_LAMBDA, lam=2.0)


def test_codec_takes_what_cantools_takes(db) -> None:
    """Other value types go through cantools: same bytes, or its error as an EncodeError."""
    for name, values in [
        ("RlsEstimate", {"Index": 7, "Counter": True, "Valid": True, "FixedValue": 3}),
        ("RlsCommand", {"Command": "set_lambda", "EffectId": "cogging", "Order": 24.0,
                        "Lambda": np.float64(0.5)}),
        ("RlsCommandAck", {"Command": 2.4, "Result": 2.6, "Counter": 3.5}),
    ]:
        want = cantools_encode(db.get_message_by_name(name), values)
        assert want is not None and _codec(None, name).encode(values) == want
    ack = _codec(None, "RlsCommandAck")
    with pytest.raises(EncodeError, match="RlsCommandAck.*Counter.*required"):
        ack.encode({"Command": 1, "Result": 0})
    with pytest.raises(EncodeError, match="RlsCommandAck.*Counter.*required"):
        ack.encode({"Command": 1, "Result": 0, "Extra": 1})  # as many signals, one wrong
    with pytest.raises(EncodeError, match="RlsCommandAck.*Extra"):
        ack.encode({"Command": 1, "Result": 0, "Counter": 1, "Extra": 1})
    with pytest.raises(EncodeError, match="RlsCommandAck"):
        ack.encode({"Command": "no such command", "Result": 0, "Counter": 1})


def test_frames_are_the_messages_python_can_would_build() -> None:
    (m,) = [encode_ack(3, CommandResult.OK, 1, timestamp=12.5)]
    want = can.Message(arbitration_id=IDS.ack, is_extended_id=False, data=bytes(m.data), dlc=8,
                       timestamp=12.5)
    for a in can.Message.__slots__:
        if a != "__weakref__":
            assert getattr(m, a) == getattr(want, a), a
    assert type(m.data) is bytearray


ESTIMATES = st.one_of(st.none(), st.floats(), st.sampled_from(
    [0.0, -0.0, math.nan, -math.nan, math.inf, -math.inf, 1e39, -1e39, F32_MAX, -F32_MAX,
     3.5e38, 1e-45]))


def reference_parameters(db, reports: list[ParameterReport], counter: int
                         ) -> list[tuple[int, bytes]]:
    """What encode_parameters sends, spelled out with cantools' strict encode."""
    def f32(x: float | None, lo: float, hi: float) -> float:
        return math.nan if x is None else min(max(float(x), lo), hi)  # NaN stays NaN

    out = []
    for r in reports:
        c = counter % 16
        valid = r.valid and r.fixed_value is not None and not math.isnan(r.fixed_value)
        for name, values in [
            ("RlsEstimate", {"Index": r.index, "Counter": c, "Valid": int(valid),
                             "FixedValue": f32(r.fixed_value, -F32_MAX, F32_MAX) if valid
                             else 0.0}),
            ("RlsSigma", {"Index": r.index, "Counter": c, "Sigma": f32(r.sigma, 0.0, F32_MAX)}),
            ("RlsReference", {"Index": r.index, "Counter": c,
                              "FloatValue": f32(r.float_value, -F32_MAX, F32_MAX)})]:
            m = db.get_message_by_name(name)
            out.append((m.frame_id, bytes(m.encode(values, scaling=True, strict=True))))
    return out


@HYPOTHESIS
@given(st.lists(st.builds(ParameterReport, index=st.integers(0, 255), fixed_value=ESTIMATES,
                          sigma=ESTIMATES, float_value=ESTIMATES, valid=st.booleans()),
                max_size=10),
       st.integers(0, 10**6))
def test_parameter_frames_are_cantools_bytes(db, reports: list[ParameterReport],
                                             counter: int) -> None:
    """Saturation (inf, beyond float32, negative sigma), NaN, None and Valid: same bytes."""
    msgs = encode_parameters(reports, counter, timestamp=3.0)
    assert [(m.arbitration_id, bytes(m.data)) for m in msgs] == \
        reference_parameters(db, reports, counter)
    assert all(m.dlc == 8 and not m.is_extended_id and m.timestamp == 3.0 for m in msgs)


def test_saturated_and_nan_estimates_on_the_wire() -> None:
    r = ParameterReport(9, fixed_value=math.inf, sigma=-1.0, float_value=-math.nan)
    est, sig, ref = (bytes(m.data) for m in encode_parameters([r], 2))
    assert est == bytes([9, 0x12, 0, 0]) + struct.pack("<f", F32_MAX)
    assert sig == bytes([9, 2, 0, 0]) + struct.pack("<f", 0.0)
    assert ref == bytes([9, 2, 0, 0]) + struct.pack("<f", -math.nan)
    r = ParameterReport(9, fixed_value=math.nan, sigma=-0.0, float_value=-1e39)
    est, sig, ref = (bytes(m.data) for m in encode_parameters([r], 2))
    assert est == bytes([9, 2]) + bytes(6)  # Valid = 0, value 0
    assert sig[4:] == struct.pack("<f", -0.0) and ref[4:] == struct.pack("<f", -F32_MAX)


@HYPOTHESIS
@given(st.builds(
    StatusReport, residual_rms=ESTIMATES.filter(lambda x: x is not None),
    update_count=st.integers(0, 2**70), windup=st.booleans(), low_excitation=st.booleans(),
    saturation=st.booleans(), frame_loss=st.booleans(), frozen=st.booleans(),
    diverged=st.booleans(), bus_fault=st.booleans(), clock_fault=st.booleans(),
    implausible=st.booleans(), active_effects=st.integers(0, 2**20),
    divergence=ESTIMATES.filter(lambda x: x is not None),
    frames_rejected=st.integers(0, 2**40), frames_lost=st.integers(0, 2**40),
    saturations=st.integers(0, 2**40), tx_dropped=st.integers(0, 2**40),
    rejects=st.fixed_dictionaries({k: st.integers(0, 2**40) for k in REJECT_FIELDS})),
    st.integers(0, 10**6))
def test_status_frames_are_cantools_bytes(db, status: StatusReport, counter: int) -> None:
    def f32(x: float) -> float:
        return min(max(x, 0.0), F32_MAX)

    s = status
    health = {sig: int(getattr(s, f)) for f, sig in zip(FLAG_NAMES, (
        "Windup", "LowExcitation", "Saturation", "FrameLoss", "Frozen", "Diverged", "BusFault",
        "ClockFault", "Implausible"), strict=True)}
    want = [("RlsStatus", {"ResidualRms": f32(s.residual_rms),
                           "UpdateCount": s.update_count % 2**32}),
            ("RlsHealth", {**health, "Counter": counter % 16,
                           "TimeRejects": s.rejects["time"] % 8,
                           "ActiveEffects": s.active_effects % 2**16,
                           "Divergence": f32(s.divergence)}),
            ("RlsCounters", {"FramesRejected": s.frames_rejected % 2**16,
                             "FramesLost": s.frames_lost % 2**16,
                             "Saturations": s.saturations % 2**16,
                             "TxDropped": s.tx_dropped % 2**16}),
            ("RlsRejects", {sig: s.rejects[k] % REJECT_WRAP[k] for k, sig in zip(
                REJECT_FIELDS[:-1], ("Crc", "Malformed", "Repeated", "Stale", "Range",
                                     "Unpaired", "Reordered", "ClockSteps", "Gaps"),
                strict=True)})]
    got = encode_status(status, counter)
    assert [bytes(m.data) for m in got] == [
        bytes(db.get_message_by_name(n).encode(v, scaling=True, strict=True)) for n, v in want]


@HYPOTHESIS
@given(st.lists(st.builds(ParameterReport, index=st.integers(0, 255),
                          effect_id=st.sampled_from(EffectId), component=st.integers(0, 255),
                          order=st.integers(0, 65535), equation=st.sampled_from(EquationId)),
                max_size=5),
       st.integers(0, 600), st.sampled_from(CommandResult), st.integers(0, 10**6),
       st.sampled_from(CommandCode), st.sampled_from(EffectId), st.integers(0, 65535),
       st.one_of(st.floats(0.0, 1.0), st.floats(), st.sampled_from([0.0, 1.0, -0.0])))
def test_info_ack_and_command_frames_are_cantools_bytes(
        db, reports: list[ParameterReport], code: int, result: CommandResult, counter: int,
        command: CommandCode, effect: EffectId, order: int, lam: float) -> None:
    def enc(name: str, values: dict[str, Any]) -> bytes | None:
        return cantools_encode(db.get_message_by_name(name), values)

    assert [bytes(m.data) for m in encode_param_info(reports)] == [
        enc("RlsParamInfo", {"Index": r.index, "Count": len(reports),
                             "EffectId": int(r.effect_id), "Component": r.component,
                             "Order": r.order, "Equation": int(r.equation)})
        for r in reports]
    assert bytes(encode_ack(code, result, counter).data) == enc(
        "RlsCommandAck", {"Command": code & 0xFF, "Result": int(result),
                          "Counter": counter % 16})
    want = enc("RlsCommand", {"Command": int(command), "EffectId": int(effect), "Order": order,
                              "Lambda": lam})
    if want is None:  # lambda outside [0, 1] or NaN... no: NaN passes cantools' range check
        with pytest.raises(EncodeError, match=r"RlsCommand\.Lambda"):
            encode_command(command, effect, order, lam)
    else:
        assert bytes(encode_command(command, effect, order, lam).data) == want


USER_DBC = """VERSION ""

NS_ :

BS_:

BU_: Canrls Tool

BO_ 801 RlsCommandAck: 8 Canrls
 SG_ Command : 7|8@0+ (1,0) [0|255] "" Tool
 SG_ Result : 15|8@0+ (1,0) [0|255] "" Tool
 SG_ Counter : 19|4@0+ (1,0) [0|15] "" Tool

BO_ 16 Mixed: 8 Tool
 SG_ Speed : 7|16@0- (0.5,-10) [-1000|1000] "rad/s" Canrls
 SG_ Mode : 16|8@1+ (1,0) [0|10] "" Canrls
 SG_ Gain : 32|32@1- (1,0) [-10|10] "" Canrls

BO_ 17 Muxed: 8 Tool
 SG_ Sel M : 0|8@1+ (1,0) [0|3] "" Canrls
 SG_ A m0 : 8|16@1+ (1,0) [0|1000] "" Canrls
 SG_ B m1 : 8|8@1- (1,0) [-100|100] "" Canrls

BO_ 18 Modes: 2 Tool
 SG_ Mode : 0|8@1+ (1,0) [0|10] "" Canrls
 SG_ Wide : 8|8@1+ (1,0) [0|1000] "" Canrls

SIG_VALTYPE_ 16 Gain : 1;
VAL_ 16 Mode 200 "special" ;
VAL_ 18 Mode 200 "special" ;
"""


@pytest.fixture
def user_dbc(tmp_path: Path) -> Path:
    path = tmp_path / "user.dbc"
    path.write_text(USER_DBC)
    return path


def test_big_endian_and_multiplexed_messages_fall_back_to_cantools(user_dbc: Path) -> None:
    db = cantools.database.load_file(str(user_dbc))
    codecs = {m.name: _codec(user_dbc, m.name) for m in db.messages}
    assert {n: c.fast for n, c in codecs.items()} == {
        "RlsCommandAck": False, "Mixed": False, "Muxed": True, "Modes": True}
    # the public encoders work with a user DBC whose RlsCommandAck is big-endian
    m = encode_ack(CommandCode.SET_LAMBDA, CommandResult.BAD_VALUE, 21, dbc=user_dbc)
    assert bytes(m.data) == db.get_message_by_name("RlsCommandAck").encode(
        {"Command": 6, "Result": 5, "Counter": 5}, scaling=True, strict=True)
    assert m.data[0] == 6 and m.data[1] == 5  # Motorola: MSB first
    rng = np.random.default_rng(7)
    mixed = db.get_message_by_name("Mixed")
    for _ in range(500):
        values = {"Speed": float(rng.uniform(-1010, 1010)), "Mode": int(rng.integers(0, 12)),
                  "Gain": float(rng.uniform(-11, 11))}
        want = cantools_encode(mixed, values)
        if want is None:
            with pytest.raises(EncodeError, match=r"Mixed\.(Speed|Mode|Gain) = "):
                codecs["Mixed"].encode(values)
        else:
            assert codecs["Mixed"].encode(values) == want
    for values in ({"Sel": 0, "A": 999}, {"Sel": 1, "B": -100}, {"Sel": 1, "B": 7}):
        want = cantools_encode(db.get_message_by_name("Muxed"), values)
        assert codecs["Muxed"].encode(values) == codecs["Muxed"]._pack(values) == want
    for values in ({"Sel": 0, "A": 1, "B": 1}, {"Sel": 1}, {"Sel": 0, "B": 1}):
        assert codecs["Muxed"]._pack(values) is None  # the signals of another value
    with pytest.raises(EncodeError, match="cannot encode Muxed.*multiplexer"):
        codecs["Muxed"].encode({"Sel": 2, "A": 1})  # within Sel's range, but no signals
    with pytest.raises(EncodeError, match=r"Muxed\.B = 101: outside \[-100, 100\]"):
        codecs["Muxed"].encode({"Sel": 1, "B": 101})
    with pytest.raises(EncodeError, match="cannot encode Muxed"):
        codecs["Muxed"].encode({"Sel": 0, "B": 1})


def test_value_table_and_bit_field_beyond_the_range(user_dbc: Path) -> None:
    db = cantools.database.load_file(str(user_dbc))
    modes, msg = _codec(user_dbc, "Modes"), db.get_message_by_name("Modes")
    # a value of the value table outside [minimum, maximum]: cantools takes it, so do we
    assert modes.encode({"Mode": 200, "Wide": 3}) == msg.encode({"Mode": 200, "Wide": 3}) \
        == bytes([200, 3])
    assert modes._pack({"Mode": 200, "Wide": 3}) is None  # through the careful path
    with pytest.raises(EncodeError, match=r"Modes\.Mode = 11: outside \[0, 10\]"):
        modes.encode({"Mode": 11, "Wide": 0})
    # within the DBC range but not the 8-bit field: cantools fails with an OverflowError
    with pytest.raises(OverflowError):
        msg.encode({"Mode": 0, "Wide": 300}, scaling=True, strict=True)
    with pytest.raises(EncodeError, match=r"Modes\.Wide = 300: raw value 300 does not fit "
                                          r"the 8-bit field \(0 \.\. 255\)"):
        modes.encode({"Mode": 0, "Wide": 300})


def test_with_estimates_is_replace() -> None:
    blank = ParameterReport(3, "cogging:24.sin", EffectId.COGGING, 0, 24, EquationId.MECHANICAL,
                            unit="N·m")
    r = blank.with_estimates(1.5, None, -2.0, False)
    want = dataclasses.replace(blank, fixed_value=1.5, sigma=None, float_value=-2.0,
                               valid=False)
    assert r == want and hash(r) == hash(want) and repr(r) == repr(want)
    assert blank.fixed_value is None and blank.valid  # unchanged
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.sigma = 1.0  # type: ignore[misc]
