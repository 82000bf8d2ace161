"""The model file, the configuration and ``canrls validate`` against hostile input:
exit 1 with one ``error:`` line naming the key, never 3 (an internal error) and never a
traceback (issue 22, items 8 and 11; docs/reliability.md, *The live path, the model
file and the configuration*).

Each regression case failed before its fix (exit 3, or exit 0 with "fit nan %"); the
hypothesis suites run the command line in-process on generated files, bounded in
examples and size.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import re
from pathlib import Path
from typing import Any

import pytest
from cli_tool import inline_toml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from canrls.can.logs import write_candump
from canrls.cli.main import main
from canrls.core.errors import CanrlsError, ConfigError
from canrls.live.daemon_settings import DAEMON_KEYS, DaemonSettings
from canrls.processor.config import AppConfig
from canrls.processor.modelfile import SavedModel
from canrls.sim.scenario import scenario, simulate

FUZZ = settings(max_examples=50, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])


def _cli(argv: list[str]) -> tuple[int, str, str]:
    """``canrls ARGV`` in-process: (exit status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as e:  # argparse
            code = int(e.code or 0)
    return code, out.getvalue(), err.getvalue()


def _one_error(code: int, err: str) -> None:
    """Exit 0, or 1 with one ``error:`` line; never 3, never a traceback."""
    assert code in (0, 1), err
    assert "Traceback" not in err and "internal error" not in err, err
    if code == 1:
        lines = [line for line in err.splitlines() if line.strip()]
        assert lines and lines[-1].startswith("error: "), err
        assert sum(line.startswith("error: ") for line in lines) == 1, err


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 1 s log of the simulated drive and the model ``canrls fit`` saves from it."""
    d = tmp_path_factory.mktemp("modelfile")
    log = d / "drive.log"
    frames = simulate(scenario("standard", effects="inertia,viscous,coulomb", seed=5,
                               duration=1.0)).frames
    write_candump(log, [frames])
    model = d / "model.json"
    code, _, err = _cli(["fit", str(log), "--kt", "0.1", "--save-model", str(model),
                         "--quiet"])
    assert code == 0, err
    return {"log": log, "model": model, "dir": d}


def _validate(files: dict[str, Path], doc: Any = None, raw: bytes | None = None,
              name: str = "bad.json") -> tuple[int, str]:
    path = files["dir"] / name
    path.write_bytes(raw if raw is not None else json.dumps(doc).encode())
    code, _, err = _cli(["validate", str(files["log"]), "--model", str(path), "--quiet"])
    return code, err


def _mutated(files: dict[str, Path], change: Any) -> dict[str, Any]:
    doc = json.loads(files["model"].read_text())
    change(doc)
    return doc


# --------------------------------------------------------------------------- regression cases
def _set(path: str, value: Any) -> Any:
    def change(doc: dict[str, Any]) -> None:
        *parents, last = path.split("/")
        d = doc
        for k in parents:
            d = d[k]
        d[last] = value
    return change


CASES = {
    "parameters as a list": (lambda d: d.update(parameters=list(d["parameters"].values())),
                             "parameters = .*must be a table"),
    "model a list": (_set("model", [1, 2]), "model = \\[1, 2\\]: must be a table"),
    "model a string": (_set("model", "inertia"), "model = 'inertia': must be a table"),
    "configuration a number": (_set("configuration", 3), "configuration = 3: must be a table"),
    "configuration.can a list": (_set("configuration/can", ["x"]),
                                 "configuration.can = \\['x'\\]: must be a table"),
    "calibration a string": (_set("calibration", "x"), "calibration = 'x': must be a table"),
    "unknown estimator key": (_set("configuration/estimator/bogus", 1),
                              "unknown key estimator.bogus"),
    "string sigma": (_set("parameters/inertia.J/sigma", "big"),
                     "parameters.inertia.J.sigma = 'big': must be a number"),
    # validate printed "± -1e+308" and tune took it as a sigma
    "negative sigma": (_set("parameters/inertia.J/sigma", -1e308),
                       "parameters.inertia.J.sigma = -1e\\+308: must be >= 0"),
    "value 10**400": (_set("parameters/inertia.J/value", 10 ** 400),
                      "parameters.inertia.J.value = an integer of about 401 digits"),
    "fit entry a number": (_set("fit/mechanical", 3), "fit.mechanical = 3: must be a table"),
    "effects a string": (_set("effects", "inertia"), "effects = 'inertia': must be a list"),
    "warmup_s 1e300": (_set("configuration/estimator/warmup_s", 1e300),
                       "estimator.warmup_s = 1e\\+300: .* at most 25000"),
    # export-c said "column energies [1]: need 3 finite values", naming no file nor key
    "energies of one column": (_set("calibration/energy/mechanical", [1.0]),
                               "calibration.energy.mechanical has 1 values, the mechanical "
                               "equation 3 parameters"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_model_file_of_the_wrong_shape_is_one_error_naming_the_key(
        files: dict[str, Path], case: str) -> None:
    change, message = CASES[case]
    code, err = _validate(files, _mutated(files, change))
    assert code == 1, err
    _one_error(code, err)
    assert re.search(message, err), err


@pytest.mark.parametrize("raw, message", [
    (b'{"format": "canrls-model", "version": 1, "x": "\xff\xfe"}', "not UTF-8 text"),
    (b"[" * 100_000 + b"]" * 100_000, "nested too deep"),
    (b'{"format": "canrls-model", "version": 1' + b"0" * 5000 + b"}", "4300 digits"),
    (b'{"format": "canrls-model", "version": 1e400}', "model file version inf"),
])
def test_a_model_file_that_does_not_parse_is_one_error(files: dict[str, Path], raw: bytes,
                                                       message: str) -> None:
    """Non-UTF-8 bytes, nesting past the recursion limit, a 5,000-digit integer: each was
    an internal error (exit 3) of the JSON reader."""
    code, err = _validate(files, raw=raw)
    assert code == 1 and message in err, err
    _one_error(code, err)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_validate_refuses_parameters_that_are_not_finite(files: dict[str, Path],
                                                          value: float) -> None:
    """NaN or infinite parameters (``NaN``/``Infinity`` in the JSON): before, ``canrls
    validate`` printed "fit nan %" with numpy's warnings and exited 0."""
    doc = _mutated(files, _set("parameters/viscous.B/value", value))
    code, err = _validate(files, raw=json.dumps(doc).encode())  # NaN, Infinity
    assert code == 1 and "parameters.viscous.B.value" in err and "finite" in err, err
    _one_error(code, err)


@pytest.mark.parametrize("value", [2.6011485745922417e150, -1e300])
def test_validate_refuses_parameters_whose_prediction_overflows(files: dict[str, Path],
                                                                value: float) -> None:
    """A finite parameter so large that the residual's energy overflows a double: before,
    the verdict's residual RMS ended in numpy's overflow warning, exit 3 (found by the
    fuzz test below)."""
    doc = _mutated(files, _set("parameters/inertia.J/value", value))
    code, err = _validate(files, doc)
    assert code == 1 and "too large for a double" in err, err
    _one_error(code, err)


@pytest.mark.parametrize("command", [["export-c", "--out", "c"], ["tune"]])
@pytest.mark.parametrize("value", [1e308, 0, "x"])
def test_a_saved_period_that_is_no_period_names_the_file_and_the_key(
        files: dict[str, Path], command: list[str], value: Any) -> None:
    """``calibration.period`` of 1e308: ``export-c`` ended in an internal error (its
    timestamp ticks overflowed), and 0 or ``"x"`` said "the fit's: the control period
    ...", naming neither the model file nor the key."""
    bad = files["dir"] / "period.json"
    bad.write_text(json.dumps(_mutated(files, _set("calibration/period", value))))
    argv = [command[0], "--model", str(bad)] + [
        str(files["dir"] / a) if a == "c" else a for a in command[1:]]
    code, _, err = _cli(argv)
    assert code == 1, err
    _one_error(code, err)
    assert f"{bad}: calibration.period: the control period must be" in err, err
    assert not (files["dir"] / "c").exists()


def test_validate_on_a_log_without_a_usable_sample_is_an_error(files: dict[str, Path]) -> None:
    """A log whose every sample falls in the filter's warm-up (60 frames): before, exit
    0 with "fit nan %, 0 samples" and numpy's "Mean of empty slice" warning."""
    short = files["dir"] / "short.log"
    short.write_text("".join(files["log"].read_text().splitlines(keepends=True)[:60]))
    code, _, err = _cli(["validate", str(short), "--model", str(files["model"]), "--quiet"])
    assert code == 1 and "no usable sample for the mechanical equation" in err, err
    _one_error(code, err)


def test_the_estimator_warmup_is_bounded_before_anything_is_allocated(
        files: dict[str, Path]) -> None:
    """``[estimator] warmup_s = 1e300``: before, a MemoryError (an array of TiB for the
    residual's colour window), exit 3; now one error naming the key and the bound."""
    conf = files["dir"] / "warm.toml"
    conf.write_text("[estimator]\nwarmup_s = 1e300\n")
    code, _, err = _cli(["fit", str(files["log"]), "--kt", "0.1", "--config", str(conf),
                         "--quiet"])
    assert code == 1 and "estimator.warmup_s = 1e+300" in err and "at most" in err, err
    _one_error(code, err)
    with pytest.raises(ConfigError, match="warmup_s"):
        AppConfig(estimator={"warmup_s": -1.0}).settings()


@pytest.mark.parametrize("command", [["validate", "LOG"], ["export-c", "--out", "c"]])
@pytest.mark.parametrize("key, value, message", [
    ("estimator/lambda", 5, "estimator.lambda = 5: must be in (0.5, 1]"),
    ("can/dbc", 5, "can.dbc = 5: must be a file path"),
    ("signals/current", 5, "[signals]: current must be \"MESSAGE.SIGNAL\" or a table"),
])
def test_an_error_of_the_saved_configuration_names_the_model_file(
        files: dict[str, Path], command: list[str], key: str, value: Any,
        message: str) -> None:
    """A model file's configuration that cannot be was blamed on where the fit had read
    it ("<defaults>: estimator.lambda = 5"): the user's file was not named."""
    bad = files["dir"] / "conf.json"
    bad.write_text(json.dumps(_mutated(files, _set(f"configuration/{key}", value))))
    rest = [str(files["log"]) if a == "LOG" else str(files["dir"] / a) if a == "c" else a
            for a in command[1:]]
    code, _, err = _cli([command[0], "--model", str(bad), *rest])
    _one_error(code, err)
    assert code == 1 and err.startswith(f"error: {bad}: configuration"), err
    assert message in err and "<defaults>" not in err, err


@pytest.mark.parametrize("formats, message", [
    ({"P": [1000, -5]}, r"fixed\.formats\.P = \[1000, -5\]: QFormat bits must be in 2\.\.64"),
    ({"P": [32, 200]}, r"fixed\.formats\.P = \[32, 200\]: QFormat frac must be in"),
    ({"WARP": [32, 20]}, r"fixed\.formats\.WARP: no such quantity \(valid: phi, y,"),
])
def test_a_q_format_of_the_configuration_that_cannot_be_names_file_and_key(
        formats: dict[str, list[int]], message: str) -> None:
    """``[fixed.formats] P = [1000, -5]`` was "QFormat bits must be in 2..64, got 1000",
    an unknown name "FixedConfig.auto got unknown override(s)", naming neither the
    configuration file nor the key."""
    cfg = AppConfig(source="drive.toml", fixed={"formats": formats})
    with pytest.raises(ConfigError, match="^drive.toml: " + message):
        cfg.settings()


# --------------------------------------------------------------------------- fuzz: model file
json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-(10 ** 400), 10 ** 400),
              st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8),
              st.sampled_from(["inertia", "mechanical", "user:x", "cogging:6", "N·m"])),
    lambda inner: st.one_of(st.lists(inner, max_size=3),
                            st.dictionaries(st.text(max_size=6), inner, max_size=3)),
    max_leaves=8)


