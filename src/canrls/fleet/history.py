"""The parameter history of a fleet, in a real database through SQLAlchemy.

SQLite (a file: the embedded default) or PostgreSQL (``postgresql://user@host/db``,
through psycopg); the schema is versioned, and the Alembic migrations shipped in
``canrls/fleet/migrations`` bring an older history up to date when it is opened
(:meth:`History.open`). Every write is an insert-or-ignore in one transaction per batch,
so a recording is never stored twice. The tables: docs/fleet.md, "The history".
"""

from __future__ import annotations

import datetime
import functools
import math
import os
import re
import time
import urllib.parse
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from canrls.core.checks import finite_or_none, json_safe
from canrls.core.errors import ConfigError
from canrls.fleet.records import (
    STATUS_OK,
    CandidateValue,
    ParameterValue,
    Recording,
)

__all__ = ["History", "HistoryURL", "require_sqlalchemy", "METADATA", "HEAD_REVISION",
           "MIGRATIONS", "NOT_A_HISTORY"]

T = TypeVar("T")

#: the directory of the Alembic migrations (shipped in the package)
MIGRATIONS = Path(__file__).resolve().parent / "migrations"
#: the schema revision this canrls writes
HEAD_REVISION = "0001"
#: the longest a SQLite history waits for another writer's lock [s]
BUSY_TIMEOUT_S = 60.0
#: the PostgreSQL advisory lock a migration holds (a constant of this application)
SCHEMA_LOCK = 0x63616E726C73  # "canrls"


def require_sqlalchemy() -> Any:
    """The ``sqlalchemy`` module.

    :raises ConfigError: SQLAlchemy or Alembic (the ``fleet`` extra) is not installed.
    """
    try:
        import alembic  # noqa: F401
        import sqlalchemy
    except ImportError as e:
        raise ConfigError(f"the fleet history needs {e.name}, which is not installed: "
                          f"pip install 'canrls[fleet]'") from e
    return sqlalchemy


def _tables() -> Any:
    sa = require_sqlalchemy()
    md = sa.MetaData()
    sa.Table("drives", md,
             sa.Column("id", sa.Integer, primary_key=True),
             sa.Column("name", sa.String(128), nullable=False, unique=True),
             sa.Column("type", sa.String(128), nullable=False, server_default=""))
    sa.Table("models", md,
             sa.Column("id", sa.Integer, primary_key=True),
             sa.Column("key", sa.String(64), nullable=False, unique=True),
             sa.Column("description", sa.Text, nullable=False))
    sa.Table("recordings", md,
             sa.Column("id", sa.Integer, primary_key=True),
             sa.Column("drive_id", sa.Integer, sa.ForeignKey("drives.id"), nullable=False),
             sa.Column("model_id", sa.Integer, sa.ForeignKey("models.id"), nullable=False),
             sa.Column("content_hash", sa.String(64), nullable=False),
             sa.Column("status", sa.String(8), nullable=False),
             sa.Column("source", sa.String(8), nullable=False),
             sa.Column("path", sa.Text, nullable=False, server_default=""),
             sa.Column("t_start", sa.Float),
             sa.Column("t_end", sa.Float),
             sa.Column("samples", sa.Integer, nullable=False, server_default="0"),
             sa.Column("frames", sa.BigInteger, nullable=False, server_default="0"),
             sa.Column("residual_rms", sa.Float),
             sa.Column("fit_percent", sa.Float),
             sa.Column("unit", sa.String(32), nullable=False, server_default=""),
             sa.Column("verdicts", sa.JSON),
             sa.Column("error", sa.Text),
             sa.Column("session", sa.String(64)),
             sa.Column("canrls_version", sa.String(32), nullable=False, server_default=""),
             sa.Column("ingested_at", sa.DateTime(timezone=True), nullable=False),
             sa.UniqueConstraint("content_hash", "model_id", name="uq_recordings_hash_model"),
             sa.Index("ix_recordings_drive_time", "drive_id", "t_start"))
    sa.Table("parameters", md,
             sa.Column("recording_id", sa.Integer,
                       sa.ForeignKey("recordings.id", ondelete="CASCADE"), primary_key=True),
             sa.Column("name", sa.String(128), primary_key=True),
             sa.Column("value", sa.Float),
             sa.Column("sigma", sa.Float),
             sa.Column("unit", sa.String(32), nullable=False, server_default=""),
             sa.Column("fixed", sa.Float),
             sa.Column("identifiable", sa.Boolean, nullable=False),
             sa.Column("prior_share", sa.Float))
    sa.Table("candidates", md,
             sa.Column("recording_id", sa.Integer,
                       sa.ForeignKey("recordings.id", ondelete="CASCADE"), primary_key=True),
             sa.Column("rank", sa.Integer, primary_key=True),
             sa.Column("effect", sa.String(64), nullable=False),
             sa.Column("explained", sa.Float),
             sa.Column("delta_bic", sa.Float),
             sa.Column("rms_after", sa.Float),
             sa.Column("identifiable", sa.Boolean, nullable=False),
             sa.Column("suggested", sa.Boolean, nullable=False))
    return md


