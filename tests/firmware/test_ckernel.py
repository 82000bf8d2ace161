"""The C kernel (src/canrls/c/firmware) against the Python specification, integer for integer.

Vectors come from :class:`canrls.estimation.fixed.estimator.FixedRLS` (``tools/gen_ckernel.py``):
the C state starts from ``FixedRLS.state()`` (so the tests hold whatever the initial
covariance policy is), then every sample's ``eps``, trace, exponent, flags, ``theta``,
every word of ``P``, ``c`` and all saturation counters are compared after each step.
The driver (``src/canrls/c/firmware/drivers/vector_driver.c``) is built with gcc for this
machine and with ``arm-linux-gnueabihf-gcc`` for 32-bit ARM (run under ``qemu-arm``); the
bare-metal Cortex-M4 example runs on ``qemu-system-arm``. Missing tools are installed
from Debian's packages when the tests run as root, otherwise those tests skip.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import subprocess
import sys
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from debian import need_tool

from canrls.core.c_escape import c_int
from canrls.estimation.fixed import kernels, layout
from canrls.estimation.fixed.estimator import FixedRLS
from canrls.estimation.fixed.formats import SITES, FixedConfig, FixedFlag, QFormat
from canrls.firmware.cgen import PLAN_64
from canrls.firmware.kernel_export import plan_c

ROOT = Path(__file__).resolve().parents[2]
KERNEL = ROOT / "src" / "canrls" / "c" / "firmware"
DRIVER = ROOT / "src" / "canrls" / "c" / "firmware" / "drivers" / "vector_driver.c"
CFLAGS = ["-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic"]


def _load(name: str) -> object:
    spec = importlib.util.spec_from_file_location(name, ROOT / "tools" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


gen = _load("gen_ckernel")
build_target = _load("build_target")

# ------------------------------------------------------------------ vectors
@dataclass
class Case:
    """One vector file: an estimator in some state, samples, frozen flags."""

    name: str
    est: FixedRLS
    Phi: np.ndarray
    Y: np.ndarray
    frozen: np.ndarray


def _rows(rng: np.random.Generator, N: int, n: int, scale: float = 1.0) -> np.ndarray:
    return rng.uniform(-scale, scale, (N, n))


def _case(name: str, n: int, lam: float, alpha: float, Phi: np.ndarray, Y: np.ndarray,
          frozen: np.ndarray | None = None, warm: int = 0, raw: bool = False,
          trace_max: float | None = None, **auto: object) -> Case:
    cfg = FixedConfig.auto(n, alpha, lam, trace_max=trace_max, **auto)  # type: ignore[arg-type]
    est = FixedRLS(cfg, n, lam, alpha, trace_max=trace_max)
    if raw:
        Pq, Yq = Phi.astype(np.int64), Y.astype(np.int64)
    else:
        Pq, Yq, _ = cfg.quantize_inputs(Phi, Y)
    if warm:
        # the C state starts where Python got to: theta, every P word, e, c, counters
        est.run(Pq[:warm], Yq[:warm], record=False)
        Pq, Yq = Pq[warm:], Yq[warm:]
    fz = np.zeros(len(Yq), bool) if frozen is None else np.asarray(frozen, bool)[warm:]
    return Case(name, est, Pq, Yq, fz)


def _cases() -> list[Case]:
    rng = np.random.default_rng(20240611)
    out = []
    # lambda = 1: P falls by orders of magnitude, the block exponent climbs
    Phi = _rows(rng, 400, 2)
    out.append(_case("n2_lam1", 2, 1.0, 1e-2, Phi, Phi @ [0.5, -0.25]))
    # lambda < 1 without excitation first: c grows and is folded into the words at e = 0,
    # the trace reaches trace_max (WINDUP), then data
    Phi = np.vstack([np.zeros((150, 3)), _rows(rng, 250, 3)])
    out.append(_case("n3_windup", 3, 0.98, 1e-1, Phi, Phi @ [0.2, 0.1, -0.3],
                     trace_max=40.0))
    # one direction unexcited for long stretches (low excitation, windup)
    Phi = _rows(rng, 500, 4)
    Phi[100:400, 2:] = 0.0
    out.append(_case("n4_partial", 4, 0.99, 1e-2, Phi,
                     Phi @ [0.1, -0.2, 0.3, 0.05] + 1e-3 * rng.standard_normal(500)))
    # narrow words, inputs beyond their 16-bit word (phi_in, y_in), raw integers
    n = 5
    Phi = np.round(_rows(rng, 300, n, 3.0) * 2**14)
    Y = np.round(Phi @ rng.uniform(-0.3, 0.3, n) * 2.0)
    out.append(_case("n5_w16_inputs", n, 0.99, 1e-1, Phi, Y, raw=True,
                     word_bits=16, acc_bits=32, input_bits=16))
    # theta and eps saturate (a too small theta range, an output far off the model)
    n = 6
    Phi = _rows(rng, 400, n)
    Y = Phi @ np.full(n, 0.6) + 0.9 * np.sign(rng.standard_normal(400))
    out.append(_case("n6_saturating", n, 0.995, 1e-2, Phi, Y, theta_max=0.5,
                     word_bits=24, acc_bits=48))
    # a checkpointed state taken mid-run, then a frozen stretch
    n = 8
    Phi = _rows(rng, 600, n)
    fz = np.zeros(600, bool)
    fz[350:420] = True
    out.append(_case("n8_warm_frozen", n, 0.99, 1e-2, Phi,
                     Phi @ rng.uniform(-0.1, 0.1, n), frozen=fz, warm=200))
    # the largest model, lambda = 1, a P format overridden (coarser than the automatic one)
    n = 12
    Phi = _rows(rng, 300, n)
    out.append(_case("n12_P_override", n, 1.0, 1e-3, Phi,
                     Phi @ rng.uniform(-0.05, 0.05, n),
                     P=QFormat(32, 20), input_bits=32))
    # n = 12, lambda < 1, small inputs
    Phi = _rows(rng, 300, n, 0.01)
    out.append(_case("n12_lam", n, 0.97, 1e-1, Phi, Phi @ rng.uniform(-1, 1, n)))
    return out


def _corrupt_case(seed: int, n: int) -> Case:
    """A state of random words (P not positive definite): every saturation and the d <= 0
    branch of the division, which only a broken state reaches."""
    rng = np.random.default_rng(seed)
    cfg = FixedConfig.auto(n, 1e-2, 0.99)
    est = FixedRLS(cfg, n, 0.99, 1e-2)
    s = est.state()
    P = rng.integers(cfg.P.lo, cfg.P.hi, (n, n), endpoint=True)
    s["P"] = np.triu(P) + np.triu(P, 1).T
    s["theta"] = rng.integers(cfg.theta.lo, cfg.theta.hi, n, endpoint=True)
    s["P_exp"] = int(rng.integers(0, 8))
    s["P_scale"] = int(rng.integers(1, est.constants["one_lam"], endpoint=True))
    # the fractions of theta below its LSB (a generator of their own: the draws above
    # and below stay those of the cases before the 64-bit estimate)
    s["theta_frac"] = np.random.default_rng(seed + 100).integers(0, 2**32 - 1, n,
                                                                   endpoint=True)
    # and of P below its words (likewise)
    F = np.random.default_rng(seed + 200).integers(-2**31, 2**31 - 1, (n, n), endpoint=True)
    s["P_frac"] = np.triu(F) + np.triu(F, 1).T
    est = FixedRLS.from_state(s)
    Pq = rng.integers(cfg.phi.lo, cfg.phi.hi, (80, n), endpoint=True)
    Yq = rng.integers(cfg.y.lo, cfg.y.hi, 80, endpoint=True)
    return Case(f"corrupt_{seed}_n{n}", est, Pq, Yq, np.zeros(80, bool))


@functools.cache
def _all_cases() -> tuple[Case, ...]:
    return tuple(_cases() + [_corrupt_case(s, n) for s, n in ((1, 3), (2, 7), (3, 10))])


@pytest.fixture(scope="module")
def vectors(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[str, Path, list[str]]]:
    d = tmp_path_factory.mktemp("vectors")
    out = []
    for c in _all_cases():
        path = d / f"{c.name}.txt"
        expected = gen.write_vectors(path, c.est, c.Phi, c.Y, c.frozen)
        out.append((c.name, path, expected))
    return out


def _compare(name: str, got: list[str], expected: list[str], n_words: int) -> None:
    assert len(got) == len(expected), f"{name}: {len(got)} lines, expected {len(expected)}"
    for k, (g, e) in enumerate(zip(got, expected, strict=True)):
        if g != e:
            gw, ew = g.split(), e.split()
            diff = [i for i, (a, b) in enumerate(zip(gw, ew, strict=True)) if a != b]
            pytest.fail(f"{name}: step {k} differs at word(s) {diff[:8]} of {n_words}:\n"
                        f"C:      {g[:300]}\nPython: {e[:300]}")


def _run_all(run: Callable[[Path, Path], None], vectors: list[tuple[str, Path, list[str]]],
             tmp_path: Path) -> None:
    for name, path, expected in vectors:
        out = tmp_path / f"{name}.out"
        run(path, out)
        got = out.read_text().splitlines()
        _compare(name, got, expected, len(expected[0].split()))


def test_vectors_cover_every_flag_and_saturation_site() -> None:
    """The cases reach every flag and every saturation counter (except acc and K, 0 by
    design: K is the high word of two normalised 31-bit words, it cannot saturate)."""
    flags = 0
    sites: set[str] = set()
    for c in _all_cases():
        est = FixedRLS.from_state(c.est.state())
        for k in range(len(c.Y)):
            est.freeze() if c.frozen[k] else est.resume()
            flags |= int(est.update(c.Phi[k], int(c.Y[k])).flags)
        sites |= set(est.saturations.nonzero())
    assert flags == int(FixedFlag.WINDUP | FixedFlag.LOW_EXCITATION | FixedFlag.SATURATION
                        | FixedFlag.FROZEN)
    assert sites == set(SITES) - {"acc", "K"}
    # n from 2 to 12, lambda = 1 and < 1, several word lengths
    assert {c.est.n for c in _all_cases()} >= {2, 3, 4, 5, 6, 8, 12}
    assert {c.est.lam == 1.0 for c in _all_cases()} == {True, False}
    assert {c.est.config.word_bits for c in _all_cases()} == {16, 24, 32}


@pytest.fixture(scope="module")
def host_driver(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cc = need_tool("gcc", ["gcc"])
    exe = tmp_path_factory.mktemp("host") / "vector_driver"
    subprocess.run([cc, *CFLAGS, "-I", str(KERNEL), str(DRIVER), str(KERNEL / "canrls_fixed.c"),
                    "-o", str(exe)], check=True, capture_output=True)
    return exe


def test_c_kernel_is_bit_exact_on_x86_64(host_driver: Path, vectors: list, tmp_path: Path
                                         ) -> None:
    _run_all(lambda i, o: subprocess.run([str(host_driver), str(i), str(o)], check=True,
                                         timeout=60), vectors, tmp_path)


def test_c_kernel_is_bit_exact_on_32_bit_arm(vectors: list, tmp_path: Path) -> None:
    cc = need_tool("arm-linux-gnueabihf-gcc", ["gcc-arm-linux-gnueabihf"])
    qemu = need_tool("qemu-arm", ["qemu-user"])
    exe = tmp_path / "vector_driver_arm"
    subprocess.run([cc, *CFLAGS, "-static", "-I", str(KERNEL), str(DRIVER),
                    str(KERNEL / "canrls_fixed.c"), "-o", str(exe)], check=True,
                   capture_output=True)
    _run_all(lambda i, o: subprocess.run([qemu, str(exe), str(i), str(o)], check=True,
                                         timeout=120), vectors, tmp_path)


def _run_fixed_n(cc: str, wrap: list[str], vectors: list, tmp_path: Path,
                 extra: Sequence[str] = ()) -> None:
    """Each case through a driver built with -DCANRLS_N = its n (loops unrolled, h~ summed
    by rows, the SMMULR path on ARM): bit for bit the same lines; a driver built for
    another n refuses the state (canrls_init_q31 takes only n = CANRLS_N). The drivers
    build, and the cases run, on every core at once."""
    n_of = {c.name: c.est.n for c in _all_cases()}
    by_n: dict[int, list] = {}
    for v in vectors:
        by_n.setdefault(n_of[v[0]], []).append(v)

    def build(n: int) -> Path:
        exe = tmp_path / f"vector_driver_n{n}"
        subprocess.run([cc, *CFLAGS, *extra, f"-DCANRLS_N={n}", "-I", str(KERNEL),
                        str(DRIVER), str(KERNEL / "canrls_fixed.c"), "-o", str(exe)],
                       check=True, capture_output=True)
        return exe

    def run(case: tuple[str, Path, list[str]]) -> list[str]:
        name, path, _ = case
        out = tmp_path / f"{name}.out"
        subprocess.run([*wrap, str(exes[n_of[name]]), str(path), str(out)], check=True,
                       timeout=120)
        return out.read_text().splitlines()

    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        exes = dict(zip(sorted(by_n), pool.map(build, sorted(by_n)), strict=True))
        for (name, _, expected), got in zip(vectors, pool.map(run, vectors), strict=True):
            _compare(name, got, expected, len(expected[0].split()))
    for n, exe in exes.items():
        other = next(v for m, w in by_n.items() if m != n for v in w)
        r = subprocess.run([*wrap, str(exe), str(other[1]), str(tmp_path / "o")],
                           capture_output=True, text=True)
        assert r.returncode == 2 and "canrls_init_q31 refused" in r.stderr


def test_c_kernel_with_a_fixed_n_is_bit_exact_on_x86_64(vectors: list, tmp_path: Path
                                                        ) -> None:
    _run_fixed_n(need_tool("gcc", ["gcc"]), [], vectors, tmp_path)


def test_c_kernel_with_a_fixed_n_is_bit_exact_on_32_bit_arm(vectors: list, tmp_path: Path
                                                            ) -> None:
    cc = need_tool("arm-linux-gnueabihf-gcc", ["gcc-arm-linux-gnueabihf"])
    qemu = need_tool("qemu-arm", ["qemu-user"])
    _run_fixed_n(cc, [qemu], vectors, tmp_path, ["-static"])


@pytest.mark.parametrize("fixed_n", [False, True], ids=["any-n", "fixed-n"])
def test_c_kernel_built_for_size_is_bit_exact_on_x86_64(vectors: list, tmp_path: Path,
                                                        fixed_n: bool) -> None:
    """-Os (CANRLS_SMALL: loops and one general instance of each step, no straight runs):
    the same integers as the specification."""
    cc = need_tool("gcc", ["gcc"])
    if fixed_n:
        _run_fixed_n(cc, [], vectors, tmp_path, ["-Os"])
        return
    exe = tmp_path / "vector_driver_os"
    subprocess.run([cc, *CFLAGS, "-Os", "-I", str(KERNEL), str(DRIVER),
                    str(KERNEL / "canrls_fixed.c"), "-o", str(exe)], check=True,
                   capture_output=True)
    _run_all(lambda i, o: subprocess.run([str(exe), str(i), str(o)], check=True, timeout=60),
             vectors, tmp_path)


def test_c_kernel_built_for_size_with_a_fixed_n_is_bit_exact_on_32_bit_arm(
        vectors: list, tmp_path: Path) -> None:
    cc = need_tool("arm-linux-gnueabihf-gcc", ["gcc-arm-linux-gnueabihf"])
    qemu = need_tool("qemu-arm", ["qemu-user"])
    _run_fixed_n(cc, [qemu], vectors, tmp_path, ["-static", "-Os"])


def test_driver_refuses_a_plan_without_a_constant(host_driver: Path, vectors: list,
                                                  tmp_path: Path) -> None:
    """The driver maps constants by name: a constant the spec drops or adds is an error."""
    _, path, _ = vectors[0]
    lines = path.read_text().splitlines()
    count = int(lines[0].split()[1])
    bad = tmp_path / "bad.txt"
    bad.write_text("\n".join([f"plan {count}", "no_such_constant 1", *lines[2:]]) + "\n")
    r = subprocess.run([str(host_driver), str(bad), str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "no_such_constant" in r.stderr


def test_plan_names_are_the_python_constants() -> None:
    """canrls_plan_q31 has exactly the fields of FixedRLS.constants, in its order."""
    text = (KERNEL / "canrls_fixed.h").read_text()
    body = text[text.index("typedef struct {"):text.index("} canrls_plan_q31;")]
    import re

    fields = [f for decl in re.findall(r"int(?:32|64)_t ([^;]+);", body)
              for f in (x.strip() for x in decl.split(","))]
    est = FixedRLS(FixedConfig.auto(3, 1e-2, 0.99), 3, 0.99, 1e-2)
    assert fields == list(est.constants)
    assert {k for k, v in est.constants.items() if not -2**31 <= v < 2**31} <= PLAN_64


_ACCESSORS_C = r"""
#include <stddef.h>
#include <stdio.h>
#include "canrls_fixed.h"
/* the pair of a parameter and of a word of P: adjacent, 8-byte aligned (one LDRD/STRD on
 * the M4) */
