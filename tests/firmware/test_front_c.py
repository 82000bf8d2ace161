"""The generated front end (``canrls_front.c``) from a hostile DBC.

A DBC is the user's: its names reach the generated C as comment text only, its numbers
(IDs, bit positions, lengths, scale factors, limits) as checked constants. Each DBC here
either exports C that builds with the export's warnings and replays its log bit for bit
through the generated front end and the table-driven one, frame by frame, or is refused
with one ``error:`` line and nothing written: C keywords and canrls' own function names
as message and signal names, 29-bit IDs up to 0x1FFFFFFF, Motorola fields across byte
boundaries, a Motorola float32 speed (its scale factor 1, 1e30 or 1e-30), a 13-bit current
at bit 3 with an odd scale factor, a 32-bit unsigned position spread over five bytes, a
float64 voltage.
"""

from __future__ import annotations

import contextlib
import io
import subprocess
from pathlib import Path

import pytest
from debian import need_tool
from front_tool import both_paths

from canrls.can.logs import write_log
from canrls.can.protocol import Protocol
from canrls.cli.main import main
from canrls.sim.scenario import Simulator, scenario

SIGNALS = ["current=canrls_target_frame.S", "speed=canrls_target_frame.data",
           "position=return_.len", "voltage=main.int"]


def _dbc(speed_scale: str = "1", speed_limit: str = "30000") -> str:
    return f'''VERSION ""

NS_ :

BS_:

BU_: Drive

BO_ 2684354559 canrls_target_frame: 8 Drive
 SG_ S : 3|13@1- (0.0123456789,0) [-50|50] "A" Vector__XXX
 SG_ data : 23|32@0- ({speed_scale},0) [-{speed_limit}|{speed_limit}] "rpm" Vector__XXX

BO_ 2147483664 return_: 6 Drive
 SG_ len : 5|32@1+ (0.01,0) [0|42949672.95] "deg" Vector__XXX

BO_ 2147483665 main: 8 Drive
 SG_ int : 0|64@1- (1,0) [-1000|1000] "V" Vector__XXX

CM_ BO_ 2684354559 "*/ #error gotcha /*";
SIG_VALTYPE_ 2684354559 data : 1;
SIG_VALTYPE_ 2147483665 int : 2;
'''


def _run(argv: list[str]) -> tuple[int, str]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        rc = main(argv)
    return rc, buf.getvalue()


@pytest.mark.parametrize(("scale", "limit"), [("1", "30000"), ("1e+30", "3e+34"),
                                               ("1e-30", "3e-26")],
                         ids=["plain-speed", "huge-scale", "tiny-scale"])
def test_a_hostile_dbc_exports_a_front_end_that_agrees_or_is_one_error(
        tmp_path: Path, scale: str, limit: str) -> None:
    need_tool("make", ["make"])
    dbc = tmp_path / "drive.dbc"
    # the log is written with the float speed in rpm; read back with a huge or tiny
    # scale factor (and limits to match) its raw values are the same, its units not
    dbc.write_text(_dbc())
    sc = scenario("standard", seed=7, duration=4.0,
                  effects="inertia,viscous,coulomb,unbalance")
    log = tmp_path / "drive.log"
    write_log(log, Simulator(sc, protocol=Protocol.load(dbc, SIGNALS)).frames())
    dbc.write_text(_dbc(scale, limit))
    saved, out = tmp_path / "model.json", tmp_path / "c"
    mapping = ["--dbc", str(dbc), *[a for s in SIGNALS for a in ("--signal", s)]]
    rc, text = _run(["fit", str(log), *mapping, "--kt", "0.1", "-e",
                     "inertia,viscous,coulomb,unbalance", "--save-model", str(saved),
                     "--quiet"])
    if rc == 0:
        rc, text = _run(["export-c", "--model", str(saved), "--out", str(out), "--vectors",
                         str(log)])
    if rc != 0:
        assert rc == 1 and text.startswith("error: ") and text.count("\n") == 1, text
        assert not out.exists()
        assert scale != "1", text
        return
    front = (out / "canrls_front.c").read_text()
    # the IDs as checked constants, the names as comment text only
    assert "id == 536870911u && extended != 0u" in front
    assert "id == 16u && extended != 0u" in front
    assert "cr_float_word((uint64_t)raw_speed_bits, 0," in front and "(uint64_t)data[4]" in front
    assert "cr_float_word(raw_voltage_bits, 1," in front
    generated, tables = both_paths(out)
    assert generated == tables
    for target in ("test", "test-tables"):
        r = subprocess.run(["make", "-s", "-C", str(out), target], capture_output=True,
                           text=True, timeout=600)
        assert r.returncode == 0, r.stdout + r.stderr
        assert "bit-exact with the specification" in r.stdout
