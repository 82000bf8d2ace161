"""canrls.can: the mapping, the codec against cantools, strict decoding, FeedbackEncoder."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import cantools
import numpy as np
import pytest
from cantools.database.can import Message, Signal
from cantools.database.conversion import BaseConversion
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from canrls.can.codec import EncodeError, SignalCodec
from canrls.can.decoder import REJECT_REASONS, DecodedFrames, Decoder, MessageFrames
from canrls.can.e2e import e2e_crc
from canrls.can.encoder import FeedbackEncoder
from canrls.can.frameblock import FrameBlock
from canrls.can.mapping import SignalMapping
from canrls.can.protocol import DEFAULT_DBC, Protocol
from canrls.core.errors import ConfigError, DecodeError, SignalError
from canrls.sim.faults import inject

DATA = Path(__file__).resolve().parents[1] / "data"
USER_DBC = DATA / "proto_user.dbc"


@pytest.fixture(scope="module")
def proto() -> Protocol:
    return Protocol.load()


@pytest.fixture(scope="module")
def cdb() -> cantools.database.can.Database:
    return cantools.database.load_file(str(DEFAULT_DBC))


def cantools_frame(msg: Message, values: dict[str, float], counter: int) -> bytes:
    """Reference encoding of a protected feedback frame: cantools encode + e2e_crc."""
    payload = bytearray(msg.encode(dict(values, Counter=counter, CRC=0), strict=True))
    payload[0] = e2e_crc(msg.frame_id, payload)
    return bytes(payload)


def feedback(n: int, seed: int = 0, t0: float = 0.0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(n) * 1e-3
    return (t, rng.uniform(-800, 800, n), rng.uniform(-800, 800, n),
            rng.uniform(0, 2 * np.pi, n), rng.uniform(-320, 320, n))


# ---------------------------------------------------------------------------
# FeedbackEncoder
# ---------------------------------------------------------------------------


class TestFeedbackEncoder:
    def test_layout_interleaved_current_first(self, proto: Protocol) -> None:
        t, i, w, th, u = feedback(5)
        b = FeedbackEncoder(proto).encode(t, i, w, th, u)
        assert len(b) == 10
        assert b.arbitration_id.tolist() == [0x101, 0x102] * 5
        assert b.dlc.tolist() == [8] * 10
        assert np.array_equal(b.t, np.repeat(t, 2))
        assert not b.is_error.any() and not b.is_remote.any() and not b.is_extended.any()
        counters = b.data[:, 1] & 0x0F
        assert counters.tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]

    def test_equals_cantools_encode_and_e2e_crc(self, proto: Protocol, cdb) -> None:
        mc, ms = cdb.get_message_by_name("DriveCurrent"), cdb.get_message_by_name("DriveSpeed")
        t, i, w, th, u = feedback(300, seed=1)
        enc = FeedbackEncoder(proto, counter=11)
        b = enc.encode(t, i, w, th, u)
        for k in range(300):
            c = (11 + k) % 16
            assert b.data[2 * k, :8].tobytes() == cantools_frame(
                mc, {"Current": i[k], "Voltage": u[k]}, c)
            assert b.data[2 * k + 1, :8].tobytes() == cantools_frame(
                ms, {"Speed": w[k], "Position": th[k]}, c)
        assert enc.counter == 311

    @settings(max_examples=60, deadline=None)
    @given(st.lists(st.tuples(st.integers(-8_000_000, 8_000_000), st.integers(-32000, 32000),
                              st.integers(-8_000_000, 8_000_000), st.integers(0, 65535),
                              st.floats(-0.5, 0.5)),
                    min_size=1, max_size=20))
    def test_equals_cantools_on_raw_grid_and_ties(self, proto: Protocol, cdb, rows) -> None:
        """Values on and half-way between raw steps (ties round half to even, like cantools)."""
        mc, ms = cdb.get_message_by_name("DriveCurrent"), cdb.get_message_by_name("DriveSpeed")
        a = np.array(rows, dtype=np.float64)
        i, u, w = (a[:, 0] + a[:, 4]) * 1e-4, a[:, 1] * 0.01, (a[:, 2] - a[:, 4]) * 1e-4
        th = a[:, 3] * 9.587379924285257e-05
        i, w = np.clip(i, -800, 800), np.clip(w, -800, 800)
        b = FeedbackEncoder(proto).encode(np.zeros(len(a)), i, w, th, u)
        for k in range(len(a)):
            assert b.data[2 * k, :8].tobytes() == cantools_frame(
                mc, {"Current": float(i[k]), "Voltage": float(u[k])}, k % 16)
            assert b.data[2 * k + 1, :8].tobytes() == cantools_frame(
                ms, {"Speed": float(w[k]), "Position": float(th[k])}, k % 16)

    def test_cantools_decodes_every_frame(self, proto: Protocol, cdb) -> None:
        t, i, w, th, u = feedback(50, seed=2)
        for msg in FeedbackEncoder(proto).encode(t, i, w, th, u).to_messages():
            d = cdb.decode_message(msg.arbitration_id, msg.data)
            assert set(d) >= {"CRC", "Counter"}

    def test_counter_continues_across_calls(self, proto: Protocol) -> None:
        t, i, w, th, u = feedback(40, seed=3)
        whole = FeedbackEncoder(proto).encode(t, i, w, th, u)
        enc = FeedbackEncoder(proto)
        parts = FrameBlock.concat([enc.encode(t[a:b], i[a:b], w[a:b], th[a:b], u[a:b])
                                   for a, b in ((0, 7), (7, 8), (8, 40))])
        assert np.array_equal(whole.data, parts.data)
        assert np.array_equal(whole.t, parts.t)

    def test_out_of_range_names_signal_and_value(self, proto: Protocol) -> None:
        enc = FeedbackEncoder(proto)
        with pytest.raises(EncodeError, match=r"DriveCurrent\.Current = 900\.5 A.*\[-800, 800\]") \
                as e:
            enc.encode([0.0, 1e-3], [1.0, 900.5], [0.0, 0.0])
        assert e.value.reason == "range"
        assert isinstance(e.value, DecodeError)
        with pytest.raises(EncodeError, match=r"DriveSpeed\.Speed = nan") as e:
            enc.encode([0.0], [1.0], [math.nan])
        assert e.value.reason == "nan"
        assert enc.counter == 0  # nothing was sent

    def test_clip_counts(self, proto: Protocol) -> None:
        enc = FeedbackEncoder(proto, clip=True)
        b = enc.encode([0.0, 1e-3, 2e-3], [900.0, -1000.0, 1.0], [0.0, 0.0, 801.0],
                       voltage=[0.0, 400.0, 0.0])
        assert enc.clipped == {"DriveCurrent.Current": 2, "DriveSpeed.Speed": 1,
                               "DriveCurrent.Voltage": 1}
        dec = Decoder(proto).decode(b)
        assert dec.rejected.total == 0
        assert dec["DriveCurrent"].values["current"].tolist() == [800.0, -800.0, 1.0]
        assert dec["DriveSpeed"].values["speed"].tolist() == [0.0, 0.0, 800.0]

    def test_position_wraps_one_turn(self, proto: Protocol) -> None:
        enc = FeedbackEncoder(proto)
        assert enc.wrapping == {"position"}
        th = np.array([0.0, 2 * np.pi - 1e-9, 2 * np.pi + 1.0, -1.0, 1000.0])
        b = enc.encode(np.zeros(5), np.zeros(5), np.zeros(5), th)
        pos = Decoder(proto).decode(b)["DriveSpeed"].values["position"]
        lsb = 2 * np.pi / 65536
        assert np.all(np.abs(np.angle(np.exp(1j * (pos - th)))) <= lsb / 2 + 1e-12)
        assert np.all((pos >= 0) & (pos < 2 * np.pi))

    def test_missing_optional_role_is_raw_zero(self, proto: Protocol) -> None:
        b = FeedbackEncoder(proto).encode([0.0], [1.0], [2.0])
        d = Decoder(proto).decode(b)
        assert d["DriveSpeed"].values["position"].tolist() == [0.0]
        assert d["DriveCurrent"].values["voltage"].tolist() == [0.0]

    def test_length_mismatch(self, proto: Protocol) -> None:
        with pytest.raises(ValueError, match="speed has 1 samples, t has 2"):
            FeedbackEncoder(proto).encode([0.0, 1.0], [1.0, 2.0], [1.0])

    def test_stagger(self, proto: Protocol) -> None:
        b = FeedbackEncoder(proto, stagger=1e-4).encode([0.0, 1e-3], [0, 0], [0, 0])
        assert np.allclose(b.t, [0.0, 1e-4, 1e-3, 1.1e-3])

# ---------------------------------------------------------------------------
# Vectorised codec against cantools
# ---------------------------------------------------------------------------


@st.composite
def signal_layouts(draw: st.DrawFn) -> tuple[Message, Signal]:
    """A one-signal message with a random layout and conversion."""
    nbytes = draw(st.sampled_from([8, 8, 12, 16]))
    is_float = draw(st.booleans()) and draw(st.booleans())
    length = draw(st.sampled_from([32, 64])) if is_float else draw(st.integers(1, 64))
    byte_order = draw(st.sampled_from(["little_endian", "big_endian"]))
    pos = draw(st.integers(0, 8 * nbytes - length))  # sequential position of the LSB / MSB
    start = pos if byte_order == "little_endian" else 8 * (pos // 8) + 7 - pos % 8
    signed = True if is_float else draw(st.booleans())
    kind = draw(st.sampled_from(["identity", "float", "int"]))
    if kind == "identity":
        scale, offset = 1, 0
    elif kind == "int" and not is_float:
        scale, offset = draw(st.integers(-1000, 1000).filter(bool)), draw(st.integers(-1000, 1000))
    elif kind == "int":
        scale, offset = draw(st.sampled_from([2.0, -5.0, 1e6])), draw(st.sampled_from([0.0, 3.0]))
    else:
        scale = draw(st.floats(1e-6, 1e3) | st.floats(-1e3, -1e-6))
        offset = draw(st.floats(-1e3, 1e3))
    conv = BaseConversion.factory(scale=scale, offset=offset, is_float=is_float)
    sig = Signal("S", start, length, byte_order=byte_order, is_signed=signed, conversion=conv,
                 minimum=None, maximum=None, unit="A")
    msg = Message(0x123, "M", nbytes, [sig], is_fd=nbytes > 8, strict=True)
    return msg, sig


def same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(signal_layouts(), st.data())
def test_decode_equals_cantools(layout, data) -> None:
    msg, sig = layout
    rows = data.draw(st.lists(st.binary(min_size=msg.length, max_size=msg.length),
                              min_size=1, max_size=8))
    codec = SignalCodec(sig, "M")
    arr = np.frombuffer(b"".join(rows), np.uint8).reshape(len(rows), msg.length)
    phys = codec.physical(arr)
    raw = codec.raw(arr)
    for k, payload in enumerate(rows):
        ref = msg.decode(payload, decode_choices=False, scaling=True)["S"]
        assert same(float(ref), float(phys[k])), (codec, payload.hex(), ref, phys[k])
        ref_raw = msg.decode(payload, decode_choices=False, scaling=False)["S"]
        if sig.conversion.is_float:
            assert same(float(ref_raw), float(raw[k]))
        else:
            assert int(ref_raw) == int(raw[k])


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(signal_layouts(), st.data())
def test_insert_equals_cantools_encode(layout, data) -> None:
    msg, sig = layout
    codec = SignalCodec(sig, "M")
    if sig.conversion.is_float:
        width = "f" if sig.length == 32 else "d"
        raws = data.draw(st.lists(st.floats(allow_nan=False, width=32 if width == "f" else 64),
                                  min_size=1, max_size=6))
    else:
        raws = data.draw(st.lists(st.integers(codec.raw_min, min(codec.raw_max, 2**63 - 1)),
                                  min_size=1, max_size=6))
    buf = np.zeros((len(raws), msg.length), np.uint8)
    codec.insert(buf, np.array(raws, np.float64 if sig.conversion.is_float else np.int64))
    for k, r in enumerate(raws):
        assert buf[k].tobytes() == msg.encode({"S": r}, scaling=False, strict=False)


def test_user_dbc_decode_equals_cantools() -> None:
    """Every mapped signal of the user DBC (big endian, mA/mV/rpm/deg, float, odd lengths)."""
    p = Protocol.load(USER_DBC, USER_MAPPING)
    db = cantools.database.load_file(str(USER_DBC))
    rng = np.random.default_rng(5)
    for m in p.messages:
        payloads = rng.integers(0, 256, (200, m.length), dtype=np.uint8)
        for r in m.roles:
            phys = r.codec.physical(payloads)
            for k in range(200):
                ref = db.get_message_by_name(m.name).decode(
                    payloads[k].tobytes(), decode_choices=False)[r.signal]
                assert same(float(ref), float(phys[k]))


# ---------------------------------------------------------------------------
# Mapping and loading
# ---------------------------------------------------------------------------

USER_MAPPING = {
    "current": {"signal": "InverterFb1.Iq", "counter": "Alive", "crc": "Chk"},
    "voltage": "InverterFb1.Uq",
    "speed": {"signal": "InverterFb2.MotorSpeed", "counter": "Alive", "crc": "Chk"},
    "position": "InverterFb3.Angle",
}


class TestMapping:
    def test_default(self, proto: Protocol) -> None:
        assert proto.is_default_dbc
        assert [m.name for m in proto.messages] == ["DriveCurrent", "DriveSpeed"]
        assert {r: (i.message, i.signal) for r, i in proto.roles.items()} == {
            "current": ("DriveCurrent", "Current"), "speed": ("DriveSpeed", "Speed"),
            "position": ("DriveSpeed", "Position"), "voltage": ("DriveCurrent", "Voltage")}
        for m in proto.messages:
            assert m.counter.name == "Counter" and m.crc.name == "CRC"
            assert m.cycle_time == pytest.approx(1e-3) and m.counter_modulo == 16
        assert proto.period == pytest.approx(1e-3)

    def test_repository_copy_is_the_default(self, default_dbc: Path) -> None:
        assert Protocol.load(default_dbc).is_default_dbc

    def test_user_dbc_units(self) -> None:
        p = Protocol.load(USER_DBC, USER_MAPPING)
        assert not p.is_default_dbc
        assert [m.name for m in p.messages] == ["InverterFb1", "InverterFb2", "InverterFb3"]
        assert p.roles["current"].si_scale == 1e-3
        assert p.roles["voltage"].si_scale == 1e-3
        assert p.roles["speed"].si_scale == pytest.approx(2 * math.pi / 60)
        assert p.roles["position"].si_scale == pytest.approx(math.pi / 180)
        fb1, fb2, fb3 = p.messages
        assert fb1.is_extended and fb1.frame_id == 0x18FF0101
        assert (fb1.counter.name, fb1.crc.name) == ("Alive", "Chk")
        assert fb3.counter is None and fb3.crc is None  # never auto-detected for user DBCs
        assert fb2.cycle_time == pytest.approx(2e-3)

    def test_user_dbc_without_configured_e2e_has_none(self) -> None:
        p = Protocol.load(USER_DBC, ["current=InverterFb1.Iq", "speed=InverterFb2.MotorSpeed"])
        assert all(m.counter is None and m.crc is None for m in p.messages)

    def test_from_strings(self) -> None:
        m = SignalMapping.from_strings([
            "current=InverterFb1.Iq", "speed=InverterFb2.MotorSpeed:rpm",
            "position=InverterFb3.Seq:0.5", "counter=InverterFb2.Alive", "crc=InverterFb2.Chk",
            "counter=InverterFb1.none"])
        assert m.roles["speed"].unit == "rpm" and m.roles["position"].scale == 0.5
        assert m.counters == {"InverterFb2": "Alive", "InverterFb1": None}
        p = Protocol.load(USER_DBC, m)
        assert p.message("InverterFb2").counter.name == "Alive"
        assert p.message("InverterFb1").counter is None
        assert p.roles["position"].si_scale == 0.5

    def test_messages_table_and_explicit_scale(self) -> None:
        p = Protocol.load(USER_DBC, {
            "current": {"signal": "InverterFb1.Iq", "scale": 0.002},
            "speed": {"message": "InverterFb2", "signal": "MotorSpeed", "unit": "1/min"},
            "voltage": {"signal": "InverterFb2.Aux", "unit": "V"},
            "messages": {"InverterFb1": {"counter": "Alive", "crc": False},
                         "InverterFb2": {"counter": False, "crc": "Chk"}}})
        assert p.roles["current"].si_scale == 0.002
        assert p.roles["voltage"].si_scale == 1.0
        fb1, fb2 = p.messages
        assert fb1.counter.name == "Alive" and fb1.crc is None
        assert fb2.counter is None and fb2.crc.name == "Chk"

    def test_default_dbc_e2e_opt_out_by_mapping(self) -> None:
        m = SignalMapping.from_strings(["crc=DriveSpeed.none"], base=SignalMapping.default())
        p = Protocol.load(None, m)
        assert p.message("DriveSpeed").crc is None and p.message("DriveCurrent").crc is not None

    @pytest.mark.parametrize("mapping, match", [
        ({"current": "Nope.Iq", "speed": "InverterFb2.MotorSpeed"},
         r"proto_user\.dbc has no message 'Nope' \(mapped to current"),
        ({"current": "InverterFb1.Id", "speed": "InverterFb2.MotorSpeed"},
         r"proto_user\.dbc: message InverterFb1 has no signal 'Id' \(mapped to current\)"),
        ({"current": "InverterFb1.Iq", "speed": "InverterFb2.Temp"},
         r"InverterFb2\.Temp: unit 'degC' of the speed signal cannot be converted to rad/s"),
        ({"current": "InverterFb1.Iq", "speed": "InverterFb2.MotorSpeed",
          "voltage": "InverterFb2.Aux"},
         r"InverterFb2\.Aux: unit '' of the voltage signal"),
        ({"current": "InverterFb1.Iq"}, r"lacks the required role speed"),
        ({"current": "InverterFb1.Iq", "speed": "InverterFb2.MotorSpeed",
          "position": "InverterFb3.LinPos"}, r"speed InverterFb2\.MotorSpeed is rotary \(rpm\) "
                                             r"but position InverterFb3\.LinPos is linear"),
        ({"current": {"signal": "InverterFb1.Iq", "counter": "Seq"},
          "speed": "InverterFb2.MotorSpeed"},
         r"message InverterFb1 has no counter signal 'Seq'"),
        ({"current": {"signal": "InverterFb1.Iq", "crc": "Alive"},
          "speed": "InverterFb2.MotorSpeed"},
         r"CRC InverterFb1\.Alive must be the 8 bits of byte 0"),
        ({"current": {"signal": "InverterFb1.Iq", "counter": "Iq"},
          "speed": "InverterFb2.MotorSpeed"},
         r"is mapped to a role and cannot also be the counter"),
        ({"current": {"signal": "InverterFb1.Iq", "counter": "Uq"},
          "speed": "InverterFb2.MotorSpeed"},
         r"counter InverterFb1\.Uq must be an unsigned integer"),
    ])
    def test_signal_errors_name_what_is_missing(self, mapping, match) -> None:
        with pytest.raises(SignalError, match=match):
            Protocol.load(USER_DBC, mapping)

    @pytest.mark.parametrize("mapping, match", [
        ({"current": "InverterFb1", "speed": "InverterFb2.MotorSpeed"}, r"current: expected"),
        ({"pressure": "A.B"}, r"unknown key 'pressure'"),
        ({"current": "InverterFb1.Iq", "rated_current": -5}, r"rated_current = -5: must be"),
        ({"current": {"signal": "InverterFb1.Iq", "units": "mA"}}, r"unknown key current\.units"),
        ({"current": {"signal": "InverterFb1.Iq", "scale": 0}}, r"current\.scale must be"),
        ({"current": {"signal": "InverterFb1.Iq", "counter": 3}}, r"current\.counter must be"),
        ({"current": "InverterFb1.Iq", "speed": "InverterFb2.MotorSpeed",
          "messages": {"InverterFb3": {"counter": "Seq"}}},
         r"counter configured for message 'InverterFb3', which no role maps"),
        (["current InverterFb1.Iq"], r"expected ROLE=MESSAGE\.SIGNAL"),
        (["pressure=A.B"], r"unknown role 'pressure'"),
    ])
    def test_config_errors(self, mapping, match) -> None:
        with pytest.raises(ConfigError, match=match):
            Protocol.load(USER_DBC, mapping)

    def test_missing_or_bad_dbc_file(self, tmp_path: Path) -> None:
        with pytest.raises(ConfigError, match=r"DBC file .*missing\.dbc: cannot read"):
            Protocol.load(tmp_path / "missing.dbc")
        bad = tmp_path / "bad.dbc"
        bad.write_text("BO_ this is not a DBC\n")
        with pytest.raises(ConfigError, match=r"cannot parse DBC file .*bad\.dbc"):
            Protocol.load(bad)

    def test_optional_default_roles_dropped_when_absent(self, tmp_path: Path) -> None:
        text = DEFAULT_DBC.read_text()
        text = text.replace(' SG_ Voltage : 40|16@1- (0.01,0) [-320|320] "V" Canrls\n', "")
        text = "\n".join(ln for ln in text.splitlines() if not ln.startswith("CM_ SG_ 257 Voltage"))
        f = tmp_path / "novoltage.dbc"
        f.write_text(text)
        p = Protocol.load(f)
        assert not p.has("voltage") and p.has("position")


# ---------------------------------------------------------------------------
# Strict decoding
# ---------------------------------------------------------------------------


def frames(proto: Protocol, n: int, seed: int = 0, **kw) -> FrameBlock:
    t, i, w, th, u = feedback(n, seed)
    return FeedbackEncoder(proto, **kw).encode(t, i, w, th, u)


def with_row(block: FrameBlock, k: int, **changes) -> FrameBlock:
    """A copy of ``block`` with row ``k`` changed (data bytes via data={byte: value})."""
    b = FrameBlock.concat([block])
    b = FrameBlock(b.t.copy(), b.arbitration_id.copy(), b.is_extended.copy(), b.is_remote.copy(),
                   b.is_error.copy(), b.dlc.copy(), b.data.copy())
    for name, v in changes.items():
        if name == "data":
            for j, x in v.items():
                b.data[k, j] = x
        else:
            getattr(b, name)[k] = v
    return b


def reseal(proto: Protocol, b: FrameBlock, k: int) -> None:
    """Recompute the CRC of row k in place (after editing its payload)."""
    b.data[k, 0] = e2e_crc(int(b.arbitration_id[k]), b.data[k, :8].tobytes())


class TestStrictDecode:
    def test_clean_stream(self, proto: Protocol) -> None:
        b = frames(proto, 100)
        dec = Decoder(proto)
        d = dec.decode(b)
        assert d.rejected.total == 0 and d.foreign == 0 and d.lost == {
            "DriveCurrent": 0, "DriveSpeed": 0}
        t, i, w, th, u = feedback(100)
        cur, spd = d["DriveCurrent"], d["DriveSpeed"]
        assert np.array_equal(cur.t, t) and np.array_equal(spd.t, t)
        assert np.array_equal(cur.index, np.arange(0, 200, 2))
        assert np.array_equal(spd.index, np.arange(1, 200, 2))
        assert np.array_equal(cur.counter, np.arange(100) % 16) and cur.counter_modulo == 16
        assert np.max(np.abs(cur.values["current"] - i)) <= 0.5e-4 + 1e-12
        assert np.max(np.abs(spd.values["speed"] - w)) <= 0.5e-4 + 1e-12
        assert np.max(np.abs(cur.values["voltage"] - u)) <= 0.5e-2 + 1e-12
        assert np.max(np.abs(spd.values["position"] - th)) <= 0.5 * 2 * np.pi / 65536 + 1e-12
        assert dec.accepted == {"DriveCurrent": 100, "DriveSpeed": 100} and dec.frames == 200

    def test_foreign_frames_ignored_and_counted(self, proto: Protocol) -> None:
        b = frames(proto, 4)
        b = with_row(b, 1, arbitration_id=0x300)
        b = with_row(b, 2, is_extended=True)  # 0x101 as an extended ID is another frame
        d = Decoder(proto).decode(b)
        assert d.foreign == 2 and d.rejected.total == 0
        assert len(d["DriveCurrent"]) == 3 and len(d["DriveSpeed"]) == 3

    def test_range_example_names_signal_message_limit_value(self, proto: Protocol) -> None:
        b = frames(proto, 4)
        raw = int(round(830.5 / 1e-4))
        b = with_row(b, 3, data={2: raw & 0xFF, 3: (raw >> 8) & 0xFF, 4: (raw >> 16) & 0xFF})
        reseal(proto, b, 3)
        dec = Decoder(proto)
        d = dec.decode(b)
        assert d.rejected["range"] == 1 and d.rejected.per_message["DriveSpeed"]["range"] == 1
        assert dec.rejected.examples["range"] == \
            "DriveSpeed.Speed = 830.5 rad/s outside [-800, 800] (t=0.001000 s)"
        assert len(d["DriveSpeed"]) == 3 and 1 not in d["DriveSpeed"].counter
        assert sum(d.lost.values()) == 0  # the frame arrived: rejected, not lost
        # named opt-out
        d2 = Decoder(Protocol.load(strict_range=False)).decode(b)
        assert d2.rejected.total == 0
        assert d2["DriveSpeed"].values["speed"][1] == pytest.approx(830.5)

    def test_length(self, proto: Protocol) -> None:
        b = with_row(frames(proto, 3), 2, dlc=6)
        dec = Decoder(proto)
        d = dec.decode(b)
        assert d.rejected["length"] == 1
        assert dec.rejected.examples["length"] == \
            "DriveCurrent: 6 bytes, expected 8 (t=0.001000 s)"

    def test_crc(self, proto: Protocol) -> None:
        b = frames(proto, 3)
        b = with_row(b, 0, data={5: b.data[0, 5] ^ 0x10})
        d = Decoder(proto).decode(b)
        assert d.rejected["crc"] == 1 and len(d["DriveCurrent"]) == 2
        assert d.rejected.examples["crc"].startswith("DriveCurrent: CRC 0x")
        assert Decoder(Protocol.load(check_crc=False)).decode(b).rejected.total == 0

    def test_error_and_remote_frames(self, proto: Protocol) -> None:
        b = frames(proto, 3)
        b = with_row(b, 0, is_error=True)
        b = with_row(b, 3, is_remote=True)
        dec = Decoder(proto)
        d = dec.decode(b)
        assert d.rejected["error_frame"] == 1 and d.rejected["remote"] == 1
        assert d.rejected.per_message["*"]["error_frame"] == 1
        assert d.rejected.per_message["DriveSpeed"]["remote"] == 1
        assert dec.rejected.examples["remote"] == "DriveSpeed: remote frame (t=0.001000 s)"

    def test_repeated_stale_and_lost(self, proto: Protocol) -> None:
        b = frames(proto, 12)
        cur = b.take(np.arange(0, 24, 2))  # DriveCurrent only, counters 0..11
        order = [0, 1, 1, 2, 5, 4, 6, 3, 7, 11]
        s = cur.take(np.array(order))
        dec = Decoder(proto)
        d = dec.decode(s)
        assert d["DriveCurrent"].counter.tolist() == [0, 1, 2, 5, 6, 7, 11]
        assert d.rejected["repeated"] == 1 and d.rejected["stale"] == 2
        assert d.lost["DriveCurrent"] == 2 + 3  # 3, 4 missing before 5; 8, 9, 10 before 11
        assert dec.rejected.examples["repeated"].startswith(
            "DriveCurrent: counter 1 repeated after counter 1")
        assert dec.rejected.examples["stale"].startswith(
            "DriveCurrent: counter 4 stale after counter 5")
        off = Decoder(Protocol.load(check_counter=False)).decode(s)
        assert off.rejected.total == 0 and len(off["DriveCurrent"]) == len(order)

    def test_lost_over_counter_wrap_uses_cycle_time(self, proto: Protocol) -> None:
        b = frames(proto, 60).take(np.arange(0, 120, 2))
        s = b.take(np.r_[0:3, 40:45])  # counters 0 1 2 | 8 9 .. : 37 frames lost (2 wraps)
        d = Decoder(proto).decode(s)
        assert d.lost["DriveCurrent"] == 37 and d.rejected.total == 0

    def test_nan_float(self) -> None:
        p = Protocol.load(USER_DBC, USER_MAPPING)
        enc = FeedbackEncoder(p)
        b = enc.encode([0.0, 2e-3], [1.0, 2.0], [10.0, 20.0], [0.1, 0.2], [24.0, 24.0])
        fb3 = [k for k in range(len(b)) if b.arbitration_id[k] == 0x211][1]
        b.data[fb3, 0:4] = np.frombuffer(np.float32(np.nan).tobytes(), np.uint8)
        dec = Decoder(p)
        d = dec.decode(b)
        assert d.rejected["nan"] == 1
        assert dec.rejected.examples["nan"] == "InverterFb3.Angle = nan deg (t=0.002000 s)"

    def test_counts_accumulate_and_summary(self, proto: Protocol) -> None:
        b = with_row(frames(proto, 3), 2, dlc=6)
        dec = Decoder(proto)
        dec.decode(b)
        dec.decode(b)
        assert dec.rejected["length"] == 2
        assert set(dec.rejected) == set(REJECT_REASONS)
        assert dec.rejected.summary().startswith("length: 2  e.g. DriveCurrent: 6 bytes")

    def test_user_dbc_roundtrip(self) -> None:
        p = Protocol.load(USER_DBC, USER_MAPPING)
        n = 50
        rng = np.random.default_rng(6)
        t = np.arange(n) * 2e-3
        i, w = rng.uniform(-800, 800, n), rng.uniform(-500, 500, n)
        th, u = rng.uniform(-100, 100, n), rng.uniform(-300, 300, n)
        b = FeedbackEncoder(p).encode(t, i, w, th, u)
        assert b.is_extended.tolist()[:3] == [True, False, False]
        d = Decoder(p).decode(b)
        assert d.rejected.total == 0
        assert np.allclose(d["InverterFb1"].values["current"], i, atol=0.5e-3)
        assert np.allclose(d["InverterFb1"].values["voltage"], u, atol=5e-3)
        assert np.allclose(d["InverterFb2"].values["speed"], w, atol=0.005 * 2 * np.pi / 60)
        assert np.allclose(d["InverterFb3"].values["position"], th, rtol=1e-6)
        assert d["InverterFb3"].counter_modulo is None
        assert d["InverterFb3"].counter.tolist() == list(range(n))
        db = cantools.database.load_file(str(USER_DBC))
        for msg in b.to_messages():
            db.decode_message(msg.arbitration_id, msg.data)


@st.composite
def faulty_stream(draw: st.DrawFn) -> tuple[list[int], list[int]]:
    """Row order of a clean 2 x 40 frame stream after faults, plus the chunk split points."""
    n = 80
    order = list(range(n))
    out: list[int] = []
    k = 0
    while k < len(order):
        f = draw(st.sampled_from(["ok"] * 6 + ["drop", "dup", "swap", "late"]))
        if f == "drop":
            k += 1
            continue
        if f == "dup":
            out += [order[k], order[k]]
        elif f == "swap" and k + 1 < len(order):
            out += [order[k + 1], order[k]]
            k += 1
        elif f == "late" and k + 4 < len(order):
            order.insert(k + 4, order[k])
        else:
            out.append(order[k])
        k += 1
    cuts = sorted(draw(st.lists(st.integers(0, len(out)), max_size=6)))
    return out, cuts


@settings(max_examples=150, deadline=None)
@given(faulty_stream(), st.sampled_from(["none", "crc", "length", "range", "foreign", "error"]))
def test_decode_is_chunk_invariant(proto_default, stream, corrupt) -> None:
    proto = proto_default
    order, cuts = stream
    base = frames(proto, 40)
    b = base.take(np.array(order, dtype=np.intp))
    if corrupt != "none" and len(b) > 5:
        k = 5
        if corrupt == "crc":
            b.data[k, 6] ^= 1
        elif corrupt == "length":
            b.dlc[k] = 7
        elif corrupt == "range":
            b.data[k, 4] = 0x7F
            reseal(proto, b, k)
        elif corrupt == "foreign":
            b.arbitration_id[k] = 0x7FF
        else:
            b.is_error[k] = True
    whole = Decoder(proto)
    ref = whole.decode(b)
    chunked = Decoder(proto)
    bounds = zip([0, *cuts], [*cuts, len(b)], strict=True)
    parts = [chunked.decode(b.take(slice(a, c))) for a, c in bounds]
    for name in ("DriveCurrent", "DriveSpeed"):
        for attr in ("t", "index", "counter"):
            assert np.array_equal(getattr(ref[name], attr),
                                  np.concatenate([getattr(p[name], attr) for p in parts]))
        for role, v in ref[name].values.items():
            assert np.array_equal(v, np.concatenate([p[name].values[role] for p in parts]))
    assert dict(chunked.rejected) == dict(whole.rejected)
    assert chunked.rejected.examples == whole.rejected.examples
    assert chunked.lost == whole.lost and chunked.foreign == whole.foreign


@pytest.fixture(scope="module")
def proto_default() -> Protocol:
    return Protocol.load()


def test_toml_mapping_of_the_docs() -> None:
    from canrls.processor.config import read_toml

    p = Protocol.load(USER_DBC, read_toml(DATA / "proto_user_mapping.toml", "signals"))
    assert p.roles["position"].si_scale == pytest.approx(math.pi / 180)
    assert p.roles["current"].si_scale == 1e-3
    assert p.message("InverterFb1").crc.name == "Chk"
    assert p.message("InverterFb3").counter is None


# ---------------------------------------------------------------------------
# The compiled fast path (Decoder._decode_fast) against the careful path
# ---------------------------------------------------------------------------


def careful_decoder(proto: Protocol) -> Decoder:
    """A decoder that takes the careful path only (no fast plan)."""
    dec = Decoder(proto)
    dec._plan = None
    return dec


def assert_same_frames(a: DecodedFrames, b: DecodedFrames) -> None:
    """Same accepted frames bit for bit (dtypes too), same rejections and counts."""
    assert list(a.messages) == list(b.messages)
    for name, x in a.messages.items():
        y = b.messages[name]
        assert (x.name, x.counter_modulo) == (y.name, y.counter_modulo)
        for u, v in [(x.t, y.t), (x.index, y.index), (x.counter, y.counter),
                     *((x.values[r], y.values[r]) for r in y.values)]:
            assert u.dtype == v.dtype and u.tobytes() == v.tobytes()
        assert list(x.values) == list(y.values)
    assert (a.lost, a.foreign) == (b.lost, b.foreign)
    assert dict(a.rejected) == dict(b.rejected)
    assert a.rejected.per_message == b.rejected.per_message
    assert a.rejected.examples == b.rejected.examples


def assert_same_decoder(a: Decoder, b: Decoder) -> None:
    assert dict(a.rejected) == dict(b.rejected)
    assert a.rejected.per_message == b.rejected.per_message
    assert a.rejected.examples == b.rejected.examples
    assert (a.lost, a.accepted, a.foreign, a.frames) == (b.lost, b.accepted, b.foreign, b.frames)


def decode_in_blocks(dec: Decoder, b: FrameBlock, size: int) -> list[DecodedFrames]:
    return [dec.decode(b.take(slice(a, a + size))) for a in range(0, max(len(b), 1), size)]


FAST_PROTOCOLS = {
    "default": lambda: Protocol.load(),
    "no-crc": lambda: Protocol.load(check_crc=False),
    "no-counter": lambda: Protocol.load(check_counter=False),
    "no-range": lambda: Protocol.load(strict_range=False),
    "user": lambda: Protocol.load(USER_DBC, USER_MAPPING),  # big endian, float, 3 messages
}


def sprinkle_faults(proto: Protocol, b: FrameBlock, rng: np.random.Generator,
                    rate: float) -> FrameBlock:
    """``b`` through the simulator's fault injection, then error, remote, foreign, short,
    out-of-range and NaN frames here and there (resealed where they carry a CRC)."""
    b, _ = inject(b, f"drop={rate},dup={rate},reorder={rate},corrupt={rate}",
                  seed=int(rng.integers(1 << 31)))
    b = with_row(b, 0)  # a writable copy
    by_id = {m.frame_id: m for m in proto.messages}
    for k in np.flatnonzero(rng.random(len(b)) < rate * 3):
        m = by_id.get(int(b.arbitration_id[k]))
        kind = rng.integers(6)
        if kind == 0:
            b.is_error[k] = True
        elif kind == 1:
            b.is_remote[k] = True
        elif kind == 2:
            b.arbitration_id[k] = 0x7FF
        elif kind == 3:
            b.dlc[k] = 7
        elif m is not None:  # a value out of range (or NaN, or any bit pattern)
            r = m.roles[int(rng.integers(len(m.roles)))].codec
            for j in r.byte_index:
                b.data[k, j] = 0x7F if kind == 4 else 0xFF
            if m.crc is not None:
                b.data[k, 0] = e2e_crc(int(b.arbitration_id[k]), b.data[k, :m.length].tobytes())
    return b


def random_stream(proto: Protocol, n: int, seed: int) -> FrameBlock:
    """n periods of in-range feedback (every mapped message), SI units."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * (proto.period or 1e-3)
    lim = {"current": 0.8, "speed": 0.8, "position": 0.9, "voltage": 0.9}
    si = {}
    for role, info in proto.roles.items():
        c = info.codec
        lo, hi = (c.minimum, c.maximum) if c.minimum is not None else (-100.0, 100.0)
        mid, half = (lo + hi) / 2, (hi - lo) / 2 * lim[role]
        si[role] = (mid + rng.uniform(-half, half, n)) * info.si_scale
    return FeedbackEncoder(proto, stagger=1e-4, counter=int(rng.integers(16))).encode(
        t, si["current"], si["speed"], si.get("position"), si.get("voltage"))


