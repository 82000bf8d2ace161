"""The straight-line front end of one model for the target: ``canrls_front.c``.

:func:`front_file` writes ``canrls_target_frame`` for one
:class:`~canrls.firmware.target_model.TargetModel` as code without tables: each message's ID,
length and CRC-8 (its ID's part folded into a constant), each field's bytes, shifts and
masks (integer or float32/float64), each filter's input and coefficients, and exactly
the columns of each equation, as constants.
It computes what the table-driven ``canrls_target_frame`` of ``canrls_target.c`` computes
from the same constants (``canrls_target_math.h`` holds the arithmetic of both), and
shares its rare steps (pairing, restart, rescale, the kernel's update, publication).
Numbers reach the C through :mod:`canrls.core.c_escape`, names only as comment text.
"""

from __future__ import annotations

from canrls.can.e2e import crc8
from canrls.core.c_escape import c_comment, c_int, c_uint
from canrls.firmware.qmath import mul_rsh
from canrls.firmware.target_model import (
    SRC_CONST,
    SRC_COS,
    SRC_RAW,
    SRC_SIN,
    SRC_STRIBECK,
    SRC_TANH,
    W_FRAC,
    Column,
    EquationSpec,
    Field,
    Message,
    TargetModel,
)

__all__ = ["front_file"]

_ROLES = ("current", "speed", "position", "voltage", "torque")
_ROLE_ENUM = ("CANRLS_CURRENT", "CANRLS_SPEED", "CANRLS_POSITION", "CANRLS_VOLTAGE",
              "CANRLS_TORQUE")


def _i(v: int, what: str, bits: int = 32) -> str:
    return c_int(v, bits, what)


def _u(v: int, what: str, bits: int = 32) -> str:
    return c_uint(v, bits, what)


def _plus(v: int, what: str) -> str:
    """`` + v`` as a 64-bit constant ("" for 0)."""
    return f" + {_i(v, what, 64)}" if v else ""


def _bytes_of(f: Field, dlc: int) -> tuple[list[tuple[int, int]], int]:
    """The payload bytes that hold field ``f`` (those before ``dlc``; the others are 0;
    a field of three bytes takes a fourth where there is one), each with its left shift in
    a word that starts at the byte of the field's lowest bit, and the field's shift in that
    word."""
    lo_byte, hi_byte = f.shift // 8, (f.shift + f.length - 1) // 8
    if f.big_endian:
        # word bit p is in byte 7 - p // 8 (byte 0 the most significant)
        first, last = 7 - hi_byte, 7 - lo_byte
        parts = [(k, 8 * (last - k)) for k in range(first, last + 1)]
    else:
        parts = [(k, 8 * (k - lo_byte)) for k in range(lo_byte, hi_byte + 1)]
    # three bytes read as four where the fourth is in the frame (masked off after): one
    # word the compiler loads at once
    if len(parts) == 3 and f.shift % 8 + f.length <= 32:
        k = parts[0][0] - 1 if f.big_endian else parts[-1][0] + 1
        if 0 <= k < dlc:
            parts = [(k, 24)] + parts if f.big_endian else parts + [(k, 24)]
    return [(k, s) for k, s in parts if k < dlc], f.shift % 8


def _word(f: Field, dlc: int, name: str) -> tuple[list[str], str]:
    """Lines that read field ``f``'s bits into ``name`` (unsigned, masked to its length)
    and the C type of ``name``."""
    parts, low = _bytes_of(f, dlc)
    wide = low + f.length > 32
    t, cast = ("uint64_t", "(uint64_t)") if wide else ("uint32_t", "(uint32_t)")
    terms = [f"{cast}data[{k}]" + (f" << {s}" if s else "") for k, s in parts] or ["0u"]
    expr = " | ".join(terms)
    if low:
        expr = f"({expr}) >> {low}"
    bits = 64 if wide else 32
    if f.length < bits:
        expr = f"({expr}) & {_u((1 << f.length) - 1, 'mask', bits)}"
    return [f"const {t} {name} = {expr};"], t