typedef char pair_is_8_bytes[sizeof(canrls_theta64) == 8 ? 1 : -1];
typedef char word_after_frac[offsetof(canrls_theta64, word) == 4 ? 1 : -1];
typedef char aligned_in_instance[offsetof(canrls_rls_q31, theta_q) % 8 == 0 ? 1 : -1];
typedef char P_pair_is_8_bytes[sizeof(canrls_P64) == 8 ? 1 : -1];
typedef char P_word_after_lo[offsetof(canrls_P64, word) == 4 ? 1 : -1];
typedef char P_aligned_in_instance[offsetof(canrls_rls_q31, P) % 8 == 0 ? 1 : -1];
PLAN
int main(void)
{
    static canrls_rls_q31 S;
    const int32_t p0[3] = {P0, P0, P0}, P_up[6] = {P0, 0, 0, P0, 0, P0};
    const int32_t Pf[6] = {PF};
    const int32_t th[3] = {TH};
    const uint32_t tf[3] = {TF};
    uint32_t j;
    if (canrls_init_q31(&S, &plan, 3, p0, 0) != CANRLS_OK) {
        return 2;
    }
    for (j = 0; j < 6; j++) {
        printf("%ld %ld\n", (long)canrls_P_q31(&S, j), (long)canrls_P_frac_q31(&S, j));
    }
    if (canrls_restore_q31(&S, th, tf, P_up, Pf, 0, ONE) != CANRLS_OK) {
        return 2;
    }
    for (j = 0; j < 3; j++) {
        printf("%ld %lu\n", (long)canrls_theta_q31(&S, j),
               (unsigned long)canrls_theta_frac_q31(&S, j));
    }
    for (j = 0; j < 6; j++) {
        printf("%ld %ld\n", (long)canrls_P_q31(&S, j), (long)canrls_P_frac_q31(&S, j));
    }
    if (canrls_restore_q31(&S, th, NULL, P_up, NULL, 0, ONE) != CANRLS_OK) {
        return 2;
    }
    for (j = 0; j < 3; j++) {
        printf("%ld %lu\n", (long)canrls_theta_q31(&S, j),
               (unsigned long)canrls_theta_frac_q31(&S, j));
    }
    for (j = 0; j < 6; j++) {
        printf("%ld %ld\n", (long)canrls_P_q31(&S, j), (long)canrls_P_frac_q31(&S, j));
    }
    return 0;
}
"""


def test_firmware_reads_the_state_through_its_accessors(tmp_path: Path) -> None:
    """The instance holds the 64-bit estimate as canrls_theta64 pairs (theta_q: frac, word)
    and the 64-bit P as canrls_P64 pairs (P: lo, word), each 8-byte aligned, so one
    LDRD/STRD per element: canrls_theta_q31 / canrls_theta_frac_q31 and canrls_P_q31 /
    canrls_P_frac_q31 give back the words and fractions canrls_init_q31 set (fractions 0)
    and canrls_restore_q31 took (NULL fractions: 0), the checkpoint's "theta",
    "theta_frac", "P" and "P_frac"."""
    header = (KERNEL / "canrls_fixed.h").read_text()
    body = header[header.index("typedef struct {\n    const canrls_plan_q31"):
                  header.index("} canrls_rls_q31;")]
    assert "canrls_theta64 theta_q[CANRLS_N_MAX];" in body
    assert "canrls_P64 P[CANRLS_TRI(CANRLS_N_MAX)];" in body
    assert " theta[" not in body and "theta_frac[" not in body
    est = FixedRLS(FixedConfig.auto(3, 1e-2, 0.99), 3, 0.99, 1e-2)
    c = est.constants
    th = [c["theta_hi"], c["theta_lo"], -1]
    tf = [0xFFFFFFFF, 0, 0x80000001]
    p0 = int(np.diag(est.P)[0])
    P_up = [p0, 0, 0, p0, 0, p0]
    Pf = [2**31 - 1, -2**31, 0, -1, 1, 12345]
    src = (_ACCESSORS_C.replace("PLAN", plan_c(c, "plan"))
           .replace("P0", str(p0)).replace("ONE", str(c["one_lam"]))
           .replace("PF", ", ".join(c_int(v) for v in Pf))
           .replace("TH", ", ".join(map(str, th))).replace("TF", ", ".join(f"{v}u" for v in tf)))
    prog = tmp_path / "accessors.c"
    prog.write_text(src)
    exe = tmp_path / "accessors"
    cc = need_tool("gcc", ["gcc"])
    subprocess.run([cc, *CFLAGS, "-I", str(KERNEL), str(prog), str(KERNEL / "canrls_fixed.c"),
                    "-o", str(exe)], check=True, capture_output=True)
    out = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout.split()
    got = [(int(a), int(b)) for a, b in zip(out[::2], out[1::2], strict=True)]
    zero = [0] * 6
    assert got == [*zip(P_up, zero, strict=True),
                   *zip(th, tf, strict=True), *zip(P_up, Pf, strict=True),
                   *zip(th, [0, 0, 0], strict=True), *zip(P_up, zero, strict=True)]


# ------------------------------------------------------------------ the pass over P
PASS_DRIVER = KERNEL / "drivers" / "pass_driver.c"
PASS_N = 4
W_MIN, W_MAX = -2**31, 2**31 - 1


def _reference(P: list[list[int]], F: list[list[int]], prm: dict[int, int]
               ) -> kernels._Reference:
    """The specification's arithmetic on one state (P words, P fractions), the plan's
    constants ``prm`` by index, every word 32 bits wide."""
    p = [0] * 48
    p[layout.I_P_LO], p[layout.I_P_HI] = W_MIN, W_MAX
    for k, v in prm.items():
        p[k] = v
    return kernels._Reference(P, F, [0] * len(SITES), p, 128, layout.MODE_SYMMETRIC)


def _spec_pass(P_s: int, sh: int, K: list[int], h: list[int], P: list[list[int]],
               F: list[list[int]]) -> list[int]:
    """What the step does to P around its diagonal (the specification's P update and block
    exponent, kernels._Reference): V_ij <- V_ij - u off the diagonal, u = K_i h~_j
    2^(32 - P_s) or rsh(K_i h~_j, 32) 2^(64 - P_s), then every V <- V 2^sh, each
    saturated and counted. The words, fractions and count, as the driver prints them."""
    ref = _reference(P, F, {})
    n = len(K)
    for i in range(n):
        for j in range(i + 1, n):
            x = ref.mul(K[i], h[j])
            u = x * 2**(32 - P_s) if P_s < 32 else ref.rsh(x, 32) * 2**(64 - P_s)
            ref.Vput(i, j, ref.Vget(i, j) - u)
    for i, j in ref.stored():
        if sh:
            ref.Vput(i, j, ref.Vget(i, j) * 2**sh)
    return [v for i, j in ref.stored() for v in (ref.P[i][j], ref.Pf[i][j])] + [
        ref.counts[layout.S_P]]


def _pass_cases(rng: np.random.Generator) -> list[tuple[int, int, list[int], list[int],
                                                        list[list[int]], list[list[int]]]]:
    """Passes of every class of P_s (PM_LOWK, the loop of PM_LOW, PM_32, PM_HIGH with the
    shift after the step, P_s = 32 + sh among them, and fused) with and without a shift, on
    words of every size (elements that saturate, differences that leave 64 bits), and
    the corners the recorded vectors do not reach: a K 2^a of -2^31 (its row in the
    general element), a D that fails the room test, a diagonal without room."""
    n, out = PASS_N, []

    def sym(w: np.ndarray) -> list[list[int]]:
        m = np.triu(w) + np.triu(w, 1).T
        return [[int(x) for x in r] for r in m]

    for P_s, sh in [(27, 0), (27, 5), (29, 1), (31, 2), (22, 3), (32, 0), (32, 4),
                    (34, 3), (40, 3), (35, 3), (45, 1), (50, 0), (60, 7)]:
        for size in (12, 24, 29, 31):
            for _ in range(12):
                K = [int(x) for x in rng.integers(-2**30, 2**30, n)]
                h = [int(x) for x in rng.integers(-2**31, 2**31, n)]
                if P_s <= 31 and rng.random() < 0.7:
                    # small enough for K 2^a and h~ 2^b to be words (PM_LOWK)
                    K = [k >> (32 - P_s) for k in K]
                P = sym(rng.integers(-2**size, 2**size, (n, n)))
                F = sym(rng.integers(W_MIN, W_MAX, (n, n), endpoint=True))
                out.append((P_s, sh, K, h, P, F))
    # K_0 2^a = -2^31 (a = 32 - P_s = 5): the row's negation is not a word
    for sh in (1, 5):
        K = [-2**26, 3 << 20, -(5 << 19), 7]
        h = [int(x) for x in rng.integers(-2**30, 2**30, n)]
        P = sym(rng.integers(-2**20, 2**20, (n, n)))
        out.append((27, sh, K, h, P, sym(np.zeros((n, n), np.int64))))
    # words at the ends of the range: V - u leaves 64 bits, V 2^sh saturates
    for P_s, sh in [(27, 2), (32, 2), (34, 3), (40, 2)]:
        K = [2**30 - 1, -2**30, 2**29, -(2**29)]
        if P_s < 32:
            K = [k >> 5 for k in K]
        h = [-2**31, 2**31 - 1, -2**31, 2**31 - 1]
        P = sym(np.array([[W_MAX, W_MAX, W_MIN, W_MAX]] * n))
        out.append((P_s, sh, K, h, P, sym(np.full((n, n), W_MAX))))
    return out


def _spec_windup(prm: dict[int, int], c: int, e: int, trw: int, sv: int, h: list[int]
                 ) -> bool:
    """The specification's windup test (kernels._Reference.forgetting) with T = trw."""
    n = len(h)
    P = [[trw if i == j == 0 else 0 for j in range(n)] for i in range(n)]
    ref = _reference(P, [[0] * n for _ in range(n)], prm)
    return ref.forgetting(h, h, sv, e, c)[1] != 0


