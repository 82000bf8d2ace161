"""``canrls fit --fixed target``: the fit's fixed column is the exported C's, bit for bit.

A fit with ``--fixed target --save-model`` takes its fixed column from the target's
integer path; ``canrls export-c`` of the saved model with the same log as vectors
reproduces it: the specification's final estimate, which the exported C reproduces word
for word (``make test``), is the fit's fixed column to the last bit; both within 0.1 %
of the float. On the simulated drive in canrls' DBC, on a user's Motorola DBC through a
window of standstill (rescales), on a CiA 402 drive reporting its torque in its own DBC,
and on an HSM150 run in its own DBC where the runs are there.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from debian import need_tool

from canrls.cli.main import main
from canrls.estimation.estimates import divergence
from canrls.firmware.load import load, target_model
from canrls.firmware.vectors import log_frames, record

sys.path.insert(0, str(Path(__file__).resolve().parent))
ROOT = Path(__file__).resolve().parents[2]
HSM = ROOT.parent / "shared" / "data" / "hsm150"


def _canrls(argv: list[str]) -> str:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(argv) == 0, buf.getvalue()
    return buf.getvalue()


def _check(log: Path, fit_args: list[str], tmp: Path, test_c: bool = True,
           fixed: str | None = "target") -> dict[str, Any]:
    saved = tmp / "m.json"
    how = ["--fixed", fixed] if fixed else []
    fit = json.loads(_canrls(["fit", str(log), *fit_args, *how, "--save-model",
                              str(saved), "--json", "--quiet"]))
    names = list(fit["parameters"])
    fixed = [fit["parameters"][n]["fixed"] for n in names]
    v = record(target_model(load(saved)), log_frames([log]))
    # the specification's estimate from the saved model is the fit's fixed column
    assert v.theta == fixed
    assert fit["fixed"]["path"] == "target" and fit["fixed"]["samples"] == v.samples
    value = [fit["parameters"][n]["value"] for n in names]
    sigma = [fit["parameters"][n]["sigma"] for n in names]
    assert divergence(value, fixed, sigma) <= 1e-3
    if test_c:
        out = tmp / "c"
        _canrls(["export-c", "--model", str(saved), "--out", str(out), "--vectors", str(log)])
        need_tool("cc", ["gcc"])
        r = subprocess.run(["make", "-s", "-C", str(out), "test"], capture_output=True,
                           text=True, timeout=600)
        assert r.returncode == 0 and "bit-exact" in r.stdout, r.stdout + r.stderr
    return fit


def test_fit_and_the_exported_c_agree_bit_for_bit(tmp_path: Path) -> None:
    log = tmp_path / "drive.log"
    effects = "inertia,viscous,coulomb,offset,unbalance"
    _canrls(["sim", "--out", str(log), "--duration", "6", "--effects", effects, "--seed", "7"])
    fit = _check(log, ["--kt", "0.1", "-e", effects], tmp_path)
    assert fit["fixed"]["rescales"] == {"mechanical": 0}


def test_through_rescales_in_a_users_dbc(tmp_path: Path) -> None:
    from test_target_c import _motorola

    log, mapping = _motorola(tmp_path)
    fit = _check(log, [*mapping, "--kt", "0.1", "-e", "inertia,viscous,coulomb"], tmp_path)
    assert fit["fixed"]["rescales"]["mechanical"] >= 1


def test_a_torque_reporting_drive_in_a_cia402_dbc(tmp_path: Path) -> None:
    # the drive's own DBC (tests/data/cia402_drive.dbc): torque in per mille of the rated
    # torque, speed and position in encoder increments; the target is the reported torque
    from test_target_c import CIA_MAP, _cia402

    log = _cia402(tmp_path)
    fit = _check(log, [*CIA_MAP, "-e", "inertia,viscous,coulomb,unbalance"], tmp_path)
    assert fit["fixed"]["path"] == "target"
    h = (tmp_path / "c" / "canrls_model.h").read_text()
    assert "CANRLS_PARAM_UNBALANCE_COS" in h
    readme = (tmp_path / "c" / "README.md").read_text()
    assert "| TPDO1 | 0x181 |" in readme and "| TPDO2 | 0x281 |" in readme, readme


def test_the_text_says_where_the_fixed_column_comes_from(tmp_path: Path) -> None:
    log = tmp_path / "drive.log"
    _canrls(["sim", "--out", str(log), "--duration", "4", "--seed", "8"])
    text = _canrls(["fit", str(log), "--kt", "0.1", "--fixed", "target", "--quiet"])
    assert "fixed point: the target's integer path from the frames on" in text
    # each equation's counts by name, not a Python dict
    line = next(x for x in text.splitlines() if x.startswith("fixed point:"))
    assert "updates: mechanical " in line and "rescales: mechanical 0" in line, line
    assert "{" not in line, line


@pytest.mark.skipif(not HSM.is_dir(), reason=f"HSM150 data not found at {HSM} (real "
                    "measurements kept outside the project; see docs/hsm150.md)")
@pytest.mark.slow
def test_an_hsm150_run_in_its_own_dbc(tmp_path: Path) -> None:
    pytest.importorskip("scipy.io", reason="scipy (test extra) reads the .mat runs")
    sys.path.insert(0, str(ROOT / "tools"))
    import hsm150_to_can as tool

    log = tool.convert(HSM / "idf_pos_0.06_1.mat", tmp_path)
    mapping = ["--dbc", str(ROOT / "tests" / "data" / "hsm150_drive.dbc"),
               *[a for s in tool.SIGNALS for a in ("--signal", s)], "--kt", str(tool.KT)]
    # one direction: the fixed point's own gap to the float is the kernel's (0.7 % on
    # the inertia, docs/hsm150.md), not the front end's: bit-exactness is what is held
    saved = tmp_path / "m.json"
    fit = json.loads(_canrls(["fit", str(log), *mapping, "-e", "inertia,viscous,coulomb,offset",
                              "--fixed", "target", "--save-model", str(saved), "--json",
                              "--quiet"]))
    v = record(target_model(load(saved)), log_frames([log]))
    assert v.theta == [p["fixed"] for p in fit["parameters"].values()]
    out = tmp_path / "c"
    _canrls(["export-c", "--model", str(saved), "--out", str(out), "--vectors", str(log)])
    r = subprocess.run(["make", "-s", "-C", str(out), "test"], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0 and "bit-exact" in r.stdout, r.stdout + r.stderr
    # and on 32-bit ARM (the Cortex-M4: make target)
    need_tool("arm-linux-gnueabihf-gcc", ["gcc-arm-linux-gnueabihf"])
    need_tool("qemu-arm", ["qemu-user"])
    r = subprocess.run(["make", "-s", "-C", str(out), "test-arm"], capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0 and "bit-exact" in r.stdout, r.stdout + r.stderr


def test_the_readme_walks_from_a_log_to_a_passing_target_test(tmp_path: Path) -> None:
    # README's "For firmware engineers": its commands, as written, in a fresh directory
    import re
    import shlex

    need_tool("cc", ["gcc"])
    need_tool("make", ["make"])
    text = (ROOT / "README.md").read_text()
    part = text[text.index("### From a log to a passing target test"):]
    block = re.search(r"```sh\n(.*?)```", part, re.S)
    assert block is not None
    lines = [shlex.split(line) for line in block.group(1).splitlines() if line.strip()]
    assert [w[0] for w in lines] == [".venv/bin/canrls"] * 3 + ["make"]
    out = ""
    for words in lines:
        cmd = [sys.executable, "-m", "canrls", *words[1:]] if words[0].endswith("canrls") \
            else words
        r = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, (words, r.stdout, r.stderr)
        out = r.stdout
    assert "bit-exact with the specification" in out, out
    # what the README says the test prints, it prints
    said = re.search(r"`(canrls replay: [^`]*)`", part.replace("\n", " "))
    assert said is not None and said.group(1) in out, (said, out)


def _daemon(log_args: list[str], extra: list[str]) -> Any:
    """The daemon as 'canrls run' builds it (not started; frames given to process())."""
    from canrls.cli.main import build_parser
    from canrls.cli.run import build_daemon

    return build_daemon(build_parser("run").parse_args(
        ["run", "-i", "virtual", "-c", "unused-one-path", *log_args, *extra]))


def _published(d: Any) -> dict[str, float]:
    return {p.name: p.fixed_value for p in d.parameter_reports()}


def test_fit_the_daemon_and_the_exported_c_agree_bit_for_bit(tmp_path: Path) -> None:
    """One integer path, by default: plain ``canrls fit`` prints the target's fixed
    column, the daemon as ``canrls run`` builds it publishes the same values from the
    same frames, and the exported C of the saved model reproduces them (``make test``).
    By name, the kernel's column is the same in both too."""
    from canrls.can.logs import read_frames

    log = tmp_path / "drive.log"
    effects = "inertia,viscous,coulomb,offset,unbalance"
    _canrls(["sim", "--out", str(log), "--duration", "6", "--effects", effects, "--seed", "9"])
    fit = _check(log, ["--kt", "0.1", "-e", effects], tmp_path, fixed=None)
    cfg = tmp_path / "daemon.toml"

    def published(extra: list[str]) -> dict[str, float]:
        # fed the log's frames in blocks of its own
        d = _daemon(["--kt", "0.1", "-e", effects], extra)
        try:
            for b in read_frames(log):
                d.process(b)
            return _published(d)
        finally:
            d.stop()

    assert published([]) == {n: p["fixed"] for n, p in fit["parameters"].items()}
    # the kernel's column, by name, in both
    cfg.write_text('[daemon]\nfixed = "kernel"\n')
    kernel = json.loads(_canrls(["fit", str(log), "--kt", "0.1", "-e", effects, "--json",
                                 "--quiet", "--fixed", "kernel"]))
    assert kernel.get("fixed") is None
    assert published(["--config", str(cfg)]) == {n: p["fixed"]
                                                  for n, p in kernel["parameters"].items()}
    assert kernel["parameters"] != fit["parameters"]


