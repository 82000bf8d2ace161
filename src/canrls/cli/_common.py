"""Options shared by the subcommands (one helper, as python-can's ``can.cli`` does for buses)."""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from canrls.core.checks import LAMBDA_MIN

if TYPE_CHECKING:  # numpy and cantools load with the configuration: not for --help
    from canrls.processor.config import AppConfig, Overrides

__all__ = ["add_max_order_option", "add_model_options", "add_bus_options",
           "add_progress_option", "config_path", "overrides", "setup", "print_json", "Progress"]


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
    g.add_argument("--dbc", metavar="FILE",
                   help="DBC of the drive (default: the DBC shipped with canrls)")
    g.add_argument("--eds", metavar="FILE",
                   help="a CiA 402 drive's EDS instead of a DBC: its default TPDO mapping "
                        "(node 1; --axes cia402:N moves it) and the roles of the 402 objects "
                        "torque, current, velocity and position actual value, the ratings "
                        "from its defaults (needs pip install 'canrls[cia402]'; "
                        "docs/cia402.md)")
    g.add_argument("--signal", action="append", metavar="ROLE=MESSAGE.SIGNAL[:UNIT]",
                   help="which signal carries a role: current, speed, position, voltage, "
                        "torque (the torque a drive reports, N·m; linear axis: N; the "
                        "mechanical output then, no --kt) (repeatable; also "
                        "counter=MESSAGE.SIGNAL, crc=MESSAGE.SIGNAL)")
    g.add_argument("--rated-torque", type=number, metavar="VALUE",
                   help="rated torque [N·m] (linear axis: rated force [N]) that a torque "
                        "signal in per mille (‰) or per cent refers to (CiA 402: 0x6076)")
    g.add_argument("--rated-current", type=number, metavar="VALUE",
                   help="rated current [A] that a current signal in per mille (‰) or per "
                        "cent refers to (CiA 402: 0x6075)")
    g.add_argument("--increments-per-rev", type=number, metavar="N",
                   help="encoder increments per revolution (linear axis: per metre) of a "
                        "position in increments (inc) and a speed in increments/s (inc/s)")
    g.add_argument("--effects", "-e", metavar="NAME,...",
                   help="effects of the model: inertia, viscous, coulomb, stribeck, offset, "
                        "unbalance, cogging:K, electrical, user:NAME "
                        "(default: inertia,viscous,coulomb)")
    g.add_argument("--kt", type=number, metavar="VALUE",
                   help="torque constant Kt [N·m/A] (linear: N/A); without it the output is "
                        "the current and parameters are per ampere; refused with a torque "
                        "signal, whose torque is the output")
    g.add_argument("--period", type=number, metavar="SECONDS",
                   help="control period [s] (default: the DBC's GenMsgCycleTime, else measured "
                        "on the log's timestamps; a stated period must agree with them within "
                        "10 %%)")
    g.add_argument("--axis", type=axis_value, metavar="rotary|linear|NAME",
                   help="rotary (rad, rad/s, N·m) or linear (m, m/s, N) axis (default: from "
                        "the DBC units of the speed and position signals); any other name "
                        "picks that axis of a machine's (--axes or [[axes]] of --config)")
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

    def num(name: str) -> float | None:
        return getattr(args, name, None)  # a number as typed (errors quote it so)

    dbc = getattr(args, "dbc", None)
    eds = getattr(args, "eds", None)
    axis = getattr(args, "axis", None)
    bus = {k: getattr(args, k) for k in ("interface", "channel", "bitrate", "fd",
                                         "data_bitrate", "timing")
           if getattr(args, k, None) is not None}
    bus.update(getattr(args, "bus_kwargs", None) or {})
    return Overrides(
        dbc=None if dbc is None else str(Path(dbc).absolute()),
        eds=None if eds is None else str(Path(eds).absolute()),
        signals=tuple(getattr(args, "signal", None) or ()),
        effects=getattr(args, "effects", None), kt=num("kt"),
        axis=axis if axis in AXIS_KINDS else None,
        axis_name=None if axis in AXIS_KINDS else axis, axes=getattr(args, "axes", None),
        lam=num("lam"), alpha=num("alpha"), period=num("period"),
        rated_torque=num("rated_torque"), rated_current=num("rated_current"),
        increments_per_rev=num("increments_per_rev"), bus=tuple(bus.items()))


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


def _clean(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    return x


def print_json(obj: Any) -> None:
    """JSON on stdout (non-finite numbers become null: JSON has no NaN)."""
    json.dump(_clean(obj), sys.stdout, indent=2, ensure_ascii=False)
    sys.stdout.write("\n")


@functools.cache
def _bar_class() -> Any:
    """tqdm without its monitor thread (the readers call back often enough); imported
    only when a bar is drawn."""
    from tqdm import tqdm

    class Bar(tqdm):  # type: ignore[type-arg]
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