def _windup_cases(rng: np.random.Generator) -> list[tuple[dict[int, int], int, int, int,
                                                          int, list[int]]]:
    """Windup tests with c = 2^k (the path that rounds h' h only where its bounds do not
    decide): T swept across the point where the answer turns, so that the other side
    falls below, within and above the bounds; |h_i| below and above 2^29."""
    out = []
    for k, vw_ps, df, top in [(30, 14, 0, 21), (27, 12, 0, 24), (30, 30, 0, 31),
                              (30, 16, 2, 21), (29, 10, -3, 22)]:
        for _ in range(6):
            h = [int(x) for x in rng.integers(-2**top, 2**top, PASS_N)]
            s = 30 - k
            est = sum(((x + (1 << s >> 1)) >> s) ** 2 for x in h) >> vw_ps
            est = est << df if df >= 0 else est >> -df
            prm = {layout.I_LAM_D: 1, layout.I_DEN_LO: W_MIN, layout.I_DEN_HI: W_MAX,
                   layout.I_HC_S: 30, layout.I_VW_PS: vw_ps, layout.I_LHS_PS: 0,
                   layout.I_CMP_DF: df, layout.I_TC_S: k, layout.I_TMAX: 0,
                   layout.I_TMAX_LIM: 0, layout.I_P_HI: W_MAX, layout.I_ONE_D: 1}
            for d in range(-2 * PASS_N, 2 * PASS_N + 1):
                if 0 < est + d <= W_MAX:
                    out.append((prm, 1 << k, 0, est + d, 0, h))
    # the squares' sum reaches 2^64 (h~_i = -2^31): the terms rounded one by one
    prm = {**prm, layout.I_VW_PS: 30, layout.I_CMP_DF: 0, layout.I_TC_S: 30}
    for trw in (1, 2, 3, 4, 5):
        out.append((prm, 1 << 30, 0, trw, 0, [W_MIN] * PASS_N))
    return out


