"""``canrls fleet``: the logs of many drives into a parameter history, and its report.

    canrls fleet ingest 'logs/{drive}/*.log' --db fleet.db --kt 0.1 \\
        -e inertia,viscous,coulomb,offset
    canrls fleet ingest --manifest plant.csv --db postgresql://canrls@db/plant --scheduler tcp://10.0.0.5:8786
    canrls fleet report --db fleet.db --out fleet-report/      # or --json

``ingest`` fits each log as ``canrls fit`` does (same options), on a Dask LocalCluster
(one worker process per core; ``--workers N``, ``--workers 0`` in this process) or an
existing cluster (``--scheduler``), and stores each recording once: a log already in the
history with the same model is skipped by its hash, a log that cannot be fitted becomes
an error row, and a killed or interrupted run is finished by running it again.
``--rank auto`` ranks the candidate effects (the diagnosis) of the recordings around
each residual change, so that the report names the effect that appeared; ``--rank all``
ranks every log. ``report`` assesses the history (change, drift, new effect, outlier:
``docs/fleet.md``) and writes the HTML page or prints the JSON.

Needs the ``fleet`` extra (``pip install 'canrls[fleet]'``): dask[distributed],
SQLAlchemy, Alembic, psycopg, matplotlib; without it this command alone says so.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from canrls.cli._common import (
    Progress,
    add_max_order_option,
    add_model_options,
    add_progress_option,
    config_path,
    number,
    overrides,
    print_json,
)
from canrls.core.errors import ConfigError

__all__ = ["add_subparser", "run_ingest", "run_report", "rank_candidates", "text_summary"]

DEFAULT_DB = "fleet.db"
#: candidates kept per ranked recording
KEEP_CANDIDATES = 8


def _nonnegative(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if n < 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 0")
    return n


def _positive_seconds(text: str) -> float:
    s = number(text)
    if not 0 < s < float("inf"):
        raise argparse.ArgumentTypeError(f"{text!r} must be a positive number of seconds")
    return s


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    from canrls.fleet.cluster import SCHEDULER_TIMEOUT, STALL_TIMEOUT, WORKERS_PER_CORE

    p = subparsers.add_parser(
        "fleet", help="many drives: ingest their logs into a parameter history, report wear",
        description="Ingest the logs of many drives into a parameter history (SQLite or "
                    "PostgreSQL) on Dask, and report what changes: drifts, changes, new "
                    "effects, outliers among siblings (docs/fleet.md).")
    sub = p.add_subparsers(title="fleet commands", dest="fleet_command", metavar="COMMAND")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    ing = sub.add_parser(
        "ingest", help="fit the logs of many drives and store each recording once",
        description="Fit every log as 'canrls fit' does (same options) on Dask and store "
                    "each recording (parameters with sigma, residual, fit, verdicts, "
                    "content hash, time range, drive, model, canrls version) in the "
                    "history, once: logs already there with this model are skipped. "
                    "A machine's logs (--axes or [[axes]]) give one recording per axis, "
                    "under the drive MACHINE.AXIS.")
    src = ing.add_argument_group("logs")
    src.add_argument("pattern", nargs="?", metavar="PATTERN",
                     help="logs with a {drive} (and optionally {type}) field, e.g. "
                          "'logs/{drive}/*.log' (quote it; * ? [...] and ** as the shell's)")
    src.add_argument("--manifest", metavar="CSV",
                     help="a CSV with path,drive[,type,dbc,config,kt,effects,signals] "
                          "instead of a pattern")
    ing.add_argument("--db", default=DEFAULT_DB, metavar="URL",
                     help=f"the history: a file (SQLite) or postgresql://USER@HOST/DB "
                          f"(default {DEFAULT_DB})")
    add_model_options(ing)
    d = ing.add_argument_group("Dask")
    d.add_argument("--workers", type=_nonnegative, default=None, metavar="N",
                   help=f"worker processes of the local cluster (default: one per core, "
                        f"at most {WORKERS_PER_CORE} per core within the open-file limit; 0: "
                        f"in this process, no Dask)")
    d.add_argument("--scheduler", metavar="ADDRESS",
                   help=f"an existing Dask scheduler (tcp://HOST:PORT) instead of a local "
                        f"cluster; it must answer and have a worker within "
                        f"{SCHEDULER_TIMEOUT:g} s; its workers must read the logs at the "
                        f"same paths")
    d.add_argument("--stall-timeout", type=_positive_seconds, default=None, metavar="S",
                   help=f"end with an error when the cluster has given no result (a log "
                        f"fitted or ranked) for S seconds; each log stored is kept "
                        f"(default {STALL_TIMEOUT:g})")
    r = ing.add_argument_group("candidate ranking (the diagnosis)")
    r.add_argument("--rank", choices=("none", "auto", "all"), default="none",
                   help="rank the effects the model lacks: 'auto' for the recordings around "
                        "each residual change (as the [fleet] table of --config finds "
                        "them), 'all' for every log (default none)")
    add_max_order_option(r, "the ranking searches")
    ing.add_argument("--retry-errors", action="store_true",
                     help="try the logs stored as errors again")
    add_progress_option(ing)
    ing.set_defaults(func=run_ingest)

    rep = sub.add_parser(
        "report", help="assess the history: drives ranked by what needs a look first",
        description="Assess every drive of the history (change and drift per parameter "
                    "with sigma and the fleet's scatter, new effects, outliers among "
                    "siblings) and write an HTML page with figures or print JSON.")
    rep.add_argument("--db", default=DEFAULT_DB, metavar="URL",
                     help=f"the history (default {DEFAULT_DB})")
    rep.add_argument("--out", "-o", metavar="DIR", help="write DIR/index.html with figures")
    rep.add_argument("--json", action="store_true", help="print one JSON object")
    rep.add_argument("--figures", type=_nonnegative, default=20, metavar="N",
                     help="drives with a section and a figure of their trends: the first "
                          "drives with alerts in the ranking (default 20)")
    rep.add_argument("--config", "-C", metavar="FILE",
                     help="a TOML file whose [fleet] table says what counts as an alert "
                          "(alpha, min_change per effect, min_times_usual, outlier_z, "
                          "prior_pairs: docs/fleet.md)")
    rep.add_argument("--alpha", type=float, default=None, metavar="P",
                     help="false-alert probability per healthy drive (default 0.001, or "
                          "[fleet] alpha)")
    rep.add_argument("--model", metavar="KEY",
                     help="only the recordings of this model (a key or its first characters)")
    rep.set_defaults(func=run_report)
    return p


def rank_candidates(path: str, protocol: Any, model: Any, settings: Any,
                    max_order: int) -> list[Any]:
    """The diagnosis's candidate ranking of one log, best first (a worker runs it)."""
    from canrls.diagnosis.analysis import diagnose_log
    from canrls.fleet.records import CandidateValue

    rep = diagnose_log([path], protocol, model, settings, max_order=max_order)
    return [CandidateValue(rank=i + 1, effect=c.effect, explained=float(c.explained),
                           delta_bic=float(c.delta_bic), rms_after=float(c.rms_after),
                           identifiable=bool(c.identifiable), suggested=bool(c.suggested))
            for i, c in enumerate(rep.candidates[:KEEP_CANDIDATES])]