@pytest.mark.parametrize("name", sorted(FAST_PROTOCOLS))
@pytest.mark.parametrize("rate", [0.0, 0.002, 0.02])
def test_fast_path_equals_careful_path_on_faulty_streams(name: str, rate: float) -> None:
    """Seeded streams with faults sprinkled in, decoded in blocks of 1..N frames and whole:
    the fast path gives the careful path's output, block by block and in total."""
    proto = FAST_PROTOCOLS[name]()
    assert Decoder(proto)._plan is not None
    for seed in range(3):
        rng = np.random.default_rng(seed)
        b = sprinkle_faults(proto, random_stream(proto, 150, seed), rng, rate)
        ref = careful_decoder(proto)
        whole = ref.decode(b)
        for size in (1, 2, 3, 4, 5, 7, 10, 33, 64, len(b)):
            fast, slow = Decoder(proto), careful_decoder(proto)
            for x, y in zip(decode_in_blocks(fast, b, size), decode_in_blocks(slow, b, size),
                            strict=True):
                assert_same_frames(x, y)
            assert_same_decoder(fast, slow)
            assert_same_decoder(fast, ref)
        assert_same_frames(Decoder(proto).decode(b), whole)


def test_fast_path_decodes_clean_blocks_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    """Clean blocks (foreign frames included) never reach the careful path."""
    for make in FAST_PROTOCOLS.values():
        proto = make()
        b = random_stream(proto, 40, 0)
        b = with_row(b, 3, arbitration_id=0x7FF)
        ref = careful_decoder(proto).decode(b)
        dec = Decoder(proto)

        def no_careful(*args: object) -> None:
            raise AssertionError("careful path used")

        monkeypatch.setattr(dec, "_decode_careful", no_careful)
        assert_same_frames(dec.decode(b), ref)
        assert ref.foreign == 1 and ref.rejected.total == 0


