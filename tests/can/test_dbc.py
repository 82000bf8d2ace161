"""The shipped DBC: one file, multiplexed parameter frames, IDs read from it.

The DBC is package data (``src/canrls/data/canrls.dbc``); ``dbc/canrls.dbc`` is a copy
for people who clone the repository and point ``cantools monitor`` at it. The copy must
be byte for byte the package file. Tools read the DBC on their own, so everything here
decodes with a cantools database loaded independently of canrls.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cantools
import pytest
from cantools.subparsers.__utils__ import format_multiplexed_name

from canrls.can.estimator_frames import (
    FrameDecoder,
    ParameterReport,
    encode_param_info,
    encode_parameters,
    frame_ids,
)
from canrls.can.protocol import DEFAULT_DBC
from canrls.core.effect_names import EffectId, EquationId

ROOT = Path(__file__).resolve().parents[2]
REPO_DBC = ROOT / "dbc" / "canrls.dbc"

#: message -> the signals that belong to parameter Index (multiplexed on it)
PER_PARAMETER = {
    "RlsEstimate": {"Valid", "FixedValue"},
    "RlsSigma": {"Sigma"},
    "RlsReference": {"FloatValue"},
    "RlsParamInfo": {"EffectId", "Component", "Order", "Equation"},
}


@pytest.fixture(scope="module")
def db() -> cantools.database.can.Database:
    return cantools.database.load_file(str(REPO_DBC), strict=True)


def test_the_repository_dbc_is_the_package_data() -> None:
    assert not DEFAULT_DBC.is_symlink() and not REPO_DBC.is_symlink()
    assert REPO_DBC.read_bytes() == DEFAULT_DBC.read_bytes(), (
        "dbc/canrls.dbc differs from the package data: edit src/canrls/data/canrls.dbc "
        "and copy it to dbc/canrls.dbc")


def test_parameter_frames_are_multiplexed_by_index(db) -> None:
    for name, per in PER_PARAMETER.items():
        m = db.get_message_by_name(name)
        assert m.is_multiplexed(), name
        sigs = {s.name: s for s in m.signals}
        assert sigs["Index"].is_multiplexer
        for s in m.signals:
            if s.name in per:
                assert s.multiplexer_signal == "Index", (name, s.name)
                assert sorted(s.multiplexer_ids) == list(range(256)), (name, s.name)
            else:  # Index itself, and what belongs to the publication (Counter, Count)
                assert s.multiplexer_ids is None, (name, s.name)
    for m in db.messages:
        if m.name not in PER_PARAMETER:
            assert not m.is_multiplexed(), m.name


REPORTS = [ParameterReport(i, "", EffectId.COGGING if i % 2 else EffectId.ELECTRICAL,
                           i % 2, 24 if i % 2 else 0,
                           EquationId.MECHANICAL if i % 2 else EquationId.ELECTRICAL,
                           fixed_value=0.5 + i, sigma=0.25 * i, float_value=-1.0 - i,
                           valid=i != 3)
           for i in (0, 1, 2, 3, 254, 255)]


def test_cantools_decodes_every_parameter_by_name(db) -> None:
    frames = encode_parameters(REPORTS, counter=5) + encode_param_info(REPORTS)
    seen: dict[tuple[str, int], dict] = {}
    for f in frames:
        m = db.get_message_by_frame_id(f.arbitration_id)
        v = m.decode(bytes(f.data), decode_choices=False)
        # cantools gives exactly the frame's signals: those of its parameter included
        assert set(v) == {s.name for s in m.signals}, m.name
        seen[(m.name, v["Index"])] = v
        # what cantools monitor keys its lines by: one line per parameter, not per frame
        assert format_multiplexed_name(m, v) == f"{m.name} :: Index={v['Index']}"
    assert set(seen) == {(n, r.index) for n in PER_PARAMETER for r in REPORTS}
    for r in REPORTS:
        est = seen[("RlsEstimate", r.index)]
        assert est["Valid"] == int(r.valid) and est["Counter"] == 5
        assert est["FixedValue"] == (r.fixed_value if r.valid else 0.0)
        assert seen[("RlsSigma", r.index)]["Sigma"] == r.sigma
        assert seen[("RlsReference", r.index)]["FloatValue"] == r.float_value
        info = seen[("RlsParamInfo", r.index)]
        assert (info["EffectId"], info["Component"], info["Order"], info["Equation"],
                info["Count"]) == (r.effect_id, r.component, r.order, r.equation, len(REPORTS))


def test_the_cantools_decode_command_shows_every_parameter(tmp_path: Path) -> None:
    frames = encode_parameters(REPORTS, counter=1)
    dump = "".join(f"  vcan0  {f.arbitration_id:03X}   [8]  "
                   + " ".join(f"{b:02X}" for b in f.data) + "\n" for f in frames)
    out = subprocess.run([sys.executable, "-m", "cantools", "decode", "--single-line",
                          str(REPO_DBC)], input=dump, capture_output=True, text=True,
                         check=True, timeout=60).stdout
    for r in REPORTS:
        assert f"RlsSigma(Index: {r.index}, Counter: 1, Sigma: {r.sigma}" in out
        want = r.fixed_value if r.valid else 0.0
        assert (f"RlsEstimate(Index: {r.index}, Counter: 1, Valid: {int(r.valid)}, "
                f"FixedValue: {want}") in out


def test_frame_decoder_reads_the_multiplexed_frames() -> None:
    fd = FrameDecoder()
    fd.feed_all(encode_parameters(REPORTS, counter=2) + encode_param_info(REPORTS))
    assert [p.index for p in fd.table()] == [r.index for r in REPORTS]
    got = fd.parameters[255]
    assert (got.fixed_value, got.sigma, got.float_value, got.equation) == (
        255.5, 63.75, -256.0, EquationId.MECHANICAL)
    assert got.name == "cogging:24.cos" and fd.count == len(REPORTS)


def test_frame_ids_are_read_from_the_dbc(db, tmp_path: Path) -> None:
    ids = frame_ids()
    by_name = {m.name: m.frame_id for m in db.messages}
    assert (ids.estimate, ids.sigma, ids.reference, ids.param_info, ids.status, ids.health,
            ids.counters, ids.command, ids.ack) == tuple(by_name[n] for n in (
                "RlsEstimate", "RlsSigma", "RlsReference", "RlsParamInfo", "RlsStatus",
                "RlsHealth", "RlsCounters", "RlsCommand", "RlsCommandAck"))
    assert ids.feedback == (by_name["DriveCurrent"], by_name["DriveSpeed"])
    assert ids.published == {by_name[n] for n in by_name if n.startswith("Rls")} - {
        ids.command, ids.ack}
    # the documented protocol (docs/protocol.md)
    assert (ids.estimate, ids.status, ids.command, ids.ack, ids.feedback) == (
        0x300, 0x310, 0x320, 0x321, (0x101, 0x102))
    # another DBC gives its own IDs
    moved = tmp_path / "moved.dbc"
    moved.write_text(REPO_DBC.read_text().replace("BO_ 800 RlsCommand", "BO_ 1600 RlsCommand")
                     .replace(" 800 ", " 1600 "))
    assert frame_ids(moved).command == 1600 and frame_ids(moved).ack == ids.ack
