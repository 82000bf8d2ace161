"""The C of one model for the target: ``canrls_model.h`` and ``canrls_model.c``.

:func:`model_files` renders a :class:`~canrls.firmware.target_model.TargetModel` as the constant
``canrls_model`` that ``src/canrls/c/firmware/canrls_target.c`` runs on. Every number goes
through :mod:`canrls.core.c_escape` (integers in the range of their C type), every name and
unit of the user's model or DBC as comment text or a string literal; nothing else
reaches the C.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from fractions import Fraction

from canrls.core.c_escape import c_comment, c_identifier, c_int, c_name_part, c_string, c_uint
from canrls.firmware.qmath import dyadic
from canrls.firmware.target_model import (
    OUT_FRAMES,
    SOURCE_NAMES,
    Column,
    EquationSpec,
    Field,
    TargetModel,
)

__all__ = ["PLAN_64", "bounds_file", "model_files", "plan_initializer", "plan_text"]

#: constants of canrls_plan_q31 held in 64 bits (the others: int32_t)
PLAN_64 = frozenset({"dividend", "trace_max_lim"})
_ROLE_ENUM = ("CANRLS_CURRENT", "CANRLS_SPEED", "CANRLS_POSITION", "CANRLS_VOLTAGE",
              "CANRLS_TORQUE")
_SRC_ENUM = ("CANRLS_SRC_RAW", "CANRLS_SRC_TANH", "CANRLS_SRC_STRIBECK", "CANRLS_SRC_SIN",
             "CANRLS_SRC_COS", "CANRLS_SRC_CONST")


def _i(v: int, what: str, bits: int = 32) -> str:
    return c_int(v, bits, what)


def _u(v: int, what: str, bits: int = 32) -> str:
    return c_uint(v, bits, what)


def plan_initializer(plan: Mapping[str, int], line_end: str = "\n") -> str:
    """The kernel's plan as a C initialiser ``{.field = value, ...}``, a field a line
    (``line_end``: what ends each line, `` \\`` and a newline inside a macro)."""
    body = f",{line_end}".join(
        f"    .{c_identifier(k, 'plan constant')} = "
        f"{_i(v, f'plan constant {k}', 64 if k in PLAN_64 else 32)}" for k, v in plan.items())
    return f"{{{line_end}{body},{line_end}}}"


def plan_text(plan: Mapping[str, int], name: str, storage: str = "static const") -> str:
    """The kernel's plan as ``STORAGE canrls_plan_q31 NAME = {...};``."""
    return (f"{storage} canrls_plan_q31 {c_identifier(name, 'plan name')} = "
            f"{plan_initializer(plan)};\n")


def _field(f: Field | None, what: str) -> str:
    if f is None:
        return "{0}"
    return (f"{{.msg = {_u(f.msg, what)}, .length = {_u(f.length, what)}, "
            f".is_float = {int(f.is_float)}u, .frac = {_i(f.frac, what)}, "
            f".is_signed = {int(f.signed)}u, .biased = {int(f.biased)}u, "
            f".big_endian = {int(f.big_endian)}u, .shift = {_u(f.shift, what)}, "
            f".lo = {_i(f.lo, what)}, .hi = {_i(f.hi, what)}}}")


def _column(c: Column, what: str) -> str:
    return (f"{{.offset = {_i(c.offset, what, 64)}, .m = {_i(c.m, what)}, "
            f".sh = {_i(c.sh, what)}, .exponent = {_i(c.exponent, what)}, "
            f".filter = {_u(c.filter, what)}, .derivative = {int(c.derivative)}u, "
            f".adaptive = {int(c.adaptive)}u, .pending = {int(c.pending)}u}}")


def _dy(x: Fraction, what: str) -> str:
    m, e = dyadic(x)
    return f"{{.m = {_u(m, what, 64)}, .e = {_i(e, what)}}}"


def _list(items: Iterable[str], indent: str = "    ") -> str:
    return ",\n".join(indent + s for s in items)


