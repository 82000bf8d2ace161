"""The HTML reports in a real browser (Debian's chromium, headless): the diagnosis,
validation and fleet pages render without console errors, every image loads, every
image has an alt text of its own, and nothing overflows at 1,400 and 800 px."""

from __future__ import annotations

from pathlib import Path

import pytest
from browser import open_page

from canrls.can.logs import write_candump
from canrls.cli.main import main
from canrls.sim.scenario import scenario, simulate

pytest.importorskip("matplotlib")

EFFECTS = "inertia,viscous,coulomb,offset"
MODEL = ["--kt", "0.1", "--effects", EFFECTS]


def _fleet_page(out: Path, logs: Path) -> Path:
    """The fleet page of six pumps: an outlier, a drift, four healthy drives."""
    from fleet_records import pump_fleet

    from canrls.fleet.detect import assess
    from canrls.fleet.fleet_report import write_html

    return write_html(assess(pump_fleet(logs, drift=True)), out)


@pytest.fixture(scope="module")
def pages(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("pages")
    logs = {}
    for seed, effects in ((1, EFFECTS + ",cogging:6"), (2, EFFECTS), (3, EFFECTS)):
        res = simulate(scenario("standard", effects=effects, seed=seed, duration=8.0))
        logs[seed] = d / f"drive{seed}.log"
        write_candump(logs[seed], [res.frames])
    assert main(["diagnose", str(logs[1]), *MODEL, "--add", "cogging:6", "--quiet",
                 "--report", str(d / "diagnosis")]) == 0
    assert main(["fit", str(logs[2]), *MODEL, "--quiet", "--save-model",
                 str(d / "m.json")]) == 0
    assert main(["validate", str(logs[3]), str(logs[1]), "--model", str(d / "m.json"),
                 "--quiet", "--report", str(d / "validation")]) == 0
    out = {"diagnosis": d / "diagnosis" / "index.html",
           "validation": d / "validation" / "index.html"}
    try:
        fleet_logs = d / "fleet-logs"
        fleet_logs.mkdir()
        out["fleet"] = _fleet_page(d / "fleet", fleet_logs)
    except ImportError:  # the fleet extra is missing: the other pages are still checked
        pass
    return out


@pytest.mark.parametrize("width", [1400, 800])
@pytest.mark.parametrize("name", ["diagnosis", "validation", "fleet"])
def test_page_renders_in_chromium(pages: dict[str, Path], name: str, width: int) -> None:
    if name not in pages:
        pytest.skip(f"the {name} page needs the fleet extra")
    check = open_page(pages[name], width)
    assert check.viewport
    assert check.errors == ()
    assert check.images and all(i["loaded"] for i in check.images), check.images
    # the alt says what the figure shows, not which file it is
    alts = [i["alt"] for i in check.images]
    assert all(len(a) > 30 and i["src"] not in a for a, i in zip(alts, check.images,
                                                                  strict=True))
    assert len(set(alts)) == len(alts)
    assert check.overflow == () and check.scroll_width <= width, check.overflow


def test_the_fleet_page_shows_the_bookkeeping_notes(tmp_path: Path) -> None:
    """Every note the JSON has (one recording, two models, equal start times, out of
    time order, a renamed drive) is shown on the page, beside its drive, never as an
    alert."""
    pytest.importorskip("sqlalchemy")
    from fleet_histories import bookkeeping_fleet

    from canrls.fleet.detect import assess
    from canrls.fleet.fleet_report import write_html

    recs, said = bookkeeping_fleet()
    fa = assess(recs)
    assert not [d.drive for d in fa.drives if d.drive in said and d.alerts]
    notes = [n for d in fa.drives for n in d.to_dict()["notes"]]
    check = open_page(write_html(fa, tmp_path / "fleet"), 1400)
    assert check.errors == () and check.overflow == (), check.overflow
    assert sorted(check.notes) == sorted(notes)
    for drive, phrase in said.items():
        assert any(phrase in n for n in fa.drive(drive).notes), (drive, phrase)
        assert any(phrase in n for n in check.notes), (drive, phrase)