def _run_pass_driver(cc: str, wrap: list[str], tmp_path: Path, extra: Sequence[str] = ()
                     ) -> None:
    exe = tmp_path / "pass_driver"
    subprocess.run([cc, *CFLAGS, *extra, f"-DCANRLS_N={PASS_N}", "-I", str(KERNEL),
                    str(PASS_DRIVER), "-o", str(exe)], check=True, capture_output=True)
    rng = np.random.default_rng(20261207)
    passes, windups = _pass_cases(rng), _windup_cases(rng)
    lines = []
    for P_s, sh, K, h, P, F in passes:
        up = [v for i in range(PASS_N) for j in range(i, PASS_N) for v in (P[i][j], F[i][j])]
        lines.append(" ".join(map(str, ["pass", P_s, sh, *K, *h, *up])))
    for prm, c, e, trw, sv, h in windups:
        plan = [prm[k] for k in (layout.I_LAM_D, layout.I_DEN_LO, layout.I_DEN_HI,
                                 layout.I_P_HI, layout.I_LHS_PS, layout.I_CMP_DF,
                                 layout.I_HC_S, layout.I_VW_PS)]
        # T = rsh(trw c, tc_s) - trace_max 2^e = trw (tc_s = log2 c, trace_max = 0)
        lines.append(" ".join(map(str, ["windup", *plan, c, e, trw, sv, *h])))
    r = subprocess.run([*wrap, str(exe)], input="\n".join(lines) + "\n", capture_output=True,
                       text=True, check=True, timeout=120)
    got = r.stdout.splitlines()
    assert len(got) == len(lines)
    for k, case in enumerate(passes):
        assert [int(x) for x in got[k].split()] == _spec_pass(*case), f"pass {k}: {lines[k]}"
    flips = set()
    for k, (prm, c, e, trw, sv, h) in enumerate(windups, start=len(passes)):
        want = _spec_windup(prm, c, e, trw, sv, h)
        assert got[k] == str(int(want)), f"windup: {lines[k]}"
        flips.add(want)
    assert flips == {False, True}


