"""Options shared by the subcommands (one helper, as python-can's ``can.cli`` does for buses)."""

from __future__ import annotations

import argparse
import functools
import json
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from canrls.core.checks import LAMBDA_MIN
from canrls.core.errors import ConfigError

if TYPE_CHECKING:  # numpy and cantools load with the configuration: not for --help
    import os
    from collections.abc import Sequence

    from canrls.diagnosis.results import SearchResult
    from canrls.estimation.model import Model
    from canrls.estimation.settings import EstimatorSettings
    from canrls.processor.config import AppConfig, Overrides

__all__ = ["add_max_order_option", "add_model_options", "add_bus_options",
           "add_progress_option", "config_path", "fit_model", "overrides", "setup", "print_json",
           "Progress"]


class _Typed(float):
    """A number that prints as the user typed it (``--kt 1e-1`` stays ``1e-1`` in errors)."""

    text: str

    def __new__(cls, text: str) -> _Typed:
        v = super().__new__(cls, text)
        v.text = text
        return v

    def __str__(self) -> str:
        return self.text

    def __format__(self, spec: str) -> str:
        return self.text if not spec else super().__format__(spec)


def _max_order(text: str) -> int:
    """argparse type: a cogging order the diagnosis searches up to (1..MAX_ORDER_LIMIT)."""
    from canrls.diagnosis.candidates import MAX_ORDER_LIMIT

    try:
        k = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text[:40]!r} is not an integer") from None
    if not 1 <= k <= MAX_ORDER_LIMIT:
        raise argparse.ArgumentTypeError(f"{text[:40]!r} must be in 1..{MAX_ORDER_LIMIT}")
    return k


def add_max_order_option(g: Any, what: str) -> None:
    """``--max-order K``: the highest cogging order ``what`` searches (checked here, as
    the diagnosis checks it, before anything runs)."""
    from canrls.diagnosis.candidates import DEFAULT_MAX_ORDER, MAX_ORDER_LIMIT

    g.add_argument("--max-order", type=_max_order, default=DEFAULT_MAX_ORDER, metavar="K",
                   help=f"highest cogging order {what} (default {DEFAULT_MAX_ORDER}, at "
                        f"most {MAX_ORDER_LIMIT})")


