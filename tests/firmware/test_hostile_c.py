"""Generated C takes nothing raw: hostile names, units, comments and sizes against
``canrls export-c`` (``canrls/core/c_escape.py``).

A model file, a configuration and a DBC carry text into the C a firmware team builds.
Each case here either is refused with one ``error:`` line where the text is read (by
``validate`` as by ``export-c``), or is rendered inert: the output compiles with the
firmware's warnings (``-std=c99 -Wall -Wextra -Werror -pedantic``) and the exported
kernel computes, bit for bit, what canrls' own fixed-point estimator computes.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_tool import cli_error
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from canrls.cli.main import main
from canrls.core.c_escape import MAX_TEXT, c_comment, c_identifier, c_int, c_string, c_uint
from canrls.core.errors import ConfigError
from canrls.estimation.pipeline import Pipeline
from canrls.firmware.kernel_export import frames_c
from canrls.firmware.load import load

ROOT = Path(__file__).resolve().parents[2]
DBC = ROOT / "dbc" / "canrls.dbc"
KERNEL = ROOT / "src" / "canrls" / "c" / "firmware"
CFLAGS = ["-std=c99", "-O0", "-Wall", "-Wextra", "-Werror", "-pedantic"]
ATTACK = "1*/\n#define canrls_update_q31(S, phi, y, st) ((void)(S))\n/*"
BASE = ["inertia", "viscous", "coulomb"]
#: the mapping of the shipped DBC, the current with a stated scale (any unit in the DBC)
SIGNALS = ('[signals]\ncurrent = { signal = "DriveCurrent.Current", scale = 1.0 }\n'
           'speed = "DriveSpeed.Speed"\nposition = "DriveSpeed.Position"\n')


def _gcc() -> str:
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not installed")
    return gcc


def _toml_str(s: str) -> str:
    """``s`` as a TOML basic string (control characters as ``\\uXXXX``)."""
    out = []
    for ch in s:
        if ch in '"\\':
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _toml(units: dict[str, str], dbc: Path | None = None) -> str:
    """A configuration with one user term per entry of ``units`` (name -> unit)."""
    effects = [*BASE, *(f"user:{n}" for n in units)]
    text = f"[model]\neffects = {json.dumps(effects)}\nkt = 0.1\n"
    for name, unit in units.items():
        text += (f'[[model.terms]]\nname = "{name}"\nexpr = "speed * abs(speed)"\n'
                 f"unit = {_toml_str(unit)}\n")
    if dbc is not None:
        text += f'[can]\ndbc = "{dbc}"\n'
    return text


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("hostile_c") / "drive.log"
    assert main(["sim", "--out", str(path), "--duration", "2", "--seed", "1"]) == 0
    return path


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory, log: Path) -> dict[str, Any]:
    """A saved model with a user term, as ``canrls fit --save-model`` writes it."""
    d = tmp_path_factory.mktemp("saved")
    cfg = d / "drive.toml"
    cfg.write_text(_toml({"drag": "rad2/s2"}))
    out = d / "m.json"
    assert main(["fit", str(log), "--config", str(cfg), "--save-model", str(out)]) == 0
    return json.loads(out.read_text())


@pytest.fixture(scope="module")
def fixed_o(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The kernel, compiled once (export-c copies it unchanged)."""
    o = tmp_path_factory.mktemp("kernel") / "canrls_fixed.o"
    subprocess.run([_gcc(), *CFLAGS, "-I", str(KERNEL), "-c", str(KERNEL / "canrls_fixed.c"),
                    "-o", str(o)], check=True, capture_output=True)
    return o