class _Lazy:
    """The tables, built at first use (SQLAlchemy is an optional dependency)."""

    def __init__(self) -> None:
        self.md: Any = None

    def __call__(self) -> Any:
        if self.md is None:
            self.md = _tables()
        return self.md


#: ``METADATA()``: the SQLAlchemy ``MetaData`` of the schema (the migrations' target)
METADATA = _Lazy()


@dataclass(frozen=True)
class HistoryURL:
    """Where a history lives, parsed once from what a user typed (:meth:`parse`): the one
    reading of a history's URL for the daemon's ``[history]``, ``canrls fleet`` and
    :meth:`History.open`, with what messages may show of it (:attr:`shown`)."""

    #: the SQLAlchemy URL (``sqlite:///...``, ``postgresql+psycopg://...``)
    url: str
    #: the SQLite database file (None: PostgreSQL)
    sqlite_path: Path | None
    #: what the user typed (a path or a URL), as messages name the history
    given: str

    @classmethod
    def parse(cls, text: str | os.PathLike[str]) -> HistoryURL:
        """A URL (``sqlite:///f.db``, ``postgresql://user@host/db``; PostgreSQL through
        psycopg) or a file path (SQLite).

        :raises ConfigError: an empty path, another kind of database, a URL that does not
            parse (a port that is not a number), or an in-memory SQLite database (it keeps
            nothing).
        """
        s = str(text)
        if "://" not in s:
            if not s:
                raise ConfigError("history: an empty database path")
            path = Path(s).expanduser().absolute()
            return cls("sqlite:///" + str(path), path, s)
        scheme, _, rest = s.partition("://")
        base = scheme.split("+", 1)[0].lower()
        if base in ("postgresql", "postgres"):
            full = "postgresql+psycopg://" + rest
        elif base == "sqlite":
            full = s
        else:
            raise ConfigError(f"history: {scheme[:40]}:// databases are not supported "
                              f"(SQLite: a file path or sqlite:///FILE; PostgreSQL: "
                              f"postgresql://USER@HOST/DB)")
        sa = require_sqlalchemy()
        try:
            url = sa.engine.make_url(full)
            url.port  # noqa: B018  (parsed here: a port that is not a number raises)
        except (sa.exc.ArgumentError, ValueError) as e:
            raise ConfigError(f"history {cls.redact(s)}: not a database URL "
                              f"({cls.scrub(_first_line(e), s)})") from None
        if base != "sqlite":
            return cls(full, None, s)
        # sqlite:///relative.db, sqlite:////absolute.db; the query (?timeout=...) is the
        # driver's, no part of the file
        db = url.database
        if not db or db == ":memory:" or url.query.get("mode") == "memory" or (
                db.startswith("file:") and "mode=memory" in db):
            raise ConfigError(f"history {cls.redact(s)}: an in-memory database keeps "
                              f"nothing (give a file: a path or sqlite:///FILE)")
        return cls(full, Path(db), s)

    @property
    def shown(self) -> str:
        """The history as messages name it: as the user gave it, without its secrets."""
        return self.redact(self.given)

    @staticmethod
    def redact(text: str) -> str:
        """``text`` (a URL, parsed or not) with its secrets replaced by ``***``: the
        password of ``user:password@`` and every query parameter named like a password,
        key or token."""
        scheme, sep, rest = text.partition("://")
        if not sep:
            return text
        head, q, query = rest.partition("?")
        if "@" in head:
            cred, _, host = head.rpartition("@")
            user, colon, _ = cred.partition(":")
            head = f"{user}{':***' if colon else ''}@{host}"
        if q:
            query = "&".join(
                f"{k}=***" if _SECRET.search(k) and eq else f"{k}{eq}{v}"
                for k, eq, v in (item.partition("=") for item in query.split("&")))
        return f"{scheme}{sep}{head}{q}{query}"

    @staticmethod
    def scrub(message: str, text: str) -> str:
        """``message`` (a driver's error about the URL ``text``) without its secrets."""
        scheme, sep, rest = text.partition("://")
        head, _, query = rest.partition("?")
        secrets = []
        if "@" in head:
            secrets.append(head.rpartition("@")[0].partition(":")[2])
        for item in query.split("&"):
            k, _, v = item.partition("=")
            if _SECRET.search(k):
                secrets.append(v)
        for x in sorted(filter(None, secrets), key=len, reverse=True):
            message = message.replace(x, "***")
        return message