def _int_field(f: Field, dlc: int, name: str) -> list[str]:
    """Lines that set ``int32_t name`` to an integer field's raw value (sign-extended,
    less its bias)."""
    lines, t = _word(f, dlc, name + "_bits")
    acc = name + "_bits" if t == "uint32_t" else f"(uint32_t){name}_bits"
    if f.signed and f.length < 32:
        half = 1 << (f.length - 1)
        # two's complement: (acc ^ 2^(L-1)) - 2^(L-1)
        lines.append(f"const int32_t {name} = (int32_t)({acc} ^ {_u(half, 'sign')}) - "
                     f"{_i(half, 'sign')};")
    elif f.biased:
        lines.append(f"const int32_t {name} = (int32_t)({acc} ^ 0x80000000u);")
    else:
        lines.append(f"const int32_t {name} = (int32_t){acc};")
    return lines


def _limits(f: Field) -> tuple[int, int]:
    """The raw values a field can hold (its range check is vacuous beyond them)."""
    if f.is_float:
        return -(2**31 - 1), 2**31 - 1
    if f.signed or f.biased:
        return -(1 << (f.length - 1)) if f.signed else -(1 << 31), (1 << (f.length - 1)) - 1
    return 0, (1 << f.length) - 1


def _field(f: Field, dlc: int, name: str, role: str) -> list[str]:
    """Lines that decode field ``f`` into ``int32_t name`` and reject it out of range."""
    rng = f"field {role}"
    if f.is_float:
        lines, t = _word(f, dlc, name + "_bits")
        word = name + "_bits" if t == "uint64_t" else f"(uint64_t){name}_bits"
        lines += [f"int32_t {name} = 0;",
                  f"/* float{f.length}: v 2^{f.frac}, half away from zero; NaN, infinity "
                  f"and beyond 31 bits rejected */",
                  f"if (!cr_float_word({word}, {int(f.length == 64)}, {_i(f.frac, rng)}, "
                  f"&{name})) {{", "    return canrls_target_reject(S, CANRLS_R_RANGE);", "}"]
    else:
        lines = _int_field(f, dlc, name)
    lo, hi = _limits(f)
    tests = ([f"{name} < {_i(f.lo, rng)}"] if f.lo > lo else []) + \
            ([f"{name} > {_i(f.hi, rng)}"] if f.hi < hi else [])
    if tests:
        lines += [f"if ({' || '.join(tests)}) {{",
                  "    return canrls_target_reject(S, CANRLS_R_RANGE);", "}"]
    return lines


def _message(tm: TargetModel, mi: int, m: Message) -> list[str]:
    """The body of the branch of message ``mi``: decode, pair, and the sample it completes."""
    what = f"message {mi}"
    out = [f"/* {c_comment(m.name, 'message')}: length {m.dlc} */",
           f"if (len != {_u(m.dlc, what)}) {{",
           "    return canrls_target_reject(S, CANRLS_R_LENGTH);", "}"]
    if m.crc:
        # E2E CRC-8 over the ID (2 bytes, little endian), then bytes 1..dlc-1: the ID's
        # part is a constant
        c0 = crc8(bytes([m.id & 0xFF, (m.id >> 8) & 0xFF]), xorout=0)
        out.append(f"/* E2E CRC-8: the ID's two bytes folded into {c0:#04x} */")
        out.append(f"uint32_t c = {_u(c0, 'crc')};")
        # built for size: by nibbles in a loop (fr_crc8); else the table's address in a
        # register, each byte one load indexed by it
        out += ["#if CANRLS_SMALL", f"c = fr_crc8(c, data, {_u(m.dlc, what)});", "#else",
                "const uint8_t *crc = cr_crc8;", "CR_OPAQUE(crc);"]
        out += [f"c = crc[c ^ data[{k}]];" for k in range(1, m.dlc)]
        out.append("#endif")
        out += ["if ((c ^ 0xFFu) != data[0]) {",
                "    return canrls_target_reject(S, CANRLS_R_CRC);", "}"]
    counter = "-1"
    if m.counter is not None:
        out.append("/* alive counter: one equal to the last accepted is a repeat */")
        out += _int_field(m.counter, m.dlc, "counter")
        out += [f"if (counter == S->last_counter[{mi}]) {{",
                "    return canrls_target_reject(S, CANRLS_R_REPEATED);", "}",
                f"S->last_counter[{mi}] = counter;"]
        counter = "counter"
    carried = [r for r in _ROLES if r in tm.roles and tm.roles[r].msg == mi]
    for r in carried:
        out.append(f"/* {r}: strict range */")
        out += _field(tm.roles[r], m.dlc, f"raw_{r}", r)
    key = counter if tm.match_counters else "-1"
    out += [f"/* pair: the frames of one period (within {tm.tol_ticks} ticks"
            f"{', the same alive counter' if tm.match_counters else ''}) */",
            f"if (!cr_pair(S, {_u(1 << mi, what)}, {key}, {_i(tm.tol_ticks, 'tolerance')}, t)) {{",
            "    return 0u;", "}"]
    out += [f"S->raw[{_ROLE_ENUM[_ROLES.index(r)]}] = raw_{r};" for r in carried]
    full = (1 << len(tm.messages)) - 1
    out += [f"if (S->open_mask != {_u(full, 'messages')}) {{", "    return 0u;", "}",
            "S->open_mask = 0u;", "return fr_sample(S, t);"]
    return out


