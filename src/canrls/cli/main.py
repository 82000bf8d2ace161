"""Entry point of the ``canrls`` console script."""

from __future__ import annotations

import argparse
import gc
import importlib
import logging
import os
import sys
from collections.abc import Sequence

from canrls import __version__
from canrls.cli import early_signals
from canrls.core.errors import CanrlsError

#: Subcommand modules, in the order ``--help`` lists them.
SUBCOMMANDS: tuple[str, ...] = (
    "demo",
    "sim",
    "fit",
    "diagnose",
    "validate",
    "fixed_sweep",
    "export_c",
    "export_dbc",
    "tune",
    "run",
    "monitor",
    "fleet",
)

log = logging.getLogger("canrls")

#: Exit status of an unexpected (non-canrls) exception: distinct from 1 (an error in the
#: input, a ``CanrlsError``), 2 (usage) and 130 (interrupted).
INTERNAL_ERROR = 3
#: Exit status when the reader of the standard output went away (``canrls fit --json |
#: head -1``): what a shell reports for a Unix tool that SIGPIPE ended, 128 + 13.
PIPE_CLOSED = 141


def named_command(argv: Sequence[str]) -> str | None:
    """The subcommand ``argv`` names (None: none, or not one of :data:`SUBCOMMANDS`)."""
    args = iter(argv)
    for a in args:
        if a == "--log-level":
            next(args, None)
        elif not a.startswith("-"):
            name = a.replace("-", "_")  # export-c, fixed-sweep: their modules' names
            return name if name in SUBCOMMANDS else None
    return None


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of every subcommand, or of ``only`` (its module alone is imported:
    ``canrls run`` loads neither the simulator nor the diagnosis)."""
    parser = argparse.ArgumentParser(
        prog="canrls",
        description="Identify the physics of an electric drive over CAN with recursive "
                    "least squares.",
        epilog="exit status: 0 done, 1 an error in the input (one 'error:' line), 2 usage, "
               "3 an internal error (one 'internal error:' line; --debug shows the "
               "traceback), 130 interrupted, 141 the reader of the output left (| head)",
    )
    parser.add_argument("--version", action="version", version=f"canrls {__version__}")
    parser.add_argument("--debug", action="store_true",
                        help="show the full traceback of an error instead of one 'error:' line")
    parser.add_argument("--log-level", default="WARNING",
                        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                        help="logging level of messages written to stderr (default: WARNING)")
    sub = parser.add_subparsers(title="subcommands", dest="command", metavar="SUBCOMMAND")
    for name in SUBCOMMANDS if only is None else (only,):
        try:
            module = importlib.import_module(f"canrls.cli.{name}")
        except ModuleNotFoundError as e:
            if e.name and e.name.startswith("canrls.cli."):
                continue  # subcommand not written yet
            log.debug("subcommand %s disabled: %s", name, e)
            continue
        module.add_subparser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``); returns the exit status:
    0 done, 1 a :class:`CanrlsError` (one ``error:`` line), 2 usage, 3 an internal error
    (one ``internal error:`` line), 130 interrupted, 141 the reader of the standard output
    left (quietly). ``--debug`` shows the traceback."""
    if argv is None:
        # the process's own command: numpy's BLAS in one thread unless the environment
        # says otherwise (set before numpy loads): the matrices are a model's, small,
        # and a pool of threads costs its start in every command
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    given = list(sys.argv[1:] if argv is None else argv)
    if argv is None and named_command(given) == "run":
        # the process's own canrls run: its signals are handled from here on, before
        # numpy, python-can and cantools load (docs/daemon.md)
        early_signals.install()
    debug = "--debug" in given[:given.index("--")] if "--" in given else "--debug" in given
    try:
        status = _run(given, process=argv is None)
        if argv is None:
            sys.stdout.flush()  # the end of the output: a reader that left is seen here
        return status
    except CanrlsError as e:
        if debug:
            raise
        print(f"error: {_one_line(e)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except Exception as e:  # a bug of canrls, not of the input: never a silent 0
        if isinstance(e, BrokenPipeError) and _stdout_closed():
            _silence_stdout()  # the reader of the output left: quietly, as Unix tools do
            return PIPE_CLOSED
        if debug:
            raise
        print(f"internal error: {type(e).__name__}: {_one_line(e)} (rerun with --debug "
              f"for the traceback, and report it)", file=sys.stderr)
        return INTERNAL_ERROR
    finally:
        if argv is None:
            # the process exits next: the collections of its way out need not go through
            # every object it made (5 % of `canrls fit` of a 10-minute log, CPU time)
            gc.freeze()


def _run(given: list[str], process: bool) -> int:
    parser = build_parser(named_command(given))
    args = parser.parse_args(given)
    #: the command is the process's own (the console script, ``python -m canrls``), which
    #: exits after it; not a call of main() from another program
    args.process_exits = process
    logging.basicConfig(level=getattr(logging, args.log_level), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


def _stdout_closed() -> bool:
    """Whether the standard output is a pipe whose reader has gone (not some other
    pipe or socket of the command that broke)."""
    import select

    try:
        poll = select.poll()
        poll.register(sys.stdout.fileno(), select.POLLOUT)
        return any(ev & select.POLLERR for _, ev in poll.poll(0))
    except (AttributeError, OSError, ValueError):  # not a file descriptor
        return False


def _silence_stdout() -> None:
    """Point the standard output at /dev/null: what is left in its buffer is dropped at
    exit instead of failing on the closed pipe again, as a Unix tool exits quietly."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    finally:
        os.close(devnull)


def _one_line(e: BaseException) -> str:
    """The message of ``e`` on one line (a multi-line message joined by " | ")."""
    return " | ".join(line.strip() for line in str(e).splitlines() if line.strip())


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
