"""``canrls fleet report``'s text: the count of alerts is the number of alerts listed."""

from __future__ import annotations

from pathlib import Path

from canrls.cli.fleet import text_summary
from canrls.fleet.detect import Alert, DriveAssessment, FleetAssessment


def _drive(name: str, *messages: str) -> DriveAssessment:
    alerts = tuple(Alert(drive=name, kind="change", series="inertia.J", z=10.0, p=1e-9,
                         message=m) for m in messages)
    return DriveAssessment(drive=name, drive_type="servo", model_key="k", model="m",
                           recordings=8, errors=0, alerts=alerts)


def test_every_alert_counted_is_listed() -> None:
    fleet = FleetAssessment(
        drives=(_drive("d1", "inertia.J changed", "residual_rms changed"),
                _drive("d2", "coulomb.Tc drifts"), _drive("d3")),
        baselines={}, spread={})
    lines = text_summary(fleet, Path("out/index.html")).splitlines()
    assert lines == ["3 drives, 3 alerts on 2 drives; report: out/index.html",
                     "  d1: inertia.J changed", "  d1: residual_rms changed",
                     "  d2: coulomb.Tc drifts"]
    quiet = FleetAssessment(drives=(_drive("d3"),), baselines={}, spread={})
    assert text_summary(quiet, None) == "1 drive, 0 alerts on 0 drives\n"
