"""The parameter history of a fleet, in a real database through SQLAlchemy.

SQLite (a file: the embedded default) or PostgreSQL (``postgresql://user@host/db``,
through psycopg); the schema is versioned, and the Alembic migrations shipped in
``canrls/fleet/migrations`` bring an older history up to date when it is opened
(:meth:`History.open`). Every write is an insert-or-ignore in one transaction per batch,
so a recording is never stored twice. The tables: docs/fleet.md, "The history".
"""

from __future__ import annotations

import datetime
import math
import os
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from canrls.core.errors import ConfigError
from canrls.fleet.records import (
    STATUS_OK,
    CandidateValue,
    ParameterValue,
    Recording,
)

__all__ = ["History", "HistoryURL", "require_sqlalchemy", "METADATA", "HEAD_REVISION",
           "MIGRATIONS"]

#: the directory of the Alembic migrations (shipped in the package)
MIGRATIONS = Path(__file__).resolve().parent / "migrations"
#: the schema revision this canrls writes
HEAD_REVISION = "0001"


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
    :meth:`History.open`."""

    #: the SQLAlchemy URL (``sqlite:///...``, ``postgresql+psycopg://...``)
    url: str
    #: the SQLite database file (None: PostgreSQL, or SQLite in memory)
    sqlite_path: Path | None

    @classmethod
    def parse(cls, text: str | os.PathLike[str]) -> HistoryURL:
        """A URL (``sqlite:///f.db``, ``postgresql://user@host/db``; PostgreSQL through
        psycopg) or a file path (SQLite).

        :raises ConfigError: an empty path, or another kind of database.
        """
        s = str(text)
        if "://" not in s:
            if not s:
                raise ConfigError("history: an empty database path")
            path = Path(s).expanduser().absolute()
            return cls("sqlite:///" + str(path), path)
        scheme, _, rest = s.partition("://")
        base = scheme.split("+", 1)[0].lower()
        if base in ("postgresql", "postgres"):
            return cls("postgresql+psycopg://" + rest, None)
        if base == "sqlite":
            # sqlite:///relative.db, sqlite:////absolute.db, sqlite:// (in memory); the
            # query (?timeout=...) is the driver's
            db = rest[1:].partition("?")[0] if rest.startswith("/") else ""
            return cls(s, Path(db) if db and db != ":memory:" else None)
        raise ConfigError(f"history: {scheme}:// databases are not supported (SQLite: a file "
                          f"path or sqlite:///FILE; PostgreSQL: postgresql://USER@HOST/DB)")

    @property
    def shown(self) -> str:
        """The URL without its password, for messages."""
        scheme, sep, rest = self.url.partition("://")
        if "@" in rest:
            cred, _, host = rest.rpartition("@")
            return f"{scheme}{sep}{cred.split(':', 1)[0]}@{host}"
        return self.url


def _num(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def _nan(x: float | None) -> float:
    return math.nan if x is None else float(x)


def _json_safe(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_json_safe(v) for v in x]
    return x


class History:
    """An open history (:meth:`open`); :meth:`close` it (or use ``with``)."""

    def __init__(self, engine: Any, where: HistoryURL) -> None:
        self.engine = engine
        self.where = where
        self._md = METADATA()
        self._drive_ids: dict[str, int] = {}
        self._model_ids: dict[str, int] = {}

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(cls, url: str | os.PathLike[str], *, upgrade: bool = True) -> History:
        """Connect to the history at ``url`` (:meth:`HistoryURL.parse`) and bring its schema
        to :data:`HEAD_REVISION` (``upgrade=False``: refuse an older schema instead).

        :raises ConfigError: the database cannot be reached or created, or its schema is
            newer than this canrls.
        """
        sa = require_sqlalchemy()
        where = HistoryURL.parse(url)
        kw: dict[str, Any] = {}
        if where.url.startswith("sqlite"):
            kw["connect_args"] = {"timeout": 60}
            if where.sqlite_path is not None and not where.sqlite_path.parent.is_dir():
                raise ConfigError(f"history {url}: directory {where.sqlite_path.parent} "
                                  f"does not exist")
        try:
            engine = sa.create_engine(where.url, **kw)
        except (ImportError, sa.exc.ArgumentError) as e:
            raise ConfigError(f"history {url}: {e}") from e
        if engine.dialect.name == "sqlite":
            @sa.event.listens_for(engine, "connect")
            def _pragmas(dbapi_conn: Any, record: Any) -> None:
                cur = dbapi_conn.cursor()
                cur.execute("PRAGMA foreign_keys=ON")
                cur.execute("PRAGMA journal_mode=WAL")
                cur.execute("PRAGMA busy_timeout=60000")
                cur.close()
        self = cls(engine, where)
        try:
            self._migrate(upgrade)
        except sa.exc.OperationalError as e:
            engine.dispose()
            raise ConfigError(f"history {where.shown}: cannot open the database "
                              f"({str(e.orig).strip().splitlines()[0]})") from e
        except BaseException:
            engine.dispose()
            raise
        return self

    def revision(self) -> str | None:
        """The schema revision the database is at (None: an empty database)."""
        from alembic.runtime.migration import MigrationContext

        with self.engine.connect() as conn:
            return MigrationContext.configure(conn).get_current_revision()

    def _migrate(self, upgrade: bool) -> None:
        from alembic import command
        from alembic.config import Config
        from alembic.script import ScriptDirectory

        cfg = Config()
        cfg.set_main_option("script_location", str(MIGRATIONS))
        heads = ScriptDirectory.from_config(cfg).get_heads()
        current = self.revision()
        if current in heads:
            return
        known = {s.revision for s in ScriptDirectory.from_config(cfg).walk_revisions()}
        if current is not None and current not in known:
            raise ConfigError(f"history {self.where.shown}: schema revision {current!r} is "
                              f"newer than this canrls knows (up to {heads[0]!r}): "
                              f"upgrade canrls")
        if current is not None and not upgrade:
            raise ConfigError(f"history {self.where.shown}: schema revision {current!r}, "
                              f"this canrls needs {heads[0]!r}")
        try:
            with self.engine.begin() as conn:
                cfg.attributes["connection"] = conn
                command.upgrade(cfg, "head")
        except Exception:
            if self.revision() in heads:  # another process upgraded it meanwhile
                return
            raise

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self) -> History:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ writing
    def _insert(self, table: Any) -> Any:
        if self.engine.dialect.name == "postgresql":
            from sqlalchemy.dialects.postgresql import insert
        else:
            from sqlalchemy.dialects.sqlite import insert
        return insert(table)

    def _id(self, conn: Any, table: str, key_col: str, key: str, values: dict[str, Any],
            cache: dict[str, int]) -> int:
        if key in cache:
            return cache[key]
        t = self._md.tables[table]
        conn.execute(self._insert(t).values({key_col: key, **values})
                     .on_conflict_do_nothing(index_elements=[key_col]))
        got = conn.execute(t.select().with_only_columns(t.c.id)
                           .where(t.c[key_col] == key)).scalar_one()
        cache[key] = int(got)
        return cache[key]

    def store(self, recordings: Iterable[Recording]) -> list[int | None]:
        """Insert ``recordings`` in one transaction, each unless its (content hash, model)
        is there already; returns each one's new row id, or None where it was there."""
        t = self._md.tables
        out: list[int | None] = []
        now = datetime.datetime.now(datetime.UTC)
        with self.engine.begin() as conn:
            for r in recordings:
                drive = self._id(conn, "drives", "name", r.drive, {"type": r.drive_type},
                                 self._drive_ids)
                model = self._id(conn, "models", "key", r.model_key,
                                 {"description": r.model}, self._model_ids)
                stmt = (self._insert(t["recordings"]).values(
                    drive_id=drive, model_id=model, content_hash=r.content_hash,
                    status=r.status, source=r.source, path=r.path, t_start=_num(r.t_start),
                    t_end=_num(r.t_end), samples=int(r.samples), frames=int(r.frames),
                    residual_rms=_num(r.residual_rms), fit_percent=_num(r.fit_percent),
                    unit=r.unit, verdicts=_json_safe(r.verdicts), error=r.error,
                    session=r.session, canrls_version=r.canrls_version, ingested_at=now)
                    .on_conflict_do_nothing(index_elements=["content_hash", "model_id"])
                    .returning(t["recordings"].c.id))
                rid = conn.execute(stmt).scalar_one_or_none()
                out.append(None if rid is None else int(rid))
                if rid is None:
                    continue
                if r.parameters:
                    conn.execute(t["parameters"].insert(), [
                        {"recording_id": rid, "name": p.name, "value": _num(p.value),
                         "sigma": _num(p.sigma), "unit": p.unit, "fixed": _num(p.fixed),
                         "identifiable": bool(p.identifiable),
                         "prior_share": _num(p.prior_share)} for p in r.parameters])
                if r.candidates:
                    conn.execute(t["candidates"].insert(), [
                        {"recording_id": rid, "rank": c.rank, "effect": c.effect,
                         "explained": _num(c.explained), "delta_bic": _num(c.delta_bic),
                         "rms_after": _num(c.rms_after), "identifiable": bool(c.identifiable),
                         "suggested": bool(c.suggested)} for c in r.candidates])
        return out

    def add_candidates(self, recording_id: int, candidates: Sequence[CandidateValue]) -> None:
        """Store the candidate ranking of a recording stored without one (a ranking
        already there is kept)."""
        t = self._md.tables["candidates"]
        with self.engine.begin() as conn:
            for c in candidates:
                conn.execute(self._insert(t).values(
                    recording_id=recording_id, rank=c.rank, effect=c.effect,
                    explained=_num(c.explained), delta_bic=_num(c.delta_bic),
                    rms_after=_num(c.rms_after), identifiable=bool(c.identifiable),
                    suggested=bool(c.suggested))
                    .on_conflict_do_nothing(index_elements=["recording_id", "rank"]))

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
    def known_hashes(self, model_key: str) -> set[str]:
        """Content hashes stored (fitted or as errors) for ``model_key``."""
        t = self._md.tables
        q = (t["recordings"].select().with_only_columns(t["recordings"].c.content_hash)
             .join_from(t["recordings"], t["models"])
             .where(t["models"].c.key == model_key))
        with self.engine.connect() as conn:
            return {row[0] for row in conn.execute(q)}

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

    def count(self, *, status: str | None = None) -> int:
        sa = require_sqlalchemy()
        r = self._md.tables["recordings"]
        q = sa.select(sa.func.count(r.c.id))
        if status is not None:
            q = q.where(r.c.status == status)
        with self.engine.connect() as conn:
            return int(conn.execute(q).scalar_one())

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


def _chunks(xs: Sequence[int], n: int) -> Iterator[Sequence[int]]:
    for i in range(0, len(xs), n):
        yield xs[i:i + n]