def _estimates_like_python(model_file: Path, out: Path, fixed_o: Path, tmp: Path,
                           rows: int = 120) -> None:
    """The exported config, linked with the kernel, runs canrls' FixedRLS bit for bit
    (every equation: one program per equation, the same quantised stream)."""
    gcc = _gcc()
    subprocess.run([gcc, *CFLAGS, "-fsyntax-only", str(out / "canrls_frames.c")],
                   check=True, capture_output=True, text=True)
    src = load(model_file)  # what export-c exports: the model, its energies, its period
    pipe = Pipeline(src.model, src.dt, src.settings, src.energy)
    config_o = tmp / "config.o"
    subprocess.run([gcc, *CFLAGS, "-I", str(out), "-c", str(out / "canrls_config.c"),
                    "-o", str(config_o)], check=True, capture_output=True, text=True)
    for e in pipe.estimators:
        est = e.frls
        est.backend = "spec"
        rng = np.random.default_rng(7)
        Phi = rng.uniform(-0.5, 0.5, (rows, est.n))
        Pq, Yq, _ = est.config.quantize_inputs(Phi, Phi @ rng.uniform(-0.3, 0.3, est.n))
        est.run(Pq, Yq, record=False)
        lo, up = e.equation.name, e.equation.name.upper()
        prog = tmp / f"main_{lo}.c"
        prog.write_text(
            '#include <stdio.h>\n#include "canrls_config.h"\n'
            f"static const int32_t phi[{rows}][CANRLS_{up}_N] = {{"
            + ",".join("{" + ",".join(map(str, r)) + "}" for r in Pq.tolist()) + "};\n"
            f"static const int32_t y[{rows}] = {{{','.join(map(str, Yq.tolist()))}}};\n"
            "int main(void) {\n  static canrls_rls_q31 S; unsigned k, j;\n"
            f"  if (canrls_{lo}_init(&S) != CANRLS_OK) return 2;\n"
            f"  for (k = 0; k < {rows}u; k++) canrls_update_q31(&S, phi[k], y[k], 0);\n"
            f"  for (j = 0; j < CANRLS_{up}_N; j++)\n"
            "    printf(\"%ld\\n\", (long)canrls_theta_q31(&S, j));\n  return 0;\n}\n")
        exe = tmp / f"main_{lo}"
        subprocess.run([gcc, *CFLAGS, "-I", str(out), str(prog), str(config_o), str(fixed_o),
                        "-o", str(exe)], check=True, capture_output=True, text=True)
        got = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout
        assert [int(x) for x in got.split()] == est.theta.tolist()
        assert any(est.theta)  # it estimated: theta moved from the prior's zero


# ------------------------------------------------------------------ item 1: the unit
def test_a_unit_that_closes_the_comment_is_refused_by_validate_and_export(
        tmp_path: Path, log: Path, saved: dict[str, Any],
        capsys: pytest.CaptureFixture[str]) -> None:
    """Item 1: a unit that closed the comment of ``canrls_config.h`` defined the
    kernel's update away; the firmware built clean with -Werror and never estimated,
    and ``validate`` accepted the same model file. Both refuse it where it is read."""
    d = json.loads(json.dumps(saved))
    d["model"]["terms"][0]["unit"] = ATTACK
    m = tmp_path / "evil.json"
    m.write_text(json.dumps(d))
    for argv in (["validate", str(log), "--model", str(m)],
                 ["export-c", "--model", str(m), "--out", str(tmp_path / "c")]):
        line = cli_error(capsys, argv)
        assert f"--model {m}" in line and "unit" in line and "U+000A" in line
    cfg = tmp_path / "evil.toml"
    cfg.write_text(_toml({"drag": ATTACK}))
    assert "U+000A" in cli_error(capsys, ["export-c", "--model", str(cfg),
                                       "--out", str(tmp_path / "c")])
    assert not (tmp_path / "c").exists()


def test_comment_delimiters_and_trigraphs_in_a_unit_are_rendered_inert(
        tmp_path: Path, fixed_o: Path) -> None:
    cfg = tmp_path / "drive.toml"
    cfg.write_text(_toml({"drag": "N*/m /* ??/ \"q\" #error x"}))
    out = tmp_path / "c"
    assert main(["export-c", "--model", str(cfg), "--out", str(out)]) == 0
    h = (out / "canrls_config.h").read_text()
    assert "N* /m / * ? ?/" in h
    _estimates_like_python(cfg, out, fixed_o, tmp_path)


