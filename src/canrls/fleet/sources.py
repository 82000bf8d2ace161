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
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from canrls.core.checks import is_positive
from canrls.core.errors import ConfigError

__all__ = ["LogSource", "from_pattern", "from_manifest", "MANIFEST_FIELDS"]

#: the columns a manifest may have (``path`` and ``drive`` required)
MANIFEST_FIELDS = ("path", "drive", "type", "dbc", "config", "kt", "effects", "signals")

#: the longest cell of a manifest (a path's limit on Linux)
MAX_CELL = 4096

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
    #: why this log cannot be ingested (a drive or type name a pattern found that is not
    #: a valid name): an error row of the ingest's summary, never stored
    error: str | None = None
    #: the manifest row that lists it (``"fleet.csv: line 3"``), for an error its
    #: overrides cause; empty for a pattern's log
    row: str = ""


def check_name(value: str, what: str, where: str) -> str:
    """A drive or type name: letters, digits and ``_ . : + -``, up to 128 characters."""
    if not _NAME.match(value):
        raise ConfigError(f"{where}: {what} {_clip(value)}: must be 1 to 128 letters, digits or "
                          f"'_.:+-' (starting with a letter or digit)")
    return value


def from_pattern(pattern: str) -> list[LogSource]:
    """The logs a pattern with a ``{drive}`` field matches, sorted by path.

    Wildcards as the shell's: ``*``, ``?``, ``[...]`` (``[!...]`` negated) within one
    component, ``**`` any number of directories; a name starting with ``.`` only where
    the pattern says ``.``. A directory reached again (a link back up the tree, two links
    to one place) is not walked twice. A file whose field is not a valid drive or type
    name is kept with its :attr:`LogSource.error` (an error row, never stored).

    :raises ConfigError: no ``{drive}`` field, a field twice, or no file matches.
    """
    names = _FIELD.findall(pattern)
    if "drive" not in names:
        raise ConfigError(f"pattern {_clip(pattern)}: needs a {{drive}} field, e.g. "
                          f"'logs/{{drive}}/*.log' (or use --manifest)")
    if len(set(names)) != len(names):
        raise ConfigError(f"pattern {_clip(pattern)}: each field may appear once")
    parts = pattern.split("/")
    first = 0
    while first < len(parts) - 1 and not _MAGIC.search(parts[first]):
        first += 1
    root = "/".join(parts[:first])
    if pattern.startswith("/") and not root:
        root = "/"
    comps = [p if p == "**" else _component(p) for p in parts[first:]]
    found: dict[str, dict[str, str]] = {}
    _walk(root, comps, 0, {}, found, set())
    out = []
    for path in sorted(found):
        fields = found[path]
        try:
            drive = check_name(fields["drive"], "drive", path)
            dtype = check_name(fields["type"], "type", path) if "type" in names else ""
        except ConfigError as e:
            out.append(LogSource(path=path, drive=fields["drive"],
                                 drive_type=fields.get("type", ""), error=str(e)))
            continue
        out.append(LogSource(path=path, drive=drive, drive_type=dtype))
    if not out:
        raise ConfigError(f"pattern {_clip(pattern)}: no file matches")
    return out


#: a component with a wildcard or a field (the walk starts above the first one)
_MAGIC = re.compile(r"[*?\[{]")


def _component(part: str) -> re.Pattern[str]:
    """One path component of a pattern as a regex: the fields as named groups, the
    wildcards as the shell means them."""
    rx = "" if part.startswith(".") else r"(?!\.)"
    i = 0
    while i < len(part):
        m = _FIELD.match(part, i)
        c = part[i]
        if m is not None:
            rx += rf"(?P<{m.group(1)}>.+?)"
            i = m.end()
            continue
        if c == "*":
            rx += ".*"
        elif c == "?":
            rx += "."
        elif c == "[" and (j := _class_end(part, i)) > 0:
            body = part[i + 1:j]
            neg = body.startswith("!")
            body = body[1:] if neg else body
            rx += "[" + ("^" if neg else "") + body.replace("\\", "\\\\").replace(
                "^", "\\^") + "]"
            i = j + 1
            continue
        else:
            rx += re.escape(c)
        i += 1
    return re.compile(rx + r"\Z", re.DOTALL)


def _class_end(part: str, i: int) -> int:
    """The index of the ``]`` closing the class that opens at ``part[i]`` (-1: none, the
    ``[`` is a character like the others)."""
    j = i + 1
    if j < len(part) and part[j] == "!":
        j += 1
    if j < len(part) and part[j] == "]":
        j += 1
    j = part.find("]", j)
    return j


