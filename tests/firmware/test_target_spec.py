"""The target's specification piece by piece, against the service it stands for.

Decoding against the host's strict decoder (Intel and Motorola, signed and unsigned,
up to 32 bits), the rejections it counts, the filter bank against the float
state-variable filter, the selection against the pipeline's (the same rows used on a
clean log), and what the target refuses, with the reason.
"""

from __future__ import annotations

import math
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from canrls.can.e2e import e2e_crc
from canrls.can.protocol import Protocol
from canrls.estimation.model import Model
from canrls.estimation.pipeline import Pipeline
from canrls.estimation.settings import EstimatorSettings
from canrls.firmware.spec import REJECTS, TargetEstimator
from canrls.firmware.target_model import TargetError, build
from canrls.processor.config import AppConfig
from canrls.sim.scenario import scenario, simulate

HEADER = 'VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: Drive\n\n'


def _user_dbc(tmp_path: Path) -> Path:
    """Fields of every kind: Motorola and Intel, signed and unsigned, 3 to 32 bits,
    across byte boundaries, 29-bit IDs."""
    p = tmp_path / "fields.dbc"
    p.write_text(HEADER + '''BO_ 2566914305 Fb: 8 Drive
 SG_ Current : 7|32@0- (0.001,0) [-2147483.648|2147483.647] "A" Vector__XXX
 SG_ Speed : 39|20@0- (0.01,0) [-5000|5000] "rpm" Vector__XXX
 SG_ Alive : 51|3@0+ (1,0) [0|7] "" Vector__XXX

BO_ 2566914306 Pos: 8 Drive
 SG_ Angle : 3|32@1+ (0.01,0) [0|42949672.95] "deg" Vector__XXX
 SG_ Volt : 35|13@1- (0.1,-2) [-400|400] "V" Vector__XXX
''')
    return p


def _model(effects: str = "inertia,viscous,coulomb,unbalance") -> Model:
    return Model(effects.split(","), kt=0.1, held=("current", "voltage"))


def test_decoding_is_the_host_decoders_for_every_kind_of_field(tmp_path: Path) -> None:
    dbc = _user_dbc(tmp_path)
    proto = Protocol.load(dbc, ["current=Fb.Current", "speed=Fb.Speed", "position=Pos.Angle",
                                "voltage=Pos.Volt"])
    tm = build(_model("inertia,viscous,coulomb,unbalance,electrical"), proto,
               EstimatorSettings(), 1e-3)
    rng = np.random.default_rng(21)
    data = rng.integers(0, 256, (4000, 8), dtype=np.uint8)
    for role, f in tm.roles.items():
        codec = proto.roles[role].codec
        raw = codec.raw(data).astype(object)
        got = [f.extract(bytes(row)) + f.bias for row in data]
        assert got == [int(x) for x in raw], role
    # the DBC's range, as raw values: the strict decoder's limits
    assert tm.roles["speed"].lo == -500000 and tm.roles["speed"].hi == 500000
    assert tm.roles["position"].biased and tm.roles["position"].lo == -(1 << 31)


def test_the_rejections_are_counted_by_reason() -> None:
    proto = Protocol.load()  # canrls' DBC: CRC and alive counters
    tm = build(_model(), proto, EstimatorSettings(), 1e-3)
    res = simulate(scenario("standard", seed=1, duration=0.05))
    frames = [(round(float(res.frames.t[k]) * 1e6), int(res.frames.arbitration_id[k]),
               bytes(res.frames.data[k, :8])) for k in range(len(res.frames))]

    def counts(est: TargetEstimator) -> dict[str, int]:
        return {k: v for k, v in zip(REJECTS, est.snapshot()["rejects"], strict=True) if v}

    t, fid, d = frames[0]
    est = TargetEstimator(tm)
    assert est.frame(fid, False, d[:7], t) == 0 and counts(est) == {"length": 1}
    bad = bytearray(d)
    bad[3] ^= 1
    assert est.frame(fid, False, bytes(bad), t) == 0 and counts(est) == {"length": 1, "crc": 1}
    assert est.frame(0x7FF, False, d, t) == 0 and counts(est) == {"length": 1, "crc": 1}
    est = TargetEstimator(tm)
    assert est.frame(fid, False, d, t) == 0 and est.frame(fid, False, d, t) == 0
    assert counts(est) == {"repeated": 1}
    est = TargetEstimator(tm)
    far = bytearray(d)
    far[2:5] = (8_100_000).to_bytes(3, "little", signed=True)         # 810 A > 800 A
    far[0] = e2e_crc(fid, far)
    assert est.frame(fid, False, bytes(far), t) == 0 and counts(est) == {"range": 1}
    # a clean stream pairs every period; one frame lost leaves its period unpaired and
    # the next sample a period late: the filter restarts
    est = TargetEstimator(tm)
    r = [est.frame(f, False, x, tt) for k, (tt, f, x) in enumerate(frames) if k != 21]
    assert sum(x & 1 for x in r) == len(frames) // 2 - 1
    assert counts(est) == {"unpaired": 1, "restarts": 1}