def test_fixed_n_pass_over_P_is_the_specification_on_x86_64(tmp_path: Path) -> None:
    """Each class of the fixed-n pass over P (the shift folded in) and the windup test's
    bounds, on inputs the recorded vectors do not reach, against the specification."""
    _run_pass_driver(need_tool("gcc", ["gcc"]), [], tmp_path)


def test_fixed_n_pass_over_P_is_the_specification_on_32_bit_arm(tmp_path: Path) -> None:
    """The same on 32-bit ARM (Thumb-2: the SMLAL, SMMLAR and UMULL forms of the pass)."""
    cc = need_tool("arm-linux-gnueabihf-gcc", ["gcc-arm-linux-gnueabihf"])
    qemu = need_tool("qemu-arm", ["qemu-user"])
    _run_pass_driver(cc, [qemu], tmp_path, ["-static"])


# ------------------------------------------------------------------ Cortex-M4
@pytest.fixture(scope="module")
def m4_tools() -> Iterator[None]:
    need_tool("arm-none-eabi-gcc", ["gcc-arm-none-eabi", "libnewlib-arm-none-eabi"])
    need_tool("qemu-system-arm", ["qemu-system-arm"])
    yield


def test_cortex_m4_example_matches_python_on_a_recorded_log(m4_tools: None, tmp_path: Path
                                                            ) -> None:
    s = gen.log_stream(duration=4.0)
    hdr = tmp_path / "stream.h"
    hdr.write_text(gen.stream_header(s))
    elf = tmp_path / "example.elf"
    build_target.build_example(hdr, elf)
    rc, text = build_target.run_example(elf, timeout=60)
    assert rc == 0, text
    assert "bit-exact with the Python FixedRLS: PASS" in text
    theta = [int(line.split("=")[1]) for line in text.splitlines() if "theta[" in line]
    assert theta == FixedRLS.from_state(s.est.state()).run(
        s.Phi, s.Y, record=False).theta_final.tolist()
    # the example fails loudly when a final word differs
    bad = hdr.read_text().replace("#define STREAM_C_FINAL ", "#define STREAM_C_FINAL 1 + ")
    hdr.write_text(bad)
    build_target.build_example(hdr, elf)
    rc, text = build_target.run_example(elf, timeout=60)
    assert rc != 0 and "FAIL" in text


def test_cortex_m4_kernel_builds_and_counts(m4_tools: None, tmp_path: Path) -> None:
    k = build_target.build_kernel(tmp_path)
    assert k.text > 0 and k.data == 0 and k.bss == 0
    assert "canrls_update_q31" in k.stack and k.worst_stack < 512
    s = gen.synthetic_stream(4, 8)
    hdr = tmp_path / "n4.h"
    hdr.write_text(gen.stream_header(s))
    elf = tmp_path / "n4.elf"
    build_target.build_example(hdr, elf)
    counts = build_target.count_instructions(elf, tmp_path)
    assert len(counts) == 8
    assert all(100 < c < 20000 for c in counts)
