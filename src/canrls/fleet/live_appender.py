"""The daemon's snapshots into the fleet history (``[history]`` of ``canrls run``).

.. code-block:: toml

    [history]
    url = "/var/lib/canrls/fleet.db"     # or postgresql://canrls@db/plant
    drive = "press-3-axis-2"             # this drive's name in the history
    type = "servo-m"                     # optional: its siblings share the type
    interval = 600                       # seconds between snapshots (default 600)

Each snapshot is a recording (source ``live``) of the model the daemon runs, with the
same model key as ``canrls fleet ingest`` gives a log fitted with the same
configuration, so live and offline recordings share one history. A run's snapshots
share a session; the detection counts a session once (its last snapshot: the
estimates of the run so far).
"""

from __future__ import annotations

import hashlib
import time
import uuid
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from canrls import __version__
from canrls.core.checks import is_positive
from canrls.core.errors import ConfigError
from canrls.fleet.history import History
from canrls.fleet.records import SOURCE_LIVE, ParameterValue, Recording
from canrls.fleet.sources import check_name

__all__ = ["HistorySettings", "LiveAppender", "HISTORY_KEYS"]

HISTORY_KEYS = {
    "url": "the history: a file (SQLite) or postgresql://USER@HOST/DB",
    "drive": "this drive's name in the history",
    "type": "this drive's type (its siblings share it)",
    "interval": "seconds between snapshots of the published parameters (default 600)",
}


@dataclass(frozen=True)
class HistorySettings:
    """The ``[history]`` table, validated."""

    url: str
    drive: str
    type: str = ""
    interval: float = 600.0

    @classmethod
    def from_table(cls, table: Mapping[str, Any], source: str = "<config>"
                   ) -> HistorySettings:
        """Errors name the file, the key and the value."""
        for k, v in table.items():
            if k not in HISTORY_KEYS:
                raise ConfigError(f"{source}: history.{k} = {v!r}: unknown key (valid: "
                                  f"{', '.join(HISTORY_KEYS)})")
        for k in ("url", "drive"):
            v = table.get(k)
            if not isinstance(v, str) or not v:
                raise ConfigError(f"{source}: history.{k} = {v!r}: must be a non-empty "
                                  f"string ({HISTORY_KEYS[k]})")
        where = f"{source}: history"
        ty = table.get("type", "")
        if not isinstance(ty, str):
            raise ConfigError(f"{source}: history.type = {ty!r}: must be a string")
        iv = table.get("interval", 600.0)
        if not is_positive(iv):
            raise ConfigError(f"{source}: history.interval = {iv!r}: must be a positive "
                              f"number of seconds")
        return cls(url=table["url"], drive=check_name(table["drive"], "drive", where),
                   type=check_name(ty, "type", where) if ty else "", interval=float(iv))


class LiveAppender:
    """Stores a daemon's snapshots (:class:`canrls.live.history_hook.Snapshot`) as recordings."""

    def __init__(self, history: History, settings: HistorySettings, model_key: str,
                 model: str) -> None:
        self.history = history
        self.settings = settings
        self.model_key = model_key
        self.model = model
        self.session = uuid.uuid4().hex
        self.started = time.time()

    @classmethod
    def open(cls, settings: HistorySettings, model_key: str, model: str) -> LiveAppender:
        return cls(History.open(settings.url), settings, model_key, model)

    def recording(self, snap: Any) -> Recording:
        est = snap.estimates
        digest = hashlib.sha256(
            f"live:{self.settings.drive}:{self.session}:{snap.seq}".encode()).hexdigest()
        eq = est.equations[0] if est.equations else None
        return Recording(
            drive=self.settings.drive, drive_type=self.settings.type, content_hash=digest,
            model_key=self.model_key, model=self.model, source=SOURCE_LIVE,
            path=f"live session {self.session[:12]} snapshot {snap.seq}",
            t_start=self.started, t_end=float(snap.t), samples=int(est.samples),
            residual_rms=float(est.residual_rms), fit_percent=float(est.fit_percent),
            unit=eq.unit if eq is not None else "",
            verdicts={"not_identifiable": [p.name for p in est.parameters
                                           if not p.identifiable]},
            parameters=tuple(ParameterValue(
                name=p.name, value=float(p.value), sigma=float(p.sigma), unit=p.unit,
                fixed=float(p.fixed), identifiable=bool(p.identifiable),
                prior_share=float(p.prior_share)) for p in est.parameters),
            session=self.session, canrls_version=__version__)

    def append(self, snap: Any) -> None:
        """Store one snapshot (a snapshot without samples yet is skipped)."""
        if snap.estimates.samples <= 0:
            return
        self.history.store([self.recording(snap)])

    def close(self) -> None:
        self.history.close()
