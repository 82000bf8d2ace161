"""The arithmetic of the target's integer path: the specification against the numbers it
stands for, and the C against the specification, on x86-64 and 32-bit ARM.

``canrls.firmware.qmath`` is held to what its functions mean (tanh, exp, sin and cos
within the tables' documented errors; float32 bits against numpy's conversion) and the
C functions of ``canrls_target.c`` (reached through
``src/canrls/c/firmware/drivers/target_math_driver.c``) to the specification, integer for
integer, on seeded random inputs and on the edges of every split (the products of 93 bits,
the shifts around 31, saturation, subnormals).
"""

from __future__ import annotations

import math
import re
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from debian import need_tool

from canrls.firmware import qmath, tables
from canrls.firmware.qmath import (
    ceil_scaled,
    clog2,
    exp_neg_q24,
    f32_bits,
    float_fixed,
    floor_scaled,
    isqrt,
    mul_rsh,
    rsh,
    sat,
    scale_p64,
    sincos_q64,
    tanh_q24,
)

ROOT = Path(__file__).resolve().parents[2]
C_DIR = ROOT / "src" / "canrls" / "c" / "firmware"
DRIVER = ROOT / "src" / "canrls" / "c" / "firmware" / "drivers" / "target_math_driver.c"
sys.path.insert(0, str(ROOT / "tools"))


def test_the_tables_are_the_generators_and_the_c_has_the_same_words() -> None:
    import gen_target_tables as gen

    header = (C_DIR / "canrls_target_tables.h").read_text()
    for name in gen.FUNCTIONS:
        kept = getattr(tables, name)
        # a libm that rounds a last bit otherwise moves a word by 1 at most
        assert all(abs(a - b) <= 1 for fs, ks in zip(gen.table(name), kept, strict=True)
                   for a, b in zip(fs, ks, strict=True)), name
        body = re.search(rf"cr_{name.lower()}\[\d+\]\[4\] = \{{(.*?)\}};", header, re.S)
        assert body is not None
        words = [int(w) for w in re.findall(r"-?\d+", body.group(1))]
        assert words == [w for seg in kept for w in seg], name
        # Horner's partial sums stay within an int32 (the C holds them in one): |p| <=
        # |c0| + |c1| + |c2| + |c3| for t < 1
        assert all(sum(abs(c) for c in seg) < 1 << 31 for seg in kept), name