def _sources(args: argparse.Namespace) -> Sequence[Any]:
    from canrls.fleet.sources import from_manifest, from_pattern

    if bool(args.pattern) == bool(args.manifest):
        raise ConfigError("fleet ingest: give a PATTERN with a {drive} field or --manifest "
                          "CSV (one of them)")
    return from_manifest(args.manifest) if args.manifest else from_pattern(args.pattern)


def run_ingest(args: argparse.Namespace) -> int:
    from canrls.fleet.cluster import dask_client, local_workers, require_dask, scheduler_address
    from canrls.fleet.history import History, HistoryURL, require_sqlalchemy
    from canrls.fleet.ingest import JobConfig, ingest

    require_sqlalchemy()
    HistoryURL.parse(args.db)  # a database this command cannot use: before anything else
    if args.workers != 0 or args.scheduler:
        require_dask()
    if args.scheduler and args.workers:
        raise ConfigError("--workers: the workers of --scheduler's cluster are its own")
    if args.scheduler:
        scheduler_address(args.scheduler)
    elif args.workers != 0:
        local_workers(args.workers)
    sources = _sources(args)
    config = JobConfig.from_overrides(config_path(args), overrides(args))
    progress = Progress("ingest", quiet=args.quiet, unit="log")
    with History.open(args.db) as history:
        if args.workers == 0 and not args.scheduler:
            summary = ingest(sources, config, history, rank=args.rank,
                             ranker=rank_candidates, max_order=args.max_order,
                             progress=progress.callback, retry_errors=args.retry_errors)
        else:
            with dask_client(args.scheduler, args.workers) as client:
                summary = ingest(sources, config, history, client=client, rank=args.rank,
                                 ranker=rank_candidates, max_order=args.max_order,
                                 progress=progress.callback, retry_errors=args.retry_errors,
                                 stall_timeout=args.stall_timeout)
        progress.close()
    if args.json:
        print_json(summary.to_dict())
    else:
        sys.stdout.write(summary.format() + "\n")
    return 1 if summary.failed else 0