def test_term_names_that_collide_in_c_are_refused_where_the_model_is_read(
        tmp_path: Path, log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``user:drag`` and ``user:DRAG`` both became ``CANRLS_MECHANICAL_USER_DRAG_C``:
    a build error in the firmware; now the model is refused by every command."""
    cfg = tmp_path / "drive.toml"
    cfg.write_text(_toml({"drag": "1", "DRAG": "1"}))
    line = cli_error(capsys, ["fit", str(log), "--config", str(cfg)])
    assert "DRAG" in line and "only in case" in line


# ------------------------------------------------------------------ what a DBC carries
def _dbc(tmp_path: Path, *edits: tuple[str, str], extra: str = "") -> Path:
    text = DBC.read_text()
    for old, new in edits:
        assert old in text
        text = text.replace(old, new, 1)
    path = tmp_path / "drive.dbc"
    path.write_bytes((text + extra).encode("cp1252", errors="replace"))  # a DBC's encoding
    return path


def _syntax(tmp_path: Path, header: str, source: str) -> None:
    """cantools' codecs compile (syntax and warnings) with the firmware's flags."""
    (tmp_path / "canrls_frames.h").write_text(header)
    (tmp_path / "canrls_frames.c").write_text(source)
    r = subprocess.run([_gcc(), *CFLAGS, "-fsyntax-only", str(tmp_path / "canrls_frames.c")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_a_dbc_unit_that_closes_the_comment_is_rendered_inert(tmp_path: Path) -> None:
    """cantools pastes a signal's unit raw into a comment of the codecs (its ``Range:``
    line): ``*/ #error injected /*`` stopped the build, anything else went in."""
    dbc = _dbc(tmp_path, ('SG_ ResidualRms : 0|32@1- (1,0) [0|3.4e+38] ""',
                          'SG_ ResidualRms : 0|32@1- (1,0) [0|3.4e+38] "*/ #error injected /*"'))
    header, source = frames_c(dbc)
    assert "* / #error injected / *" in header
    _syntax(tmp_path, header, source)


@pytest.mark.parametrize(("edit", "extra", "message"), [
    (('CM_ BO_ 768 "Fixed-point', 'CM_ BO_ 768 "x *\\\n/ int injected; /* Fixed-point'), "",
     "message RlsEstimate: comment = 'x *\\\\': character 4"),
    (("", ""), 'BA_DEF_ SG_  "SystemSignalLongSymbol" STRING ;\n'
               'BA_ "SystemSignalLongSymbol" SG_ 784 ResidualRms "Rms\n#error injected";\n',
     "message RlsStatus: a signal name = 'Rms\\n#error injected': not a C identifier"),
    ((' SG_ Counter : 16|4@1+ (1,0) [0|15] "" Tool\n\n\nCM_',
      ' SG_ Counter : 16|4@1+ (1,0) [0|15] "" Tool\n SG_ COUNTER : 24|4@1+ (1,0) [0|15] "" '
      'Tool\n\n\nCM_'), "",
     "message RlsCommandAck: signal Counter and signal COUNTER both become COUNTER"),
    (("", ""), 'VAL_ 801 Result 99999999999999999999999 "Huge" 0 "Ok" ;\n',
     "message RlsCommandAck: signal Result: value of a choice = 99999999999999999999999"),
], ids=["backslash-newline", "long-name", "snake-collision", "huge-choice"])
def test_dbc_text_cantools_would_paste_into_c_is_refused(
        tmp_path: Path, edit: tuple[str, str], extra: str, message: str) -> None:
    """A backslash-newline in a message comment closed cantools' comment (its escape
    misses a line splice), a long name (``SystemSignalLongSymbol``) went raw into a
    string literal, two signals with one snake-case name and a choice beyond 64 bits
    broke the build. Each is refused before cantools sees it, naming message and signal
    (``export-c`` generates the codecs of the shipped DBC; the guard holds for any)."""
    dbc = _dbc(tmp_path, *([edit] if edit[0] else []), extra=extra)
    with pytest.raises(ConfigError) as e:
        frames_c(dbc)
    assert str(dbc) in str(e.value) and message in str(e.value)