def _q24_arg(name: str, ctype: str, arg: tuple[int, int, int] | None, what: str,
             eq: str, sat: bool = True) -> list[str]:
    """Lines setting the Q24 argument ``name = rsh(speed m + b, sh)`` (saturated to 32
    bits unless ``sat`` is false; 0 without one)."""
    if arg is None or arg[0] == 0:
        return [f"const {ctype} {name} = 0;"]
    cast = "(int32_t)" if ctype == "int32_t" else ""
    v = (f"cr_rsh((int64_t)S->raw[CANRLS_SPEED] * {_i(arg[0], what)}{_plus(arg[1], what)}, "
         f"{_i(arg[2], what)})")
    return [f"/* {eq} */",
            f"const {ctype} {name} = {cast}cr_sat({v}, INT32_MIN, INT32_MAX);" if sat else
            f"const {ctype} {name} = {v};"]


def _inputs(tm: TargetModel) -> list[str]:
    """Lines computing what the filters' inputs share: the Q24 arguments and the phase."""
    kinds = {f.kind for f in tm.filters}
    out = []
    if kinds & {SRC_TANH, SRC_STRIBECK}:
        # z reaches only tanh: cr_tanh_q24_wide(z) = cr_tanh_q24(z saturated)
        out += _q24_arg("z", "int64_t", tm.tanh_arg, "tanh", "z = w / band, Q24", sat=False)
    if SRC_STRIBECK in kinds:
        out += _q24_arg("r", "int64_t", tm.stribeck_arg, "stribeck", "r = w / ws, Q24")
    if kinds & {SRC_SIN, SRC_COS}:
        ph = tm.phase
        if ph is None or ph[0] == 0:
            out.append("const uint64_t ph = 0u;")
        else:
            po = f" + (uint64_t){c_uint(ph[1], 64, 'phase')}" if ph[1] else ""
            out += ["/* phase = raw PM + PO, turns in Q64 (modulo one turn) */",
                    f"const uint64_t ph = (uint64_t)(int64_t)S->raw[CANRLS_POSITION] * "
                    f"(uint64_t){c_uint(ph[0], 64, 'phase')}{po};"]
    return out


def _input(tm: TargetModel, i: int) -> list[str]:
    """Lines setting ``u``, the input of filter ``i``."""
    f = tm.filters[i]
    if f.kind == SRC_RAW:
        return [f"const int32_t u = S->raw[{_ROLE_ENUM[_ROLES.index(f.role)]}];"]
    if f.kind == SRC_TANH:
        return ["/* tanh(w / band) */", "const int32_t u = cr_tanh_q24_wide(z);"]
    if f.kind == SRC_STRIBECK:
        return ["/* x = (w / ws)^2, Q24, at most 32 ; tanh(w / band) exp(-(w / ws)^2) */",
                "int64_t x = cr_rsh(r * r, 24);",
                "x = x < ((int64_t)32 << 24) ? x : (int64_t)32 << 24;",
                "const int32_t u = (int32_t)cr_rsh((int64_t)cr_tanh_q24_wide(z) * "
                "cr_exp_neg_q24(x), 30);"]
    # sin, cos of k theta: the phase times k (modulo one turn); its quadrant and place
    order = f"(uint64_t){_u(f.order, 'harmonic', 64)}"
    quadrant = "(uint32_t)(p >> 62)" if f.kind == SRC_SIN else "((uint32_t)(p >> 62) + 1u) & 3u"
    return [f"const uint64_t p = {order} * ph;",
            f"const int32_t u = cr_quarter({quadrant}, (uint32_t)(p >> 30));"]