def _after(d: Any, log: Path, frames: Any) -> dict[str, float]:
    """What the target's path computes from ``frames`` alone, with the daemon's
    calibration and period as they are now (its path started again there)."""
    from canrls.firmware.native import TargetFeed
    from canrls.firmware.target_fit import fit_model

    feed = TargetFeed(fit_model(d.processor.result("canrls run"), d.protocol,
                                d.pipeline.settings))
    feed.feed(frames)
    return {name: v for name, (v, _) in feed.fixed().items()}


def _sim_frames(tmp_path: Path, seed: int) -> tuple[Path, Any]:
    """An 8 s simulated log and its frames in one block."""
    from canrls.can.frameblock import FrameBlock
    from canrls.can.logs import read_frames

    log = tmp_path / "drive.log"
    _canrls(["sim", "--out", str(log), "--duration", "8", "--seed", str(seed)])
    return log, FrameBlock.concat(list(read_frames(log)))


def test_a_reset_command_starts_the_target_path_again_and_says_so(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from canrls.can.estimator_frames import CommandCode, encode_command
    from canrls.live.journal import JOURNAL

    log, frames = _sim_frames(tmp_path, 11)
    half = len(frames) // 2
    d = _daemon(["--kt", "0.1", "--commands"], [])
    try:
        d.process(frames.take(slice(0, half)))
        before = _published(d)
        with caplog.at_level("INFO", logger=JOURNAL.name):
            d.process([encode_command(CommandCode.RESET)])
        assert "reset: the fixed point's integer path starts again from its prior" \
            in caplog.text
        rest = frames.take(slice(half, None))
        d.process(rest)
        after = _published(d)
        assert after == _after(d, log, rest) and after != before
    finally:
        d.stop()


def test_an_added_effect_starts_the_target_path_again_on_the_new_model(
        tmp_path: Path) -> None:
    """The command add_effect: the target's path starts again on the completed model, its
    calibration the processor's for that model (before: the old model's column energies
    stopped the estimator thread)."""
    from canrls.can.estimator_frames import CommandCode, EffectId, encode_command

    log, frames = _sim_frames(tmp_path, 14)
    half = len(frames) // 2
    d = _daemon(["--kt", "0.1", "--commands"], [])
    try:
        d.process(frames.take(slice(0, half)))
        d.process([encode_command(CommandCode.ADD_EFFECT, EffectId.OFFSET)])
        assert "offset" in d.model.effect_names
        rest = frames.take(slice(half, None))
        d.process(rest)
        after = _published(d)
        assert "offset.T0" in after and after == _after(d, log, rest)
    finally:
        d.stop()


def test_a_checkpoint_after_an_added_effect_resumes_with_it(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A checkpoint taken after add_effect resumes with the effect and the target's path
    (before: its calibration held the old model's column energies, and the file was set
    aside at the next start, the effect lost)."""
    from canrls.can.estimator_frames import CommandCode, EffectId, encode_command

    _, frames = _sim_frames(tmp_path, 14)
    half = len(frames) // 2
    cfg = tmp_path / "daemon.toml"
    cfg.write_text(f'[daemon]\ncheckpoint = "{tmp_path / "ckpt.bin"}"\n')
    d = _daemon(["--kt", "0.1", "--commands", "--config", str(cfg)], [])
    try:
        d.process(frames.take(slice(0, half)))
        d.process([encode_command(CommandCode.ADD_EFFECT, EffectId.OFFSET)])
        d.process(frames.take(slice(half, None)))
        assert d.checkpoint() is not None
    finally:
        d.stop()
    d = _daemon(["--kt", "0.1", "--commands", "--config", str(cfg)], [])
    try:
        _start_resumed(d, caplog, "continues from the checkpoint")
        assert "offset" in d.model.effect_names
    finally:
        d.stop()


def test_freeze_and_set_lambda_reach_the_target_path(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The command freeze holds the published fixed column as it holds the kernel's,
    resume lets it move again; set_lambda starts the path again with the new forgetting
    factor (a new kernel plan), said in the log."""
    from canrls.can.estimator_frames import CommandCode, encode_command

    log, frames = _sim_frames(tmp_path, 13)
    q = len(frames) // 4
    d = _daemon(["--kt", "0.1", "--commands"], [])
    try:
        d.process(frames.take(slice(0, q)))
        d.process([encode_command(CommandCode.FREEZE)])
        held = _published(d)
        d.process(frames.take(slice(q, 2 * q)))
        assert _published(d) == held
        d.process([encode_command(CommandCode.RESUME)])
        d.process(frames.take(slice(2 * q, 3 * q)))
        assert _published(d) != held
        with caplog.at_level("WARNING"):
            d.process([encode_command(CommandCode.SET_LAMBDA, lam=0.999)])
            rest = frames.take(slice(3 * q, None))
            d.process(rest)
        assert "starts again from its prior (lambda 0.999" in caplog.text
        assert d.pipeline.settings.lam == pytest.approx(0.999)
        assert _published(d) == _after(d, log, rest)
    finally:
        d.stop()


def _checkpointed(tmp_path: Path, frames: Any, name: str) -> Path:
    """The configuration of a daemon checkpointing to ``name``, after a daemon ran
    ``frames``, checkpointed and stopped."""
    cfg = tmp_path / f"{name}.toml"
    cfg.write_text(f'[daemon]\ncheckpoint = "{tmp_path / name}"\n')
    d = _daemon(["--kt", "0.1", "--config", str(cfg)], [])
    try:
        d.process(frames)
        assert d.checkpoint() is not None
    finally:
        d.stop()
    return cfg


def _target_state(d: Any) -> Any:
    """The target's C state as a checkpoint of ``d`` holds it (every byte)."""
    from canrls.live.checkpoint import load_checkpoint

    path = d.checkpoint()
    assert path is not None
    return load_checkpoint(path).state["target"]["state"]


def _start_resumed(d: Any, caplog: pytest.LogCaptureFixture, says: str) -> None:
    """Start ``d``, resumed from its checkpoint; its journal ``says`` what of the target's
    integer path."""
    from canrls.live.journal import JOURNAL

    assert d.resumed_from is not None
    with caplog.at_level("INFO", logger=JOURNAL.name):
        d.start()
    assert f"resumed from {d.resumed_from}: the fixed point's integer path {says}" \
        in caplog.text


def test_a_resume_from_a_checkpoint_continues_the_target_path_bit_for_bit(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Run, checkpoint, stop, resume: the daemon publishes the fixed column of one that
    never stopped on the same frames, its C state the same to the byte."""
    log, frames = _sim_frames(tmp_path, 12)
    half = len(frames) // 2
    cfg = _checkpointed(tmp_path, frames.take(slice(0, half)), "ckpt.bin")
    d = _daemon(["--kt", "0.1", "--config", str(cfg)], [])
    whole = tmp_path / "whole.toml"  # the daemon that never stops
    whole.write_text(f'[daemon]\ncheckpoint = "{tmp_path / "whole.ckpt"}"\n')
    w = _daemon(["--kt", "0.1", "--config", str(whole)], [])
    try:
        w.process(frames)
        _start_resumed(d, caplog, "continues from the checkpoint")
        rest = frames.take(slice(half, None))
        d.process(rest)
        assert _published(d) == _published(w) != _after(d, log, rest)
        assert bytes(_target_state(d)) == bytes(_target_state(w))
        assert not d._fixed_path.settling()  # it continued: judged as the float at once
    finally:
        d.stop()
        w.stop()


def test_a_checkpoint_without_the_target_state_starts_the_path_again_and_says_so(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A checkpoint of the older schema (no target state) still resumes: the target's
    path starts again from its prior, said in the journal."""
    from canrls.live.checkpoint import load_checkpoint, save_checkpoint

    log, frames = _sim_frames(tmp_path, 12)
    half = len(frames) // 2
    cfg = _checkpointed(tmp_path, frames.take(slice(0, half)), "ckpt.bin")
    cp = load_checkpoint(tmp_path / "ckpt.bin")
    del cp.state["target"]
    save_checkpoint(tmp_path / "ckpt.bin", cp)
    d = _daemon(["--kt", "0.1", "--config", str(cfg)], [])
    try:
        _start_resumed(d, caplog, "starts again from its prior (the checkpoint holds no "
                                  "target state)")
        rest = frames.take(slice(half, None))
        d.process(rest)
        assert _published(d) == _after(d, log, rest)
    finally:
        d.stop()


@pytest.mark.parametrize(("field", "value"), [
    ("layout", "0" * 64), ("layout", [1, 2]), ("state", b"short"), ("t0", "soon"),
    ("model", None), ("model", "+1"), ("state", "frame_loss")],
    ids=["other-headers", "layout-array", "short-state", "t0-text", "no-model", "other-model",
         "a-field-out-of-range"])
def test_a_damaged_target_state_starts_the_path_again_and_says_so(
        tmp_path: Path, caplog: pytest.LogCaptureFixture, field: str, value: Any) -> None:
    """A checkpoint's target state of other C headers, of another target model or with a
    field of the wrong type or size: the estimators resume, the target's path starts
    again and the journal says why; nothing is fatal."""
    import numpy as np

    from canrls.live.checkpoint import load_checkpoint, save_checkpoint

    log, frames = _sim_frames(tmp_path, 12)
    cfg = _checkpointed(tmp_path, frames.take(slice(0, len(frames) // 2)), "ckpt.bin")
    cp = load_checkpoint(tmp_path / "ckpt.bin")
    target = cp.state["target"]
    if value == "frame_loss":
        # the state's size and layout kept, its flag frame_loss (the last word of
        # canrls_target before its 4 bytes of padding) 7: refused by the state's check
        target[field][-8] = 7
    else:
        target[field] = (np.frombuffer(value, np.uint8) if isinstance(value, bytes)
                         else np.array(value) if isinstance(value, list)
                         else target[field] + 1 if value == "+1" else value)
    save_checkpoint(tmp_path / "ckpt.bin", cp)
    d = _daemon(["--kt", "0.1", "--config", str(cfg)], [])
    try:
        _start_resumed(d, caplog, "starts again from its prior (the checkpoint's target "
                                  "state does not fit (" + ("the target's C does not take "
                                  "this state: Target: the state's a flag (0 or 1)"
                                  if value == "frame_loss" else ""))
        if value == "frame_loss":
            # from its prior against the float restored: not judged until it caught up
            d.process(frames.take(slice(len(frames) // 2, len(frames) // 2 + 2000)))
            assert d._fixed_path.settling() == {"mechanical"}
    finally:
        d.stop()


def test_the_daemon_takes_the_target_path_only_by_name(tmp_path: Path) -> None:
    cfg = tmp_path / "daemon.toml"
    cfg.write_text('[daemon]\nfixed = "float"\n')
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        assert main(["run", "-i", "virtual", "-c", "x", "--config", str(cfg), "--kt",
                     "0.1"]) == 1
    assert "daemon.fixed = 'float'" in buf.getvalue() and "'target'" in buf.getvalue()


def test_a_model_the_target_cannot_run_is_refused_by_name(tmp_path: Path) -> None:
    log = tmp_path / "drive.log"
    _canrls(["sim", "--out", str(log), "--duration", "4", "--seed", "8"])
    cfg = tmp_path / "drive.toml"
    cfg.write_text('[model]\neffects = ["inertia", "viscous", "user:drag"]\nkt = 0.1\n'
                   '[[model.terms]]\nname = "drag"\nexpr = "omega * abs(omega)"\n'
                   'range = [-1e4, 1e4]\n')
    # asked for by name, the target's path is an error
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        assert main(["fit", str(log), "--config", str(cfg), "--fixed", "target"]) == 1
    assert "error:" in buf.getvalue() and "user term" in buf.getvalue()
    # by default the fit takes the kernel's column and says why, in text and in JSON
    text = _canrls(["fit", str(log), "--config", str(cfg), "--quiet"])
    assert "fixed point: the kernel on the float front end (the target's integer path " \
           "does not run this model: " in text and "user term" in text
    fit = json.loads(_canrls(["fit", str(log), "--config", str(cfg), "--quiet", "--json"]))
    assert fit["fixed"]["path"] == "kernel" and "user term" in fit["fixed"]["why"]
    assert all(math.isfinite(p["fixed"]) for p in fit["parameters"].values())


def _diverged_after_add(tmp_path: Path, skew: float = 1.0) -> tuple[bool, list[bool], Any]:
    """A daemon without the drive's unbalance, the effect added by a command half way,
    frames fed in blocks of 50; whether the status says Diverged before the command and
    after each block after it, and the daemon's path. ``skew``: the path's fixed values
    multiplied by it wherever they are judged (a real divergence)."""
    import time

    from canrls.can.estimator_frames import CommandCode, EffectId, encode_command
    from canrls.can.frameblock import FrameBlock
    from canrls.can.logs import read_frames

    log = tmp_path / "drive.log"
    _canrls(["sim", "--out", str(log), "--duration", "16", "--seed", "5", "--effects",
             "inertia,viscous,coulomb,offset,unbalance"])
    frames = FrameBlock.concat(list(read_frames(log)))
    d = _daemon(["--kt", "0.1", "-e", "inertia,viscous,coulomb,offset", "--commands"], [])
    path = d._fixed_path
    fixed = path.fixed
    if skew != 1.0:
        def skewed() -> Any:
            out = fixed()
            if out and not path.settling():
                out = {k: (v * skew, ok) for k, (v, ok) in out.items()}
            return out
        path.fixed = skewed
    half, n = len(frames) // 2, len(frames)
    try:
        d.process(frames.take(slice(0, half)))
        before = d.publisher.status(time.monotonic()).diverged
        d.process([encode_command(CommandCode.ADD_EFFECT, EffectId.UNBALANCE)])
        flags = []
        for a in range(half, n, 50):
            d.process(frames.take(slice(a, min(a + 50, n))))
            flags.append(d.publisher.status(time.monotonic()).diverged)
        return before, flags, path
    finally:
        d.stop()


def test_a_path_restarted_by_add_effect_is_not_judged_diverged_until_it_caught_up(
        tmp_path: Path) -> None:
    """add_effect starts the target's path again from its prior while the float keeps its
    values: until the path has had as many updates as the float had then, their
    difference is no divergence (it was flagged for 36 of 320 blocks, 0.8 s of data)."""
    before, flags, path = _diverged_after_add(tmp_path)
    assert not before and not any(flags)
    assert not path.settling() and path.running.run_info().updates["mechanical"] > 7000


def test_a_real_divergence_is_still_flagged_after_add_effect(tmp_path: Path) -> None:
    """The same, the path's values off by half where it is judged: Diverged, at once on
    a path that never started again, and once the restarted one caught up."""
    before, flags, _ = _diverged_after_add(tmp_path, skew=1.5)
    assert before and flags[-1] and not flags[0]


def test_the_updates_a_restarted_path_needs() -> None:
    from canrls.firmware.target_live import settle_updates

    assert settle_updates({"mechanical": 7805}, 1.0) == {"mechanical": 7805}
    assert settle_updates({"mechanical": 7805, "electrical": 100}, 0.999) == {
        "mechanical": 3000, "electrical": 100}
