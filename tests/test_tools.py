"""tools/: the SocketCAN set-up script, the systemd unit, and a smoke run of the soak.

This kernel has no CAN support, so ``setup_can.sh`` runs against stand-ins for ``ip``
and ``modprobe`` placed first on PATH: they record their arguments (and answer ``ip
link show`` as the test says), and the test checks the exact commands the script
would give on a real machine. The unit file goes through ``systemd-analyze verify``
where that tool is installed. ``tools/soak.py`` runs for a few simulated seconds (the
hour-long soak is not part of the test run).
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

TOOLS = Path(__file__).resolve().parent.parent / "tools"
SETUP = TOOLS / "setup_can.sh"
UNIT = TOOLS / "canrls.service"

_STANDIN = """#!/bin/sh
echo "$(basename "$0") $*" >> "{log}"
if [ "$1 $2" = "link show" ] && [ -e "{dir}/exists-$3" ]; then exit 0; fi
if [ "$1 $2" = "link show" ]; then exit 1; fi
exit 0
"""


def _run(tmp_path: Path, *args: str, existing: tuple[str, ...] = ()
         ) -> tuple[int, list[str], str]:
    """Run setup_can.sh with ``args``; (exit code, commands run, stderr)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    log = tmp_path / "commands.log"
    log.write_text("")
    for name in ("ip", "modprobe"):
        p = bin_dir / name
        p.write_text(_STANDIN.format(log=log, dir=tmp_path))
        p.chmod(p.stat().st_mode | stat.S_IXUSR)
    for iface in existing:
        (tmp_path / f"exists-{iface}").touch()
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"}
    r = subprocess.run(["sh", str(SETUP), *args], env=env, capture_output=True, text=True,
                       timeout=30)
    return r.returncode, log.read_text().splitlines(), r.stderr


def test_setup_script_parses() -> None:
    assert subprocess.run(["sh", "-n", str(SETUP)], capture_output=True).returncode == 0


def test_setup_real_controller_with_bitrate_restart_and_error_reporting(tmp_path: Path
                                                                         ) -> None:
    rc, cmds, _ = _run(tmp_path, "can0", "500000", "200")
    assert rc == 0
    assert cmds == [
        "ip link set can0 down",
        "ip link set can0 type can bitrate 500000 restart-ms 200 berr-reporting on",
        "ip link set can0 txqueuelen 1000",
        "ip link set can0 up",
        "ip -details link show can0",
    ]
    rc, cmds, _ = _run(tmp_path, "can1")  # defaults: 1 Mbit/s, restart after 100 ms
    assert rc == 0 and cmds[1] == ("ip link set can1 type can bitrate 1000000 restart-ms 100 "
                                   "berr-reporting on")


def test_setup_virtual_interface_created_once(tmp_path: Path) -> None:
    rc, cmds, _ = _run(tmp_path, "vcan0")
    assert rc == 0
    assert cmds == ["modprobe vcan", "ip link show vcan0", "ip link add dev vcan0 type vcan",
                    "ip link set vcan0 up", "ip -details link show vcan0"]
    rc, cmds, _ = _run(tmp_path, "vcan0", existing=("vcan0",))
    assert rc == 0 and "ip link add dev vcan0 type vcan" not in cmds


def test_setup_down_and_usage(tmp_path: Path) -> None:
    rc, cmds, _ = _run(tmp_path, "down", "vcan0")
    assert rc == 0 and cmds == ["ip link set vcan0 down", "ip link delete vcan0"]
    rc, cmds, _ = _run(tmp_path, "down", "can0")
    assert rc == 0 and cmds == ["ip link set can0 down"]
    for args in ((), ("down",), ("down", "a", "b")):
        rc, cmds, err = _run(tmp_path, *args)
        assert rc == 2 and cmds == [] and "usage:" in err


@pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                    reason="systemd-analyze is not installed")
def test_systemd_unit_verifies_without_warnings(tmp_path: Path) -> None:
    r = subprocess.run(["systemd-analyze", "verify", str(UNIT)], capture_output=True,
                       text=True, timeout=60, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stderr.strip() == "" and r.stdout.strip() == ""


def test_systemd_unit_is_notify_with_watchdog_and_restart() -> None:
    text = UNIT.read_text()
    lines = {line.split("=", 1)[0]: line.split("=", 1)[1]
             for line in text.splitlines() if "=" in line and not line.startswith("#")}
    assert lines["Type"] == "notify" and lines["Restart"] == "on-failure"
    assert lines["WatchdogSec"].endswith("s") and lines["KillSignal"] == "SIGTERM"
    assert "--log-level" in lines["ExecStart"] and " run " in lines["ExecStart"]


# --------------------------------------------------------------------------- tools/soak.py

SOAK = TOOLS / "soak.py"
SRC = TOOLS.parent / "src"
#: every kind of fault, often enough to occur in a few simulated seconds
_SMOKE_FAULTS = ("drop=0.01,dup=0.01,reorder=0.01,corrupt=0.01,counter=0.01,dlc=0.01,"
                 "silence=0.2s@1s,tstep=0.0005,tstep_max=0.2s,cmd=0.001,cmd_burst=4,"
                 "errframe=0.001")


def _soak(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (str(SRC), os.environ.get("PYTHONPATH", "")) if p)}
    return subprocess.run([sys.executable, str(SOAK), "--quiet", *args], env=env,
                          cwd=tmp_path, capture_output=True, text=True, timeout=300)


def test_soak_smoke_run_counts_every_fault_and_judges(tmp_path: Path) -> None:
    """A few simulated seconds of the soak: the daemon takes every frame, every kind of
    fault is injected and counted, every parameter is compared, and the run ends with a
    verdict (the figures themselves are the tool's output, not asserted here)."""
    r = _soak(tmp_path, "--duration", "4", "--seed", "3", "--faults", _SMOKE_FAULTS)
    out = r.stdout
    assert r.returncode in (0, 1), r.stderr
    m = re.search(r"^frames processed: (\d+) of (\d+) offered \(twin: (\d+) of (\d+)\)", out,
                  re.M)
    assert m is not None, out
    assert m.group(1) == m.group(2) and m.group(3) == m.group(4) == "8000"
    counts = dict(re.findall(r"^  (\w+) +(\d+)$", out, re.M))
    for kind in ("dropped", "silenced", "corrupted", "miscounted", "resized", "duplicated",
                 "reordered", "clock_steps", "commands", "error_frames"):
        assert int(counts[kind]) > 0, kind
    injected = re.search(r"^faults injected: (\d+)", out, re.M)
    assert injected is not None, out
    total = int(injected.group(1))
    assert total == sum(int(v) for v in counts.values())
    assert re.search(rf"^faults survived: {total} of {total}$", out, re.M), out
    # the daemon answered every injected command and saw every error frame
    assert re.search(rf"commands {counts['commands']} \(rejected \d+\), acknowledgements",
                     out), out
    assert f"error frames {counts['error_frames']};" in out
    params = re.findall(r"^  (\S+) +fixed .* sigma", out, re.M)
    assert len(params) == 3 + 2 + 2 + 1  # n = 8 of the default model
    assert re.search(r"^RSS \[MB\] at each tenth of the run: 0 s [\d.]+(, [\d.]+ s [\d.]+){10}$",
                     out, re.M), out
    # both criteria printed, each parameter judged by both, the verdict's named
    for c in ("literal", "accuracy"):
        assert re.search(rf"^criterion {c} \(lost when .*\): (met|not met \(.*\))", out,
                         re.M), out
    assert len(re.findall(r"\[literal: (kept|lost)/(kept|lost), accuracy: (kept|lost)/"
                          r"(kept|lost)\]$", out, re.M)) == len(params)
    verdicts = re.findall(r"^criterion (\w+) .*; the verdict's$", out, re.M)
    assert len(verdicts) == 1, out
    assert re.search(r"^process: peak RSS [\d.]+ MB at the start, [\d.]+ MB at the end; "
                     r"threads \d+ at the start, \d+ while the faulted run served \(twin \d+\), "
                     r"\d+ at the end$", out, re.M), out
    last = out.strip().splitlines()[-1]
    assert last.startswith("PASSED: " if r.returncode == 0 else "FAILED: not met: ")
    assert r.returncode == 1 or f"no parameter lost ({verdicts[0]})" in last
    assert r.returncode == 1 or last.endswith("; threads back to 1 at the end")
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_soak_of_two_axes_judges_each_axis_and_the_machine(tmp_path: Path) -> None:
    """A few simulated seconds of two drives on one bus, one daemon per axis: each axis
    takes its own frames and every error frame on the bus (no more, no fewer), answers
    its own drive's commands, survives its own faults and is judged against its twin;
    the machine's verdict is the first line of the verdict block, each axis's after it,
    and the threads are back to the start's."""
    r = _soak(tmp_path, "--duration", "3", "--seed", "3", "--axes", "2",
              "--faults", _SMOKE_FAULTS)
    out = r.stdout
    assert r.returncode in (0, 1), r.stderr
    assert out.startswith("soak: 2 axes on one bus"), out
    heads = re.findall(r"^(axis\d): feedback IDs (0x\w+), (0x\w+), own frames (0x\w+)\.\., "
                       r"command (0x\w+);", out, re.M)
    assert heads == [("axis1", "0x101", "0x102", "0x300", "0x320"),
                     ("axis2", "0x111", "0x112", "0x340", "0x360")], out
    parts = re.split(r"^axis\d: ", out, flags=re.M)[1:]
    parts[-1] = parts[-1].split("\nthe machine:")[0]
    counts = [dict(re.findall(r"^    (\w+) +(\d+)$", p, re.M)) for p in parts]
    errors = sum(int(c["error_frames"]) for c in counts)
    for p, c in zip(parts, counts, strict=True):
        m = re.search(r"^  frames processed: (\d+) of (\d+) offered \(twin: (\d+) of (\d+)\)",
                      p, re.M)
        assert m is not None, p
        assert m.group(1) == m.group(2) and m.group(3) == m.group(4) == "6000"
        for kind in ("dropped", "corrupted", "miscounted", "resized", "duplicated",
                     "reordered", "commands"):
            assert int(c[kind]) > 0, (kind, p)
        total = sum(int(v) for v in c.values())
        assert re.search(rf"^  faults injected: {total} ", p, re.M), p
        assert re.search(rf"^  faults survived: {total} of {total}$", p, re.M), p
        # its own drive's commands, none of the other's; every error frame of the bus
        assert re.search(rf"commands {c['commands']} \(rejected \d+\), acknowledgements", p), p
        assert f"error frames {errors};" in p, (errors, p)
        assert len(re.findall(r"\[literal: (kept|lost)/(kept|lost), accuracy: (kept|lost)/"
                              r"(kept|lost)\]$", p, re.M)) == 8
    # the receive clock is the bus's: its steps hit the axes' frames, and error frames
    m = re.search(r"^the machine: frames of no axis 0 \(twin 0\); steps of the bus's receive "
                  r"clock (\d+) ", out, re.M)
    assert m is not None and int(m.group(1)) > 0, out
    steps = [int(c["clock_steps"]) for c in counts]
    assert max(steps) <= int(m.group(1)) <= sum(steps), (steps, out)
    m = re.search(r"^process: peak RSS [\d.]+ MB at the start, [\d.]+ MB at the end; threads "
                  r"(\d+) at the start, (\d+) while the faulted run served \(twin \d+\), (\d+) "
                  r"at the end$", out, re.M)
    assert m is not None and int(m.group(2)) > int(m.group(1)) == int(m.group(3)), out
    verdict = out.strip().splitlines()[-3:]
    assert verdict[0].startswith("PASSED: " if r.returncode == 0 else "FAILED: not met: ")
    for line, name in zip(verdict[1:], ("axis1", "axis2"), strict=True):
        assert re.fullmatch(rf"  {name}: (passed|failed: .+)", line), verdict
    assert r.returncode == 1 or verdict[1:] == ["  axis1: passed", "  axis2: passed"]
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_soak_bad_fault_spec_is_one_line(tmp_path: Path) -> None:
    r = _soak(tmp_path, "--duration", "1", "--faults", "drop=2")
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1].startswith("soak.py: error: --faults:")
    assert "drop" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize(("axes", "why"), [("0", "1 to 32 simulated drives"),
                                           ("21", "outside the standard IDs")])