def test_a_dbc_without_canrls_frames_is_one_error(tmp_path: Path) -> None:
    """A DBC without canrls' frames ended the frame IDs' lookup in a KeyError."""
    text = DBC.read_text()
    dbc = tmp_path / "drive.dbc"
    dbc.write_text(text[:text.index("BO_ 768 ")])  # the drive's messages alone
    with pytest.raises(ConfigError, match=f"DBC file {dbc}: no message RlsEstimate, RlsSigma"):
        frames_c(dbc)


def test_the_output_signals_dbc_names_and_unit_go_into_c_as_escaped_strings(
        tmp_path: Path, fixed_o: Path) -> None:
    """The export names the DBC signal the output is decoded from, and its unit, in C
    strings: the user's DBC text, escaped byte by byte."""
    unit = "A */ ??/ #error x"
    dbc = _dbc(tmp_path, ('SG_ Current : 16|24@1- (0.0001,0) [-800|800] "A"',
                          f'SG_ Current : 16|24@1- (0.0001,0) [-800|800] "{unit}"'))
    cfg = tmp_path / "drive.toml"
    cfg.write_text(_toml({}, dbc) + SIGNALS)
    out = tmp_path / "c"
    assert main(["export-c", "--model", str(cfg), "--out", str(out)]) == 0
    assert c_string(unit) in (out / "canrls_config.c").read_text()
    _estimates_like_python(cfg, out, fixed_o, tmp_path)


# ------------------------------------------------------------------ item 12: the size
def test_more_parameters_than_the_kernel_holds_stops_the_build(tmp_path: Path,
                                                               fixed_o: Path) -> None:
    """Item 12: a model of 13 parameters built with default flags (only a comment named
    -DCANRLS_N_MAX); its init failed at run time and an update segfaulted. Now the
    export's own bounds (canrls_bounds.h) hold its 13 parameters, a build with fewer
    (-DCANRLS_N_MAX=12, the package's maxima; or the kernel alone) stops with #error, and
    builds with the flag it names."""
    gcc = _gcc()
    cfg = tmp_path / "big.toml"
    cfg.write_text('[model]\neffects = ["inertia", "viscous", "coulomb", "offset", '
                   '"stribeck", "unbalance", "cogging:6", "cogging:12", "cogging:24"]\n'
                   "kt = 0.1\n")
    out = tmp_path / "c"
    assert main(["export-c", "--model", str(cfg), "--out", str(out)]) == 0
    assert "#define CANRLS_N_MAX 13" in (out / "canrls_bounds.h").read_text()
    for defs in (["-DCANRLS_N_MAX=12"], ["-DCANRLS_N_MAX=12", "-DCANRLS_FRONT"]):
        for f in ("canrls_config.c", "canrls_model.c"):
            r = subprocess.run([gcc, *CFLAGS, *defs, "-c", str(out / f), "-o",
                                str(tmp_path / "x.o")], capture_output=True, text=True)
            assert r.returncode != 0, f
            assert "#error" in r.stderr and "-DCANRLS_N_MAX=" in r.stderr, f
    kernel = tmp_path / "k"
    assert main(["export-c", "--model", str(cfg), "--out", str(kernel), "--kernel-only"]) == 0
    r = subprocess.run([gcc, *CFLAGS, "-c", str(kernel / "canrls_config.c"), "-o",
                        str(tmp_path / "x.o")], capture_output=True, text=True)
    assert r.returncode != 0
    assert "#error" in r.stderr and "-DCANRLS_N_MAX=13" in r.stderr
    subprocess.run([gcc, *CFLAGS, "-c", str(out / "canrls_config.c"), "-o",
                    str(tmp_path / "x.o")], check=True, capture_output=True)
    prog = tmp_path / "main.c"
    prog.write_text('#include "canrls_config.h"\nint main(void) {\n'
                    "  static canrls_rls_q31 S;\n"
                    "  return canrls_mechanical_init(&S) == CANRLS_OK ? 0 : 2;\n}\n")
    subprocess.run([gcc, *CFLAGS, "-DCANRLS_N_MAX=13", "-I", str(out), str(prog),
                    str(out / "canrls_config.c"), str(out / "canrls_fixed.c"),
                    "-o", str(tmp_path / "main")], check=True, capture_output=True)
    subprocess.run([str(tmp_path / "main")], check=True)