def number(text: str) -> float:
    """argparse type: a float that errors quote as typed."""
    try:
        return _Typed(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def add_model_options(p: argparse.ArgumentParser) -> None:
    """``--config --dbc --signal --rated-torque --rated-current --increments-per-rev
    --effects --kt --period --axis --lambda --alpha --json``."""
    g = p.add_argument_group("model and protocol (each also settable in --config)")
    g.add_argument("--config", "-C", metavar="FILE",
                   help="TOML configuration ([model], [estimator], [fixed], [can], [signals])")
    g.add_argument("--dbc", metavar="FILE", action=_GroupOption,
                   help="DBC of the drive (default: the DBC shipped with canrls); after "
                        "--axis NAME, that axis's")
    g.add_argument("--eds", metavar="FILE", action=_GroupOption,
                   help="a CiA 402 drive's EDS instead of a DBC: its default TPDO mapping "
                        "(node 1; --axes cia402:N moves it) and the roles of the 402 objects "
                        "torque, current, velocity and position actual value, the ratings "
                        "from its defaults; canrls run reads the mapping and ratings from "
                        "each node over SDO first, never writing (needs pip install "
                        "'canrls[cia402]'; docs/cia402.md); after --axis NAME, that axis's")
    g.add_argument("--signal", action=_GroupOption, metavar="ROLE=MESSAGE.SIGNAL[:UNIT]",
                   help="which signal carries a role: current, speed, position, voltage, "
                        "torque (the torque a drive reports, N·m; linear axis: N; the "
                        "mechanical output then, no --kt) (repeatable; also "
                        "counter=MESSAGE.SIGNAL, crc=MESSAGE.SIGNAL); after --axis NAME, "
                        "that axis's only")
    g.add_argument("--rated-torque", type=number, action=_GroupOption, metavar="VALUE",
                   help="rated torque [N·m] (linear axis: rated force [N]) that a torque "
                        "signal in per mille (‰) or per cent refers to (CiA 402: 0x6076)")
    g.add_argument("--rated-current", type=number, action=_GroupOption, metavar="VALUE",
                   help="rated current [A] that a current signal in per mille (‰) or per "
                        "cent refers to (CiA 402: 0x6075)")
    g.add_argument("--increments-per-rev", type=number, action=_GroupOption, metavar="N",
                   help="encoder increments per revolution (linear axis: per metre) of a "
                        "position in increments (inc) and a speed in increments/s (inc/s)")
    g.add_argument("--effects", "-e", metavar="NAME,...",
                   help="effects of the model: inertia, viscous, coulomb, stribeck, offset, "
                        "unbalance, cogging:K, electrical, user:NAME "
                        "(default: inertia,viscous,coulomb)")
    g.add_argument("--kt", type=number, metavar="VALUE", action=_GroupOption,
                   help="torque constant Kt [N·m/A] (linear: N/A); without it the output is "
                        "the current and parameters are per ampere; refused with a torque "
                        "signal, whose torque is the output; after --axis NAME, that axis's")
    g.add_argument("--period", type=number, metavar="SECONDS",
                   help="control period [s] (default: the DBC's GenMsgCycleTime, else measured "
                        "on the log's timestamps; a stated period must agree with them within "
                        "10 %%)")
    g.add_argument("--axis", type=axis_value, metavar="rotary|linear|NAME",
                   action=_AxisGroup,
                   help="rotary (rad, rad/s, N·m) or linear (m, m/s, N) axis (default: from "
                        "the DBC units of the speed and position signals); any other name "
                        "picks that axis of a machine's (--axes or [[axes]] of --config); "
                        "followed by --signal, --dbc, --eds, --ids, --kt or a rating, it "
                        "declares that axis instead, one group per axis: --axis a --ids "
                        "cia402:1 --signal ... --axis b --dbc odrive.dbc --signal ... "
                        "(replaces [[axes]]); --axis NAME again, alone, picks one of them")
    g.add_argument("--ids", metavar="RULE:N", action=_GroupOption,
                   help="after --axis NAME: that axis's ID rule (cia402:N, cansimple:N, "
                        "offset:N)")
    g.add_argument("--axes", metavar="RULE:LIST",
                   help="the axes of a machine on one bus, the DBC's frames moved by an ID "
                        "rule: cia402:1-6 (nodes 1..6: node1 .. node6), cansimple:0,1 "
                        "(ODrive node << 5 | command: node0, node1), offset:0,0x20 (the "
                        "DBC's IDs + each offset: axis1, axis2); replaces [[axes]] "
                        "(docs/configuration.md)")
    g.add_argument("--lambda", dest="lam", type=number, metavar="L",
                   help=f"forgetting factor in ({LAMBDA_MIN:g}, 1] (default 1: all data weigh "
                        "the same; "
                        "below 1 the estimate tracks changes, memory 1/(1-L) samples)")
    g.add_argument("--alpha", type=number, metavar="A",
                   help="ridge weight: the prior weighs like A samples of each column, "
                        "P0 = diag(1/(A e_j)) with e_j its mean square; 1e-9 to 1e9, "
                        "and at least what the fixed-point words hold: P0 needs a Q "
                        "format (32-bit words: about 1e-5 for a few parameters, 1e-3 for "
                        "30 below lambda 1; the error names the smallest for the model) "
                        "(default 0.01)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")


class _AxisGroup(argparse.Action):
    """``--axis``: the kind or axis name (``args.axis``), and a new group the options
    after it belong to (``args.axis_groups``: [(name, {option: value})])."""

    def __call__(self, parser: argparse.ArgumentParser, ns: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        setattr(ns, self.dest, values)
        ns.axis_groups = [*(getattr(ns, "axis_groups", None) or []), (values, {})]


class _GroupOption(argparse.Action):
    """``--signal``, ``--dbc``, ``--eds``, ``--kt``, ``--ids`` and the ratings: of the
    ``--axis NAME`` group open
    (the last ``--axis`` given, unless a kind), else of every axis."""

    def __call__(self, parser: argparse.ArgumentParser, ns: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        from canrls.processor.axes import AXIS_KINDS

        groups = getattr(ns, "axis_groups", None) or []
        if groups and groups[-1][0] not in AXIS_KINDS:
            name, opts = groups[-1]
            if self.dest == "signal":
                opts.setdefault("signal", []).append(values)
            elif self.dest in opts:
                parser.error(f"--axis {name}: {option_string} given twice in the group")
            else:
                opts[self.dest] = values
        elif self.dest == "ids":
            parser.error(f"{option_string} {values}: belongs to an --axis NAME group "
                         f"(--axis NAME --ids RULE:N ...)")
        elif self.dest == "signal":
            ns.signal = [*(getattr(ns, "signal", None) or []), values]
        else:
            setattr(ns, self.dest, values)


#: options after ``--axis NAME`` that declare that axis (its frames): with one of them
#: and no ``--axes``, every ``--axis NAME`` is a group of its own options
_DECLARING = ("signal", "dbc", "eds", "ids")


def axis_groups(args: argparse.Namespace) -> tuple[
        tuple[tuple[str, tuple[tuple[str, Any], ...]], ...], str | None, dict[str, Any]]:
    """The ``--axis NAME ...`` groups: (groups, pick, loose).

    Without ``--axes`` and with an ``--axis NAME`` followed by ``--signal``, ``--dbc``,
    ``--eds`` or ``--ids``, every ``--axis NAME`` declares an axis: ``groups`` holds each
    (name, ((option, value), ...)), paths made absolute, and ``pick`` the axis named by a
    later ``--axis NAME`` alone. Otherwise ``--axis NAME`` picks an axis of ``--axes`` or
    ``[[axes]]`` and the options after it are every axis's (``loose``)."""
    from pathlib import Path

    from canrls.processor.axes import AXIS_KINDS

    given = [(n, o) for n, o in getattr(args, "axis_groups", None) or []
             if n not in AXIS_KINDS]
    declaring = any(k in o for _, o in given for k in _DECLARING)
    if getattr(args, "axes", None) is not None or not declaring:
        loose: dict[str, Any] = {}
        for name, opts in given:
            if "ids" in opts:
                raise ConfigError(f"--axis {name} --ids {opts['ids']}: with --axes "
                                  f"{args.axes} the rule gives each axis's IDs")
            for k, v in opts.items():
                loose[k] = [*loose.get(k, ()), *v] if k == "signal" else v
        return (), None, loose
    out: list[tuple[str, tuple[tuple[str, Any], ...]]] = []
    pick = None
    for name, opts in given:
        if not opts and any(n == name for n, _ in out):
            pick = name  # --axis NAME again, alone: the axis a command works on
            continue
        d = dict(opts)
        for k in ("dbc", "eds"):
            if k in d:
                d[k] = str(Path(d[k]).absolute())
        if "signal" in d:
            d["signal"] = tuple(d["signal"])
        out.append((name, tuple(d.items())))
    return tuple(out), pick, {}


def axis_value(text: str) -> str:
    """argparse type of ``--axis``: ``rotary``, ``linear`` or an axis name (an identifier)."""
    if not (text.isascii() and text.isidentifier()):
        raise argparse.ArgumentTypeError(f"{text!r} is neither rotary, linear nor an axis "
                                         f"name (an identifier)")
    return text


def add_log_arguments(p: argparse.ArgumentParser, several: str) -> None:
    """The LOG arguments of the commands that read logs, and ``--skip-bad-lines``;
    ``several`` says what the command makes of several logs."""
    p.add_argument("log", metavar="LOG", nargs="+",
                   help=f"CAN log(s): .log (candump), .asc, .blf, .trc, .csv; {several}")
    p.add_argument("--skip-bad-lines", action="store_true",
                   help="count unparsable log lines instead of stopping at the first")


def add_report_option(p: Any) -> None:
    """``--report DIR`` on a parser or an argument group: the HTML page with figures."""
    p.add_argument("--report", metavar="DIR",
                   help="write DIR/index.html with SVG figures (needs matplotlib: "
                        "pip install 'canrls[report]')")


def add_progress_option(p: argparse.ArgumentParser) -> None:
    """``--quiet``: no progress bar (there is none either when stderr is not a terminal)."""
    p.add_argument("--quiet", "-q", action="store_true",
                   help="no progress bar on stderr (none either when stderr is not a terminal)")


def add_bus_options(p: argparse.ArgumentParser) -> None:
    """python-can's own bus arguments (``-i/-c/-b``, ``--bus-kwargs``)."""
    import can.cli

    can.cli.add_bus_arguments(p, group_title="CAN bus (python-can; overrides [can] of --config)")


def overrides(args: argparse.Namespace) -> Overrides:
    """The configuration the options of :func:`add_model_options` and
    :func:`add_bus_options` set: the one place the arguments become configuration."""
    from pathlib import Path

    from canrls.processor.axes import AXIS_KINDS
    from canrls.processor.config import Overrides

    groups, pick, loose = axis_groups(args)

    def opt(name: str) -> Any:
        """An option, given before any --axis NAME or after one that picks."""
        return loose.get(name, getattr(args, name, None))

    dbc = opt("dbc")
    eds = opt("eds")
    axis = getattr(args, "axis", None)
    bus = {k: getattr(args, k) for k in ("interface", "channel", "bitrate", "fd",
                                         "data_bitrate", "timing")
           if getattr(args, k, None) is not None}
    bus.update(getattr(args, "bus_kwargs", None) or {})
    return Overrides(
        dbc=None if dbc is None else str(Path(dbc).absolute()),
        eds=None if eds is None else str(Path(eds).absolute()),
        signals=(*(getattr(args, "signal", None) or ()), *loose.get("signal", ())),
        effects=getattr(args, "effects", None), kt=opt("kt"),
        axis=axis if axis in AXIS_KINDS else None,
        axis_name=pick if groups else None if axis in AXIS_KINDS else axis,
        axes=getattr(args, "axes", None), groups=groups,
        lam=opt("lam"), alpha=opt("alpha"), period=opt("period"),
        rated_torque=opt("rated_torque"), rated_current=opt("rated_current"),
        increments_per_rev=opt("increments_per_rev"), bus=tuple(bus.items()))


def config_path(args: argparse.Namespace) -> str | None:
    """``--config`` as an absolute path (None without it)."""
    from pathlib import Path

    c = getattr(args, "config", None)
    return None if c is None else str(Path(c).absolute())


def setup(args: argparse.Namespace, *, every_axis: bool = False) -> AppConfig:
    """The configuration file with the command line applied on top: of the one axis the
    command works on (``--axis NAME`` of a machine's), or the machine's with
    ``every_axis``."""
    from canrls.processor.config import load_config

    cfg = load_config(getattr(args, "config", None), overrides(args))
    return cfg if every_axis else cfg.one_axis()



def fit_model(logs: Sequence[str | os.PathLike[str]], protocol: Any, model: Model,
              settings: EstimatorSettings, *,
              skip_bad_lines: bool = False) -> tuple[Model, tuple[SearchResult, ...]]:
    """The model as ``canrls fit`` identifies it on ``logs``: a Stribeck speed its
    configuration leaves open searched on the record (the diagnosis's search, loaded only
    then), and the :class:`~canrls.diagnosis.results.SearchResult` of each value found."""
    if "stribeck" not in model.effect_names or "stribeck_speed" in model.options_given:
        return model, ()
    from canrls.diagnosis.search import search_model

    return search_model(logs, protocol, model, settings, skip_bad_lines=skip_bad_lines)


def print_json(obj: Any) -> None:
    """JSON on stdout (non-finite numbers become null: JSON has no NaN)."""
    from canrls.core.checks import json_safe

    json.dump(json_safe(obj), sys.stdout, indent=2, ensure_ascii=False)
    sys.stdout.write("\n")


@functools.cache
def _bar_class() -> Any:
    """tqdm without its monitor thread (the readers call back often enough); imported
    only when a bar is drawn."""
    from tqdm import tqdm

    class Bar(tqdm):
        monitor_interval = 0

    return Bar


class Progress:
    """A ``progress(done, total)`` callback drawing a tqdm bar on stderr (sizes in bytes,
    or counts of ``unit``).

    Silent with ``quiet`` (``--quiet``) or when stderr is not a terminal: then
    :attr:`callback` is None and the reader skips the calls. The bar appears at the first
    call and closes when ``done`` reaches ``total`` (or with :meth:`close`).

    tqdm, not a bar of our own: rate, time left and the terminal's width come with it,
    for one small pure-Python dependency.
    """

    def __init__(self, label: str, *, quiet: bool = False, enabled: bool | None = None,
                 unit: str = "B") -> None:
        self.label = label
        self.unit = unit
        self.enabled = (not quiet and sys.stderr.isatty()) if enabled is None else enabled
        self._bar: Any = None

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled or total <= 0:
            return
        bar = self._bar
        if bar is None:
            sized = self.unit == "B"
            bar = self._bar = _bar_class()(desc=self.label, total=total, unit=self.unit,
                                           unit_scale=sized, unit_divisor=1024 if sized else 1000,
                                           file=sys.stderr, dynamic_ncols=True)
        bar.total = total
        bar.update(done - bar.n)
        if done >= total:
            self.close()

    def close(self) -> None:
        """Close the bar (leaving its last state on the terminal); a next call starts anew."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    @property
    def callback(self) -> Callable[[int, int], None] | None:
        return self if self.enabled else None