def _filters(tm: TargetModel) -> list[str]:
    """Lines advancing every filter of the bank by one sample, its coefficients constants."""
    a = [_i(v, "A") for v in tm.A]
    out = _inputs(tm)
    for i, f in enumerate(tm.filters):
        if f.kind == SRC_CONST:
            continue
        g = [_i(v, "G") for v in tm.G[f.hold]]
        fx = _i(f.fx, "fx")
        out += [f"{{ /* filter {i}: {c_comment(f.label, 'filter')}, FX {f.fx} */"]
        if f.narrow:
            out += ["    " + s for s in _input(tm, i) + _narrow_rows(i, a, g)] + ["}"]
            continue
        body = _input(tm, i) + [
            "int32_t uh, ul;",
            f"cr_split_input(u, {fx}, &uh, &ul);",
            f"if (!S->primed[{i}]) {{",
            "    /* at rest on the first sample: x = [u 2^FX, 0] */",
            f"    S->x1[{i}] = cr_shl(u, {fx});",
            f"    S->x2[{i}] = 0;",
            f"    S->primed[{i}] = 1u;",
            "} else {",
            f"    const int64_t x1 = S->x1[{i}], x2 = S->x2[{i}];",
            "    /* x1 = A00 x1 + A01 x2 + (G0_1 u[k-1] + G1_1 u[k]) 2^FX */",
            f"    S->x1[{i}] = cr_svf_row({a[0]}, {a[1]}, {g[0]}, {g[2]}, x1, x2, "
            f"S->uph[{i}], S->upl[{i}], uh, ul);",
            "    /* x2 = A10 x1 + A11 x2 + (G0_2 u[k-1] + G1_2 u[k]) 2^FX */",
            f"    S->x2[{i}] = cr_svf_row({a[2]}, {a[3]}, {g[1]}, {g[3]}, x1, x2, "
            f"S->uph[{i}], S->upl[{i}], uh, ul);",
            "}",
            f"S->uph[{i}] = uh;",
            f"S->upl[{i}] = ul;"]
        out += ["    " + s for s in body] + ["}"]
    return out


def _narrow_rows(i: int, a: list[str], g: list[str]) -> list[str]:
    """Lines advancing narrow filter ``i`` (32-bit states, ``fx`` 0: the last input is
    ``uph 2^31 + upl``) from its input ``u``."""
    return ["int32_t uh, ul;",
            "cr_split_input(u, 0, &uh, &ul);",
            f"if (!S->primed[{i}]) {{",
            "    /* at rest on the first sample: x = [u, 0] */",
            f"    S->x1[{i}] = u;",
            f"    S->x2[{i}] = 0;",
            f"    S->primed[{i}] = 1u;",
            "} else {",
            "    /* 32-bit states (an input bounded by 1), each row saturated to int32 */",
            f"    const int32_t x1 = (int32_t)S->x1[{i}], x2 = (int32_t)S->x2[{i}];",
            f"    const int32_t up = (int32_t)(((uint32_t)S->uph[{i}] << 31) | "
            f"(uint32_t)S->upl[{i}]);",
            "    /* x1 = A00 x1 + A01 x2 + G0_1 u[k-1] + G1_1 u[k] */",
            f"    S->x1[{i}] = cr_svf_row32({a[0]}, {a[1]}, {g[0]}, {g[2]}, x1, x2, up, u);",
            "    /* x2 = A10 x1 + A11 x2 + G0_2 u[k-1] + G1_2 u[k] */",
            f"    S->x2[{i}] = cr_svf_row32({a[2]}, {a[3]}, {g[1]}, {g[3]}, x1, x2, up, u);",
            "}",
            f"S->uph[{i}] = uh;",
            f"S->upl[{i}] = ul;"]


def _state(c: Column) -> str:
    """X + O of a column."""
    x = f"S->{'x2' if c.derivative else 'x1'}[{c.filter}]"
    return f"({x} + {_i(c.offset, 'offset', 64)})" if c.offset else x