# ------------------------------------------------------------------ the renderers
def test_the_renderers_refuse_or_neutralise() -> None:
    assert c_comment("a */ b /* c ??/", "x") == "a * / b / * c ? ?/"
    for bad in ("a\nb", "a\\", "\u202e", "a\x00", "x" * (MAX_TEXT + 1), 3):
        with pytest.raises(ConfigError):
            c_comment(bad, "unit")
    assert c_identifier("Rls_1", "x") == "Rls_1"
    for bad in ("1a", "a b", "ä", "", "a" * 64, None):
        with pytest.raises(ConfigError):
            c_identifier(bad, "name")
    assert c_string('a"b\\?\n·') == '"a\\042b\\134\\077\\012\\302\\267"'
    assert c_int(-(2 ** 31)) == "(-2147483647 - 1)" and c_int(np.int64(5), 64) == "5LL"
    assert c_uint(2 ** 32 - 1) == "4294967295u"
    for bad in (2 ** 31, 1.5, True, "1"):
        with pytest.raises(ConfigError):
            c_int(bad)


# ------------------------------------------------------------------ fuzz: compile and run
DANGEROUS = ["*/", "/*", "??/", "\\", "\n", "\r", "\t", '"', "'", "#define x", "\u202e",
             "\u2028", "\x00", "\x7f", "·", "²", "%s", "{", "}", ";", "//", "ä"]
_text = st.lists(st.one_of(st.sampled_from(DANGEROUS),
                           st.text(st.characters(codec="utf-8"), max_size=6)),
                 max_size=5).map("".join)
_name = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,12}", fullmatch=True)


def _refused(text: str) -> bool:
    return any(c == "\\" or not c.isprintable() for c in text) or len(text) > MAX_TEXT