def _walk(top: str, comps: list[Any], i: int, fields: dict[str, str],
          found: dict[str, dict[str, str]], seen: set[tuple[int, int, int]]) -> None:
    """Match ``comps[i:]`` below directory ``top`` (``""``: the working directory),
    adding each file to ``found`` with its fields; ``seen`` holds the directories walked
    (device, inode, component), so that a link loop or two links to one place end."""
    try:
        st = os.stat(top or ".")
        key = (st.st_dev, st.st_ino, i)
        if key in seen:
            return
        seen.add(key)
        with os.scandir(top or ".") as it:
            entries = sorted(it, key=lambda e: e.name)
    except OSError:  # unreadable or gone: nothing there to match
        return
    comp = comps[i]
    last = i == len(comps) - 1
    if comp == "**":
        if last:
            return
        _walk(top, comps, i + 1, fields, found, seen)
        for e in entries:
            if not e.name.startswith(".") and _is_dir(e):
                _walk(_join(top, e.name), comps, i, fields, found, seen)
        return
    for e in entries:
        m = comp.match(e.name)
        if m is None:
            continue
        got = {**fields, **{k: v for k, v in m.groupdict().items() if v is not None}}
        if last:
            if _is_file(e):
                found.setdefault(_join(top, e.name), got)
        elif _is_dir(e):
            _walk(_join(top, e.name), comps, i + 1, got, found, seen)


def _join(top: str, name: str) -> str:
    return name if not top else (top + name if top.endswith("/") else f"{top}/{name}")


def _is_dir(e: os.DirEntry[str]) -> bool:
    try:
        return e.is_dir()
    except OSError:
        return False


def _is_file(e: os.DirEntry[str] | Path) -> bool:
    try:
        return e.is_file()
    except (OSError, ValueError):  # a name too long for the system, a NUL in it
        return False


def _clip(text: str, n: int = 120) -> str:
    """``text`` quoted, cut to ``n`` characters (an error line stays a line)."""
    return repr(text) if len(text) <= n else repr(text[:n]) + f"... ({len(text)} characters)"


def from_manifest(path: str | os.PathLike[str]) -> list[LogSource]:
    """The logs a manifest CSV lists (see the module docstring).

    :raises ConfigError: a missing column, an empty required cell, a bad value or a file
        that does not exist, naming the manifest, the line and the field.
    """
    p = Path(path)
    base = p.resolve().parent
    try:
        # utf-8-sig: a spreadsheet's CSV starts with a byte order mark
        f = open(p, newline="", encoding="utf-8-sig")
    except OSError as e:
        raise ConfigError(f"{p}: cannot read the manifest ({e.strerror or e})") from e
    out = []
    with f:
        try:
            reader = csv.DictReader(f)
            header = reader.fieldnames or []
            unknown = [h for h in header if h not in MANIFEST_FIELDS]
            if unknown:
                raise ConfigError(f"{p}: line 1: unknown column {_clip(unknown[0])} (valid: "
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
                for col, v in cells.items():
                    if len(v) > MAX_CELL:
                        raise ConfigError(f"{where}: field {_clip(col)}: {len(v)} characters "
                                          f"(at most {MAX_CELL})")
                log = Path(cells["path"])
                log = log if log.is_absolute() else base / log
                if not _is_file(log):
                    raise ConfigError(f"{where}: field 'path': {_clip(cells['path'])}: no such "
                                      f"file")

                def rel(name: str, w: str = where, c: dict[str, str] = cells) -> str | None:
                    v = c.get(name)
                    if not v:
                        return None
                    q = Path(v)
                    q = q if q.is_absolute() else base / q
                    if not _is_file(q):
                        raise ConfigError(f"{w}: field {name!r}: {_clip(v)}: no such file")
                    return str(q)

                kt = None
                if cells.get("kt"):
                    try:
                        kt = float(cells["kt"])
                    except ValueError:
                        kt = math.nan
                    if not is_positive(kt):
                        raise ConfigError(f"{where}: field 'kt': {_clip(cells['kt'])} must be a "
                                          f"positive number")
                signals = tuple(s for s in re.split(r"[;\s]+", cells.get("signals", "")) if s)
                out.append(LogSource(
                    path=str(log), drive=check_name(cells["drive"], "drive", where),
                    drive_type=check_name(cells["type"], "type", where)
                    if cells.get("type") else "",
                    dbc=rel("dbc"), config=rel("config"), kt=kt,
                    effects=cells.get("effects") or None, signals=signals, row=where))
        except csv.Error as e:
            raise ConfigError(f"{p}: line {reader.line_num}: {e}") from e
        except UnicodeDecodeError as e:
            raise ConfigError(f"{p}: not a UTF-8 text file ({e.reason})") from e
    if not out:
        raise ConfigError(f"{p}: the manifest lists no log")
    return out
