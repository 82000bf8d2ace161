"""Fuzz suites of the files canrls reads and of the options that name them: DBC files,
logs (candump ``.log``, ``.asc``, ``.csv``, ``.blf``) and the command line of ``sim``,
``fit`` and ``export-c``. On every generated input: a result, or one canrls error (one
``error:`` line, exit status 1; 2 for argparse's usage errors), never an internal error
(exit 3) or a traceback. Bounded numbers of examples, derandomized (seeded).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from canrls.can.logs import LogReadStats, read_frames
from canrls.can.protocol import Protocol
from canrls.cli.main import main
from canrls.core.errors import ConfigError, LogFormatError

ROOT = Path(__file__).resolve().parents[2]
DBC_TEXT = (ROOT / "dbc" / "canrls.dbc").read_text()
def fuzz(examples: int) -> settings:
    """Bounded, derandomized (seeded) examples; fixtures shared across them."""
    return settings(max_examples=examples, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture,
                                           HealthCheck.too_slow])

_number = st.one_of(  # the values that broke canrls first: hypothesis tries them early
    st.sampled_from(["0", "1e308", "1e999", "999999", "-1e999", "-0", "4294967296", "0.0",
                     "1e-320", "65", "64", "512", "-1"]),
    st.integers(-(2 ** 70), 2 ** 70).map(str),
    st.floats(allow_nan=False, allow_infinity=False).map(repr))
_dbc_text = st.text(st.characters(codec="utf-8", exclude_characters='"'), max_size=20)
_SG = re.compile(r"(SG_ \w+(?: \w+)? : )(\d+)\|(\d+)@([01])([+-]) \(([^,]+),([^)]+)\) "
                 r"\[([^|]+)\|([^\]]+)\] \"([^\"]*)\"")
#: the signals of the drive's feedback (DriveCurrent, DriveSpeed): the ones canrls decodes
_SIGNALS = [m for m in _SG.finditer(DBC_TEXT) if m.start() < DBC_TEXT.index("BO_ 768 ")]


@st.composite
def _mutated_dbc(draw: st.DrawFn) -> str:
    """The shipped DBC with a few fields of a few signals or messages replaced."""
    text = DBC_TEXT
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["signal", "message", "comment", "junk"]))
        if kind == "signal":
            m = draw(st.sampled_from(_SIGNALS))
            groups = list(m.groups())
            k = draw(st.sampled_from([5, 6, 2, 1, 7, 8, 9, 3, 4]))  # scale, offset, length..
            groups[k] = draw(_dbc_text) if k == 9 else draw(_number)
            new = (f"{groups[0]}{groups[1]}|{groups[2]}@{groups[3]}{groups[4]} "
                   f"({groups[5]},{groups[6]}) [{groups[7]}|{groups[8]}] \"{groups[9]}\"")
            text = text.replace(m.group(0), new, 1)
        elif kind == "message":
            name = draw(st.sampled_from(["DriveCurrent", "DriveSpeed", "RlsStatus"]))
            text = re.sub(rf"(BO_ \d+ {name}: )\d+", lambda mm: mm.group(1) + draw(_number),
                          text, count=1)
        elif kind == "comment":
            text = text.replace('CM_ SG_ 257 Current "', f'CM_ SG_ 257 Current "{draw(_dbc_text)}',
                                1)
        else:
            lines = text.splitlines(keepends=True)
            at = draw(st.integers(0, len(lines)))
            lines.insert(at, draw(st.text(max_size=40)) + "\n")
            text = "".join(lines)
    return text


@fuzz(40)
@given(text=_mutated_dbc())
def test_random_dbc_files_load_or_raise_a_config_error(
        tmp_path_factory: pytest.TempPathFactory, text: str) -> None:
    path = tmp_path_factory.mktemp("dbc") / "drive.dbc"
    path.write_bytes(text.encode("utf-8", errors="surrogatepass"))
    try:
        proto = Protocol.load(path)
    except ConfigError as e:  # SignalError too: a unit that does not convert
        assert str(e)
        return
    for role in ("current", "speed"):  # what loads is usable: finite, non-empty ranges
        lo, hi = proto.signal_range(role) or (-1.0, 1.0)
        assert math.isfinite(lo) and math.isfinite(hi) and lo < hi


# ------------------------------------------------------------------ logs
_ids = st.one_of(st.integers(0, 0x7FF), st.integers(0, 2 ** 40))
_bytes = st.lists(st.integers(0, 255), max_size=10)
_junk = st.text(max_size=30)


@st.composite
def _asc(draw: st.DrawFn) -> str:
    lines = ["date Sat Nov 28 17:00:11.938 2026", "base hex  timestamps absolute",
             "internal events logged", "Begin Triggerblock Thu Jan 01 00:00:00.0 1970"]
    for _ in range(draw(st.integers(0, 6))):
        if draw(st.booleans()):
            data = draw(_bytes)
            ext = draw(st.booleans())
            ident = f"{draw(_ids):X}{'x' if ext else ''}"
            t = draw(st.sampled_from(["0.001000", "1e300", "nan", "-5", "12.5"]))
            lines.append(f" {t} 1  {ident:<15} Rx   d {len(data)} "
                         + " ".join(f"{b:02X}" for b in data))
        else:
            lines.append(draw(_junk))
    return "\n".join(lines) + "\n"


@st.composite
def _csv(draw: st.DrawFn) -> str:
    lines = ["timestamp,arbitration_id,extended,remote,error,dlc,data"]
    for _ in range(draw(st.integers(0, 6))):
        if draw(st.booleans()):
            t = draw(st.sampled_from(["0.001", "1e300", "inf", "-1", "2.5"]))
            data = draw(st.sampled_from(["AQ==", "", "x", "AAAAAAAAAAA="]))
            lines.append(f"{t},0x{draw(_ids):X},{draw(st.integers(0, 1))},0,0,"
                         f"{draw(st.integers(0, 70))},{data}")
        else:
            lines.append(draw(_junk))
    return "\n".join(lines) + "\n"


@fuzz(60)
@given(data=st.one_of(_asc().map(lambda s: (".asc", s.encode())),
                      _csv().map(lambda s: (".csv", s.encode())),
                      st.binary(max_size=300).map(lambda b: (".blf", b)),
                      st.binary(max_size=300).map(lambda b: (".asc", b)),
                      st.binary(max_size=300).map(lambda b: (".csv", b))))
def test_random_asc_csv_and_blf_logs_read_or_raise_a_log_format_error(
        tmp_path_factory: pytest.TempPathFactory, data: tuple[str, bytes]) -> None:
    suffix, content = data
    path = tmp_path_factory.mktemp("log") / f"x{suffix}"
    path.write_bytes(content)
    st_ = LogReadStats()
    try:
        blocks = list(read_frames(path, chunk_size=3, stats=st_))
    except LogFormatError as e:
        assert str(path) in str(e)
        return
    for b in blocks:  # what reads is frames: IDs of 29 bits, finite bounded times
        assert (b.arbitration_id <= 0x1FFFFFFF).all()
        assert all(abs(t) <= 1e10 for t in b.t.tolist())


@fuzz(20)
@given(lines=st.lists(st.one_of(
    st.from_regex(r"\([0-9.e+-]{1,12}\) [!-~]{1,6} [0-9A-Fa-f]{1,9}#[0-9A-FR#]{0,20}",
                  fullmatch=True),
    st.text(max_size=40)), max_size=8), long=st.integers(0, 3))
def test_random_candump_logs_with_long_lines_read_or_raise_a_log_format_error(
        tmp_path_factory: pytest.TempPathFactory, lines: list[str], long: int) -> None:
    path = tmp_path_factory.mktemp("log") / "x.log"
    body = "\n".join(lines)
    if long:  # a line beyond the bound, a comment or not
        body += "\n" + ("# " if long == 1 else "(") + "7" * 70_000 * long
    path.write_bytes(body.encode("utf-8", errors="surrogatepass"))
    for skip in (False, True):
        try:
            list(read_frames(path, chunk_size=2, skip_bad_lines=skip))
        except LogFormatError as e:
            assert not skip or "skip" not in str(e)
            assert str(path) in str(e)


# ------------------------------------------------------------------ the command line
_float_text = st.one_of(st.floats().map(repr),
                        st.sampled_from(["1e300", "-1", "0", "nan", "inf", "0.01", "x", ""]))


@fuzz(25)
@given(duration=st.one_of(st.sampled_from(["0.01", "0.02"]), _float_text),
       seed=st.one_of(st.integers(-5, 5).map(str), st.sampled_from(["-1", "x", "1" * 30])),
       channel=st.one_of(st.sampled_from(["can0", "a b", "ä", "", "#", "x" * 70]),
                         st.text(max_size=8)),
       start=st.one_of(st.sampled_from(["0", "5"]), _float_text),
       suffix=st.sampled_from([".log", ".asc", ".csv", ".blf", ".trc", ".xyz", ""]))
def test_random_sim_options_never_end_in_an_internal_error(
        tmp_path_factory: pytest.TempPathFactory, capsys: pytest.CaptureFixture[str],
        bounded_writes: int, duration: str, seed: str, channel: str, start: str,
        suffix: str) -> None:
    d = tmp_path_factory.mktemp("sim")
    out = d / f"x{suffix}"
    argv = ["sim", "--out", str(out), f"--duration={duration}", f"--seed={seed}",
            f"--channel={channel}", f"--start-time={start}"]
    if "\0" in " ".join(argv):
        return  # no process can be given a NUL byte in its arguments
    capsys.readouterr()
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse: usage errors
        rc = e.code  # type: ignore[assignment]
    err = capsys.readouterr().err
    assert rc in (0, 1, 2), err
    assert "Traceback" not in err and "internal error" not in err, err
    if rc == 0:
        assert sum(len(b) for b in read_frames(out)) > 0
    else:
        assert not [p for p in d.iterdir() if p.name.endswith(".part")]


@fuzz(6)
@given(dt=_float_text, out=st.sampled_from(["drive.toml", "x\nb", "", "c/d", "c"]))
def test_random_export_c_options_never_end_in_an_internal_error(
        tmp_path_factory: pytest.TempPathFactory, capsys: pytest.CaptureFixture[str],
        dt: str, out: str) -> None:
    d = tmp_path_factory.mktemp("export")
    cfg = d / "drive.toml"
    cfg.write_text('[model]\neffects = ["inertia", "viscous"]\nkt = 0.1\n')
    capsys.readouterr()
    try:
        rc = main(["export-c", "--model", str(cfg), "--out", str(d / out) if out else "",
                   f"--dt={dt}"])
    except SystemExit as e:
        rc = e.code  # type: ignore[assignment]
    err = capsys.readouterr().err
    assert rc in (0, 1, 2), err
    assert "Traceback" not in err and "internal error" not in err, err