def test_soak_bad_axes_is_one_line(tmp_path: Path, axes: str, why: str) -> None:
    r = _soak(tmp_path, "--duration", "1", "--axes", axes)
    assert r.returncode == 2
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith(f"soak.py: error: --axes {axes}: ") and why in last, r.stderr
    assert "Traceback" not in r.stderr and r.stdout == ""


def _soak_module():  # type: ignore[no-untyped-def]
    import importlib.util
    spec = importlib.util.spec_from_file_location("_soak_tool", SOAK)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    try:
        spec.loader.exec_module(mod)
    finally:
        del sys.modules[spec.name]
    return mod


# ------------------------------------------------- the daemon the benchmarks measure

#: what a daemon built without the target's path logs (canrls.live.daemon): its fixed
#: column is then not the one ``canrls run`` publishes
_NO_TARGET = "no target path was given"
#: the shortest runs of the benchmarks: one rate, one latency run, no memory; one axis
_SHORT = {"bench_daemon.py": ("--rates", "2000", "--seconds", "0.3", "--latency-rate", "2000",
                              "--latency-runs", "1", "--skip-memory"),
          "bench_axes.py": ("--axes", "1", "--seconds", "0.3")}


@pytest.mark.parametrize("tool", sorted(_SHORT))
def test_benchmark_measures_the_daemon_canrls_run_builds(tmp_path: Path, tool: str) -> None:
    """The benchmarks build their daemons as ``canrls run`` does (the target's integer path
    publishes the fixed column, ``[daemon] fixed`` by default), so their figures are the
    daemon's: no warning that the target's path is missing."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (str(SRC), os.environ.get("PYTHONPATH", "")) if p)}
    r = subprocess.run([sys.executable, str(TOOLS / tool), *_SHORT[tool]], env=env,
                       cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert _NO_TARGET not in r.stderr, r.stderr
    assert r.stdout.strip(), r.stderr


def test_soak_builds_the_daemon_canrls_run_builds(caplog: pytest.LogCaptureFixture) -> None:
    """The soak's daemons (the faulted run's and the twin's) are built as ``canrls run``
    builds them: the target's path publishes the fixed column, no warning that it is
    missing (the soak counts the daemon's warnings rather than printing them)."""
    soak = _soak_module()
    with caplog.at_level(logging.WARNING, logger="canrls"):
        soak.make_daemon("soak-fixed-path", soak.EFFECTS)  # [daemon] fixed by default
    assert [r.getMessage() for r in caplog.records] == []


def test_soak_judges_a_parameter_by_the_accuracy_the_faults_cost() -> None:
    """The soak's verdict per parameter: lost when the faults leave it further from the
    drive's truth than the fault-free twin by more than 2 sigma; a move of more than
    2 sigma from the twin that is no less accurate (the twin's own bias reweighted,
    docs/reliability.md "## Soak") is kept. Without a true value: within 2 sigma of the
    twin."""
    from canrls.can.estimator_frames import ParameterReport
    soak = _soak_module()

    def rr(values: dict[str, float], sigma: float = 1e-9) -> object:
        r = soak.RunResult("x")
        r.params = {k: ParameterReport(index=i, name=k, fixed_value=v, sigma=sigma,
                                       float_value=v) for i, (k, v) in enumerate(values.items())}
        return r

    truth = {"inertia.J": 2.0e-4, "offset.T0": 5e-3, "viscous.B": 1e-4}
    # the twin 13 sigma above the truth (its bias); the faulted run:
    free = rr({"inertia.J": 2.0e-4 + 13e-9, "offset.T0": 5e-3, "viscous.B": 1e-4})
    faulted = rr({"inertia.J": 2.0e-4 + 10.6e-9,   # 2.4 sigma from the twin, closer to truth
                  "offset.T0": 5e-3 + 2.5e-9,      # 2.5 sigma further from the truth
                  "viscous.B": 1e-4 - 1.9e-9})     # 1.9 sigma further: kept
    rows = soak.compare(faulted, free, truth)
    verdict = {(n, w): v for n, w, _z, _g, v in rows}
    for which in ("fixed_value", "float_value"):
        assert verdict[("inertia.J", which)] == ""
        assert verdict[("viscous.B", which)] == ""
        assert verdict[("offset.T0", which)].startswith("worse by 2.5 > 2 sigma")
    z = {n: zz for n, w, zz, _g, _v in rows if w == "float_value"}
    assert z["inertia.J"] == pytest.approx(-2.4)
    # no true value (a real drive): the twin is the reference, 2 sigma
    rows = soak.compare(faulted, free, None)
    lost = sorted({n for n, _w, _z, _g, v in rows if v})
    assert lost == ["inertia.J", "offset.T0"]


# ----------------------------------------------------------------- tools/gap_fill_cost.py
def test_gap_fill_cost_prints_each_variant_against_the_twin(tmp_path: Path) -> None:
    """A few simulated seconds of the measurement behind docs/reliability.md ("Why not
    within 2 sigma of the twin"): a row per variant, every parameter in sigma; the
    patched gap filler is put back."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (str(SRC), os.environ.get("PYTHONPATH", "")) if p)}
    r = subprocess.run([sys.executable, str(TOOLS / "gap_fill_cost.py"), "--duration", "3",
                        "--fraction", "0.01", "--seeds", "1", "--variants", "line", "oracle"],
                       env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    rows = re.findall(r"^  (line|oracle|twin-tru)((?:\s+[+-]\d+\.\d\d){8})", r.stdout, re.M)
    assert [v for v, _ in rows] == ["line", "oracle", "twin-tru"], r.stdout
    assert "30 single-sample gaps" in r.stdout
    assert list(tmp_path.iterdir()) == []