def _equation_c(e: EquationSpec, tm: TargetModel) -> tuple[str, str]:
    """Arrays of one equation and its ``canrls_equation`` initialiser."""
    lo = c_name_part(e.name, "equation").lower()
    out = [f"/* ---- equation {c_comment(e.name, 'equation')}: {e.n} parameters */\n"]
    cols = []
    for c in e.columns:
        src = tm.filters[c.filter]
        cols.append(f"/* {c_comment(c.name, 'parameter')}: {SOURCE_NAMES[src.kind]} "
                    f"{'sF' if c.derivative else 'F'} */ " + _column(c, f"column {c.name}"))
    out.append(f"static const canrls_column cols_{lo}[] = {{\n{_list(cols)},\n}};\n")
    out.append(plan_text(e.plan, f"plan_{lo}"))
    out.append(f"static const int32_t p0_{lo}[] = {{{', '.join(_i(v, 'P0') for v in e.p0)}}};\n")
    out.append(f"static const int64_t terms_{lo}[] = {{"
               f"{', '.join(_i(v, 'trace term', 64) for v in e.trace_terms)}}};\n")
    out.append(f"static const canrls_dyadic ridge_{lo}[] = {{"
               f"{', '.join(_dy(r, 'ridge') for r in e.ridge)}}};\n\n")
    s = e.selection
    what = f"equation {e.name}"
    init = [f".n = {_u(e.n, what)}", f".index = {_u(e.index, what)}",
            f".cross = {int(s.cross)}u", f".trace_follows = {int(e.trace_follows)}u",
            f".columns = cols_{lo}", f".output = {_column(e.output, 'output')}",
            f".warmup = {_i(s.warmup, what)}", f".min_w = {_i(s.min_w, what, 64)}",
            f".max_w = {_i(s.max_w, what, 64)}", f".plan = &plan_{lo}", f".p0 = p0_{lo}",
            f".e0 = {_i(e.e0, what)}", f".f_phi = {_i(e.f_phi, what)}",
            f".f_y = {_i(e.f_y, what)}", f".f_theta = {_i(e.f_theta, what)}",
            f".f_eps = {_i(e.f_eps, what)}",
            f".theta_h = {_i(e.theta_half.bit_length() - 1, what)}",
            f".rms_shift = {_i(e.rms_shift, what)}",
            f".trace_cap = {_i(e.trace_cap, what, 64)}", f".trace_terms = terms_{lo}",
            f".ridge = ridge_{lo}", f".floor_ridge = {_dy(e.prior_floor, what)}",
            f".floor_term = {_i(e.floor_term, what, 64)}",
            f".first_ridge = {_dy(e.first_ridge, what)}",
            f".first_term = {_i(e.first_term, what, 64)}"]
    return "".join(out), "{\n" + _list(init, "        ") + ",\n    }"


def _out_frame(tm: TargetModel, name: str) -> str:
    if tm.out is None:
        return "{0}"
    f = tm.out[name]
    sigs = OUT_FRAMES[name]
    starts = [f.fields[s][0] for s in sigs] + [0] * (8 - len(sigs))
    lens = [f.fields[s][1] for s in sigs] + [0] * (8 - len(sigs))
    return (f"{{.id = {_u(f.id, name)}, .start = {{{', '.join(_u(x, name) for x in starts)}}}, "
            f".length = {{{', '.join(_u(x, name) for x in lens)}}}}}")


def _bounds(tm: TargetModel) -> dict[str, int]:
    """The bounds of ``tm``'s build (``canrls_bounds.h``): what it has, at least one of each
    (a C array is never empty)."""
    return {"CANRLS_N_MAX": max(e.n for e in tm.equations),
            "CANRLS_TARGET_MSG_MAX": max(1, len(tm.messages)),
            "CANRLS_TARGET_FILTER_MAX": max(1, len(tm.filters)),
            "CANRLS_TARGET_EQ_MAX": max(1, len(tm.equations))}


def bounds_file(tm: TargetModel, source: str) -> str:
    """``canrls_bounds.h`` of the export of ``tm``: its own bounds in place of the
    maxima of ``src/canrls/c/firmware/canrls_bounds.h``, each ``#ifndef``-overridable."""
    t = [f"/* canrls_bounds.h -- generated by `canrls export-c` from {source}: do not edit.\n"
         " *\n * The build's bounds, this model's own (the package's canrls_bounds.h holds the\n"
         " * maxima of every model): the state (canrls_target) holds what this model has.\n"
         " * Each is #ifndef-overridable, for every file of the build alike (the state's\n"
         " * layout depends on them). */\n"
         "#ifndef CANRLS_BOUNDS_H\n#define CANRLS_BOUNDS_H\n"]
    for name, v in _bounds(tm).items():
        t.append(f"\n#ifndef {name}\n#define {name} {int(v)}\n#endif\n")
    if len(tm.equations) == 1:
        t.append("\n/* The plan of the model's one equation, a constant of the kernel\n"
                 " * (canrls_fixed.c): its shifts, ranges and constants folded into the code;\n"
                 " * canrls_init_q31 refuses any other plan. -DCANRLS_PLAN_RUNTIME reads it from\n"
                 " * the instance instead (the same integers). */\n"
                 "#define CANRLS_PLAN_CONST "
                 + plan_initializer(tm.equations[0].plan, " \\\n") + "\n")
    t.append("\n#endif /* CANRLS_BOUNDS_H */\n")
    return "".join(t)


