"""The whole estimator in C against its specification, bit for bit, from a log's frames.

For each drive the simulator writes a log in a DBC, ``canrls fit --save-model``
identifies it, ``canrls export-c --vectors LOG`` writes the C and the test vectors, and
the exported Makefile's host test replays every frame through ``canrls_target_frame``
and compares every state record and every published frame with the specification's:
on x86-64 (gcc) and on 32-bit ARM (``arm-linux-gnueabihf-gcc`` under ``qemu-arm``);
``make check-float`` finds no floating-point routine in the Cortex-M4 objects. The
drives: canrls' own DBC (unbalance); a user's DBC with 29-bit IDs, Motorola 32-bit
fields in mA, 0.01 rpm and 0.01 deg, its raw range as limits, standing still through
the calibration window (rescales); a CiA 402 drive reporting its torque; both equations
with Stribeck friction and cogging at lambda < 1 with dropped, corrupted, duplicated and
reordered frames; a speed that reads exactly zero at standstill (pending columns); and
the estimator frames left out.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
import subprocess
from pathlib import Path
from typing import Any

import pytest
from debian import need_tool

from canrls.can.logs import write_log
from canrls.can.protocol import Protocol
from canrls.cli.main import main
from canrls.sim.excitation import Sequence, constant, standard
from canrls.sim.scenario import Simulator, scenario

#: the target's C (the repository's bounds: canrls_bounds.h, the maxima)
C_DIR = Path(__file__).resolve().parents[2] / "src" / "canrls" / "c" / "firmware"
CIA_MAP = ["--dbc", str(Path(__file__).resolve().parents[1] / "data" / "cia402_drive.dbc"),
           "--signal", "torque=TPDO1.TorqueActual", "--signal", "speed=TPDO2.VelocityActual",
           "--signal", "position=TPDO2.PositionActual", "--rated-torque", "0.32",
           "--increments-per-rev", "131072"]


ODRIVE_MAP = ["--dbc", str(Path(__file__).resolve().parents[1] / "data" / "odrive_cansimple.dbc"),
              *[a for s in ("speed=Get_Encoder_Estimates.Vel_Estimate",
                            "position=Get_Encoder_Estimates.Pos_Estimate",
                            "current=Get_Iq.Iq_Measured") for a in ("--signal", s)]]


def _quiet(argv: list[str]) -> str:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(argv)
    assert rc == 0, buf.getvalue()
    return buf.getvalue()


def _sim(d: Path, name: str, args: list[str]) -> Path:
    log = d / f"{name}.log"
    _quiet(["sim", "--out", str(log), *args])
    return log


def _motorola(d: Path, noise: bool = True) -> tuple[Path, list[str]]:
    """The user's DBC of tests/processor/test_scaling.py (29-bit IDs, Motorola 32-bit fields in mA,
    0.01 rpm and 0.01 deg, the raw range as limits), the drive still for 3 s first."""
    from user_drives import SIGNALS, user_dbc

    dbc = d / "user.dbc"
    dbc.write_text(user_dbc(None))
    exc = Sequence([(constant(0.0), 3.0), standard()])
    sc = scenario("standard", seed=3, duration=9.0, excitation=exc,
                  **({} if noise else {"speed_noise": 0.0}))
    log = d / ("motorola.log" if noise else "exact.log")
    write_log(log, Simulator(sc, protocol=Protocol.load(dbc, SIGNALS)).frames())
    return log, ["--dbc", str(dbc), *[a for s in SIGNALS for a in ("--signal", s)]]


def _cia402(d: Path) -> Path:
    from user_drives import cia402_log

    from canrls.sim.scenario import simulate

    log = d / "cia402.log"
    cia402_log(simulate(scenario("standard", effects="inertia,viscous,coulomb,unbalance",
                                  seed=5, duration=6.0)), log)
    return log


def _odrive(d: Path) -> Path:
    from user_drives import odrive_log

    from canrls.sim.scenario import simulate

    log = d / "odrive.log"
    odrive_log(simulate(scenario("standard", effects="inertia,viscous,coulomb,unbalance",
                                 seed=6, duration=6.0)), log)
    return log


#: name -> (how to make the log, fit arguments, export arguments)
DRIVES: dict[str, Any] = {
    "own": (lambda d: _sim(d, "own", ["--duration", "8", "--seed", "1", "--effects",
                                      "inertia,viscous,coulomb,offset,unbalance"]),
            ["--kt", "0.1", "-e", "inertia,viscous,coulomb,offset,unbalance"], []),
    "motorola": (lambda d: _motorola(d)[0], None, []),
    "cia402": (_cia402, [*CIA_MAP, "-e", "inertia,viscous,coulomb,unbalance"], []),
    "odrive": (_odrive, [*ODRIVE_MAP, "--kt", "0.1", "-e", "inertia,viscous,coulomb,unbalance"],
               []),
    "faults": (lambda d: _sim(d, "faults", [
        "--duration", "8", "--seed", "2", "--effects",
        "inertia,viscous,coulomb,stribeck,offset,cogging:6,electrical",
        "--faults", "drop=0.01,dup=0.005,reorder=0.01,corrupt=0.002"]),
        ["--kt", "0.1", "--lambda", "0.999", "-e",
         "inertia,viscous,coulomb,stribeck,offset,cogging:6,electrical"], []),
    "pending": (lambda d: _motorola(d, noise=False)[0], None, ["--every", "500"]),
    "no-frames": (lambda d: _sim(d, "plain", ["--duration", "5", "--seed", "4"]),
                  ["--kt", "0.1"], ["--frames", "none"]),
}


@pytest.fixture(scope="module")
def drives(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, Any]]:
    """Each drive's log, saved model, fit (JSON) and export directory."""
    d = tmp_path_factory.mktemp("target_c")
    out: dict[str, dict[str, Any]] = {}
    for name, (make, fit_args, export_args) in DRIVES.items():
        log = make(d)
        if fit_args is None:
            fit_args = [*_motorola(d, noise=name != "pending")[1], "--kt", "0.1",
                        "-e", "inertia,viscous,coulomb"]
        saved = d / f"{name}.json"
        fit = json.loads(_quiet(["fit", str(log), *fit_args, "--save-model", str(saved),
                                 "--fixed", "target", "--quiet", "--json"]))
        exp = d / f"c_{name}"
        text = _quiet(["export-c", "--model", str(saved), "--out", str(exp), "--vectors",
                       str(log), *export_args])
        out[name] = {"log": log, "saved": saved, "fit": fit, "out": exp, "text": text}
    return out