def test_the_filter_bank_follows_the_float_filter() -> None:
    """The integer states against the float SVF on the same raw samples: the filtered
    speed and acceleration within 1e-8 of their range."""
    from canrls.estimation.svf import SVF

    proto = Protocol.load()
    tm = build(_model("inertia,viscous"), proto, EstimatorSettings(), 1e-3)
    est = TargetEstimator(tm)
    rng = np.random.default_rng(22)
    k_speed = float(proto.roles["speed"].codec.scale) * proto.roles["speed"].si_scale
    w = np.cumsum(rng.normal(0, 2000, 5000)).astype(np.int64)
    w = np.clip(w, -8_000_000, 8_000_000)
    svf = SVF(25.0, 1e-3, 0.7071)
    f, sf = svf.process(w * k_speed)
    fi = [i for i, fl in enumerate(tm.filters) if fl.role == "speed"][0]
    fx = tm.filters[fi].fx
    xs, vs = [], []
    for v in w.tolist():
        est.raw = {"current": 0, "speed": v}
        est._filter(est._inputs())  # one sample through the bank (no estimator)
        xs.append(est.x1[fi])
        vs.append(est.x2[fi])
    x1 = np.ldexp(np.array(xs, float), -fx) * k_speed
    x2 = np.ldexp(np.array(vs, float), -fx) * k_speed / 1e-3
    assert np.max(np.abs(x1 - f)) < 1e-8 * np.ptp(f)
    assert np.max(np.abs(x2 - sf)) < 1e-7 * np.ptp(sf)


def test_a_bounded_input_is_filtered_in_32_bits_near_the_float_filter() -> None:
    """tanh of the speed (an input bounded by 1) through its narrow filter: int32 states
    in Q30 that follow the float filter of the same input within 1e-7 of its range (8e-9
    and 1.2e-8 measured); a filter whose gain would leave int32 (zeta 0.2: an L1 gain
    above 2) keeps 64-bit states."""
    from canrls.estimation.svf import SVF
    from canrls.firmware.target_model import SRC_TANH

    proto = Protocol.load()
    model = _model("inertia,viscous,coulomb")
    tm = build(model, proto, EstimatorSettings(), 1e-3)
    fi = [i for i, fl in enumerate(tm.filters) if fl.kind == SRC_TANH][0]
    assert tm.filters[fi].narrow
    est = TargetEstimator(tm)
    rng = np.random.default_rng(23)
    w = np.clip(np.cumsum(rng.normal(0, 2000, 5000)), -400_000, 400_000).astype(np.int64)
    us, xs, vs = [], [], []
    for v in w.tolist():
        est.raw = {"current": 0, "speed": v}
        u = est._inputs()
        est._filter(u)  # one sample through the bank (no estimator)
        us.append(u[fi])
        xs.append(est.x1[fi])
        vs.append(est.x2[fi])
    assert all(-(1 << 31) <= x < 1 << 31 for x in xs + vs)
    f, sf = SVF(model.cutoff_hz, 1e-3, model.zeta).process(np.ldexp(np.array(us, float), -30))
    x1 = np.ldexp(np.array(xs, float), -30)
    x2 = np.ldexp(np.array(vs, float), -30) / 1e-3
    assert np.max(np.abs(x1 - f)) < 1e-7 * np.ptp(f)
    assert np.max(np.abs(x2 - sf)) < 1e-7 * np.ptp(sf)
    low = Model(["inertia", "viscous", "coulomb"], kt=0.1, held=("current", "voltage"),
                zeta=0.2)
    tm2 = build(low, proto, EstimatorSettings(), 1e-3)
    wide = [fl for fl in tm2.filters if fl.kind == SRC_TANH][0]
    assert not wide.narrow and wide.fx > 0


