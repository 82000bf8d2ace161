"""Which logs belong to which drive: a glob with fields, or a manifest CSV.

A **pattern** is a path with ``{drive}`` (required) and optionally ``{type}`` fields and
shell wildcards, e.g. ``logs/{drive}/*.log`` or ``plant/{type}/{drive}/*.log``: each
field matches one path component (or part of one) and names the drive (and its type)
of every file found.

A **manifest** is a CSV file with a header: ``path`` and ``drive`` (required),
``type``, ``dbc``, ``config``, ``kt``, ``effects`` and ``signals`` (optional; signals as
``ROLE=MESSAGE.SIGNAL[:UNIT]`` separated by spaces or ``;``), each row one log. Paths
are relative to the manifest's directory. An empty cell takes the command line's
value. Errors name the manifest, the line and the field.
"""

from __future__ import annotations

import csv
import glob
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from canrls.core.checks import is_positive
from canrls.core.errors import ConfigError

__all__ = ["LogSource", "from_pattern", "from_manifest", "MANIFEST_FIELDS"]

#: the columns a manifest may have (``path`` and ``drive`` required)
MANIFEST_FIELDS = ("path", "drive", "type", "dbc", "config", "kt", "effects", "signals")

_FIELD = re.compile(r"\{(drive|type)\}")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.:+-]{0,127}$")


@dataclass(frozen=True)
class LogSource:
    """One log to ingest, with its drive and what overrides the command line's
    configuration for it (from a manifest row)."""

    path: str
    drive: str
    drive_type: str = ""
    dbc: str | None = None
    config: str | None = None
    kt: float | None = None
    effects: str | None = None
    signals: tuple[str, ...] = field(default_factory=tuple)


def check_name(value: str, what: str, where: str) -> str:
    """A drive or type name: letters, digits and ``_ . : + -``, up to 128 characters."""
    if not _NAME.match(value):
        raise ConfigError(f"{where}: {what} {value!r}: must be 1 to 128 letters, digits or "
                          f"'_.:+-' (starting with a letter or digit)")
    return value


def from_pattern(pattern: str) -> list[LogSource]:
    """The logs a pattern with a ``{drive}`` field matches, sorted by path.

    :raises ConfigError: no ``{drive}`` field, a field twice, or no file matches.
    """
    names = _FIELD.findall(pattern)
    if "drive" not in names:
        raise ConfigError(f"pattern {pattern!r}: needs a {{drive}} field, e.g. "
                          f"'logs/{{drive}}/*.log' (or use --manifest)")
    if len(set(names)) != len(names):
        raise ConfigError(f"pattern {pattern!r}: each field may appear once")
    wild = _FIELD.sub("*", pattern)
    # the fields as regex groups, the rest as the glob means it (* ? within a component)
    rx = ""
    for part in re.split(r"(\{drive\}|\{type\}|\*\*|\*|\?)", pattern):
        if part == "{drive}":
            rx += r"(?P<drive>[^/]+?)"
        elif part == "{type}":
            rx += r"(?P<type>[^/]+?)"
        elif part == "**":
            rx += r".*"
        elif part == "*":
            rx += r"[^/]*"
        elif part == "?":
            rx += r"[^/]"
        else:
            rx += re.escape(part)
    full = re.compile(rx + r"$")
    out = []
    for path in sorted(glob.glob(wild, recursive=True)):
        m = full.match(path)
        if m is None or not os.path.isfile(path):
            continue
        drive = check_name(m.group("drive"), "drive", path)
        dtype = check_name(m.group("type"), "type", path) if "type" in names else ""
        out.append(LogSource(path=path, drive=drive, drive_type=dtype))
    if not out:
        raise ConfigError(f"pattern {pattern!r}: no file matches")
    return out


def from_manifest(path: str | os.PathLike[str]) -> list[LogSource]:
    """The logs a manifest CSV lists (see the module docstring).

    :raises ConfigError: a missing column, an empty required cell, a bad value or a file
        that does not exist, naming the manifest, the line and the field.
    """
    p = Path(path)
    base = p.resolve().parent
    try:
        f = open(p, newline="", encoding="utf-8")
    except OSError as e:
        raise ConfigError(f"{p}: cannot read the manifest ({e.strerror or e})") from e
    out = []
    with f:
        try:
            reader = csv.DictReader(f)
            header = reader.fieldnames or []
            unknown = [h for h in header if h not in MANIFEST_FIELDS]
            if unknown:
                raise ConfigError(f"{p}: line 1: unknown column {unknown[0]!r} (valid: "
                                  f"{', '.join(MANIFEST_FIELDS)})")
            for col in ("path", "drive"):
                if col not in header:
                    raise ConfigError(f"{p}: line 1: no {col!r} column (the header needs "
                                      f"at least path,drive)")
            for row in reader:
                line = reader.line_num
                where = f"{p}: line {line}"
                cells = {k: (v or "").strip() for k, v in row.items() if k is not None}
                if None in row:
                    raise ConfigError(f"{where}: more cells than columns")
                for col in ("path", "drive"):
                    if not cells.get(col):
                        raise ConfigError(f"{where}: field {col!r} is empty")
                log = Path(cells["path"])
                log = log if log.is_absolute() else base / log
                if not log.is_file():
                    raise ConfigError(f"{where}: field 'path': {cells['path']!r}: no such file")

                def rel(name: str, w: str = where, c: dict[str, str] = cells) -> str | None:
                    v = c.get(name)
                    if not v:
                        return None
                    q = Path(v)
                    q = q if q.is_absolute() else base / q
                    if not q.is_file():
                        raise ConfigError(f"{w}: field {name!r}: {v!r}: no such file")
                    return str(q)

                kt = None
                if cells.get("kt"):
                    try:
                        kt = float(cells["kt"])
                    except ValueError:
                        kt = math.nan
                    if not is_positive(kt):
                        raise ConfigError(f"{where}: field 'kt': {cells['kt']!r} must be a "
                                          f"positive number")
                signals = tuple(s for s in re.split(r"[;\s]+", cells.get("signals", "")) if s)
                out.append(LogSource(
                    path=str(log), drive=check_name(cells["drive"], "drive", where),
                    drive_type=check_name(cells["type"], "type", where)
                    if cells.get("type") else "",
                    dbc=rel("dbc"), config=rel("config"), kt=kt,
                    effects=cells.get("effects") or None, signals=signals))
        except csv.Error as e:
            raise ConfigError(f"{p}: line {reader.line_num}: {e}") from e
        except UnicodeDecodeError as e:
            raise ConfigError(f"{p}: not a UTF-8 text file ({e.reason})") from e
    if not out:
        raise ConfigError(f"{p}: the manifest lists no log")
    return out