#: query parameters of a URL whose values are secrets
_SECRET = re.compile(r"pass|pwd|secret|token|key", re.IGNORECASE)


def _first_line(e: BaseException) -> str:
    text = str(getattr(e, "orig", None) or e).strip()
    return (text.splitlines() or [type(e).__name__])[0][:300]


#: what a history that is not canrls's, or whose file is damaged, is called in errors
NOT_A_HISTORY = "not a canrls history, or damaged"


def _guarded(method: Callable[..., T]) -> Callable[..., T]:
    """``method`` of :class:`History` with the database's errors as one
    :class:`ConfigError` naming the history (its password removed)."""

    @functools.wraps(method)
    def guarded(self: History, *args: Any, **kw: Any) -> T:
        try:
            return method(self, *args, **kw)
        except require_sqlalchemy().exc.DBAPIError as e:
            raise self._error(e) from e

    return guarded


def _nan(x: float | None) -> float:
    return math.nan if x is None else float(x)


class History:
    """An open history (:meth:`open`); :meth:`close` it (or use ``with``)."""

    def __init__(self, engine: Any, where: HistoryURL) -> None:
        self.engine = engine
        #: where it lives (its URL, its SQLite file, and how messages name it)
        self.where = where
        self._md = METADATA()
        self._drive_ids: dict[str, int] = {}
        self._model_ids: dict[str, int] = {}

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(cls, url: str | os.PathLike[str], *, upgrade: bool = True,
             read_only: bool = False) -> History:
        """Connect to the history at ``url`` (:meth:`HistoryURL.parse`) and bring its schema
        to :data:`HEAD_REVISION` (``upgrade=False``: refuse an older schema instead).
        ``read_only``: never write (a report; a SQLite history this user cannot write is
        read as it is on disk).

        :raises ConfigError: the database cannot be reached or created, is not a canrls
            history or is damaged, or its schema is newer than this canrls.
        """
        where = HistoryURL.parse(url)
        path = where.sqlite_path
        if path is not None and not path.parent.is_dir():
            raise ConfigError(f"history {where.shown}: directory {path.parent} does not "
                              f"exist")
        if path is not None and read_only:
            try:
                return cls._open(where, False, _read_only_url(path, "mode=ro"))
            except ConfigError as e:
                if not isinstance(e.__cause__, require_sqlalchemy().exc.OperationalError):
                    raise
            # no -shm can be made beside it: read the file as it is
            return cls._open(where, False, _read_only_url(path, "immutable=1"))
        return cls._open(where, upgrade and not read_only, None)

    @classmethod
    def _open(cls, where: HistoryURL, upgrade: bool, read_only: str | None) -> History:
        """:meth:`open` of ``where`` (``read_only``: the URL of a read-only SQLite file)."""
        sa = require_sqlalchemy()
        kw: dict[str, Any] = {}
        if where.sqlite_path is not None:
            kw["connect_args"] = {"timeout": BUSY_TIMEOUT_S}
        try:
            engine = sa.create_engine(read_only or where.url, **kw)
        except (ImportError, sa.exc.ArgumentError, ValueError) as e:
            raise ConfigError(f"history {where.shown}: "
                              f"{where.scrub(_first_line(e), where.url)}") from e
        if engine.dialect.name == "sqlite":
            @sa.event.listens_for(engine, "connect")
            def _pragmas(dbapi_conn: Any, record: Any) -> None:
                cur = dbapi_conn.cursor()
                cur.execute("PRAGMA foreign_keys=ON")
                cur.execute(f"PRAGMA busy_timeout={int(BUSY_TIMEOUT_S * 1000)}")
                cur.close()
        self = cls(engine, where)
        try:
            self._migrate(upgrade)
            if engine.dialect.name == "sqlite" and read_only is None:
                self._wal()
        except sa.exc.DBAPIError as e:
            engine.dispose()
            raise self._error(e) from e
        except BaseException:
            engine.dispose()
            raise
        return self

    def _wal(self) -> None:
        """SQLite's write-ahead log (readers beside the writer), set once the file is
        known to be a history: the mode stays in the file, another program's database is
        never changed. The switch does not wait for a lock as statements do: it is
        retried while other creators of a new history hold one (up to the busy timeout)."""
        sa = require_sqlalchemy()
        deadline = time.monotonic() + BUSY_TIMEOUT_S
        with self.engine.connect() as conn:
            while conn.exec_driver_sql("PRAGMA journal_mode").scalar() != "wal":
                try:
                    conn.exec_driver_sql("PRAGMA journal_mode=WAL")
                except sa.exc.OperationalError as e:
                    if "locked" not in str(e.orig) or time.monotonic() > deadline:
                        raise
                    time.sleep(0.01)

    def _error(self, e: Any) -> ConfigError:
        """A database error as one line naming the history: a damaged or foreign SQLite
        file is :data:`NOT_A_HISTORY`."""
        sa = require_sqlalchemy()
        why = self.where.scrub(_first_line(e), self.where.url)
        damaged = self.engine.dialect.name == "sqlite" and (
            not isinstance(e, sa.exc.OperationalError)
            or any(w in why for w in ("malformed", "no such table", "no such column")))
        if damaged:
            return ConfigError(f"history {self.where.shown}: {NOT_A_HISTORY} ({why})")
        return ConfigError(f"history {self.where.shown}: cannot use the database ({why})")

    def revision(self) -> str | None:
        """The schema revision the database is at (None: an empty database)."""
        from alembic.runtime.migration import MigrationContext

        with self.engine.connect() as conn:
            return MigrationContext.configure(conn).get_current_revision()

    def _migrate(self, upgrade: bool) -> None:
        from alembic import command
        from alembic.config import Config
        from alembic.runtime.migration import MigrationContext
        from alembic.script import ScriptDirectory

        cfg = Config()
        cfg.set_main_option("script_location", str(MIGRATIONS))
        heads = ScriptDirectory.from_config(cfg).get_heads()
        current = self.revision()
        if current not in heads:
            known = {s.revision for s in ScriptDirectory.from_config(cfg).walk_revisions()}
            if current is not None and current not in known:
                raise ConfigError(f"history {self.where.shown}: schema revision {current!r} "
                                  f"is newer than this canrls knows (up to {heads[0]!r}): "
                                  f"upgrade canrls")
            if not upgrade:
                if current is None:
                    raise ConfigError(f"history {self.where.shown}: {NOT_A_HISTORY} (no "
                                      f"schema revision)")
                raise ConfigError(f"history {self.where.shown}: schema revision "
                                  f"{current!r}, this canrls needs {heads[0]!r}")
            # one creator at a time: the others wait, then find it made
            with self._schema_lock() as conn:
                current = MigrationContext.configure(conn).get_current_revision()
                if current is None:
                    self._refuse_foreign(conn)
                if current not in heads:
                    cfg.attributes["connection"] = conn
                    command.upgrade(cfg, "head")
                    if self.engine.dialect.name == "sqlite":
                        self._foreign_keys_hold(conn)
        self._check_tables()

    @contextmanager
    def _schema_lock(self) -> Iterator[Any]:
        """A connection holding the database's write lock for a migration: SQLite's
        ``BEGIN IMMEDIATE`` (its DDL then in the one transaction), PostgreSQL's
        transaction-scoped advisory lock."""
        sa = require_sqlalchemy()
        if self.engine.dialect.name == "sqlite":
            with self.engine.connect() as raw:
                conn = raw.execution_options(isolation_level="AUTOCOMMIT")
                # SQLite alters a table by copying it and dropping the old one, and a
                # drop with foreign keys on deletes every parameter and candidate of it
                # (ON DELETE CASCADE): off for the migration (outside the transaction, or
                # SQLite ignores it), checked before the commit (_foreign_keys_hold)
                conn.exec_driver_sql("PRAGMA foreign_keys=OFF")
                try:
                    conn.exec_driver_sql("BEGIN IMMEDIATE")
                    try:
                        yield conn
                    except BaseException:
                        conn.exec_driver_sql("ROLLBACK")
                        raise
                    conn.exec_driver_sql("COMMIT")
                finally:
                    conn.exec_driver_sql("PRAGMA foreign_keys=ON")
            return
        with self.engine.begin() as conn:
            conn.execute(sa.select(sa.func.pg_advisory_xact_lock(SCHEMA_LOCK)))
            yield conn

    def _foreign_keys_hold(self, conn: Any) -> None:
        """Refuse a migrated SQLite history whose rows point at rows that are not there
        (the migration is rolled back)."""
        bad = conn.exec_driver_sql("PRAGMA foreign_key_check").fetchall()
        if bad:
            tables = sorted({str(row[0]) for row in bad})
            raise ConfigError(f"history {self.where.shown}: the migration left rows of "
                              f"{', '.join(tables)} pointing at rows that are not there "
                              f"({len(bad)}); nothing was changed")

    def _refuse_foreign(self, conn: Any) -> None:
        """An unversioned database with tables of this schema, or a SQLite file with any
        table, is not an empty history: it is not changed."""
        sa = require_sqlalchemy()
        tables = set(sa.inspect(conn).get_table_names())
        ours = tables & set(self._md.tables)
        if ours or (tables and self.engine.dialect.name == "sqlite"):
            raise ConfigError(f"history {self.where.shown}: {NOT_A_HISTORY} (tables "
                              f"{', '.join(sorted(tables)[:5])} without a schema revision)")

    def _check_tables(self) -> None:
        sa = require_sqlalchemy()
        with self.engine.connect() as conn:
            missing = set(self._md.tables) - set(sa.inspect(conn).get_table_names())
        if missing:
            raise ConfigError(f"history {self.where.shown}: {NOT_A_HISTORY} (no table "
                              f"{', '.join(sorted(missing))})")

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self) -> History:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ writing
    def _insert(self, table: Any) -> Any:
        if self.engine.dialect.name == "postgresql":
            from sqlalchemy.dialects.postgresql import insert as pg_insert

            return pg_insert(table)
        from sqlalchemy.dialects.sqlite import insert

        return insert(table)

    def _id(self, conn: Any, table: str, key_col: str, key: str, values: dict[str, Any],
            cache: dict[str, int], learned: dict[str, int]) -> int:
        """The row id of ``key`` in ``table``, inserted if missing; an id read inside the
        open transaction goes to ``learned``, kept in ``cache`` only once it commits (a
        rolled-back insert must not leave an id of a row that does not exist)."""
        if key in cache:
            return cache[key]
        if key in learned:
            return learned[key]
        t = self._md.tables[table]
        conn.execute(self._insert(t).values({key_col: key, **values})
                     .on_conflict_do_nothing(index_elements=[key_col]))
        got = conn.execute(t.select().with_only_columns(t.c.id)
                           .where(t.c[key_col] == key)).scalar_one()
        learned[key] = int(got)
        return learned[key]

    @_guarded
    def store(self, recordings: Iterable[Recording]) -> list[int | None]:
        """Insert ``recordings`` in one transaction, each unless its (content hash, model)
        is there already (or earlier in ``recordings``); returns each one's new row id, or
        None where it was there. A batch takes one statement per table (the drivers send
        many rows a statement), not one per recording."""
        t = self._md.tables
        recs = list(recordings)
        now = datetime.datetime.now(datetime.UTC)
        drives: dict[str, int] = {}
        models: dict[str, int] = {}
        with self.engine.begin() as conn:
            rows = [{
                "drive_id": self._id(conn, "drives", "name", r.drive, {"type": r.drive_type},
                                     self._drive_ids, drives),
                "model_id": self._id(conn, "models", "key", r.model_key,
                                     {"description": r.model}, self._model_ids, models),
                "content_hash": r.content_hash, "status": r.status, "source": r.source,
                "path": r.path, "t_start": finite_or_none(r.t_start),
                "t_end": finite_or_none(r.t_end), "samples": int(r.samples),
                "frames": int(r.frames), "residual_rms": finite_or_none(r.residual_rms),
                "fit_percent": finite_or_none(r.fit_percent), "unit": r.unit,
                "verdicts": json_safe(r.verdicts), "error": r.error, "session": r.session,
                "canrls_version": r.canrls_version, "ingested_at": now} for r in recs]
            if not rows:
                return []
            rt = t["recordings"]
            stmt = (self._insert(rt)
                    .on_conflict_do_nothing(index_elements=["content_hash", "model_id"])
                    .returning(rt.c.id, rt.c.content_hash, rt.c.model_id))
            # the rows a conflict skipped return nothing: each new id found by its key
            new = {(h, m): int(rid) for rid, h, m in conn.execute(stmt, rows)}
            out = [new.pop((row["content_hash"], row["model_id"]), None) for row in rows]
            params = [{"recording_id": rid, "name": p.name, "value": finite_or_none(p.value),
                       "sigma": finite_or_none(p.sigma), "unit": p.unit,
                       "fixed": finite_or_none(p.fixed), "identifiable": bool(p.identifiable),
                       "prior_share": finite_or_none(p.prior_share)}
                      for r, rid in zip(recs, out, strict=True) if rid is not None
                      for p in r.parameters]
            if params:
                conn.execute(t["parameters"].insert(), params)
            cands = [_candidate_row(rid, c) for r, rid in zip(recs, out, strict=True)
                     if rid is not None and r.candidates for c in r.candidates]
            if cands:
                conn.execute(t["candidates"].insert(), cands)
        self._drive_ids.update(drives)  # committed: the rows exist
        self._model_ids.update(models)
        return out

    @_guarded
    def add_candidates(self, recording_id: int, candidates: Sequence[CandidateValue]) -> None:
        """Store the candidate ranking of a recording stored without one (a ranking
        already there is kept)."""
        t = self._md.tables["candidates"]
        with self.engine.begin() as conn:
            for c in candidates:
                conn.execute(self._insert(t).values(_candidate_row(recording_id, c))
                             .on_conflict_do_nothing(index_elements=["recording_id", "rank"]))

    @_guarded
    def forget_errors(self, model_key: str) -> int:
        """Delete the error rows of ``model_key`` (so their logs are tried again); returns
        how many."""
        t = self._md.tables
        with self.engine.begin() as conn:
            mid = conn.execute(t["models"].select().with_only_columns(t["models"].c.id)
                               .where(t["models"].c.key == model_key)).scalar_one_or_none()
            if mid is None:
                return 0
            res = conn.execute(t["recordings"].delete().where(
                (t["recordings"].c.model_id == mid)
                & (t["recordings"].c.status != STATUS_OK)))
            return int(res.rowcount or 0)

    # ------------------------------------------------------------------ reading
    @_guarded
    def known_hashes(self, model_key: str) -> set[str]:
        """Content hashes stored (fitted or as errors) for ``model_key``."""
        t = self._md.tables
        q = (t["recordings"].select().with_only_columns(t["recordings"].c.content_hash)
             .join_from(t["recordings"], t["models"])
             .where(t["models"].c.key == model_key))
        with self.engine.connect() as conn:
            return {row[0] for row in conn.execute(q)}

    @_guarded
    def models(self) -> list[tuple[str, str, int]]:
        """``(key, description, recordings)`` of every model in the history."""
        sa = require_sqlalchemy()
        t = self._md.tables
        q = (sa.select(t["models"].c.key, t["models"].c.description,
                       sa.func.count(t["recordings"].c.id))
             .select_from(t["models"].outerjoin(t["recordings"]))
             .group_by(t["models"].c.id).order_by(t["models"].c.id))
        with self.engine.connect() as conn:
            return [(k, d, int(n)) for k, d, n in conn.execute(q)]

    @_guarded
    def count(self, *, status: str | None = None) -> int:
        sa = require_sqlalchemy()
        r = self._md.tables["recordings"]
        q = sa.select(sa.func.count(r.c.id))
        if status is not None:
            q = q.where(r.c.status == status)
        with self.engine.connect() as conn:
            return int(conn.execute(q).scalar_one())

    @_guarded
    def recordings(self, *, model_key: str | None = None, drive: str | None = None,
                   status: str | None = None) -> list[Recording]:
        """The recordings (with parameters and candidates), by drive and start time."""
        return list(self._iter(model_key, drive, status))

    def _iter(self, model_key: str | None, drive: str | None,
              status: str | None) -> Iterator[Recording]:
        sa = require_sqlalchemy()
        t = self._md.tables
        r, d, m = t["recordings"], t["drives"], t["models"]
        q = (sa.select(r, d.c.name.label("drive_name"), d.c.type.label("drive_type"),
                       m.c.key.label("model_key"), m.c.description.label("model_desc"))
             .select_from(r.join(d).join(m)))
        if model_key is not None:
            q = q.where(m.c.key == model_key)
        if drive is not None:
            q = q.where(d.c.name == drive)
        if status is not None:
            q = q.where(r.c.status == status)
        # NULL times (error rows) last in both databases (SQLite sorts them first)
        q = q.order_by(d.c.name, r.c.t_start.is_(None), r.c.t_start, r.c.id)
        with self.engine.connect() as conn:
            rows = list(conn.execute(q).mappings())
            ids = [row["id"] for row in rows]
            params: dict[int, list[ParameterValue]] = {}
            cands: dict[int, list[CandidateValue]] = {}
            for chunk in _chunks(ids, 500):
                pq = (t["parameters"].select().where(t["parameters"].c.recording_id.in_(chunk))
                      .order_by(t["parameters"].c.recording_id))
                for p in conn.execute(pq).mappings():
                    params.setdefault(p["recording_id"], []).append(ParameterValue(
                        name=p["name"], value=_nan(p["value"]), sigma=_nan(p["sigma"]),
                        unit=p["unit"], fixed=_nan(p["fixed"]),
                        identifiable=bool(p["identifiable"]),
                        prior_share=_nan(p["prior_share"])))
                cq = (t["candidates"].select().where(t["candidates"].c.recording_id.in_(chunk))
                      .order_by(t["candidates"].c.recording_id, t["candidates"].c.rank))
                for c in conn.execute(cq).mappings():
                    cands.setdefault(c["recording_id"], []).append(CandidateValue(
                        rank=c["rank"], effect=c["effect"], explained=_nan(c["explained"]),
                        delta_bic=_nan(c["delta_bic"]), rms_after=_nan(c["rms_after"]),
                        identifiable=bool(c["identifiable"]), suggested=bool(c["suggested"])))
        for row in rows:
            rid = row["id"]
            yield Recording(
                id=rid, drive=row["drive_name"], drive_type=row["drive_type"],
                content_hash=row["content_hash"], model_key=row["model_key"],
                model=row["model_desc"], status=row["status"], source=row["source"],
                path=row["path"], t_start=_nan(row["t_start"]), t_end=_nan(row["t_end"]),
                samples=row["samples"], frames=row["frames"],
                residual_rms=_nan(row["residual_rms"]), fit_percent=_nan(row["fit_percent"]),
                unit=row["unit"], verdicts=dict(row["verdicts"] or {}), error=row["error"],
                session=row["session"], canrls_version=row["canrls_version"],
                parameters=tuple(sorted(params.get(rid, []), key=lambda p: p.name)),
                candidates=tuple(cands[rid]) if rid in cands else None)

    @contextmanager
    def connection(self) -> Iterator[Any]:
        """A connection for one's own queries (bound parameters only)."""
        with self.engine.connect() as conn:
            yield conn


def _candidate_row(recording_id: int, c: CandidateValue) -> dict[str, Any]:
    """The row of the candidates table that holds ``c`` of a recording."""
    return {"recording_id": recording_id, "rank": c.rank, "effect": c.effect,
            "explained": finite_or_none(c.explained), "delta_bic": finite_or_none(c.delta_bic),
            "rms_after": finite_or_none(c.rms_after), "identifiable": bool(c.identifiable),
            "suggested": bool(c.suggested)}


def _chunks(xs: Sequence[int], n: int) -> Iterator[Sequence[int]]:
    for i in range(0, len(xs), n):
        yield xs[i:i + n]


def _read_only_url(path: Path, how: str) -> str:
    """A SQLAlchemy URL opening the SQLite file ``path`` read-only (``how``:
    ``mode=ro``, or ``immutable=1`` where no -shm file can be made beside it)."""
    return f"sqlite:///file:{urllib.parse.quote(str(path))}?{how}&uri=true"