def run_report(args: argparse.Namespace) -> int:
    import dataclasses

    from canrls.fleet.detect import DetectionSettings, assess
    from canrls.fleet.fleet_report import report_dict, write_html
    from canrls.fleet.history import History, HistoryURL
    from canrls.fleet.records import STATUS_OK

    if not args.out and not args.json:
        raise ConfigError("fleet report: give --out DIR (HTML) or --json (or both)")
    settings = DetectionSettings.from_file(args.config)
    if args.alpha is not None:
        if not 0 < args.alpha < 1:
            raise ConfigError(f"--alpha {args.alpha}: must be between 0 and 1")
        settings = dataclasses.replace(settings, alpha=args.alpha)
    where = HistoryURL.parse(args.db)
    if where.sqlite_path is not None and not where.sqlite_path.is_file():
        raise ConfigError(f"--db {where.shown}: no such history (canrls fleet ingest "
                          f"makes it)")
    if args.out:
        from canrls.fleet.fleet_report import require_matplotlib

        require_matplotlib()  # before the long part
    with History.open(args.db, upgrade=False, read_only=True) as history:
        models = history.models()
        key = None
        if args.model:
            keys = [k for k, _, _ in models if k.startswith(args.model)]
            if len(keys) != 1:
                raise ConfigError(f"--model {args.model}: matches {len(keys)} models of the "
                                  f"history (have: {', '.join(k[:12] for k, _, _ in models)})")
            key = keys[0]
            models = [m for m in models if m[0] == key]
        recs = history.recordings(model_key=key)
    fleet = assess(recs, settings=settings)
    page = None
    if args.out:
        page = write_html(fleet, args.out, models=models,
                          recordings=sum(1 for r in recs if r.status == STATUS_OK),
                          errors=sum(1 for r in recs if r.status != STATUS_OK),
                          figures=args.figures)
    if args.json:
        d = report_dict(fleet, models)
        if page is not None:
            d["report"] = str(page)
        print_json(d)
    else:
        sys.stdout.write(text_summary(fleet, page))
    return 0


def _plural(n: int, noun: str) -> str:
    """``n noun``, the noun in the plural but for one."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def text_summary(fleet: Any, page: Path | None) -> str:
    """The text of ``canrls fleet report``: the counts, then every alert the count counts,
    drive by drive (ranked; each drive's most severe first)."""
    flagged = [d for d in fleet.drives if d.alerts]
    head = (f"{_plural(len(fleet.drives), 'drive')}, {_plural(len(fleet.alerts), 'alert')} "
            f"on {_plural(len(flagged), 'drive')}" + (f"; report: {page}" if page else ""))
    return "".join([f"{head}\n", *(f"  {d.drive}: {a.message}\n"
                                    for d in flagged for a in d.alerts)])
