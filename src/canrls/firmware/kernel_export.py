"""The C code of a user's model for the target: ``canrls export-c`` writes it.

A firmware engineer gets one directory that compiles as it is (``-std=c99 -Wall -Wextra
-Werror``, for the host or ``arm-none-eabi-gcc``):

* ``canrls_fixed.h``, ``canrls_fixed.c``, ``canrls_bounds.h`` -- the fixed-point RLS kernel
  and its compile-time bounds (a copy of ``canrls/c/firmware``; the whole estimator's
  export writes its own ``canrls_bounds.h``), bit-exact with
  :class:`canrls.estimation.fixed.estimator.FixedRLS`;
* ``canrls_config.h``, ``canrls_config.c`` -- per equation of the model: its parameters
  (names, units), its output y (what it is, the DBC signal it comes from and that
  signal's scaling to SI: a torque-reporting drive's torque is the mechanical output,
  ``CANRLS_MECHANICAL_TARGET_TORQUE 1``, with no Kt), the power-of-two scaling of its
  columns and output, the Q formats,
  the kernel's plan (``canrls_plan_q31``, the integers ``FixedRLS.constants`` holds) and
  an ``init`` function that starts an instance from the prior ``FixedRLS`` starts from;
* ``canrls_frames.h``, ``canrls_frames.c`` -- the C codecs of canrls' parameter and
  command frames, generated from the DBC by cantools (``cantools generate_c_source``).

The estimators are the ones the pipeline builds for the model (:class:`Pipeline`), so
the plan, the formats and the prior are those the service runs. A configuration gives
the scaling its ranges decide (config > DBC limits > default); a saved model (the JSON
of ``canrls fit --save-model``) gives the scaling frozen by its calibration.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from canrls.can.estimator_frames import frame_ids
from canrls.can.protocol import DEFAULT_DBC, Protocol, load_dbc
from canrls.core.c_escape import c_comment, c_float, c_identifier, c_int, c_name_part, c_string
from canrls.core.errors import ConfigError
from canrls.core.files import write_texts
from canrls.core.units import rating_of
from canrls.estimation.fixed.estimator import FixedRLS
from canrls.estimation.fixed.formats import QUANTITIES
from canrls.estimation.model import Model
from canrls.estimation.pipeline import Pipeline
from canrls.firmware.cgen import plan_text
from canrls.processor.config import AppConfig
from canrls.processor.period import control_period

__all__ = ["KERNEL_FILES", "Export", "plan_c", "export_c", "frames_c"]

#: The kernel's files, copied from the package (``canrls/c/firmware``).
KERNEL_FILES = ("canrls_bounds.h", "canrls_fixed.h", "canrls_fixed.c")


def plan_c(constants: dict[str, int], name: str = "canrls_plan",
           storage: str = "static const") -> str:
    """The plan as ``STORAGE canrls_plan_q31 NAME = {.field = value, ...};``."""
    return plan_text(constants, name, storage)


@dataclass(frozen=True)
class Export:
    """What :func:`export_c` wrote: the directory, its files and the equations."""

    out: Path
    files: tuple[Path, ...]
    equations: tuple[str, ...]

    def __str__(self) -> str:
        return (f"{self.out}: {', '.join(p.name for p in self.files)} "
                f"(equations: {', '.join(self.equations)})")


def _output_lines(eq: Any, protocol: Protocol | None) -> tuple[str, str]:
    """What the header and the source say of ``eq``'s output: the quantity, the DBC
    signal it is decoded from (its names in C strings: a user's text) and that signal's
    scaling to SI. Text as comment text or string literals, numbers only finite ones."""
    P = c_name_part(eq.name, "equation")
    lo = P.lower()
    role = c_comment(eq.output.signal, f"equation {eq.name}: output signal")
    info = None if protocol is None else protocol.roles.get(eq.output.signal)
    torque = int(eq.output.signal == "torque")
    unit = c_comment(eq.output.unit, f"equation {eq.name}: output unit")
    si_unit = {"current": "A", "voltage": "V"}.get(eq.output.signal, unit)
    gain = eq.output.gain
    g = c_float(gain, f"equation {eq.name}: Kt")
    value = role if gain == 1.0 else f"{g} * {role}"
    h = [f"/* output y: {c_comment(eq.output.description, f'equation {eq.name}: output')} "
         f"[{unit}]" + (", no Kt" if torque else "" if gain == 1.0 else f", Kt = {g}")]
    c = ""
    if info is not None:
        where = f"the {eq.output.signal} signal {info.message}.{info.signal}"
        per_raw = c_float(info.si_per_raw, f"{where}: scale")
        off = info.si_offset
        rating = rating_of(eq.output.signal, info.unit)
        of = ""
        if rating is not None and protocol is not None:
            r = c_float(getattr(protocol.mapping.ratings, rating), f"{where}: {rating}")
            of = f",\n * relative to {c_comment(rating, 'rating')} = {r} {si_unit}"
        h.append(f": the {role} signal\n * canrls_{lo}_output_signal, DBC unit "
                 f"canrls_{lo}_output_unit{of}:\n * {role} [{si_unit}] = raw * {per_raw}"
                 + (f" + {c_float(off, f'{where}: offset')}" if off else ""))
        c = (f"const char canrls_{lo}_output_signal[] = "
             f"{c_string(f'{info.message}.{info.signal}')};\n"
             f"const char canrls_{lo}_output_unit[] = {c_string(info.unit or '')};\n")
    h.append(f";\n * y = round({value} * 2^(CANRLS_{P}_Y_FRAC - CANRLS_{P}_OUTPUT_EXP)) */\n"
             f"#define CANRLS_{P}_OUTPUT_TORQUE {torque} /* 1: the torque the drive reports, "
             f"0: not */\n")
    if info is not None:
        h.append(f"extern const char canrls_{lo}_output_signal[];\n"
                 f"extern const char canrls_{lo}_output_unit[];\n")
    return "".join(h), c


def _old_names(P: str, signal: bool) -> str:
    """The names the header gave the output before it was called so, as aliases of the
    new ones (deprecated: removed in the next release)."""
    lo = P.lower()
    old = [(f"CANRLS_{P}_TARGET_EXP", f"CANRLS_{P}_OUTPUT_EXP"),
           (f"CANRLS_{P}_TARGET_TORQUE", f"CANRLS_{P}_OUTPUT_TORQUE")]
    if signal:
        old += [(f"canrls_{lo}_target_{k}", f"canrls_{lo}_output_{k}") for k in ("signal", "unit")]
    return "".join(f"#define {a} {b}\n" for a, b in old)


class _Names:
    """The macros and symbols a generated file defines: each derived name once (two
    parameters that become the same C name are refused, naming both)."""

    def __init__(self, where: str = "") -> None:
        self.where = where
        self.seen: dict[str, str] = {}

    def __call__(self, name: str, origin: str) -> str:
        c_identifier(name, f"{self.where}{origin}")
        if name in self.seen and self.seen[name] != origin:
            raise ConfigError(f"{self.where}{self.seen[name]} and {origin} both become "
                              f"{name} in the generated C: rename one")
        self.seen[name] = origin
        return name


def _config_files(pipeline: Pipeline, source: str,
                  protocol: Protocol | None = None) -> tuple[str, str]:
    """``canrls_config.h`` and ``canrls_config.c`` for the estimators of ``pipeline``
    (``protocol``: the DBC signals of the outputs).

    Every name, unit and number goes through :mod:`canrls.core.c_escape`: names as validated
    identifiers, text as comment text, numbers from validated integers and finite floats.
    """
    src = c_comment(source, "the model's source")
    names = _Names()
    h = [f"/* canrls_config.h -- generated by `canrls export-c` from {src}: do not edit.\n"
         " *\n * Per equation: the parameters (theta[j] = canrls_theta_q31(S, j), the word\n"
         " * the kernel publishes, normalised: the physical value is\n"
         " * theta[j] * 2^-f_theta * 2^(output - columns[j])), the Q formats (Qm.f: f\n"
         " * fraction bits of a word of b bits), the kernel's plan and an init function\n"
         " * (the prior of canrls' FixedRLS). Inputs: phi[j] = round(column_j * 2^(f_phi -\n"
         " * columns[j])), y = round(output * 2^(f_y - output)). */\n",
         "#ifndef CANRLS_CONFIG_H\n#define CANRLS_CONFIG_H\n\n#include \"canrls_fixed.h\"\n\n"]
    c = [f"/* canrls_config.c -- generated by `canrls export-c` from {src}: do not edit. */\n"
         "#include \"canrls_config.h\"\n\n"]
    old: list[str] = []  # per equation: its output's old names
    sizes = {est.equation.n for est in pipeline.estimators}
    if len(sizes) == 1:
        # one n for every equation: the kernel can be built for it, its loops unrolled
        n = c_int(sizes.pop(), what="the number of parameters")
        h.append(f"/* Every equation has {n} parameters: build canrls_fixed.c (and this\n"
                 f" * file's users) with -DCANRLS_N={n} for the kernel made for that n, the\n"
                 f" * same integers in fewer instructions (docs/fixed_point.md, \"A fixed n\").\n"
                 f" * Without it the kernel takes any n up to CANRLS_N_MAX. */\n"
                 f"#define CANRLS_CONFIG_N {n}\n"
                 f"#if defined(CANRLS_N) && CANRLS_N != CANRLS_CONFIG_N\n"
                 f"#error \"canrls: built with -DCANRLS_N other than this model's n "
                 f"(CANRLS_CONFIG_N)\"\n#endif\n\n")
    for est in pipeline.estimators:
        eq = est.equation
        frls: FixedRLS = est.frls
        P = c_name_part(eq.name, "equation")
        lo = P.lower()
        pre = names(f"CANRLS_{P}", f"equation {eq.name}")
        cfg = frls.config
        st = frls.state()
        n = c_int(eq.n, what=f"equation {eq.name}: the number of parameters")
        h.append(f"/* ---- equation {c_comment(eq.name, 'equation')}: "
                 f"{c_comment(eq.output.description, f'equation {eq.name}: output')} "
                 f"[{c_comment(eq.output.unit, f'equation {eq.name}: unit')}], {n} "
                 f"parameters, lam = {c_float(frls.lam, 'lambda')} */\n")
        h.append(f"#define {names(pre + '_N', f'equation {eq.name}: n')} {n}\n")
        # the kernel's buffers hold CANRLS_N_MAX parameters (12 unless the build says
        # more): a larger model stops the build here, not the firmware at run time
        h.append(f"#if CANRLS_{P}_N > CANRLS_N_MAX\n"
                 f"#error \"canrls: equation {c_comment(eq.name, 'equation')} has "
                 f"{n} parameters, more than CANRLS_N_MAX: build every file, "
                 f"canrls_fixed.c too, with -DCANRLS_N_MAX={n}\"\n#endif\n")
        for j, prm in enumerate(eq.parameters):
            origin = f"parameter {prm.name}"
            macro = names(f"{pre}_{c_name_part(prm.name, origin)}", origin)
            h.append(f"#define {macro} {j} /* theta[{j}]: "
                     f"{c_comment(prm.name, origin)} "
                     f"[{c_comment(prm.unit, f'{origin}: unit')}] */\n")
        cols = [c_int(x, what=f"equation {eq.name}: column exponent")
                for x in eq.scaling.columns]
        s_y = c_int(eq.scaling.output, what=f"equation {eq.name}: output exponent")
        h.append(f"/* scaling: column exponents [{', '.join(cols)}], "
                 f"output exponent {s_y} */\n")
        h.append(f"#define {names(pre + '_OUTPUT_EXP', 'output exponent')} {s_y}\n")
        names(pre + "_TARGET_EXP", "output exponent (old name)")
        old.append(_old_names(P, protocol is not None
                              and protocol.roles.get(eq.output.signal) is not None))
        th, tc = _output_lines(eq, protocol)
        h.append(th)
        c.append(tc)
        for q in QUANTITIES:
            fmt = getattr(cfg, q)
            Q = c_name_part(q, "quantity")
            h.append(f"#define {names(f'{pre}_{Q}_BITS', f'the format of {q}')} "
                     f"{c_int(fmt.bits, what=f'{q} bits')}\n"
                     f"#define {names(f'{pre}_{Q}_FRAC', f'the format of {q}')} "
                     f"{c_int(fmt.frac, what=f'{q} fraction bits')}\n")
        h.append(f"extern const canrls_plan_q31 canrls_{lo}_plan;\n"
                 f"extern const int32_t canrls_{lo}_column_exp[CANRLS_{P}_N];\n"
                 f"extern const char *const canrls_{lo}_names[CANRLS_{P}_N];\n"
                 f"/** canrls_init_q31() with the plan and the prior of the service (P0, e0). */\n"
                 f"int canrls_{lo}_init(canrls_rls_q31 *S);\n\n")
        p0 = np.diag(np.asarray(st["P"])).tolist()
        c.append(plan_c(frls.constants, f"canrls_{lo}_plan", "const"))
        c.append(f"const int32_t canrls_{lo}_column_exp[CANRLS_{P}_N] = {{"
                 f"{', '.join(cols)}}};\n")
        c.append(f"const char *const canrls_{lo}_names[CANRLS_{P}_N] = {{"
                 f"{', '.join(c_string(p.name) for p in eq.parameters)}}};\n")
        c.append(f"static const int32_t canrls_{lo}_p0[CANRLS_{P}_N] = {{"
                 f"{', '.join(c_int(int(x), what='P0') for x in p0)}}};\n\n"
                 f"int canrls_{lo}_init(canrls_rls_q31 *S)\n{{\n"
                 f"    return canrls_init_q31(S, &canrls_{lo}_plan, CANRLS_{P}_N, "
                 f"canrls_{lo}_p0, {c_int(int(st['P_exp']), what='P exponent')});\n}}\n\n")
    h.append("/* Deprecated: the names of the output y before it was called so (the regression\n"
             " * target); they go in the next release. */\n" + "".join(old) + "\n")
    h.append("#endif /* CANRLS_CONFIG_H */\n")
    return "".join(h), "".join(c)


def _dbc_comment(text: str | None, what: str) -> str | None:
    """A DBC comment for cantools' C: every line comment text (:func:`c_comment`)."""
    if text is None:
        return None
    return "\n".join(c_comment(line.expandtabs(4).rstrip(), what)
                     for line in text.splitlines())


def frames_c(dbc: str | Path = DEFAULT_DBC) -> tuple[str, str]:
    """cantools' C codecs (header, source) of canrls' own frames (parameters, status,
    commands) in ``dbc`` (default: the shipped DBC, whose frames the daemon publishes).

    cantools pastes the DBC's names, units, comments and numbers into the C; of the
    messages exported, every name must be a C identifier whose C form (cantools'
    snake case) is unique, every comment and unit comment text, every number a finite
    one of its C type, before cantools sees them."""
    from cantools.database.can import Database
    from cantools.database.can.c_source import camel_to_snake_case, generate

    dbc = Path(dbc)
    full, _ = load_dbc(dbc)
    ids = frame_ids(dbc)
    own = {v for k, v in vars(ids).items() if k != "feedback" and isinstance(v, int)}
    msgs = [m for m in full.messages if m.frame_id in own]
    if not msgs:
        raise ConfigError(f"{dbc}: none of canrls' frames found")
    messages = _Names(f"DBC {dbc}: ")
    for m in msgs:
        c_identifier(m.name, f"DBC {dbc}: a message name")  # shown with repr until valid
        mw = f"DBC {dbc}: message {m.name}"
        messages(camel_to_snake_case(m.name).upper(), f"message {m.name}")
        m.comment = _dbc_comment(m.comment, f"{mw}: comment")
        if m.cycle_time is not None:
            c_int(m.cycle_time, 32, f"{mw}: cycle time")
        signals = _Names(f"{mw}: ")
        for sig in m.signals:
            c_identifier(sig.name, f"{mw}: a signal name")
            sw = f"{mw}: signal {sig.name}"
            signals(camel_to_snake_case(sig.name).upper(), f"signal {sig.name}")
            sig.comment = _dbc_comment(sig.comment, f"{sw}: comment")
            if sig.unit is not None:
                sig.unit = c_comment(sig.unit, f"{sw}: unit")
            for what, v in (("scale", sig.scale), ("offset", sig.offset),
                            ("minimum", sig.minimum), ("maximum", sig.maximum)):
                if v is not None:
                    c_float(v, f"{sw}: {what}")
            if sig.raw_initial is not None:
                c_float(sig.raw_initial, f"{sw}: initial value")
            for value in (sig.choices or {}):
                c_int(value, 64, f"{sw}: value of a choice")
    db = Database(messages=msgs, nodes=full.nodes, buses=full.buses, version=full.version)
    header, src, _, _ = generate(db, "canrls_frames", "canrls_frames.h", "canrls_frames.c",
                                 "canrls_frames_fuzzer.c")
    return header, src


def export_c(cfg: AppConfig, out: str | Path, *, model: Model | None = None,
             dt: float | None = None, energy: Mapping[str, Sequence[float]] | None = None,
             source: str = "the configuration", what: str | None = None,
             frames: bool = True) -> Export:
    """Write the kernel, the configuration of ``model`` (default: the configuration's) and
    the frame codecs into the directory ``out`` (made if missing; ``what`` names it in
    errors, default the path); see the module docstring. Each file is written to a
    temporary and renamed (:func:`canrls.core.files.write_texts`).

    ``energy`` (``{equation: column energies}``, a calibration's) scales the prior as the
    service does after its calibration window; without it the prior is the ridge alone
    (every column energy 1), the prior of an estimator that has not calibrated.
    ``frames=False``: no codecs of canrls' frames (``canrls export-c --frames none``).
    ``dt``: the control period (:func:`~canrls.processor.period.control_period`: else
    the DBC's cycle time, else 1 ms); ``canrls export-c`` passes the one
    :func:`canrls.firmware.load.load` decided, a saved model's measured one included."""
    label = what or str(out)
    protocol = cfg.protocol()
    model = cfg.model_for(protocol) if model is None else model
    period = control_period(given=dt, dbc=protocol.period).value
    pipeline = Pipeline(model, period, cfg.settings(), energy)
    # everything generated before anything is written
    kernel = resources.files("canrls") / "c" / "firmware"
    texts = [(name, (kernel / name).read_text()) for name in KERNEL_FILES]
    ch, cc = _config_files(pipeline, source, protocol)
    texts += [("canrls_config.h", ch), ("canrls_config.c", cc)]
    if frames:
        # the frames the daemon publishes are the shipped DBC's, whatever DBC the drive's
        # feedback is read with (a user's DBC has none of them)
        fh, fc = frames_c(DEFAULT_DBC)
        texts += [("canrls_frames.h", fh), ("canrls_frames.c", fc)]
    files = write_texts(out, texts, label)
    return Export(Path(out), tuple(files), tuple(e.equation.name for e in pipeline.estimators))