def test_fast_path_hands_over_at_the_first_bad_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    """The frames before the first bad one stay decoded; the rest go the careful way."""
    proto = Protocol.load()
    b = with_row(frames(proto, 10), 13, dlc=6)  # frame 13 of 20 is short
    dec, ref = Decoder(proto), careful_decoder(proto)
    calls: list[tuple[int, int]] = []
    careful = dec._decode_careful

    def spy(block: FrameBlock, base: int) -> DecodedFrames:
        calls.append((len(block), base))
        return careful(block, base)

    monkeypatch.setattr(dec, "_decode_careful", spy)
    for part in (slice(0, 3), slice(3, None)):
        assert_same_frames(dec.decode(b.take(part)), ref.decode(b.take(part)))
    assert calls == [(7, 13)]  # frames 13..19 of the stream
    assert dec.rejected["length"] == 1 and len(dec.rejected.examples) == 1


def test_fast_path_declined_where_it_cannot_match_bit_for_bit(tmp_path: Path) -> None:
    """A field beyond payload byte 7, a 16-bit float or an integer scaling beyond int64:
    no fast plan (the careful path decodes)."""
    def proto(sig: Signal, length: int = 8) -> Protocol:
        other = Signal("S", 0, 8, unit="A")
        db = cantools.database.can.Database(messages=[
            Message(0x123, "M", length, [sig], is_fd=length > 8, strict=True),
            Message(0x124, "N", 8, [other], strict=True)])
        f = tmp_path / "m.dbc"
        f.write_text(db.as_dbc_string())
        return Protocol.load(f, {"current": "M.S", "speed": {"signal": "N.S", "unit": "rad/s"}})

    assert Decoder(proto(Signal("S", 0, 16, unit="A")))._plan is not None
    assert Decoder(proto(Signal("S", 64, 16, unit="A"), length=12))._plan is None
    assert Decoder(proto(Signal("S", 0, 64, conversion=BaseConversion.factory(scale=3, offset=0),
                        unit="A")))._plan is None
    half = SignalCodec(Signal("S", 0, 16, conversion=BaseConversion.factory(
        scale=1, offset=0, is_float=True), unit="A"), "M")
    assert half.scaling() is None