def _const_state(tm: TargetModel, c: Column) -> int | None:
    """X + O of a column of the constant's filter (its state never moves: x1 = 2^(30 + FX),
    x2 = 0, as the state check holds a loaded one), else None."""
    f = tm.filters[c.filter]
    if f.kind != SRC_CONST:
        return None
    return (0 if c.derivative else 1 << (30 + f.fx)) + c.offset


def _value(tm: TargetModel, c: Column, j: int) -> tuple[str, bool]:
    """The expression of column ``c``'s value ``rsh((X + O) m, sh)`` (``j``: its index),
    and whether it is an int32 by its arithmetic (then not saturated).

    A fixed column (neither adaptive nor pending) keeps its model's shift (a rescale moves
    only the others; the state check holds a loaded one to it), so its shift is a constant:
    of the constant's filter the value is one; with ``m = 2^k`` and ``sh > k``, ``sh >= 31``
    it is ``rsh(X + O, sh - k)`` (exactly ``rsh((X + O) 2^k, sh)``), without the products,
    and of a narrow filter's int32 state (no offset) a 32-bit shift, an int32.
    """
    fixed = not c.adaptive and not c.pending
    const = _const_state(tm, c)
    if fixed and const is not None:
        return _i(mul_rsh(const, c.m, c.sh), "column", 64), False
    x = _state(c) if const is None else _i(const, "column", 64)
    if not fixed:
        return f"cr_mul_rsh({x}, {_i(c.m, 'm')}, q->sh[{j}])", False
    k = c.m.bit_length() - 1
    if c.m > 0 and c.m == 1 << k and c.sh >= 31 and c.sh > k:
        if tm.filters[c.filter].narrow and not c.offset and c.sh - k <= 31:
            return f"cr_rsh32((int32_t){x}, {_i(c.sh - k, 'sh')})", True
        return f"cr_rsh({x}, {_i(c.sh - k, 'sh')})", False
    return f"cr_mul_rsh({x}, {_i(c.m, 'm')}, {_i(c.sh, 'sh')})", False


