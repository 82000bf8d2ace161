"""A small fleet's history for the report tests, without ingesting anything.

:func:`pump_fleet` makes the recordings of six pumps, recorded weekly: one with twice
its siblings' inertia (an outlier) and, with ``drift``, one whose viscous friction
grows by 5 % a week. Each recording's log is an empty file in ``logs``, so a page can
link it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from canrls.fleet.records import ParameterValue, Recording

__all__ = ["pump_fleet"]


def pump_fleet(logs: Path, *, drift: bool = False, seed: int = 35) -> list[Recording]:
    """The recordings of drives ``d0``..``d5`` (type ``pump``), ``d5`` the outlier."""
    rng = np.random.default_rng(seed)
    recs = []
    for i in range(6):
        for k in range(6):
            path = logs / f"d{i} #{k}.log"
            path.write_text("")
            J = 1e-3 * (2.0 if i == 5 else 1.0) * (1 + 0.01 * rng.standard_normal())
            params = [ParameterValue("inertia.J", J, 1e-6, unit="kg·m²")]
            if drift:
                B = 1e-4 * (1 + 0.05 * k * (i == 4)) * (1 + 0.01 * rng.standard_normal())
                params.append(ParameterValue("viscous.B", B, 1e-7, unit="N·m·s/rad"))
            recs.append(Recording(
                drive=f"d{i}", drive_type="pump", content_hash=f"{i * 10 + k:064x}",
                model_key="m" * 64, model="inertia", path=str(path),
                t_start=1.7e9 + 7 * 86400 * k, residual_rms=1e-3 * (1 + 0.01 * rng.random()),
                parameters=tuple(params), id=i * 10 + k))
    return recs
