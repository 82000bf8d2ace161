"""``canrls export-c``: the exported directory compiles for the host and the Cortex-M4.

The configuration header holds the plan of the pipeline's own FixedRLS (checked by
compiling a program that runs the exported kernel on the stream of a FixedRLS built like
the pipeline's and compares the final estimate); the frame codecs are cantools'.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from debian import need_tool

from canrls.cli.main import main
from canrls.core.errors import ConfigError
from canrls.estimation.pipeline import Pipeline
from canrls.firmware.kernel_export import export_c
from canrls.firmware.load import load
from canrls.processor.config import AppConfig

CFLAGS = ["-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic"]
TOML = """\
[model]
effects = ["inertia", "viscous", "coulomb", "offset"]
kt = 0.1
"""


@pytest.fixture
def exported(tmp_path: Path) -> Path:
    cfg = tmp_path / "drive.toml"
    cfg.write_text(TOML)
    out = tmp_path / "c"
    assert main(["export-c", "--model", str(cfg), "--out", str(out)]) == 0
    return out


def test_export_writes_kernel_config_and_frames(exported: Path) -> None:
    names = sorted(p.name for p in exported.iterdir())
    # and the whole estimator (tests/firmware/test_target_c.py)
    assert names == ["Makefile", "README.md", "canrls_bounds.h", "canrls_config.c",
                     "canrls_config.h", "canrls_fixed.c", "canrls_fixed.h", "canrls_frames.c",
                     "canrls_frames.h",
                     "canrls_front.c", "canrls_model.c", "canrls_model.h", "canrls_target.c",
                     "canrls_target.h", "canrls_target_check.c", "canrls_target_check.h",
                     "canrls_target_math.h", "canrls_target_tables.h", "size_main.c"]
    h = (exported / "canrls_config.h").read_text()
    assert "#define CANRLS_MECHANICAL_N 4" in h
    assert "CANRLS_MECHANICAL_INERTIA_J 0" in h and "int canrls_mechanical_init(" in h
    assert "int canrls_frames_rls_estimate_pack(" in (exported / "canrls_frames.h").read_text()


def _front(c: Path) -> list[str]:
    """The generated front end builds only with -DCANRLS_FRONT (its #error says so)."""
    return ["-DCANRLS_FRONT"] if c.name == "canrls_front.c" else []


def test_exported_directory_compiles_with_gcc(exported: Path) -> None:
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not installed")
    for c in sorted(exported.glob("*.c")):
        subprocess.run([gcc, *CFLAGS, *_front(c), "-c", str(c), "-o", str(c.with_suffix(".o"))],
                       check=True, capture_output=True)


def test_exported_directory_compiles_for_the_cortex_m4(exported: Path) -> None:
    cc = need_tool("arm-none-eabi-gcc", ["gcc-arm-none-eabi", "libnewlib-arm-none-eabi"])
    for c in sorted(exported.glob("*.c")):
        subprocess.run([cc, "-mcpu=cortex-m4", "-mthumb", *CFLAGS, *_front(c), "-c", str(c),
                        "-o", str(c.with_suffix(".m4.o"))], check=True, capture_output=True)


@pytest.mark.parametrize("build", [[], ["-DCANRLS_N=4"]], ids=["any-n", "fixed-n"])
def test_exported_plan_runs_like_the_pipelines_estimator(exported: Path, tmp_path: Path,
                                                         build: list[str]) -> None:
    """A host program with the exported config runs the pipeline's FixedRLS bit for bit,
    with the kernel built for any n and for the model's n (the header's advice)."""
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not installed")
    cfg = load(tmp_path / "drive.toml").config
    protocol = cfg.protocol()
    pipe = Pipeline(cfg.model_for(protocol), protocol.period or 1e-3, cfg.settings())
    est = pipe.estimators[0].frls
    est.backend = "spec"
    rng = np.random.default_rng(3)
    Phi = rng.uniform(-0.5, 0.5, (300, est.n))
    Pq, Yq, _ = est.config.quantize_inputs(Phi, Phi @ np.array([0.2, -0.1, 0.05, 0.01]))
    est.run(Pq, Yq, record=False)
    rows = ",\n".join("{" + ", ".join(map(str, r)) + "}" for r in Pq.tolist())
    prog = tmp_path / "check.c"
    prog.write_text(
        '#include <stdio.h>\n#include "canrls_config.h"\n'
        f"static const int32_t phi[{len(Yq)}][CANRLS_MECHANICAL_N] = {{{rows}}};\n"
        f"static const int32_t y[{len(Yq)}] = {{{', '.join(map(str, Yq.tolist()))}}};\n"
        "int main(void) {\n  static canrls_rls_q31 S; unsigned k, j;\n"
        "  if (canrls_mechanical_init(&S) != CANRLS_OK) return 2;\n"
        f"  for (k = 0; k < {len(Yq)}u; k++) canrls_update_q31(&S, phi[k], y[k], 0);\n"
        "  for (j = 0; j < CANRLS_MECHANICAL_N; j++)\n"
        "    printf(\"%ld\\n\", (long)canrls_theta_q31(&S, j));\n"
        "  return 0;\n}\n")
    exe = tmp_path / "check"
    subprocess.run([gcc, *CFLAGS, *build, "-I", str(exported), str(prog),
                    str(exported / "canrls_config.c"), str(exported / "canrls_fixed.c"),
                    "-o", str(exe)], check=True, capture_output=True)
    out = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout
    assert [int(x) for x in out.split()] == est.theta.tolist()


def test_a_saved_model_that_is_not_one_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "m.json"
    p.write_text("{}")
    with pytest.raises(ConfigError):
        load(p)


def test_export_c_api_names_the_equations(tmp_path: Path) -> None:
    cfg = AppConfig()
    cfg.model = {"effects": ["inertia", "viscous"], "kt": 0.1}
    r = export_c(cfg, tmp_path / "out")
    assert r.equations == ("mechanical",) and len(r.files) == 7
    assert "mechanical" in str(r)


def test_header_says_the_models_n_and_refuses_another(exported: Path) -> None:
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not installed")
    h = (exported / "canrls_config.h").read_text()
    assert "-DCANRLS_N=4" in h and "#define CANRLS_CONFIG_N 4" in h
    c = exported / "canrls_config.c"
    r = subprocess.run([gcc, *CFLAGS, "-DCANRLS_N=5", "-c", str(c), "-o",
                        str(c.with_suffix(".o"))], capture_output=True, text=True)
    assert r.returncode != 0 and "CANRLS_N other than this model's n" in r.stderr


def test_make_size_m4_measures_what_a_firmware_links(exported: Path) -> None:
    """``make size-m4`` links the least program that calls the API (``size_main.c``) with
    ``--gc-sections`` and prints the image's ``.text`` + ``.rodata``: the table-driven
    front end's functions, which the generated one does not call, are not in it."""
    need_tool("arm-none-eabi-gcc", ["gcc-arm-none-eabi", "libnewlib-arm-none-eabi"])
    r = subprocess.run(["make", "-s", "-C", str(exported), "size-m4"], capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    m = re.search(r"-Os \.text \+ \.rodata linked: (\d+) B \(the goal of under 12288 B: "
                  r"(met|missed)\)", r.stdout)
    assert m is not None, r.stdout
    elf = exported / "canrls_size.elf"
    size = subprocess.run(["arm-none-eabi-size", "-A", str(elf)], capture_output=True,
                          text=True, check=True).stdout
    total = sum(int(s.group(2)) for s in re.finditer(r"^(\.text|\.rodata)\s+(\d+)", size, re.M))
    assert int(m.group(1)) == total and (m.group(2) == "met") == (total < 12288)
    nm = subprocess.run(["arm-none-eabi-nm", str(elf)], capture_output=True, text=True,
                        check=True).stdout
    names = {line.split()[-1] for line in nm.splitlines()}
    assert {"canrls_target_frame", "canrls_target_publish", "canrls_target_adapt",
            "canrls_update_q31"} <= names
    assert not {"canrls_target_pair", "canrls_target_step", "canrls_target_sampled"} & names