def _paths(doc: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every key path of a JSON document."""
    out = [prefix]
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for k, v in enumerate(doc):
            out += _paths(v, (*prefix, k))
    return out


mutations = st.lists(st.tuples(st.integers(0, 10 ** 6), st.sampled_from(["set", "drop"]),
                               json_values), min_size=1, max_size=3)


@FUZZ
@given(changes=mutations)
@example(changes=[(3, "set", {"model": 1})])
@example(changes=[(40, "set", None)])
def test_fuzz_a_saved_model_never_an_internal_error(files: dict[str, Path],
                                                    changes: list[tuple[int, str, Any]]) -> None:
    """A valid saved model with values replaced or keys dropped anywhere: ``canrls
    validate`` ends in a result or one error line, never exit 3 or a traceback."""
    doc = json.loads(files["model"].read_text())
    for where, how, value in changes:
        paths = _paths(doc)[1:]
        path = paths[where % len(paths)]
        parent = doc
        for k in path[:-1]:
            parent = parent[k]
        if how == "drop":
            del parent[path[-1]]
        else:
            parent[path[-1]] = value
    code, err = _validate(files, raw=json.dumps(doc).encode(), name="fuzz.json")
    _one_error(code, err)


@FUZZ
@given(doc=json_values)
def test_fuzz_any_json_document_as_a_model_never_an_internal_error(
        files: dict[str, Path], doc: Any) -> None:
    if isinstance(doc, dict):  # mostly past the format check
        doc = {"format": "canrls-model", "version": 1, **doc}
    code, err = _validate(files, raw=json.dumps(doc).encode(), name="fuzz.json")
    _one_error(code, err)
    with contextlib.suppress(CanrlsError):
        SavedModel.from_dict(doc, "fuzz")


# --------------------------------------------------------------------------- fuzz: TOML
_KEYS = {
    "model": ["effects", "kt", "axis", "pitch", "filter", "terms", "ranges", "scaling"],
    "estimator": ["lambda", "alpha", "trace_max", "warmup_s", "gap_periods", "calibration_s",
                  "rms_time_s", "max_phase_step", "min_speed"],
    "fixed": ["word_bits", "acc_bits", "input_bits", "theta_max", "formats"],
    "can": ["dbc", "period", "strict_range", "check_crc", "check_counter", "interface"],
    "signals": ["current", "speed", "position", "voltage", "messages"],
    "daemon": list(DAEMON_KEYS),
}
toml_scalars = st.one_of(
    st.booleans(), st.integers(-(2 ** 63), 2 ** 63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, 1e300, -1.0, 1e-300, 0.001, 25.0]),
    st.text(max_size=10),
    st.sampled_from(["inertia", "coulomb", "cogging:6", "user:a", "rotary", "linear",
                     "DriveSpeed.Speed", "DriveCurrent.Current:mA", "a\x00b", "nope.dbc",
                     "current", "omega"]))
toml_values = st.recursive(
    toml_scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=3),
        st.dictionaries(st.sampled_from(["cutoff_hz", "zeta", "held", "name", "expr",
                                         "range", "signal", "unit", "P", "mechanical"]),
                        inner, max_size=3)),
    max_leaves=8)
toml_documents = st.dictionaries(
    st.sampled_from(list(_KEYS)),
    st.sampled_from(list(_KEYS)).flatmap(
        lambda t: st.dictionaries(st.sampled_from(_KEYS[t]), toml_values, max_size=4)),
    max_size=4)


@settings(FUZZ, max_examples=30)
@given(doc=toml_documents)
@example(doc={"can": {"dbc": "a\x00b"}})
@example(doc={"estimator": {"warmup_s": 1e300}})
@example(doc={"daemon": {"checkpoint": "a\x00b"}})
def test_fuzz_a_configuration_never_an_internal_error(files: dict[str, Path],
                                                      doc: dict[str, Any]) -> None:
    """Random TOML configurations through ``canrls fit`` (every table but ``[daemon]``
    builds something there) and through the ``[daemon]`` table's validation that
    ``canrls run`` does first: one error line or a result, never exit 3."""
    conf = files["dir"] / "fuzz.toml"
    conf.write_text("".join(f"[{table}]\n" + "".join(f"{json.dumps(k)} = {inline_toml(v)}\n"
                                                      for k, v in body.items())
                            for table, body in doc.items()))
    code, _, err = _cli(["fit", str(files["log"]), "--kt", "0.1", "--config", str(conf),
                         "--quiet"])
    _one_error(code, err)
    cfg = None
    with contextlib.suppress(CanrlsError):
        cfg = AppConfig.load(conf)
    if cfg is not None:
        with contextlib.suppress(CanrlsError):
            DaemonSettings.from_table(cfg.daemon, cfg.source, cfg.base_dir)


@pytest.mark.parametrize("doc, key", [
    ('[can]\ndbc = "a\\u0000b"\n', "can.dbc"),
    ('[daemon]\ncheckpoint = "cp\\u0000.bin"\n', "daemon.checkpoint"),
    ('[daemon]\nmodel_file = "m\\u0000.toml"\n', "daemon.model_file"),
])
def test_a_nul_byte_in_a_path_of_the_configuration_names_the_key(
        files: dict[str, Path], doc: str, key: str) -> None:
    """A path with a NUL byte: before, Python's "embedded null byte" from the first
    open, an internal error (exit 3)."""
    conf = files["dir"] / "nul.toml"
    conf.write_text(doc)
    with pytest.raises(ConfigError, match=key.replace(".", "\\.")):
        cfg = AppConfig.load(conf)
        cfg.dbc_path()
        DaemonSettings.from_table(cfg.daemon, cfg.source, cfg.base_dir)
    code, _, err = _cli(["fit", str(files["log"]), "--kt", "0.1", "--config", str(conf),
                         "--quiet"])
    _one_error(code, err)
    if key == "can.dbc":
        assert code == 1 and key in err, err
