"""The C code of a user's model for the target: ``canrls export-c`` writes it.

A firmware engineer gets one directory that compiles as it is (``-std=c99 -Wall -Wextra
-Werror``, for the host or ``arm-none-eabi-gcc``):

* ``canrls_fixed.h``, ``canrls_fixed.c`` -- the fixed-point RLS kernel (a copy of
  ``canrls/c``), bit-exact with :class:`canrls.estimation.fixed.FixedRLS`;
* ``canrls_config.h``, ``canrls_config.c`` -- per equation of the model: its parameters
  (names, units), its target (what it is, the DBC signal it comes from and that
  signal's scaling to SI: a torque-reporting drive's torque is the mechanical target,
  ``CANRLS_MECHANICAL_TARGET_TORQUE 1``, with no Kt), the power-of-two scaling of its
  columns and target, the Q formats,
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

import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from canrls.can.frames import frame_ids
from canrls.can.protocol import DEFAULT_DBC, Protocol
from canrls.can.units import rating_of
from canrls.config import AppConfig
from canrls.errors import ConfigError
from canrls.estimation.fixed import FixedRLS
from canrls.estimation.model import Model
from canrls.estimation.pipeline import Pipeline

__all__ = ["KERNEL_FILES", "PLAN_64", "Export", "plan_c", "c_int", "export_c"]

#: The kernel's files, copied from the package (``canrls/c``).
KERNEL_FILES = ("canrls_fixed.h", "canrls_fixed.c")
#: Constants of the plan held in 64 bits in ``canrls_plan_q31`` (all others: int32_t).
PLAN_64 = frozenset({"dividend", "trace_max_lim"})
_QUANTITIES = ("phi", "y", "theta", "P", "K", "eps", "h", "den", "g", "lam")


def c_int(v: int, bits: int = 32) -> str:
    """``v`` as a C constant expression of ``bits`` bits (the most negative value as
    ``-MAX - 1``, which C has no literal for)."""
    if v == -(1 << (bits - 1)):
        return f"(-{-(v + 1)}{'LL' if bits == 64 else ''} - 1)"
    return f"{v}LL" if bits == 64 else str(v)


def plan_c(constants: dict[str, int], name: str = "canrls_plan",
           storage: str = "static const") -> str:
    """The plan as ``STORAGE canrls_plan_q31 NAME = {.field = value, ...};``."""
    body = ",\n".join(f"    .{k} = {c_int(v, 64 if k in PLAN_64 else 32)}"
                      for k, v in constants.items())
    return f"{storage} canrls_plan_q31 {name} = {{\n{body},\n}};\n"


def _ident(s: str) -> str:
    return re.sub(r"\W", "_", s)


def _c_string(s: str) -> str:
    """``s`` as a C string literal in plain ASCII: quotes, backslashes and ``?`` (no
    trigraphs) escaped, every other byte outside printable ASCII (its UTF-8) as an
    octal escape."""
    out = []
    for b in s.encode("utf-8"):
        ch = chr(b)
        if ch in '"\\?':
            out.append("\\" + ch)
        elif 0x20 <= b < 0x7F:
            out.append(ch)
        else:
            out.append(f"\\{b:03o}")
    return '"' + "".join(out) + '"'


@dataclass(frozen=True)
class Export:
    """What :func:`export_c` wrote: the directory, its files and the equations."""

    out: Path
    files: tuple[Path, ...]
    equations: tuple[str, ...]

    def __str__(self) -> str:
        return (f"{self.out}: {', '.join(p.name for p in self.files)} "
                f"(equations: {', '.join(self.equations)})")


def _target_lines(eq: Any, protocol: Protocol | None) -> tuple[str, str]:
    """What the header and the source say of ``eq``'s target: the quantity, the DBC
    signal it is decoded from (its names in C strings: a user's text) and that signal's
    scaling to SI."""
    P, lo = eq.name.upper(), _ident(eq.name)
    role = eq.target.signal
    info = None if protocol is None else protocol.roles.get(role)
    torque = int(role == "torque")
    si_unit = {"current": "A", "voltage": "V"}.get(role, eq.target.unit)
    gain = eq.target.gain
    value = role if gain == 1.0 else f"{gain!r} * {role}"
    h = [f"/* target y: {eq.target.description} [{eq.target.unit}]"
         + (", no Kt" if torque else "" if gain == 1.0 else f", Kt = {gain!r}")]
    c = ""
    if info is not None:
        per_raw = float(info.codec.scale) * info.si_scale
        off = float(info.codec.offset) * info.si_scale
        rating = rating_of(role, info.unit)
        of = ""
        if rating is not None and protocol is not None:
            of = (f",\n * relative to {rating} = {getattr(protocol.mapping.ratings, rating)!r}"
                  f" {si_unit}")
        h.append(f": the {role} signal\n * canrls_{lo}_target_signal, DBC unit "
                 f"canrls_{lo}_target_unit{of}:\n * {role} [{si_unit}] = raw * {per_raw!r}"
                 + (f" + {off!r}" if off else ""))
        c = (f"const char canrls_{lo}_target_signal[] = "
             f"{_c_string(f'{info.message}.{info.signal}')};\n"
             f"const char canrls_{lo}_target_unit[] = {_c_string(info.unit)};\n")
    h.append(f";\n * y = round({value} * 2^(CANRLS_{P}_Y_FRAC - CANRLS_{P}_TARGET_EXP)) */\n"
             f"#define CANRLS_{P}_TARGET_TORQUE {torque} /* 1: the torque the drive reports, "
             f"0: not */\n")
    if info is not None:
        h.append(f"extern const char canrls_{lo}_target_signal[];\n"
                 f"extern const char canrls_{lo}_target_unit[];\n")
    return "".join(h), c


def _config_files(pipeline: Pipeline, source: str,
                  protocol: Protocol | None = None) -> tuple[str, str]:
    """``canrls_config.h`` and ``canrls_config.c`` for the estimators of ``pipeline``
    (``protocol``: the DBC signals of the targets)."""
    h = [f"/* canrls_config.h -- generated by `canrls export-c` from {source}: do not edit.\n"
         " *\n * Per equation: the parameters (theta[j] = canrls_theta_q31(S, j), the word\n"
         " * the kernel publishes, normalised: the physical value is\n"
         " * theta[j] * 2^-f_theta * 2^(target - columns[j])), the Q formats (Qm.f: f\n"
         " * fraction bits of a word of b bits), the kernel's plan and an init function\n"
         " * (the prior of canrls' FixedRLS). Inputs: phi[j] = round(column_j * 2^(f_phi -\n"
         " * columns[j])), y = round(target * 2^(f_y - target)). */\n",
         "#ifndef CANRLS_CONFIG_H\n#define CANRLS_CONFIG_H\n\n#include \"canrls_fixed.h\"\n\n"]
    c = [f"/* canrls_config.c -- generated by `canrls export-c` from {source}: do not edit. */\n"
         "#include \"canrls_config.h\"\n\n"]
    sizes = {est.equation.n for est in pipeline.estimators}
    if len(sizes) == 1:
        # one n for every equation: the kernel can be built for it, its loops unrolled
        n = sizes.pop()
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
        P = eq.name.upper()
        lo = _ident(eq.name)
        cfg = frls.config
        st = frls.state()
        h.append(f"/* ---- equation {eq.name}: {eq.target.description} [{eq.target.unit}],"
                 f" {eq.n} parameters, lam = {frls.lam!r} */\n")
        h.append(f"#define CANRLS_{P}_N {eq.n}\n")
        if eq.n > 12:
            h.append(f"#define CANRLS_N_MAX_NEEDED_{P} {eq.n} /* build with -DCANRLS_N_MAX={eq.n} */\n")
        for j, prm in enumerate(eq.parameters):
            h.append(f"#define CANRLS_{P}_{_ident(prm.name).upper()} {j} "
                     f"/* theta[{j}]: {prm.name} [{prm.unit}] */\n")
        h.append(f"/* scaling: column exponents {list(eq.scaling.columns)}, "
                 f"target exponent {eq.scaling.target} */\n")
        h.append(f"#define CANRLS_{P}_TARGET_EXP {eq.scaling.target}\n")
        th, tc = _target_lines(eq, protocol)
        h.append(th)
        c.append(tc)
        for q in _QUANTITIES:
            fmt = getattr(cfg, q)
            h.append(f"#define CANRLS_{P}_{q.upper()}_BITS {fmt.bits}\n"
                     f"#define CANRLS_{P}_{q.upper()}_FRAC {fmt.frac}\n")
        h.append(f"extern const canrls_plan_q31 canrls_{lo}_plan;\n"
                 f"extern const int32_t canrls_{lo}_column_exp[CANRLS_{P}_N];\n"
                 f"extern const char *const canrls_{lo}_names[CANRLS_{P}_N];\n"
                 f"/** canrls_init_q31() with the plan and the prior of the service (P0, e0). */\n"
                 f"int canrls_{lo}_init(canrls_rls_q31 *S);\n\n")
        p0 = np.diag(np.asarray(st["P"])).tolist()
        c.append(plan_c(frls.constants, f"canrls_{lo}_plan", "const"))
        c.append(f"const int32_t canrls_{lo}_column_exp[CANRLS_{P}_N] = {{"
                 f"{', '.join(str(int(x)) for x in eq.scaling.columns)}}};\n")
        c.append(f"const char *const canrls_{lo}_names[CANRLS_{P}_N] = {{"
                 f"{', '.join(_c_string(p.name) for p in eq.parameters)}}};\n")
        c.append(f"static const int32_t canrls_{lo}_p0[CANRLS_{P}_N] = {{"
                 f"{', '.join(c_int(int(x)) for x in p0)}}};\n\n"
                 f"int canrls_{lo}_init(canrls_rls_q31 *S)\n{{\n"
                 f"    return canrls_init_q31(S, &canrls_{lo}_plan, CANRLS_{P}_N, "
                 f"canrls_{lo}_p0, {int(st['P_exp'])});\n}}\n\n")
    h.append("#endif /* CANRLS_CONFIG_H */\n")
    return "".join(h), "".join(c)


def _frames_files(dbc: Path, source: str) -> tuple[str, str]:
    """cantools' C codecs of canrls' own frames (parameters, commands) in ``dbc``."""
    import cantools
    from cantools.database.can.c_source import generate

    full = cantools.database.load_file(str(dbc), database_format="dbc", strict=True)
    ids = frame_ids(dbc)
    own = {v for k, v in vars(ids).items() if k != "feedback" and isinstance(v, int)}
    msgs = [m for m in full.messages if m.frame_id in own]
    if not msgs:
        raise ConfigError(f"{dbc}: none of canrls' frames found")
    db = cantools.database.can.Database(messages=msgs, nodes=full.nodes,
                                        buses=full.buses, version=full.version)
    header, src, _, _ = generate(db, "canrls_frames", "canrls_frames.h", "canrls_frames.c",
                                 "canrls_frames_fuzzer.c")
    return header, src


def export_c(cfg: AppConfig, out: str | Path, *, model: Model | None = None,
             dt: float | None = None, energy: Mapping[str, Sequence[float]] | None = None,
             source: str = "the configuration", frames: bool = True) -> Export:
    """Write the kernel, the configuration of ``model`` (default: the configuration's) and
    the frame codecs into ``out`` (created); see the module docstring.

    ``energy`` (``{equation: column energies}``, a calibration's) scales the prior as the
    service does after its calibration window; without it the prior is the ridge alone
    (every column energy 1), the prior of an estimator that has not calibrated.
    ``frames=False``: no codecs of canrls' frames (``canrls export-c --frames none``)."""
    out = Path(out)
    protocol = cfg.protocol()
    model = cfg.model_for(protocol) if model is None else model
    period = protocol.period if dt is None else dt
    pipeline = Pipeline(model, period or 1e-3, cfg.settings(), energy)
    out.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    kernel = resources.files("canrls") / "c"
    for name in KERNEL_FILES:
        p = out / name
        p.write_text((kernel / name).read_text())
        files.append(p)
    ch, cc = _config_files(pipeline, source, protocol)
    texts = [("canrls_config.h", ch), ("canrls_config.c", cc)]
    if frames:
        # the frames the daemon publishes are the shipped DBC's, whatever DBC the drive's
        # feedback is read with (a user's DBC has none of them)
        fh, fc = _frames_files(DEFAULT_DBC, source)
        texts += [("canrls_frames.h", fh), ("canrls_frames.c", fc)]
    for name, text in texts:
        p = out / name
        p.write_text(text)
        files.append(p)
    return Export(out, tuple(files), tuple(e.equation.name for e in pipeline.estimators))


def load_source(path: str | Path) -> tuple[AppConfig, Model | None,
                                           dict[str, list[float]] | None, str]:
    """A configuration (TOML) or a saved model (JSON of ``canrls fit --save-model``):
    the configuration, the model to export (None: the configuration's), the column
    energies of its calibration (None for a configuration) and a label."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        try:
            from canrls.modelfile import SavedModel  # type: ignore[import-not-found]
        except ImportError as e:  # the saved-model format is not in this build
            raise ConfigError(f"{path}: saved models need canrls.modelfile") from e
        saved: Any = SavedModel.load(path)
        energy = (saved.calibration or {}).get("energy")
        model = saved.build_model()
        scaling = (saved.calibration or {}).get("scaling")
        if scaling:
            # the energies are measured in the calibration's exponents, not the ones the
            # fit ended with: the prior in the units it was measured in
            model = model.with_scaling(scaling)
        return saved.config(), model, energy, f"the saved model {path.name}"
    return AppConfig.load(path), None, None, f"the configuration {path.name}"