@settings(max_examples=8, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(terms=st.dictionaries(_name, _text, max_size=2), comment=_text, dbc_unit=_text)
def test_export_of_random_names_units_and_comments_compiles_and_estimates(
        tmp_path_factory: pytest.TempPathFactory, fixed_o: Path,
        capsys: pytest.CaptureFixture[str], terms: dict[str, str], comment: str,
        dbc_unit: str) -> None:
    """Random term names, units (with every dangerous sequence we know), a random DBC
    comment and units: ``export-c`` refuses (one error line, exit 1; a term's unit
    exactly when it is not printable text without a backslash, names exactly when two
    differ only in case) or writes C that compiles with -Werror and estimates as canrls
    does; cantools' codecs of that DBC are refused or compile."""
    tmp = tmp_path_factory.mktemp("fuzz")
    # a DBC string cannot hold a quote; a trailing backslash would escape its end
    clean = lambda s: s.replace('"', "'").rstrip("\\")  # noqa: E731
    dbc = _dbc(tmp, ('CM_ BO_ 768 "Fixed-point', f'CM_ BO_ 768 "{clean(comment)} Fixed-point'),
               ('SG_ ResidualRms : 0|32@1- (1,0) [0|3.4e+38] ""',
                f'SG_ ResidualRms : 0|32@1- (1,0) [0|3.4e+38] "{clean(dbc_unit)}"'),
               ('SG_ Current : 16|24@1- (0.0001,0) [-800|800] "A"',
                f'SG_ Current : 16|24@1- (0.0001,0) [-800|800] "{clean(dbc_unit)}"'))
    try:
        header, source = frames_c(dbc)
    except ConfigError:
        pass
    else:
        _syntax(tmp, header, source)
    cfg = tmp / "drive.toml"
    cfg.write_text(_toml(terms, dbc) + SIGNALS)
    out = tmp / "c"
    capsys.readouterr()
    rc = main(["export-c", "--model", str(cfg), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc in (0, 1), err
    assert rc == 0 or (err.startswith("error: ") and err.count("\n") == 1), err
    units_bad = any(_refused(u) for u in terms.values())
    names_bad = len({n.upper() for n in terms}) < len(terms)
    if units_bad or names_bad:
        assert rc == 1
    if rc == 1:
        assert not out.exists()
        return
    h = (out / "canrls_config.h").read_text()
    assert not re.search(r"^\s*#\s*define\s+canrls_update", h, re.M)
    _estimates_like_python(cfg, out, fixed_o, tmp)


# ------------------------------------------------------------ the export's frames and vectors
@pytest.mark.parametrize(("own", "name"), [(768, "RlsEstimate"), (800, "RlsCommand")])
def test_a_drive_frame_on_an_id_of_canrls_is_refused_unless_frames_none(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], own: int, name: str) -> None:
    """Issue 30, 8: a DBC that put the drive's current on RlsEstimate's ID exported,
    built and passed: the firmware would have taken its own publications as feedback."""
    text = DBC.read_text()
    dbc = tmp_path / "drive.dbc"
    dbc.write_text(text[:text.index("BO_ 768 ")].replace("BO_ 257 DriveCurrent",
                                                         f"BO_ {own} DriveCurrent"))
    cfg = tmp_path / "drive.toml"
    cfg.write_text(_toml({}, dbc) + "period = 0.001\n")  # in [can], after dbc
    out = tmp_path / "c"
    line = cli_error(capsys, ["export-c", "--model", str(cfg), "--out", str(out)])
    assert f"message DriveCurrent (0x{own:X}: current, voltage) has the ID of canrls' " \
           f"{name}" in line and "--frames none" in line, line
    assert not out.exists()
    assert main(["export-c", "--model", str(cfg), "--out", str(out), "--frames", "none"]) == 0


@pytest.fixture(scope="module")
def model_json(tmp_path_factory: pytest.TempPathFactory, log: Path) -> Path:
    out = tmp_path_factory.mktemp("vectors") / "m.json"
    assert main(["fit", str(log), "--kt", "0.1", "-e", ",".join(BASE), "--quiet",
                 "--save-model", str(out)]) == 0
    return out


@pytest.mark.parametrize(("content", "message"), [
    ("", "no CAN frames in the log"),
    ("(0.000000) can0 123#0011223344556677\n(0.001000) can0 123#00\n",
     "none of the mapped messages occurs in the 2 frames read: expected 0x101 "
     "(DriveCurrent), 0x102 (DriveSpeed)"),
], ids=["no-frames", "no-mapped-frame"])
def test_vectors_from_a_log_fit_would_refuse_are_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], model_json: Path,
        content: str, message: str) -> None:
    """Issue 30, 9: export-c --vectors exited 0, then the export's make test failed to
    compile (-Werror=type-limits on an empty table). Refused as canrls fit refuses it,
    nothing written."""
    bad = tmp_path / "bad.log"
    bad.write_text(content)
    out = tmp_path / "c"
    line = cli_error(capsys, ["export-c", "--model", str(model_json), "--out", str(out),
                              "--vectors", str(bad)])
    assert message in line, line
    if "mapped" in message:  # the log is named, as canrls fit names it
        assert line.startswith(f"error: {bad.name}: "), line
    assert not out.exists()


def test_vectors_of_a_log_too_short_to_publish_build_and_pass(
        tmp_path: Path, log: Path, model_json: Path) -> None:
    """75 samples, no publication: the host test compiled a constant comparison with
    the empty table (-Werror=type-limits); now it builds and replays bit for bit."""
    from debian import need_tool

    need_tool("make", ["make"])
    short = tmp_path / "short.log"
    short.write_text("".join(log.read_text().splitlines(keepends=True)[:150]))
    out = tmp_path / "c"
    assert main(["export-c", "--model", str(model_json), "--out", str(out), "--vectors",
                 str(short)]) == 0
    r = subprocess.run(["make", "-s", "-C", str(out), "test"], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 publications: bit-exact with the specification" in r.stdout
