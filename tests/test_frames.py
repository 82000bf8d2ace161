"""canrls.frames: estimator, status and command frames through cantools."""

from __future__ import annotations

import math
from pathlib import Path

import can
import cantools
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canrls.errors import CommandError
from canrls.frames import (
    COMPONENTS,
    FLAG_NAMES,
    Command,
    CommandAck,
    CommandCode,
    CommandFrameError,
    CommandResult,
    EffectId,
    Equation,
    FrameDecoder,
    ParameterReport,
    StatusReport,
    decode_command,
    encode_ack,
    encode_command,
    encode_param_info,
    encode_parameters,
    encode_status,
    parameter_name,
    parse_effect,
)
from canrls.protocol import EncodeError

REPO_DBC = Path(__file__).resolve().parent.parent / "dbc" / "canrls.dbc"


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
    assert table("RlsParamInfo", "Equation") == {int(e): e.name.lower() for e in Equation}
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
    ParameterReport(0, "inertia.J", EffectId.INERTIA, 0, 0, Equation.MECHANICAL,
                    1.25e-3, 2e-6, 1.2501e-3, "kg·m²"),
    ParameterReport(1, "cogging:24.sin", EffectId.COGGING, 0, 24, Equation.MECHANICAL,
                    -0.03, 1e-4, -0.0301, "N·m"),
    ParameterReport(2, "electrical.Ke", EffectId.ELECTRICAL, 2, 0, Equation.ELECTRICAL,
                    0.12, None, 0.1201, "V·s/rad"),
]


def test_parameter_frames_round_trip(db) -> None:
    msgs = encode_parameters(REPORTS, counter=21) + encode_param_info(REPORTS)
    assert [m.arbitration_id for m in msgs] == [0x300, 0x301, 0x302] * 3 + [0x303] * 3
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
    bus_fault=st.booleans(), active_effects=st.integers(0, 511),
    divergence=st.floats(0, 2.0**20, width=32), frames_rejected=st.integers(0, 10**6),
    frames_lost=st.integers(0, 10**6), saturations=st.integers(0, 10**6),
    tx_dropped=st.integers(0, 10**6)), st.integers(0, 1000))
def test_status_round_trip(status: StatusReport, counter: int) -> None:
    msgs = encode_status(status, counter)
    assert [m.arbitration_id for m in msgs] == [0x310, 0x311, 0x312]
    db = cantools.database.load_file(str(REPO_DBC))
    for m in msgs:
        db.decode_message(m.arbitration_id, m.data)
    assert db.decode_message(0x311, msgs[1].data)["Counter"] == counter % 16
    fd = FrameDecoder()
    fd.feed_all(msgs)
    s = fd.status
    assert s.update_count == status.update_count % 2**32
    for k in ("frames_rejected", "frames_lost", "saturations", "tx_dropped"):
        assert getattr(s, k) == getattr(status, k) % 65536
    for k in FLAG_NAMES:
        assert getattr(s, k) == getattr(status, k)
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
    assert m.arbitration_id == 0x320
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
    return can.Message(arbitration_id=0x320, is_extended_id=False, data=data[:dlc], dlc=dlc)


@pytest.mark.parametrize("msg, result, match", [
    (raw_command(9), CommandResult.UNKNOWN_COMMAND, "unknown command code 9"),
    (raw_command(0), CommandResult.UNKNOWN_COMMAND, "unknown command code 0"),
    (raw_command(1, dlc=6), CommandResult.MALFORMED, "DLC 6, expected 8"),
    (raw_command(6, lam=0.0), CommandResult.BAD_VALUE, r"lambda = 0\.0 outside \(0, 1\]"),
    (raw_command(6, lam=1.5), CommandResult.BAD_VALUE, "lambda = 1.5"),
    (raw_command(6, lam=-0.5), CommandResult.BAD_VALUE, "lambda = -0.5"),
    (raw_command(6, lam=math.nan), CommandResult.BAD_VALUE, "lambda = nan"),
    (raw_command(4, effect=0), CommandResult.UNKNOWN_EFFECT, "unknown effect id 0"),
    (raw_command(5, effect=10), CommandResult.UNKNOWN_EFFECT, "unknown effect id 10"),
    (raw_command(4, effect=7), CommandResult.BAD_VALUE, "cogging needs an order"),
    (raw_command(4, effect=1, order=3), CommandResult.BAD_VALUE, "order 3, inertia takes none"),
    (can.Message(arbitration_id=0x321, data=bytes(8)), CommandResult.MALFORMED,
     "not RlsCommand"),
    (can.Message(arbitration_id=0x320, is_extended_id=True, data=bytes(8)),
     CommandResult.MALFORMED, "not RlsCommand"),
    (can.Message(arbitration_id=0x320, is_extended_id=False, is_remote_frame=True, dlc=8),
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
    assert fd.feed(can.Message(arbitration_id=0x101, data=bytes(8))) is None
    assert fd.feed(can.Message(arbitration_id=0x300, is_extended_id=False, data=bytes(3))) is None
    assert (fd.ignored, fd.malformed) == (1, 1)


def test_encode_out_of_range_names_frame() -> None:
    with pytest.raises(EncodeError, match="RlsCommand"):
        encode_command(CommandCode.SET_LAMBDA, lam=2.0)