@st.composite
def two_message_protocols(draw: st.DrawFn) -> tuple[str, dict[str, object]]:
    """DBC text with current and speed in two messages of random layouts and scalings."""
    msgs = []
    for k, name in enumerate(("M", "N")):
        msg, sig = draw(signal_layouts())
        if draw(st.booleans()):  # a range, both limits (cantools writes a missing one as 0)
            lo = draw(st.floats(-1e6, 1e6))
            sig.minimum, sig.maximum = lo, lo + draw(st.floats(0, 1e6))
        msgs.append(Message(0x123 + k, name, msg.length, [sig], is_fd=msg.length > 8,
                            strict=True))
    unit = draw(st.sampled_from(["A", "mA"]))
    mapping = {"current": {"signal": "M.S", "unit": unit},
               "speed": {"signal": "N.S", "unit": draw(st.sampled_from(["rad/s", "rpm"]))}}
    return cantools.database.can.Database(messages=msgs).as_dbc_string(), mapping


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(two_message_protocols(), st.data())
def test_fast_path_equals_careful_path_on_random_layouts(tmp_path_factory, layout, data) -> None:
    """Any field layout and scaling (identity, integer, float; 32/64-bit floats), random
    payloads (NaN, out of range): the same values bit for bit, the same rejections."""
    text, mapping = layout
    f = tmp_path_factory.mktemp("dbc") / "m.dbc"
    f.write_text(text)
    proto = Protocol.load(f, mapping)
    n = data.draw(st.integers(1, 24))
    width = max(m.length for m in proto.messages)
    payloads = data.draw(st.lists(st.binary(min_size=width, max_size=width), min_size=n,
                                  max_size=n))
    b = FrameBlock.allocate(n, width)
    for k, p in enumerate(payloads):
        m = proto.messages[k % 2]
        b.t[k], b.arbitration_id[k], b.dlc[k] = k * 1e-3, m.frame_id, m.length
        b.is_extended[k] = m.is_extended
        b.data[k] = np.frombuffer(p, np.uint8)
    size = data.draw(st.integers(1, n))
    fast, slow = Decoder(proto), careful_decoder(proto)
    for x, y in zip(decode_in_blocks(fast, b, size), decode_in_blocks(slow, b, size),
                    strict=True):
        assert_same_frames(x, y)
    assert_same_decoder(fast, slow)