def test_the_same_rows_are_used_as_in_the_pipeline() -> None:
    """On a clean run the selection (warm-up, the speed band, reversals) uses the
    pipeline's rows: the same count of updates."""
    res = simulate(scenario("standard", seed=2, duration=6.0))
    proto = Protocol.load()
    model = _model("inertia,viscous,coulomb")
    settings = EstimatorSettings()
    pipe = Pipeline(model.with_options(coulomb_band=0.04), 1e-3, settings)
    pipe.process(res.measured)
    tm = build(model.with_options(coulomb_band=0.04), proto, settings, 1e-3)
    est = TargetEstimator(tm)
    b = res.frames
    for k in range(len(b)):
        est.frame(int(b.arbitration_id[k]), False, bytes(b.data[k, :8]),
                  round(float(b.t[k]) * 1e6))
    assert est.eqs[0].updates == pipe.estimators[0].samples > 3000


def test_what_the_target_cannot_run_is_refused_with_the_reason(tmp_path: Path) -> None:
    proto = Protocol.load()
    terms = {"drag": {"expr": "omega * abs(omega)", "range": [-1e4, 1e4]}}
    with pytest.raises(TargetError, match="user term"):
        build(Model(["inertia", "user:drag"], kt=0.1, terms=terms), proto,
              EstimatorSettings(), 1e-3)
    dbc = tmp_path / "float.dbc"
    dbc.write_text(HEADER + '''BO_ 256 Fb: 8 Drive
 SG_ Current : 0|32@1- (1,0) [-100|100] "A" Vector__XXX
 SG_ Speed : 32|16@1- (1,0) [-100|100] "rad/s" Vector__XXX

SIG_VALTYPE_ 256 Speed : 1;
''')
    p = Protocol.load(dbc, ["current=Fb.Current", "speed=Fb.Speed"])
    with pytest.raises(TargetError, match="16-bit float"):
        build(_model("inertia,viscous"), p, EstimatorSettings(), 1e-3)
    with pytest.raises(TargetError, match="whole number of timestamp ticks"):
        build(_model("inertia"), proto, EstimatorSettings(), 1.0000001e-3 / 3)
    with pytest.raises(TargetError, match="wraps"):
        build(Model(["inertia", "cogging:2"], kt=0.1, axis="linear", pitch=0.01, wrap=0.015),
              Protocol.load(), EstimatorSettings(), 1e-3)


def test_a_big_endian_float64_signal_is_its_value_in_fixed_point(tmp_path: Path) -> None:
    import struct

    dbc = tmp_path / "double.dbc"
    dbc.write_text(HEADER + '''BO_ 256 Fb: 4 Drive
 SG_ Current : 7|32@0- (0.001,0) [-100|100] "A" Vector__XXX

BO_ 257 Sp: 8 Drive
 SG_ Speed : 7|64@0- (2,1) [-301|99] "rad/s" Vector__XXX

SIG_VALTYPE_ 257 Speed : 2;
''')
    p = Protocol.load(dbc, ["current=Fb.Current", "speed=Sp.Speed"])
    tm = build(_model("inertia,viscous"), p, EstimatorSettings(), 1e-3)
    f = tm.roles["speed"]
    # the raw range -151 .. 49 ((phys - 1) / 2): 151 < 2^8, so 22 fraction bits in 30
    assert f.is_float and f.big_endian and f.length == 64 and f.frac == 22
    assert (f.lo, f.hi) == (-151 << 22, 49 << 22)
    assert f.extract(struct.pack(">d", -2.75)) == round(-2.75 * 2 ** 22)
    assert f.extract(struct.pack(">d", 2 ** -23 + 2 ** -60)) == 1   # half away from zero
    assert f.extract(struct.pack(">d", -(2 ** -23))) == -1
    assert f.extract(struct.pack(">d", float("nan"))) is None
    assert f.extract(struct.pack(">d", float("-inf"))) is None
    # and the signal's scale and offset go to the columns: k = 2 2^-22, o = 0.5 2^22
    from canrls.firmware.target_model import _scale

    assert _scale(p, "speed", f) == (Fraction(2, 2 ** 22), Fraction(2 ** 21))


def test_the_config_without_calibration_exports_the_uncalibrated_prior(tmp_path: Path) -> None:
    from canrls.firmware.load import load, target_model

    cfg = tmp_path / "drive.toml"
    cfg.write_text('[model]\neffects = ["inertia", "viscous", "coulomb"]\nkt = 0.1\n')
    src = load(cfg)
    assert src.energy is None and src.period_source == "the DBC's cycle time"
    tm = target_model(src)
    pipe = Pipeline(AppConfig.load(cfg).model_for(src.protocol), 1e-3, src.settings)
    assert list(tm.equations[0].p0) == np.diag(pipe.estimators[0].frls.P).tolist()
    assert math.isclose(tm.dt, 1e-3)