def _equation(tm: TargetModel, e: EquationSpec, k: int) -> list[str]:
    """The check of the normalisation and the update of equation ``k``: its columns in
    locals (``v0``.. and ``y``), in memory only for a rescale."""
    name = c_comment(e.name, "equation")
    vs = [f"v{j}" for j in range(e.n)]
    args = "".join(f"int64_t {v}, " for v in vs)
    lim = _i(1 << e.f_phi, "f_phi", 64)
    ch = [f"/* equation {name}: whether this used sample changes the normalisation */",
          f"static int fr_changes_{k}(const canrls_target *S, const canrls_target_eq *q, "
          f"{args}int64_t y)", "{"]
    # a pending column's value is 0 while its state is (rsh(0 m, sh) = 0), so its rule
    # "pending ? X + O != 0 : |phi| > 2^f" is "(pending and X + O != 0) or |phi| > 2^f":
    # the pending flags, all read as one word, first, then the limits
    # (only a column pending in the model can be: the state check holds a loaded one to it)
    pend = [(f"q->pending[{j}]", c) for j, c in enumerate(e.columns) if c.pending]
    pend += [("q->pending_y", e.output)] if e.output.pending else []
    if pend:
        words = (e.n + 7) // 8
        ch += [f"    uint64_t pending[{max(words, 1)}] = {{0u}};",
               f"    memcpy(pending, q->pending, {_u(e.n, 'columns')});",
               "    if (" + "".join(f"pending[{w}] != 0u || " for w in range(words))
               + "q->pending_y) {"]
        for flag, c in pend:
            ch += [f"        if ({flag} && {_state(c)} != 0) {{", "            return 1;",
                   "        }"]
        ch.append("    }")
    else:
        ch += ["    (void)S;", "    (void)q;"]
    for j, c in enumerate(e.columns):
        if c.adaptive:
            ch += [f"    if (v{j} > {lim} || -v{j} > {lim}) {{", "        return 1;", "    }"]
        else:
            ch.append(f"    (void)v{j};")
    lim_y = _i(1 << e.f_y, "f_y", 64)
    ch += [f"    return y > {lim_y} || -y > {lim_y};", "}", ""]
    n = max(e.n, 1)
    up = [f"static CR_NOINLINE void fr_update_{k}(canrls_target *S)", "{",
          f"    canrls_target_eq *q = &S->eq[{k}];"]
    if vs:
        up.append(f"    int64_t {', '.join(vs)}, y;")
    else:
        up.append("    int64_t y;")
    up += [f"    int32_t phq[{n}];",
           "    int rescaled = 0;",
           "    for (;;) {",
           "        /* the columns and output, rsh((X + O) m, sh) */"]
    values = [_value(tm, c, j) for j, c in enumerate(e.columns)]
    for j, c in enumerate(e.columns):
        up.append(f"        v{j} = {values[j][0]}; /* {c_comment(c.name, 'parameter')} */")
    up += [f"        y = cr_mul_rsh({_state(e.output)}, {_i(e.output.m, 'm')}, q->sh_y);",
           f"        if (rescaled || !fr_changes_{k}(S, q, {''.join(v + ', ' for v in vs)}y)) {{",
           "            break;", "        }",
           "        { /* a rescale, then the values again */",
           f"            int64_t phi[{n}] = {{{', '.join(vs) or '0'}}};",
           f"            canrls_target_adapt(S, {_u(k, 'equation')}, phi, y);", "        }",
           "        rescaled = 1;", "    }",
           "    /* the words of the kernel: saturated to int32 where the value can leave it */"]
    if not e.columns:
        up.append("    phq[0] = 0;")
    for j, c in enumerate(e.columns):
        up.append(f"    phq[{j}] = (int32_t)v{j}; /* an int32: a narrow state's shift */"
                  if values[j][1] else f"    phq[{j}] = {_word32(f'v{j}', c.adaptive, e.f_phi)};")
    up += ["    /* the update; ms <- ms + (eps^2 - ms) >> rms_shift */",
           f"    cr_step(q, phq, {_word32('y', True, e.f_y)}, {_i(e.rms_shift, 'rms shift')});",
           "}", ""]
    return ch + up


def _word32(v: str, bounded: bool, frac: int) -> str:
    """The int32 word of the int64 value ``v`` for the kernel: ``v`` itself where the range
    analysis bounds it, else saturated (``cr_sat32``, as the specification saturates).

    A data-scaled column (and the output) is bounded by ``2^frac <= 2^30``: a used
    sample's value above it changes the normalisation first (``fr_changes_k``), and
    ``canrls_target_adapt`` raises the exponent until ``4 |v| <= 2^frac`` (``16 |v|`` for
    a first value), while a pending one is 0 until its first value. Any other column
    (tanh, sin, cos, the constant: a fixed exponent) is saturated.
    """
    if bounded and frac <= 30:
        return f"(int32_t){v} /* |{v}| <= 2^{frac}: fr_changes, canrls_target_adapt */"
    return f"cr_sat32({v})"


def _selection(e: EquationSpec, k: int) -> list[str]:
    """Lines of the sample's selection for equation ``k`` and its update."""
    s = e.selection
    what = f"equation {e.name}"
    tests = []
    if s.min_w > 0:
        tests.append(f"aw < {_i(s.min_w, what, 64)}")
    if s.max_w >= 0:
        tests.append(f"aw > {_i(s.max_w, what, 64)}")
    if s.cross:
        tests.append("(q->w_last < 0 && w > 0) || (w < 0 && q->w_last > 0)")
    out = [f"{{ /* equation {c_comment(e.name, 'equation')}: the selection */",
           f"    canrls_target_eq *q = &S->eq[{k}];"]
    if s.min_w > 0 or s.max_w >= 0:
        out.append("    const int64_t aw = w < 0 ? -w : w;")
    if tests:
        out += [f"    if ({' || '.join(tests)}) {{",
                f"        q->left = {_i(s.warmup + 1, what)};", "    }"]
    out += ["    q->w_last = w;", "    if (q->left > 0) {", "        q->left--;", "    } else {",
            f"        fr_update_{k}(S);", "    }", "}"]
    return out