def test_decoded_frames_stay_frozen_dataclasses() -> None:
    d = Decoder(Protocol.load()).decode(frames(Protocol.load(), 2))
    m = d["DriveCurrent"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.t = m.t  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        d.foreign = 1  # type: ignore[misc]
    assert dataclasses.replace(m, name="x").name == "x" and dataclasses.replace(m) == m
    assert [f.name for f in dataclasses.fields(MessageFrames)] == [
        "name", "t", "index", "counter", "values", "counter_modulo"]
    assert repr(d).startswith("DecodedFrames(messages={'DriveCurrent': MessageFrames(")


WIDE_FIELDS = [  # (start, length, byte order, signed, float, scale, offset, scaling mode)
    (0, 55, "little_endian", True, False, 3, -7, "int"),        # raw * scale beyond 2**53
    (2, 60, "little_endian", False, False, 5, 11, "int"),
    (7, 57, "big_endian", True, False, -2, 1, "int"),
    (0, 64, "little_endian", True, False, 1, 0, "identity"),
    (0, 64, "little_endian", False, False, 1, 0, "identity"),  # uint64 -> float64
    (7, 64, "big_endian", False, False, 1e-3, 0.5, "float"),
    (1, 63, "little_endian", False, False, 0.1, 0.5, "float"),
    (0, 64, "little_endian", True, True, -5.0, 0.0, "float"),
    (0, 32, "little_endian", True, True, 2.0, 3.0, "float"),
    (7, 32, "big_endian", True, True, 1, 0, "identity"),
]


@pytest.mark.parametrize("field", WIDE_FIELDS, ids=lambda f: f"{f[1]}bit-{f[2][0]}-{f[7]}")
def test_fast_path_scaling_of_wide_fields(tmp_path: Path, field: tuple) -> None:
    """Every scaling mode on fields wide enough that float arithmetic would round where
    SignalCodec.physical computes exactly (and back): bit for bit the careful values."""
    start, length, order, signed, is_float, scale, offset, mode = field
    sig = Signal("S", start, length, byte_order=order, is_signed=signed, unit="A",
                 conversion=BaseConversion.factory(scale=scale, offset=offset, is_float=is_float))
    db = cantools.database.can.Database(messages=[
        Message(0x123, "M", 8, [sig], strict=True),
        Message(0x124, "N", 8, [Signal("S", 0, 8, unit="A")], strict=True)])
    f = tmp_path / "wide.dbc"
    f.write_text(db.as_dbc_string())
    proto = Protocol.load(f, {"current": "M.S", "speed": {"signal": "N.S", "unit": "rad/s"}})
    codec = proto.roles["current"].codec
    assert codec.scaling()[0] == {"identity": 0, "int": 1, "float": 2}[mode]
    n = 400
    b = FrameBlock.allocate(n, 8)
    b.t[:] = np.arange(n) * 1e-3
    b.arbitration_id[:] = np.where(np.arange(n) % 2, 0x124, 0x123)
    b.dlc[:] = 8
    b.data[:] = np.random.default_rng(length).integers(0, 256, (n, 8), dtype=np.uint8)
    for size in (1, 3, n):
        fast, slow = Decoder(proto), careful_decoder(proto)
        for x, y in zip(decode_in_blocks(fast, b, size), decode_in_blocks(slow, b, size),
                        strict=True):
            assert_same_frames(x, y)
    got = Decoder(proto).decode(b)["M"]
    want = codec.physical(b.data[got.index]) * proto.roles["current"].si_scale
    assert got.values["current"].tobytes() == want.tobytes() and len(got) > n // 4


# -- DBC scale x unit factor: one product ---------------------------------------------
def test_scale_times_unit_factor_is_taken_from_the_role(monkeypatch: pytest.MonkeyPatch,
                                                        tmp_path: Path) -> None:
    """The SI value of one raw unit (the DBC scale times the unit's factor to SI) is
    RoleInfo.si_per_raw_exact: the firmware's integers, the C export's comment and the
    encoder's full-turn test read it (before, each multiplied the two itself)."""
    from canrls.can.codec import RoleInfo
    from canrls.can.encoder import FeedbackEncoder
    from canrls.firmware import target_model
    from canrls.processor.config import read_toml

    # an integer field as it stands in the frame (no bias, no fraction bits)
    int_field = target_model.Field(msg=0, big_endian=False, shift=0, length=16, signed=True,
                                   lo=-32768, hi=32767)
    user = Protocol.load(USER_DBC, read_toml(DATA / "proto_user_mapping.toml", "signals"))
    for p in (Protocol.load(), user):
        for role, info in p.roles.items():
            c = info.codec
            assert info.si_per_raw == float(c.scale) * info.si_scale, role
            assert target_model._scale(p, role, int_field)[0] == info.si_per_raw_exact
    proto = Protocol.load()
    assert FeedbackEncoder(proto).wrapping == {"position"}
    from fractions import Fraction

    doubled = property(lambda self: 2 * Fraction(self.codec.scale) * Fraction(self.si_scale))
    monkeypatch.setattr(RoleInfo, "si_per_raw_exact", doubled)
    speed = proto.roles["speed"]
    assert target_model._scale(proto, "speed", int_field)[0] == 2 * Fraction(speed.codec.scale)
    assert FeedbackEncoder(proto).wrapping == frozenset()  # two turns now: no wrapping


@pytest.mark.parametrize("old, new, message", [
    ("BO_ 258 DriveSpeed", "BO_ 258 DriveCurrent",
     r"2 messages are named DriveCurrent \(0x101, 0x102; mapped to current\)"),
    ("BO_ 258 DriveSpeed", "BO_ 257 DriveSpeed",
     r"messages DriveCurrent \(mapped to current\) and DriveSpeed share the ID 0x101"),
])
def test_a_mapped_message_whose_name_or_id_is_given_twice_is_refused(
        tmp_path: Path, caplog: pytest.LogCaptureFixture, old: str, new: str,
        message: str) -> None:
    """Two messages of one name or one ID: cantools logged "Overwriting message ..." (a
    second, time-stamped line on stderr) and kept one, so the error blamed something
    else ("message DriveCurrent has no signal 'Current'", "DriveSpeed never occurs")."""
    dbc = tmp_path / "twice.dbc"
    dbc.write_text(DEFAULT_DBC.read_text().replace(old, new))
    with pytest.raises(SignalError, match=rf"^DBC {dbc}: {message}"):
        Protocol.load(dbc, SignalMapping.default())
    assert not [r for r in caplog.records if "Overwriting" in r.getMessage()]