def _make(out: Path, target: str) -> str:
    r = subprocess.run(["make", "-s", "-C", str(out), target], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    return r.stdout


@pytest.mark.parametrize("name", list(DRIVES))
def test_the_c_is_bit_exact_on_x86_64(drives: dict[str, dict[str, Any]], name: str) -> None:
    need_tool("make", ["make"])
    need_tool("cc", ["gcc"])
    out = _make(drives[name]["out"], "test")
    assert "bit-exact with the specification" in out, out
    m = re.search(r"(\d+) frames, (\d+) samples, (\d+) state records, (\d+) publications", out)
    assert m is not None and int(m.group(2)) > 1000 and int(m.group(3)) >= 2
    assert int(m.group(4)) > 10


@pytest.mark.parametrize("name", ["own", "motorola", "faults", "pending"])
def test_the_c_built_for_size_is_bit_exact(drives: dict[str, dict[str, Any]], name: str,
                                           tmp_path: Path) -> None:
    """-Os (CANRLS_SMALL: the kernel's loops and helpers out of line, the rescale's and the
    publication's shifts out of line, the CRC-8 by nibbles) replays the same integers: the
    drives with rescales, pending columns, lambda < 1 and rejected frames."""
    import shutil

    need_tool("make", ["make"])
    need_tool("cc", ["gcc"])
    out = tmp_path / "c"
    shutil.copytree(drives[name]["out"], out)
    flags = "-std=c99 -Os -Wall -Wextra -Wconversion -Wpedantic -Werror"
    r = subprocess.run(["make", "-s", "-B", "-C", str(out), "test", f"CFLAGS={flags}"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and "bit-exact with the specification" in r.stdout, (
        r.stdout + r.stderr)


@pytest.mark.parametrize("name", list(DRIVES))
def test_the_generated_front_end_and_the_tables_agree_after_every_frame(
        drives: dict[str, dict[str, Any]], name: str) -> None:
    """Issue 34, 3: the export's canrls_front.c (straight-line code for this model and DBC)
    and the table-driven canrls_target_frame of canrls_target.c, fed the same frames (the
    rejected ones included), hold the same state after every frame and publish the same
    frames; and both replay the vectors bit for bit (``make test``, ``make test-tables``)."""
    from front_tool import both_paths

    out = drives[name]["out"]
    front = (out / "canrls_front.c").read_text()
    # straight-line: nothing of the model's tables is read by the generated frame path
    assert "S->model" not in front and "->messages" not in front and "->filters" not in front
    generated, tables = both_paths(out)
    assert generated.count("\n") >= 1000
    assert generated == tables
    assert "bit-exact with the specification" in _make(out, "test-tables")


@pytest.mark.parametrize("name", ["motorola", "faults", "pending", "odrive"])
def test_the_c_is_bit_exact_on_32_bit_arm(drives: dict[str, dict[str, Any]], name: str) -> None:
    need_tool("arm-linux-gnueabihf-gcc", ["gcc-arm-linux-gnueabihf"])
    need_tool("qemu-arm", ["qemu-user"])
    assert "bit-exact with the specification" in _make(drives[name]["out"], "test-arm")


#: a driver of the exported kernel: init with the model's plan, then with each field of it
#: changed (its low bit flipped); prints each field and what canrls_init_q31 returned
_PLAN_DRIVER = """#include <stdio.h>
#include "canrls_model.h"
int main(void)
{
    static canrls_rls_q31 S;
    const canrls_equation *e = &canrls_model.equations[0];
    printf("model %d\\n", canrls_init_q31(&S, e->plan, e->n, e->p0, e->e0));
#define TRY(f) { canrls_plan_q31 q = *e->plan; q.f ^= 1; \\
        printf(#f " %d\\n", canrls_init_q31(&S, &q, e->n, e->p0, e->e0)); }
    CANRLS_PLAN_FIELDS(TRY)
    return 0;
}
"""


def test_the_kernel_of_a_one_equation_export_takes_its_own_plan_alone(
        drives: dict[str, dict[str, Any]]) -> None:
    """An export of one equation makes its plan a constant of the kernel
    (``CANRLS_PLAN_CONST`` in its canrls_bounds.h): ``canrls_init_q31`` then refuses a
    plan that differs in any field but ``trace_max_lam`` (the target moves it with the
    prior); built with ``-DCANRLS_PLAN_RUNTIME`` it takes any plan. A model of two
    equations has no constant plan."""
    need_tool("cc", ["gcc"])
    out = drives["own"]["out"]
    assert "#define CANRLS_PLAN_CONST {" in (out / "canrls_bounds.h").read_text()
    assert "CANRLS_PLAN_CONST" not in (drives["faults"]["out"] / "canrls_bounds.h").read_text()
    (out / "plan_driver.c").write_text(_PLAN_DRIVER)
    got = {}
    for name, defs in (("const", []), ("runtime", ["-DCANRLS_PLAN_RUNTIME"])):
        exe = out / f"plan_driver_{name}"
        subprocess.run(["cc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-DCANRLS_N=6",
                        *defs, "-I", str(out), str(out / "plan_driver.c"),
                        str(out / "canrls_model.c"), str(out / "canrls_fixed.c"), "-o",
                        str(exe)], check=True)
        run = subprocess.run([str(exe)], capture_output=True, text=True, check=True)
        got[name] = dict(line.split() for line in run.stdout.splitlines())
    const, runtime = got["const"], got["runtime"]
    assert len(const) == 49 and const.pop("model") == "0" and const.pop("trace_max_lam") == "0"
    assert set(const.values()) == {"-1"}, const
    # read at run time: a plan of other shifts is taken (the kernel checks its ranges only)
    assert runtime["model"] == runtime["h_os"] == runtime["s_os"] == runtime["eps_os"] == "0"


def test_the_cortex_m4_objects_hold_no_floating_point(drives: dict[str, dict[str, Any]]) -> None:
    need_tool("arm-none-eabi-gcc", ["gcc-arm-none-eabi", "libnewlib-arm-none-eabi"])
    out = drives["faults"]["out"]
    assert "no floating point" in _make(out, "check-float")
    # the check finds one: cantools' codecs use double
    r = subprocess.run(["arm-none-eabi-gcc", "-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=soft",
                        "-c", "canrls_frames.c", "-o", "frames.o"], cwd=out, capture_output=True)
    assert r.returncode == 0
    nm = subprocess.run(["arm-none-eabi-nm", "frames.o"], cwd=out, capture_output=True,
                        text=True).stdout
    assert re.search(r"__aeabi_[df]", nm)


def test_the_export_replays_on_the_cortex_m4_with_its_stack_and_state(
        drives: dict[str, dict[str, Any]]) -> None:
    """``make test-m4`` of an export: bit for bit on a Cortex-M4 under QEMU, then the
    deepest stack and the state, within what docs/target.md states (the ODrive-style
    float32 drive, canrls' own, and the user's Motorola DBC, whose rescales take the
    deepest stack)."""
    need_tool("arm-none-eabi-gcc", ["gcc-arm-none-eabi", "libnewlib-arm-none-eabi"])
    need_tool("qemu-system-arm", ["qemu-system-arm"])
    doc = (Path(__file__).resolve().parents[2] / "docs" / "target.md").read_text()
    m = re.search(r"stack below (\d+) B and the state at (\d+) B", doc)
    assert m is not None
    stack_max, state = int(m.group(1)), int(m.group(2))
    for name in ("own", "odrive", "motorola"):
        out = _make(drives[name]["out"], "test-m4")
        assert "bit-exact with the specification" in out, out
        got = re.search(r"stack: (\d+) bytes; state \(canrls_target\): (\d+) bytes", out)
        assert got is not None, out
        # the export's bounds are its model's (canrls_bounds.h): less than the maxima's
        assert 0 < int(got.group(1)) < stack_max and 0 < int(got.group(2)) < state, out
    # the repository's bounds, the maxima (the extension's state), on the Cortex-M4
    src = drives["own"]["out"]
    (src / "state_size.c").write_text(
        '#include "canrls_target.h"\n'
        f"typedef char state_size[sizeof(canrls_target) == {state} ? 1 : -1];\n")
    maxima = re.findall(r"#define (CANRLS_\w+) (\d+)", (C_DIR / "canrls_bounds.h").read_text())
    subprocess.run(["arm-none-eabi-gcc", "-mcpu=cortex-m4", "-mthumb", "-std=c99", "-Werror",
                    *(f"-D{k}={v}" for k, v in maxima), "-c", str(src / "state_size.c"),
                    "-o", str(src / "state_size.o")], check=True)


def test_a_difference_fails_the_test(drives: dict[str, dict[str, Any]], tmp_path: Path) -> None:
    # the replay can fail: one published word changed in the vectors
    import shutil

    out = tmp_path / "c"
    shutil.copytree(drives["own"]["out"], out)
    v = out / "canrls_vectors.h"
    text = v.read_text()
    head, tail = text.split("vec_pub_data", 1)
    k = tail.index("{", tail.index("{") + 1) + 1
    tail = tail[:k] + str((int(tail[k:tail.index(",", k)]) + 1) % 256) + tail[tail.index(",", k):]
    v.write_text(head + "vec_pub_data" + tail)
    r = subprocess.run(["make", "-s", "-C", str(out), "test"], capture_output=True, text=True)
    assert r.returncode != 0 and "1 differ from the specification" in r.stdout, r.stdout
    # the first sample that differs and which value: the publication's first frame
    first = (r"first difference: sample \d+ \(frame \d+\), publication 0, frame 0 "
             r"\(bytes 0\.\.3 little endian\): expected -?\d+, got -?\d+")
    assert re.search(first, r.stdout), r.stdout
    # and a word of a state record: named by its place in the record
    v.write_text(text)
    head, tail = text.split("vec_cp[", 1)
    k = tail.index("{") + 1
    w = list(re.finditer(r"-?\d+", tail[k:]))[30]   # word 30 of the first record
    tail = tail[:k + w.start()] + str(int(w.group()) + 1) + tail[k + w.end():]
    v.write_text(head + "vec_cp[" + tail)
    r = subprocess.run(["make", "-s", "-C", str(out), "test"], capture_output=True, text=True)
    m = re.search(r"first difference: sample (\d+) \(frame \d+\), state (.+) of equation 0: "
                  r"expected (-?\d+), got (-?\d+)", r.stdout)
    assert r.returncode != 0 and m is not None, r.stdout
    assert m.group(1) == "1000" and int(m.group(3)) == int(m.group(4)) + 1


def test_the_rescales_and_the_pending_columns_run_on_the_target(
        drives: dict[str, dict[str, Any]]) -> None:
    from canrls.firmware.load import load, target_model
    from canrls.firmware.vectors import log_frames, record

    for name, first in (("motorola", False), ("pending", True)):
        src = load(drives[name]["saved"])
        tm = target_model(src)
        pend = [c.name for e in tm.equations for c in e.columns if c.pending]
        assert bool(pend) == first, pend
        v = record(tm, log_frames([drives[name]["log"]]))
        rescales = v.checkpoints[-1][1][-1]
        assert rescales >= 1, name
        fit = drives[name]["fit"]
        assert fit["equations"]["mechanical"]["rescale_count"] >= 1


def test_the_target_follows_the_float_within_0_1_percent(
        drives: dict[str, dict[str, Any]]) -> None:
    """The specification's estimate against the fit's float and fixed point: within
    0.1 % of the float (or of 3 sigma for a parameter near 0), and the fit's fixed
    column to the bit."""
    from canrls.estimation.estimates import divergence
    from canrls.firmware.load import load, target_model
    from canrls.firmware.vectors import log_frames, record

    for name in ("own", "motorola", "cia402", "pending", "odrive"):
        tm = target_model(load(drives[name]["saved"]))
        v = record(tm, log_frames([drives[name]["log"]]))
        params = drives[name]["fit"]["parameters"]
        names = [p.name for e in tm.equations for p in e.parameters]
        value = [params[n]["value"] for n in names]
        sigma = [params[n]["sigma"] for n in names]
        assert divergence(value, v.theta, sigma) <= 1e-3, (name, v.theta, value)
        # and the fit's own fixed column is the target's, to the bit
        assert [params[n]["fixed"] for n in names] == v.theta, name


def test_float32_signals_decode_and_nan_infinity_and_out_of_range_are_rejected(
        drives: dict[str, dict[str, Any]]) -> None:
    """The ODrive-style drive's float32 fields in fixed point: every frame whose velocity
    is NaN, infinite or outside the DBC's range is rejected as out of range (the float
    decoder rejects the same samples), -0.0 and a subnormal pass; the export is whole."""
    from user_drives import ODRIVE_BAD

    from canrls.firmware.load import load, target_model
    from canrls.firmware.spec import REJECTS
    from canrls.firmware.vectors import log_frames, record

    tm = target_model(load(drives["odrive"]["saved"]))
    f = tm.roles["speed"]
    assert f.is_float and f.length == 32 and f.frac == 30 - 8  # 200 rev/s in 30 bits
    v = record(tm, log_frames([drives["odrive"]["log"]]))
    rejected = v.checkpoints[-1][1][1 + REJECTS.index("range")]
    n_bad = 6000 // 397
    passes = sum(1 for k in range(n_bad)
                 if -200 <= ODRIVE_BAD[k % len(ODRIVE_BAD)] <= 200)
    assert rejected == n_bad - passes == 12
    assert drives["odrive"]["fit"]["equations"]["mechanical"]["samples"] > 5000
    out = drives["odrive"]["out"]
    assert {"Makefile", "README.md", "canrls_target.c", "canrls_vectors.h"} <= {
        p.name for p in out.iterdir()}


def test_the_readme_and_the_header_say_what_the_firmware_needs(
        drives: dict[str, dict[str, Any]]) -> None:
    out = drives["own"]["out"]
    readme = (out / "README.md").read_text()
    for what in ("canrls_target_init(&S, &canrls_model)", "canrls_target_frame(",
                 "canrls_target_publish(", "-DCANRLS_N=6", "make check-float", "make test",
                 "inertia.J", "unbalance.cos", "no floating point"):
        assert what in readme, what
    h = (out / "canrls_model.h").read_text()
    assert "#define CANRLS_PARAM_UNBALANCE_COS 5u" in h and "CANRLS_N != 6" in h
    assert not (drives["no-frames"]["out"] / "canrls_frames.c").exists()
    assert ".has_frames = 0u" in (drives["no-frames"]["out"] / "canrls_model.c").read_text()
    # both equations: their n differ, the kernel is built for any n
    h2 = (drives["faults"]["out"] / "canrls_model.h").read_text()
    assert "build without -DCANRLS_N" in h2


@pytest.mark.parametrize("name", ["own", "no-frames"])
def test_the_readme_s_c_compiles_with_the_export_s_warnings(
        drives: dict[str, dict[str, Any]], name: str) -> None:
    # what a firmware engineer copies: the README's C, built as the Makefile builds
    cc = need_tool("cc", ["gcc"])
    out = drives[name]["out"]
    blocks = re.findall(r"```c\n(.*?)```", (out / "README.md").read_text(), re.S)
    assert len(blocks) == 1
    (out / "use.c").write_text(blocks[0])
    mk = (out / "Makefile").read_text()
    flags = re.search(r"^CFLAGS \?= (.*)$", mk, re.M).group(1).split()  # type: ignore[union-attr]
    defs = re.search(r"^DEFS \?= ?(.*)$", mk, re.M).group(1).split()  # type: ignore[union-attr]
    r = subprocess.run([cc, *flags, "-Wsign-conversion", *defs, "-c", "use.c", "-o", "use.o"],
                       cwd=out, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert ("can_send(&out[i])" in blocks[0]) == (name == "own")
    if name == "own":
        # and canrls' README's, on the same export
        text = (Path(__file__).resolve().parents[2] / "README.md").read_text()
        part = text[text.index("### From a log to a passing target test"):]
        (out / "use_readme.c").write_text(re.findall(r"```c\n(.*?)```", part, re.S)[0])
        r = subprocess.run([cc, *flags, "-Wsign-conversion", *defs, "-c", "use_readme.c",
                            "-o", "use_readme.o"], cwd=out, capture_output=True, text=True,
                           timeout=120)
        assert r.returncode == 0, r.stderr


def test_a_user_term_is_refused_with_the_reason(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "drive.toml"
    cfg.write_text('[model]\neffects = ["inertia", "viscous", "user:drag"]\nkt = 0.1\n'
                   '[[model.terms]]\nname = "drag"\nexpr = "omega * abs(omega)"\n'
                   'range = [-1e4, 1e4]\n')
    # the kernel and its configuration are written, the whole estimator is not: why, on
    # stderr
    assert main(["export-c", "--model", str(cfg), "--out", str(tmp_path / "c")]) == 0
    err = capsys.readouterr().err
    assert "the whole estimator is not written" in err and "user:drag" in err
    assert "user term" in err and "--kernel-only" in err, err
    assert (tmp_path / "c" / "canrls_config.h").exists()
    assert not (tmp_path / "c" / "canrls_target.c").exists()
    # vectors need the whole estimator: an error, nothing written
    log = tmp_path / "x.log"
    log.write_text("(0.0) can0 101#0000000000000000\n")
    assert main(["export-c", "--model", str(cfg), "--out", str(tmp_path / "v"),
                 "--vectors", str(log)]) == 1
    assert "user term" in capsys.readouterr().err and not (tmp_path / "v").exists()
    assert main(["export-c", "--model", str(cfg), "--out", str(tmp_path / "k"),
                 "--kernel-only"]) == 0
    assert not (tmp_path / "k" / "canrls_target.c").exists()


def test_the_whole_estimator_is_written_only_into_a_directory(
        drives: dict[str, dict[str, Any]], tmp_path: Path) -> None:
    """export_target, called on its own, refuses an output that is a file (as export_c
    does) and replaces a link planted at a name instead of writing through it."""
    from canrls.core.errors import ConfigError
    from canrls.firmware.load import load, target_model
    from canrls.firmware.target_export import export_target

    src = load(drives["own"]["saved"])
    tm = target_model(src)
    a_file = tmp_path / "out"
    a_file.write_text("precious")
    with pytest.raises(ConfigError, match="exists and is a regular file, not a directory"):
        export_target(src, a_file, tm)
    assert a_file.read_text() == "precious"
    out = tmp_path / "fw"
    out.mkdir()
    precious = tmp_path / "precious.txt"
    precious.write_text("precious")
    (out / "README.md").symlink_to(precious)
    export_target(src, out, tm)
    assert precious.read_text() == "precious" and not (out / "README.md").is_symlink()


def test_only_the_words_that_can_leave_int32_are_saturated_in_the_generated_step(
        drives: dict[str, dict[str, Any]], monkeypatch: pytest.MonkeyPatch) -> None:
    """The generated front end hands a data-scaled column and the output to the kernel
    without saturating them, since they are within 2^f by then (f <= 30): a larger value
    changes the normalisation first and the rescale leaves them within it. Checked on the
    specification's values over the drives with rescales, pending columns and frame
    faults, and in the generated C: every other column saturated but a narrow filter's
    (an int32 by its arithmetic), and the shift of a fixed column (neither adaptive nor
    pending) a constant."""
    from canrls.firmware.load import load, target_model
    from canrls.firmware.spec import TargetEstimator
    from canrls.firmware.vectors import log_frames, record

    used: list[tuple[Any, list[int], int]] = []
    last: dict[int, tuple[list[int], int]] = {}
    values, update = TargetEstimator._values, TargetEstimator._update

    def _values(self: TargetEstimator, es: Any) -> tuple[list[int], int]:
        last[id(es)] = values(self, es)
        return last[id(es)]

    def _update(self: TargetEstimator, es: Any) -> None:
        update(self, es)
        used.append((es.spec, *last[id(es)]))

    monkeypatch.setattr(TargetEstimator, "_values", _values)
    monkeypatch.setattr(TargetEstimator, "_update", _update)
    for name in ("own", "motorola", "pending", "faults"):
        used.clear()
        tm = target_model(load(drives[name]["saved"]))
        record(tm, log_frames([drives[name]["log"]]))
        assert used, name
        for e, phi, y in used:
            assert e.f_phi <= 30 and e.f_y <= 30
            assert abs(y) <= 1 << e.f_y, (name, e.name, y)
            for c, v in zip(e.columns, phi, strict=True):
                assert not c.adaptive or abs(v) <= 1 << e.f_phi, (name, c.name, v)
                # a narrow filter's column: an int32 by its arithmetic
                assert not tm.filters[c.filter].narrow or -(1 << 31) <= v < 1 << 31, \
                    (name, c.name, v)
        front = (drives[name]["out"] / "canrls_front.c").read_text()
        for k, e in enumerate(tm.equations):
            body = front[front.index(f"static CR_NOINLINE void fr_update_{k}("):]
            body = body[:body.index("\n}\n")]
            for j, c in enumerate(e.columns):
                word = f"phq[{j}] = (int32_t)v{j}" if c.adaptive \
                    else f"phq[{j}] = cr_sat32(v{j})"
                narrow = f"phq[{j}] = (int32_t)v{j}; /* an int32: a narrow state's shift */"
                assert word in body or (tm.filters[c.filter].narrow and narrow in body), \
                    (name, c.name, body)
                # a fixed column's shift is its model's (a rescale moves only the others)
                fixed = not c.adaptive and not c.pending
                assert (f"q->sh[{j}]" in body) != fixed, (name, c.name, body)
            assert "(int32_t)y" in body, body