def _crc_small() -> str:
    """``fr_crc8``: the E2E CRC-8 by nibbles, for the build for size (``CANRLS_SMALL``)."""
    # one nibble's remainder: the byte table's first 16 entries, T[v] for v < 16
    nib = ", ".join(str(crc8(bytes([v]), init=0, xorout=0)) for v in range(16))
    return f"""#if CANRLS_SMALL
/* built for size: the E2E CRC-8 (SAE J1850) from c over bytes 1..len-1 by nibbles, the
 * same integers as cr_crc8 with 16 bytes of table (two lookups a byte, in a loop) */
static uint32_t fr_crc8(uint32_t c, const uint8_t *data, uint32_t len)
{{
    static const uint8_t nib[16] = {{{nib}}};
    uint32_t k;
    for (k = 1u; k < len; k++) {{
        c ^= data[k];
        c = ((c << 4) & 0xF0u) ^ nib[c >> 4];
        c = ((c << 4) & 0xF0u) ^ nib[c >> 4];
    }}
    return c;
}}
#endif

"""


def _indent(lines: list[str], by: str = "    ") -> str:
    # the preprocessor's lines (#if CANRLS_SMALL) at the left margin
    return "\n".join(by + s if s and not s.startswith("#") else s for s in lines)


def front_file(tm: TargetModel, source: str) -> str:
    """``canrls_front.c`` of ``tm`` (``source``: what it was exported from, for the
    comment)."""
    src = c_comment(source, "the model's source")
    head = f"""/* canrls_front.c -- generated by `canrls export-c` from {src}: do not edit.
 *
 * canrls_target_frame() for this model and DBC in straight-line code: the same integers
 * as the table-driven one of canrls_target.c (canrls_target_math.h holds the arithmetic
 * of both), without reading the model's tables at run time. Build every file with
 * -DCANRLS_FRONT (canrls_target.c then leaves its own canrls_target_frame out).
 */
#include <string.h>

#include "canrls_target.h"
#include "canrls_target_math.h"

#ifndef CANRLS_FRONT
#error "canrls: build every file with -DCANRLS_FRONT when canrls_front.c is linked"
#endif

"""
    parts = [head]
    if any(m.crc for m in tm.messages):
        parts.append(_crc_small())
    for k, e in enumerate(tm.equations):
        parts.append(_indent(_equation(tm, e, k), "") + "\n")
    sample = [
        "const int32_t dt = (int32_t)(t - S->last_t);",
        "int64_t w;",
        f"if (!S->has_t || dt < 0 || dt > {_i(tm.gap_ticks, 'gap')}) {{",
        "    /* the first sample, time going back, or a period missing: restart */",
        "    if (S->has_t) {", "        S->rejects[CANRLS_R_RESTARTS]++;", "    }",
        "    canrls_target_restart(S);", "}",
        "S->has_t = 1u;", "S->last_t = t;",
        *_filters(tm),
        f"/* the speed of the selection: W = raw 2^{W_FRAC} + offset */",
        f"w = (int64_t)S->raw[CANRLS_SPEED] * ((int64_t)1 << {W_FRAC})"
        f"{_plus(tm.w_offset, 'speed offset')};"]
    for k, e in enumerate(tm.equations):
        sample += _selection(e, k)
    sample.append(f"return cr_sampled(S, {_u(tm.publish_every, 'publication')});")
    parts.append("/* one sample, complete in S->raw, at time t: filters, selection, updates */\n"
                 "static uint32_t fr_sample(canrls_target *S, uint32_t t)\n{\n"
                 + _indent(sample) + "\n}\n\n")
    frame = [] if tm.messages else ["(void)id;", "(void)extended;", "(void)data;", "(void)len;",
                                    "(void)t;", "(void)S;"]
    for mi, m in enumerate(tm.messages):
        ext = "extended != 0u" if m.extended else "extended == 0u"
        frame += [f"if (id == {_u(m.id, f'message {mi}')} && {ext}) {{",
                  *["    " + s for s in _message(tm, mi, m)], "}"]
    frame.append("return 0u;")
    parts.append("uint32_t canrls_target_frame(canrls_target *S, uint32_t id, uint32_t extended,\n"
                 "                             const uint8_t *data, uint32_t len, uint32_t t)\n"
                 "{\n" + _indent(frame) + "\n}\n")
    return "".join(parts)
