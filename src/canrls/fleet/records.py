"""The values a fleet's history holds: one :class:`Recording` per log (or per live
snapshot), with its :class:`ParameterValue` rows and, where ranked, its
:class:`CandidateValue` rows. Plain frozen dataclasses: the ingest makes them, the
history stores and reads them back, the detection reads them."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

__all__ = ["ParameterValue", "CandidateValue", "Recording", "STATUS_OK", "STATUS_ERROR",
           "SOURCE_LOG", "SOURCE_LIVE"]

#: a recording fitted: its parameters are stored
STATUS_OK = "ok"
#: a log that could not be fitted: the row names the file and the reason
STATUS_ERROR = "error"
#: a recording from a log file (``canrls fleet ingest``)
SOURCE_LOG = "log"
#: a snapshot of the daemon's published parameters (``canrls run`` with ``[history] url``)
SOURCE_LIVE = "live"


@dataclass(frozen=True)
class ParameterValue:
    """One parameter of one recording: the float estimate, its sigma as the estimator
    reports it, the fixed-point value and whether the data could identify it."""

    name: str
    value: float
    sigma: float
    unit: str = ""
    fixed: float = math.nan
    identifiable: bool = True
    prior_share: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "value": self.value, "sigma": self.sigma,
                "unit": self.unit, "fixed": self.fixed, "identifiable": self.identifiable,
                "prior_share": self.prior_share}


@dataclass(frozen=True)
class CandidateValue:
    """One effect the model lacks, as the diagnosis ranked it on this recording."""

    rank: int
    effect: str
    explained: float
    delta_bic: float
    rms_after: float
    identifiable: bool
    suggested: bool

    def to_dict(self) -> dict[str, Any]:
        return {"rank": self.rank, "effect": self.effect, "explained": self.explained,
                "delta_bic": self.delta_bic, "rms_after": self.rms_after,
                "identifiable": self.identifiable, "suggested": self.suggested}


@dataclass(frozen=True)
class Recording:
    """One recording of one drive, as the history stores it.

    ``content_hash`` (SHA-256 of the log's bytes; for a live snapshot, of its drive,
    session and time) and ``model_key`` (:func:`canrls.fleet.ingest.model_key`) make
    it unique: the history holds each pair once. ``t_start``/``t_end`` are the log's
    first and last timestamps (epoch seconds for ``candump -l`` logs).
    """

    drive: str
    content_hash: str
    model_key: str
    model: str
    status: str = STATUS_OK
    source: str = SOURCE_LOG
    path: str = ""
    drive_type: str = ""
    t_start: float = math.nan
    t_end: float = math.nan
    samples: int = 0
    frames: int = 0
    residual_rms: float = math.nan
    fit_percent: float = math.nan
    unit: str = ""
    verdicts: dict[str, Any] = field(default_factory=dict)
    parameters: tuple[ParameterValue, ...] = ()
    candidates: tuple[CandidateValue, ...] | None = None
    error: str | None = None
    session: str | None = None
    canrls_version: str = ""
    #: the history's row id (None before it is stored)
    id: int | None = None

    @property
    def ok(self) -> bool:
        return self.status == STATUS_OK

    def parameter(self, name: str) -> ParameterValue | None:
        for p in self.parameters:
            if p.name == name:
                return p
        return None

    def to_dict(self) -> dict[str, Any]:
        return {"id": self.id, "drive": self.drive, "type": self.drive_type,
                "path": self.path, "source": self.source, "status": self.status,
                "error": self.error, "content_hash": self.content_hash,
                "model_key": self.model_key, "model": self.model,
                "t_start": self.t_start, "t_end": self.t_end, "samples": self.samples,
                "frames": self.frames, "residual_rms": self.residual_rms,
                "fit_percent": self.fit_percent, "unit": self.unit,
                "verdicts": self.verdicts,
                "parameters": {p.name: p.to_dict() for p in self.parameters},
                "candidates": None if self.candidates is None
                else [c.to_dict() for c in self.candidates],
                "session": self.session, "canrls_version": self.canrls_version}