def model_files(tm: TargetModel, source: str) -> tuple[str, str]:
    """``canrls_model.h`` and ``canrls_model.c`` of ``tm`` (``source``: what it was
    exported from, for the comment)."""
    src = c_comment(source, "the model's source")
    sizes = [e.n for e in tm.equations]
    nmax = max(sizes)
    names = [p.name for e in tm.equations for p in e.parameters]
    h = [f"/* canrls_model.h -- generated by `canrls export-c` from {src}: do not edit.\n"
         " *\n * The model the whole estimator runs on the target (canrls_target.h): the\n"
         " * constant canrls_model, for canrls_target_init(). What it holds:\n *\n"]
    for i, mm in enumerate(tm.messages):
        h.append(f" *   message {i}: {c_comment(mm.name, 'message')} (id {mm.id:#x}"
                 f"{', 29-bit' if mm.extended else ''}, {mm.dlc} bytes"
                 f"{', E2E CRC' if mm.crc else ''}{', alive counter' if mm.counter else ''})\n")
    for i, f in enumerate(tm.filters):
        h.append(f" *   filter {i}: {c_comment(f.label, 'filter')}, state fraction {f.fx} bits\n")
    k = 0
    for e in tm.equations:
        h.append(f" *   equation {c_comment(e.name, 'equation')}: Q formats phi Q.{e.f_phi}, "
                 f"y Q.{e.f_y}, theta Q.{e.f_theta}, eps Q.{e.f_eps}; lambda "
                 f"{e.lam!r}\n")
        for p, s in zip(e.parameters, e.exponents, strict=False):
            h.append(f" *     parameter {k}: {c_comment(p.name, 'parameter')} "
                     f"[{c_comment(p.unit, 'unit')}], column exponent {s}\n")
            k += 1
    h.append(f" *   period {tm.dt_ticks} ticks of {tm.tick_s!r} s; a publication every "
             f"{tm.publish_every} samples{'' if tm.out else ' (no estimator frames)'}\n */\n")
    h.append("#ifndef CANRLS_MODEL_H\n#define CANRLS_MODEL_H\n\n#include \"canrls_target.h\"\n\n")
    h.append(f"#define CANRLS_MODEL_NPARAMS {_u(tm.n_params, 'parameters')}\n")
    h.append(f"#define CANRLS_MODEL_NMAX {nmax} /* the largest equation */\n")
    for e in tm.equations:
        h.append(f"#define CANRLS_MODEL_N_{c_name_part(e.name, 'equation')} {e.n}\n")
    for i, nm in enumerate(names):
        h.append(f"#define CANRLS_PARAM_{c_name_part(nm, 'parameter')} {i}u\n")
    h.append(f"#define CANRLS_MODEL_PERIOD_TICKS {_u(tm.dt_ticks, 'period')}\n\n")
    h.append("#if CANRLS_N_MAX < CANRLS_MODEL_NMAX\n"
             "#error \"canrls: the model has more parameters than CANRLS_N_MAX: build every "
             "file with -DCANRLS_N_MAX=CANRLS_MODEL_NMAX or more\"\n#endif\n")
    for name, v in _bounds(tm).items():
        if name != "CANRLS_N_MAX":
            h.append(f"#if {name} < {v}\n#error \"canrls: the model needs {name} of at "
                     f"least {v} (canrls_bounds.h)\"\n#endif\n")
    if len(set(sizes)) == 1:
        h.append(f"/* one n for every equation: build with -DCANRLS_N={nmax} (every file) for\n"
                 f" * the kernel made for it, the same integers in fewer instructions */\n"
                 f"#if defined(CANRLS_N) && CANRLS_N != {nmax}\n"
                 f"#error \"canrls: built with -DCANRLS_N other than this model's n ({nmax})\"\n"
                 f"#endif\n")
    else:
        h.append("/* equations of different n: build the kernel for any n (no -DCANRLS_N) */\n"
                 "#if defined(CANRLS_N)\n#error \"canrls: this model's equations have "
                 "different n: build without -DCANRLS_N\"\n#endif\n")
    h.append("\nextern const canrls_target_model canrls_model;\n"
             "/** The parameters' names, in the order of canrls_target_theta(). */\n"
             "extern const char *const canrls_model_names[CANRLS_MODEL_NPARAMS];\n"
             "\n#endif /* CANRLS_MODEL_H */\n")

    c = [f"/* canrls_model.c -- generated by `canrls export-c` from {src}: do not edit. */\n"
         "#include \"canrls_model.h\"\n\n"]
    msgs: list[str] = []
    for mm in tm.messages:
        w = f"message {mm.name}"
        carried = [_ROLE_ENUM[k] for k, r in enumerate(("current", "speed", "position",
                                                        "voltage", "torque"))
                   if r in tm.roles and tm.roles[r].msg == len(msgs)]
        msgs.append(f"/* {c_comment(mm.name, 'message')} */ "
                    f"{{.id = {_u(mm.id, w)}, .extended = {int(mm.extended)}u, "
                    f".dlc = {_u(mm.dlc, w)}, .crc = {int(mm.crc)}u, "
                    f".has_counter = {int(mm.counter is not None)}u, "
                    f".nroles = {len(carried)}u, .roles = {{{', '.join(carried) or '0'}}}, "
                    f".counter = {_field(mm.counter, w)}}}")
    c.append(f"static const canrls_message messages[] = {{\n{_list(msgs)},\n}};\n")
    flts = []
    for f in tm.filters:
        role = _ROLE_ENUM[("current", "speed", "position", "voltage", "torque").index(f.role)] \
            if f.role else "0"
        flts.append(f"/* {c_comment(f.label, 'filter')} */ {{.kind = {_SRC_ENUM[f.kind]}, "
                    f".role = {role}, .order = {_u(f.order, 'order')}, .hold = {f.hold}u, "
                    f".fx = {_i(f.fx, 'fx')}}}")
    c.append(f"static const canrls_filter filters[] = {{\n{_list(flts)},\n}};\n\n")
    eq_inits = []
    for e in tm.equations:
        arrays, eq_init = _equation_c(e, tm)
        c.append(arrays)
        eq_inits.append(eq_init)
    c.append(f"static const canrls_equation equations[] = {{\n    "
             f"{(',' + chr(10) + '    ').join(eq_inits)},\n}};\n\n")
    info = [f"{{{_u(a, 'effect')}, {_u(b, 'component')}, {_u(d, 'equation')}, 0}}"
            for a, b, _, d in tm.param_info]
    c.append(f"static const uint8_t param_info[][4] = {{{', '.join(info)}}};\n")
    c.append(f"static const uint16_t param_order[] = {{"
             f"{', '.join(_u(o, 'order') for _, _, o, _ in tm.param_info)}}};\n\n")
    c.append(f"const char *const canrls_model_names[CANRLS_MODEL_NPARAMS] = {{"
             f"{', '.join(c_string(n) for n in names)}}};\n\n")
    roles = [_field(tm.roles.get(r), f"role {r}")
             for r in ("current", "speed", "position", "voltage", "torque")]
    ta = tm.tanh_arg or (0, 0, 0)
    sa = tm.stribeck_arg or (0, 0, 0)
    ph = tm.phase or (0, 0)
    match = int(tm.match_counters)
    g = ", ".join("{" + ", ".join(_i(v, "G") for v in row) + "}" for row in tm.G)
    init = [f".nmsg = {_u(len(tm.messages), 'messages')}",
            f".nfilters = {_u(len(tm.filters), 'filters')}",
            f".neq = {_u(len(tm.equations), 'equations')}",
            ".nparams = CANRLS_MODEL_NPARAMS", ".messages = messages",
            ".roles = {\n        " + ",\n        ".join(roles) + "}",
            f".match_counters = {match}u",
            f".dt_ticks = {_i(tm.dt_ticks, 'period')}", f".gap_ticks = {_i(tm.gap_ticks, 'gap')}",
            f".tol_ticks = {_i(tm.tol_ticks, 'tolerance')}",
            f".w_offset = {_i(tm.w_offset, 'speed offset', 64)}",
            ".filters = filters", ".equations = equations",
            f".publish_every = {_u(tm.publish_every, 'publication')}",
            f".active_effects = {_u(tm.active_effects, 'effects')}",
            ".param_info = param_info", ".param_order = param_order",
            f".has_frames = {int(tm.out is not None)}u",
            f".estimate = {_out_frame(tm, 'RlsEstimate')}",
            f".info = {_out_frame(tm, 'RlsParamInfo')}",
            f".status = {_out_frame(tm, 'RlsStatus')}",
            f".health = {_out_frame(tm, 'RlsHealth')}"]
    # the filters' inputs and coefficients: constants of the generated front end's code
    # (canrls_front.c), read from here by the table-driven path alone
    table = [f".tanh_m = {_i(ta[0], 'tanh')}", f".tanh_sh = {_i(ta[2], 'tanh')}",
             f".tanh_b = {_i(ta[1], 'tanh', 64)}",
             f".strib_m = {_i(sa[0], 'stribeck')}", f".strib_sh = {_i(sa[2], 'stribeck')}",
             f".strib_b = {_i(sa[1], 'stribeck', 64)}",
             f".phase_m = {_u(ph[0], 'phase', 64)}", f".phase_o = {_u(ph[1], 'phase', 64)}",
             f".A = {{{', '.join(_i(v, 'A') for v in tm.A)}}}", f".G = {{{g}}}"]
    c.append("const canrls_target_model canrls_model = {\n" + _list(init) + ",\n"
             "#ifndef CANRLS_FRONT\n" + _list(table) + ",\n#endif\n};\n")
    return "".join(h), "".join(c)