@pytest.mark.parametrize("name,f,bound", [
    ("TANH", lambda x: math.tanh(8 * x), 1.1e-5),
    ("SIN", lambda x: math.sin(math.pi * x / 2), 7e-8),
    ("EXP2", lambda x: 2.0 ** -x, 4e-8),
])
def test_each_table_is_within_its_documented_error(name: str, f: object, bound: float) -> None:
    tab = getattr(tables, name)
    us = list(range(0, 1 << 32, (1 << 32) // 50000)) + [(1 << 32) - 1]
    worst = max(abs(qmath.table_eval(tab, u) / 2 ** 30 - f(u / 2 ** 32)) for u in us)  # type: ignore[operator]
    assert worst <= bound, (name, worst)
    # the segments join: tanh(0) and sin(0) are 0 exactly, 2^-0 is 1
    assert qmath.table_eval(tab, 0) == (1 << 30 if name == "EXP2" else 0)


def test_the_functions_mean_what_they_say() -> None:
    rng = np.random.default_rng(11)
    for z in rng.integers(-(12 << 24), 12 << 24, 2000).tolist() + [0, 8 << 24, -(8 << 24)]:
        assert abs(tanh_q24(z) / 2 ** 30 - math.tanh(z / 2 ** 24)) < 1.1e-5
        assert tanh_q24(-z) == -tanh_q24(z)
    for x in rng.integers(0, 40 << 24, 2000).tolist() + [0]:
        assert abs(exp_neg_q24(x) / 2 ** 30 - math.exp(-x / 2 ** 24)) < 1e-7
    for ph in rng.integers(0, 1 << 63, 2000, dtype=np.uint64).tolist() + [0, 1 << 62, 3 << 62]:
        ph = int(ph) * 2 + 1 if ph % 3 else int(ph)
        ph &= (1 << 64) - 1
        s, c = sincos_q64(ph)
        a = 2 * math.pi * ph / 2 ** 64
        assert abs(s / 2 ** 30 - math.sin(a)) < 1e-7 and abs(c / 2 ** 30 - math.cos(a)) < 1e-7


def test_float32_bits_round_to_nearest_even_and_saturate() -> None:
    rng = np.random.default_rng(12)
    vs = rng.integers(-(1 << 31), 1 << 31, 3000).tolist() + [1, -1, (1 << 31) - 1, -(1 << 31),
                                                             (1 << 24) + 1, (1 << 25) + 3]
    es = rng.integers(-180, 110, 3000).tolist() + [0, -149, -150, -160, 97, 100, 127]
    for v, e in zip(vs, es + [0] * (len(vs) - len(es)), strict=False):
        want = np.float32(v * 2.0 ** e) if abs(v * 2.0 ** e) < 3.4e38 else np.float32(
            math.copysign(3.4e38, v))
        got = np.array([f32_bits(v, e)], np.uint32).view(np.float32)[0]
        if v * 2.0 ** e != 0 and abs(v * 2.0 ** e) < 3.4e38:
            # numpy rounds the float64 (exact here: |v| < 2^31) to float32, ties to even
            assert got == want, (v, e, got, want)
        elif v == 0:
            assert f32_bits(v, e) == 0
    assert f32_bits(1, 200) == qmath.F32_SAT and f32_bits(-1, 200) == 0x80000000 | qmath.F32_SAT


def _float_words(rng: np.random.Generator) -> list[tuple[int, int]]:
    """Seeded (bits, width) of float32 and float64 fields: random words, NaN, infinities,
    zeros of both signs, subnormals, and values around every power of two."""
    out = [(int(rng.integers(0, 1 << 32)), 32) for _ in range(1500)]
    out += [(int(rng.integers(0, 1 << 63)) * 2 + int(rng.integers(0, 2)), 64) for _ in range(1500)]
    for x in (0.0, -0.0, 1e-40, -1e-45, 0.5, 1.5, 2.5, -2.5, 3e38, math.inf, -math.inf, math.nan):
        out.append((int(np.array([x], np.float32).view(np.uint32)[0]), 32))
        out.append((int(np.array([x], np.float64).view(np.uint64)[0]), 64))
    for e in range(-70, 40):
        for x in (2.0 ** e, -(2.0 ** e) * 1.5, 2.0 ** e * (1 - 2 ** -24)):
            out.append((int(np.array([x], np.float32).view(np.uint32)[0]), 32))
            out.append((int(np.array([x], np.float64).view(np.uint64)[0]), 64))
    return out


def test_a_float_field_is_its_value_in_fixed_point_rounded_half_away() -> None:
    rng = np.random.default_rng(14)
    for bits, width in _float_words(rng):
        frac = int(rng.integers(-60, 61))
        x = np.array([bits], np.uint32 if width == 32 else np.uint64).view(
            np.float32 if width == 32 else np.float64)[0]
        got = float_fixed(bits, width, frac)
        if not np.isfinite(x):
            assert got is None, (bits, width)
            continue
        # the exact value times 2^frac, rounded half away from zero
        q = Fraction(float(x)) * Fraction(2) ** frac
        want = math.floor(abs(q) + Fraction(1, 2))
        assert got == (-want if q < 0 else want), (float(x), frac, got, want)


def _ops() -> list[tuple[str, list[int], str]]:
    """Seeded operations on the edges of every split, with the specification's results."""
    rng = np.random.default_rng(13)
    ops: list[tuple[str, list[int], str]] = []

    def add(name: str, args: list[int], want: object) -> None:
        w = " ".join(str(int(x)) for x in (want if isinstance(want, tuple) else (want,)))
        ops.append((name, args, w))

    big = [0, 1, -1, (1 << 61) - 1, -(1 << 61) + 1, (1 << 31) - 1, -(1 << 31), 1 << 31]
    edges = [0, 1, -1, (1 << 31) - 1, -(1 << 31), (1 << 30), -(1 << 30)]
    for _ in range(3000):
        x = int(rng.choice(big)) if rng.random() < 0.1 else int(
            rng.integers(-(1 << 60), 1 << 60)) >> int(rng.integers(0, 60))
        m = int(rng.integers(1 << 30, 1 << 31)) * (1 if rng.random() < 0.5 else -1)
        s = int(rng.choice([0, 1, 30, 31, 32, 33, 62, 92, 93, 94, 120])) if rng.random() < 0.3 \
            else int(rng.integers(0, 100))
        add("mul_rsh", [x, m, s], mul_rsh(x, m, s))
        a = abs(x) or 1
        add("clog2_mul", [a, abs(m)], clog2(a * abs(m)))
        n = int(rng.integers(0, 1 << 62)) >> int(rng.integers(0, 62))
        add("isqrt", [n], isqrt(n))
        add("rsh", [x, s], rsh(x, s) if s < 64 else 0)
        # the filter's row: rsh(a0 x1 + a1 x2 + (g0 up + g1 u) 2^fx, 30), |x| < 2^60,
        # |u| 2^fx < 2^59, the row's coefficients summing below 2^31
        a0, a1, g0, g1 = (int(v) for v in rng.integers(-(1 << 29), 1 << 29, 4))
        if rng.random() < 0.1:
            # an input's coefficient at the model's bound 2^30 (2g no int32)
            g0, a0, a1 = int(rng.choice([1 << 30, -(1 << 30)])), a0 >> 2, a1 >> 2
        fx = int(rng.integers(0, 41))
        x1, x2 = (int(v) >> int(rng.integers(0, 60)) for v in
                  rng.integers(-(1 << 59), 1 << 59, 2))
        ub = min(1 << 31, 1 << max(0, 58 - fx))
        up, u = (int(v) >> int(rng.integers(0, 20)) for v in rng.integers(-ub, ub, 2))
        add("svf", [a0, a1, g0, g1, x1, x2, up, u, fx],
            rsh(a0 * x1 + a1 * x2 + ((g0 * up + g1 * u) << fx), 30))
        # a narrow filter's row: int32 words, fx 0, saturated to int32 (some at its ends)
        w32 = [int(rng.choice([(1 << 31) - 1, -(1 << 31)])) if rng.random() < 0.3 else
               int(rng.integers(-(1 << 31), 1 << 31)) >> int(rng.integers(0, 31))
               for _ in range(4)]
        add("svf32", [a0, a1, g0, g1, *w32],
            sat(rsh(a0 * w32[0] + a1 * w32[1] + g0 * w32[2] + g1 * w32[3], 30),
                -(1 << 31), (1 << 31) - 1))
        mm = int(rng.integers(0, 1 << 53))
        e = int(rng.integers(-80, 70))
        add("floor", [mm, e], floor_scaled(mm, e))
        add("ceil", [mm, e], ceil_scaled(mm, e))
        z = int(rng.integers(-(1 << 31), 1 << 31))
        add("tanh", [z], tanh_q24(z))
        # not saturated: the generated front end's argument, around +-8 and int32's ends
        zw = int(rng.choice([8 << 24, (8 << 24) - 1, (1 << 31), -(1 << 31) - 1, 1 << 62])) * \
            int(rng.choice([1, -1])) if rng.random() < 0.3 else \
            int(rng.integers(-(1 << 62), 1 << 62)) >> int(rng.integers(0, 62))
        add("tanh_wide", [zw], tanh_q24(sat(zw, -(1 << 31), (1 << 31) - 1)))
        xe = int(rng.integers(0, 33 << 24))
        add("exp", [xe], exp_neg_q24(xe))
        ph = int(rng.integers(0, 1 << 63)) * 2 + int(rng.integers(0, 2))
        add("sincos", [ph], sincos_q64(ph))
        v = int(rng.integers(-(1 << 31), 1 << 31))
        ev = int(rng.integers(-200, 140))
        add("f32", [v, ev], f32_bits(v, ev))
        # an element of the 64-bit P scaled by 2^s: words at the ends of int32 (the pair
        # just below -2^63), fractions of either sign, shifts across every split
        pw = int(rng.choice(edges)) if rng.random() < 0.2 else int(
            rng.integers(-(1 << 31), 1 << 31)) >> int(rng.integers(0, 32))
        pf = int(rng.choice(edges)) if rng.random() < 0.2 else int(
            rng.integers(-(1 << 31), 1 << 31))
        ps = int(rng.choice([-100, -95, -94, -64, -63, -34, -33, -32, -31, -2, -1, 0, 1, 31,
                             32, 33, 63, 64, 90])) if rng.random() < 0.3 \
            else int(rng.integers(-70, 70))
        plo, phi = ((-(1 << 31), (1 << 31) - 1) if rng.random() < 0.5
                    else (0, int(rng.integers(1, 1 << 31))))
        if not plo <= pw <= phi:
            pw = sat(pw, plo, phi)
        w2, f2, clamped = scale_p64(pw, pf, ps, plo, phi)
        add("p64", [pw, pf, ps, plo, phi], (w2, f2, int(clamped)))
    for sign in (1, -1):
        # a narrow row beyond int32 either way: saturated
        w = sign * ((1 << 31) - 1)
        add("svf32", [1 << 29] * 4 + [w] * 4, sign * (1 << 31) - (sign > 0))
    for bits, width in _float_words(rng):
        frac = int(rng.integers(-60, 61)) if rng.random() < 0.5 else int(rng.integers(0, 40))
        shift = int(rng.integers(0, 33)) if width == 32 else 0
        r = float_fixed(bits, width, frac)
        ops.append(("float", [bits, width, frac, shift, int(rng.integers(0, 2))],
                    "reject" if r is None or abs(r) > (1 << 31) - 1 else str(r)))
    return ops


def _check(cmd: list[str], ops: list[tuple[str, list[int], str]]) -> None:
    text = "".join(f"{name} {' '.join(map(str, args))}\n" for name, args, _ in ops)
    r = subprocess.run(cmd, input=text, capture_output=True, text=True, check=True, timeout=300)
    got = r.stdout.splitlines()
    assert len(got) == len(ops)
    bad = [(name, args, want, g) for (name, args, want), g in zip(ops, got, strict=True)
           if g != want]
    assert not bad, bad[:5]


def _build(cc: str, out: Path, flags: list[str]) -> Path:
    exe = out / "math_driver"
    subprocess.run([cc, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", *flags, "-I",
                    str(C_DIR), str(DRIVER), str(C_DIR / "canrls_fixed.c"), "-o", str(exe)],
                   check=True, capture_output=True, text=True)
    return exe


def test_the_c_arithmetic_is_the_specification_on_x86_64(tmp_path: Path) -> None:
    _check([str(_build(need_tool("gcc", ["gcc"]), tmp_path, []))], _ops())


def test_the_c_arithmetic_is_the_specification_on_32_bit_arm(tmp_path: Path) -> None:
    cc = need_tool("arm-linux-gnueabihf-gcc", ["gcc-arm-linux-gnueabihf"])
    qemu = need_tool("qemu-arm", ["qemu-user"])
    _check([qemu, str(_build(cc, tmp_path, ["-static"]))], _ops())


def test_the_c_arithmetic_built_for_size_is_the_specification(tmp_path: Path) -> None:
    """-Os (CANRLS_SMALL): the rare steps' shifts, bit lengths and square root out of line."""
    cc = need_tool("arm-linux-gnueabihf-gcc", ["gcc-arm-linux-gnueabihf"])
    qemu = need_tool("qemu-arm", ["qemu-user"])
    _check([str(_build(need_tool("gcc", ["gcc"]), tmp_path, ["-Os"]))], _ops())
    _check([qemu, str(_build(cc, tmp_path, ["-static", "-Os"]))], _ops())


def test_a_difference_would_show(tmp_path: Path) -> None:
    # the check can fail: one wrong expectation is found
    ops = _ops()[:50]
    name, args, want = ops[7]
    ops[7] = (name, args, str(int(want.split()[0]) + 1) + want[len(want.split()[0]):])
    with pytest.raises(AssertionError):
        _check([str(_build(need_tool("gcc", ["gcc"]), tmp_path, []))], ops)
