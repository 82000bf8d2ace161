"""``canrls.fleet.detect`` on simulated parameter histories: wear told from weather.

The histories are simulated directly, not fitted from logs (``fleet_histories``: per
recording the estimate a fit gives, its sigma and the bias of its excitation and
length, week-to-week jitter of friction, five changing drives among 40), so that ten
seeds at four jitters cost seconds; ``test_fleet.py`` and
``test_wear_and_weather_on_real_fits`` below hold the same conclusion on estimates of
the real pipeline.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from fleet_histories import CHANGES, simulated_fleet

from canrls.core.errors import ConfigError
from canrls.fleet import detect, multiplicity
from canrls.fleet.detect import DetectionSettings, assess
from canrls.fleet.records import Recording

SEEDS = range(101, 111)


def _right(fa: detect.FleetAssessment, drive: str, what: str) -> bool:
    a = fa.drive(drive).headline
    if a is None:
        return False
    if what in ("unbalance", "cogging:5"):
        return a.kind == "new effect" and a.effect == what
    return a.series == what


#: a normal jitter of standard deviation 5 %: the Coulomb friction of the most exposed
#: drives moving 7.5 % a week (a third of the weeks by more) against a wear of 3 % a
#: week; with the family-wise p under the tests' own correlation 43/50 are found (seeds
#: 201-210: 42/50), and 5 of the 7 missed drifts have p > alpha on their best test
#: alone, so no count of the tests can find them (docs/fleet.md)
_BEYOND = pytest.mark.xfail(strict=True, reason="a 3 % a week drift under a normal "
                            "weather of up to 7.5 % a week: 43/50 found, 5 of the 7 "
                            "misses have p > alpha on one test alone")


@pytest.mark.parametrize(("jitter", "gaussian"), [
    (0.0, False), (0.01, False), (0.02, False), (0.05, False),
    (0.0, True), (0.01, True), (0.02, True), pytest.param(0.05, True, marks=_BEYOND)])
def test_wear_is_told_from_weather(jitter: float, gaussian: bool) -> None:
    """Over 10 simulated fleets (40 drives x 10 weekly recordings, each recording with
    its own excitation and length, friction jittering week to week: within ±``jitter``
    uniformly, or ``gaussian`` a normal of that standard deviation): every changing
    drive but at most 5 % is alerted with the right parameter or effect, and at most
    1 % of the healthy drives is alerted at all."""
    found = changing = false = healthy = 0
    missed, wrong = [], []
    for seed in SEEDS:
        f = simulated_fleet(seed, jitter, gaussian=gaussian)
        fa = assess(f.recordings)
        for d, (what, _) in f.changing.items():
            changing += 1
            if _right(fa, d, what):
                found += 1
            else:
                missed.append((seed, d, what, [a.message for a in fa.drive(d).alerts]))
        for d in f.healthy:
            healthy += 1
            if fa.drive(d).alerts:
                false += 1
                wrong.append((seed, d, fa.drive(d).alerts[0].message))
    print(f"\njitter {'sd ' if gaussian else '±'}{100 * jitter:.0f} %: {found}/{changing} "
          f"changing drives alerted "
          f"right, {false}/{healthy} healthy drives alerted")
    assert changing == 5 * len(SEEDS) and healthy == 35 * len(SEEDS)
    assert found >= 0.95 * changing, missed
    assert false <= 0.01 * healthy, wrong


def test_sigma_alone_and_the_size_that_matters_do_not_suffice(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Without the learned scatter (each recording's sigma alone, tau = 0), the size
    that matters alone leaves healthy drives alerted: their friction moves 10 % and
    more from one excitation and week to the next, by many of its sigma."""
    monkeypatch.setattr(detect, "_own_tau", lambda pairs: 0.0)
    monkeypatch.setattr(detect, "estimate_tau", lambda pairs, quantile=0.5: 0.0)
    f = simulated_fleet(SEEDS[0], 0.05)
    fa = assess(f.recordings)
    false = [d for d in f.healthy if fa.drive(d).alerts]
    assert len(false) > 0.1 * len(f.healthy)


def test_an_alert_says_when_what_how_much_since_when_why_and_what_to_check() -> None:
    f = simulated_fleet(SEEDS[0], 0.02)
    fa = assess(f.recordings)
    by_what = {what: d for d, (what, _) in f.changing.items()}
    a = fa.drive(by_what["coulomb.Tc"]).headline
    assert a is not None and a.kind == "drift" and a.relative > 0.1
    first = a.message.split(". ")[0]
    # the date seen, the parameter, the size, the date since, against its usual change
    assert first.startswith(detect.when(a.seen) + ": coulomb.Tc +")
    assert f"since {detect.when(a.since)}" in first
    assert f"{a.times_usual:.0f}× its usual week-to-week change" in first
    assert "recording" not in a.message  # a date, not "recording 5 of 8"
    assert "Likely cause: more Coulomb friction: bearing or seal wear, lubrication" in a.message
    assert a.message.endswith("Check the bearings and seals, the lubrication.")
    j = fa.drive(by_what["inertia.J"]).headline
    assert j is not None and j.kind == "change" and "more inertia: a changed" in j.cause
    assert j.relative == pytest.approx(0.25, abs=0.02)
    c = fa.drive(by_what["cogging:5"]).headline
    assert c is not None and c.effect == "cogging:5" and "order 5" in c.cause
    d = a.to_dict()
    assert d["since_date"] == detect.when(a.since) and d["check"] == a.check


def test_a_change_must_be_large_enough_to_matter() -> None:
    """The viscous friction rising 40 % is alerted; with 80 % required it is not (a
    step is also a steep drift from the recording before: +50 % or so at the last), and
    with 80 % for every parameter (``[fleet] min_change``) no parameter change is."""
    f = simulated_fleet(SEEDS[0], 0.01)
    d = next(d for d, (what, _) in f.changing.items() if what == "viscous.B")
    assert assess(f.recordings).drive(d).headline.series == "viscous.B"
    cfg = DetectionSettings.from_table({"min_change": {"viscous": 0.8}}, "plant.toml")
    assert not [a for a in assess(f.recordings, settings=cfg).drive(d).alerts
                if a.series == "viscous.B"]
    cfg = DetectionSettings.from_table({"min_change": {e: 0.8 for e in
                                                       ("inertia", "viscous", "coulomb")}})
    fa = assess(f.recordings, settings=cfg)
    assert {a.kind for a in fa.alerts} <= {"new effect"}


@pytest.mark.parametrize("table, message", [
    ({"alpah": 0.01}, "plant.toml: unknown key fleet.alpah = 0.01 (valid: alpha"),
    ({"alpha": 1.5}, "plant.toml: fleet.alpha = 1.5: must be between 0 and 1"),
    ({"min_times_usual": "3"}, "plant.toml: fleet.min_times_usual = '3': must be a number"),
    ({"min_change": 0.1}, "plant.toml: fleet.min_change = 0.1: must be a table"),
    ({"min_change": {"colomb": 0.1}}, "plant.toml: fleet.min_change.colomb: unknown effect"),
    ({"min_change": {"coulomb": -0.1}}, "plant.toml: fleet.min_change.coulomb = -0.1: must"),
    ({"prior_pairs": 2.5}, "plant.toml: fleet.prior_pairs = 2.5: must be an integer"),
])
def test_fleet_settings_errors_name_the_file_and_key(table: dict, message: str) -> None:
    with pytest.raises(ConfigError) as e:
        DetectionSettings.from_table(table, "plant.toml")
    assert str(e.value).startswith(message)


def test_the_defaults_are_documented() -> None:
    """Every default size that matters is in docs/fleet.md with its value."""
    doc = (Path(__file__).resolve().parents[2] / "docs" / "fleet.md").read_text()
    for name, x in detect.MIN_CHANGE.items():
        assert f"`{name}` {100 * x:.0f} %" in doc, name
    assert f"`min_times_usual` {detect.MIN_TIMES_USUAL:g}" in doc
    assert f"`prior_pairs` {detect.PRIOR_PAIRS}" in doc


# ------------------------------------------------------------------ the family's p
def test_a_drives_p_is_the_chance_that_a_healthy_drive_reaches_its_z() -> None:
    """The family-wise p of a drive bounds, and comes close to, the chance that any
    change or drift test of any of its series reaches that |z| while the drive is
    healthy (a seeded Monte Carlo of its series: every z is linear in the values);
    counting every test (Bonferroni) overstates that chance by half and more."""
    f = simulated_fleet(SEEDS[0], 0.05, gaussian=True)
    da = assess(f.recordings).drive(f.healthy[0])
    rng = np.random.default_rng(7)
    draws = 200_000
    families, zmax = [], np.zeros(draws)
    for name, se in sorted(da.series.items()):
        tau = da.scatter[name]
        fam = detect._tests(se, tau)
        families.append(fam)
        n = len(se.y)
        # z = A y: the row of each test from the series' unit vectors
        A = np.array([[t.z for t in detect._tests(dataclasses.replace(se, y=e), tau).found]
                      for e in np.eye(n)]).T
        y = rng.normal(size=(draws, n)) * np.sqrt(se.s ** 2 + tau ** 2)
        zmax = np.maximum(zmax, np.abs(y @ A.T).max(axis=1))
    c = 3.5
    chance = float(np.mean(zmax >= c))
    p = multiplicity.family_p(c, [(len(fam.found), fam.links) for fam in families])
    tests = sum(len(fam.found) for fam in families)
    assert tests >= 5 * 15
    assert chance <= p <= 1.25 * chance, (p, chance)
    assert tests * multiplicity.phi_tail(c) > 1.5 * chance


# ------------------------------------------------------------------ the bookkeeping
def _healthy(jitter: float = 0.02) -> tuple[list[Recording], str]:
    f = simulated_fleet(SEEDS[1], jitter)
    return list(f.recordings), f.healthy[0]


def test_a_drive_with_one_recording_is_said_never_alerted() -> None:
    recs, d = _healthy()
    mine = [r for r in recs if r.drive == d]
    recs = [r for r in recs if r.drive != d] + [dataclasses.replace(
        mine[0], parameters=tuple(dataclasses.replace(p, value=p.value * 3)
                                  for p in mine[0].parameters))]
    da = assess(recs).drive(d)
    assert da.recordings == 1 and not [a for a in da.alerts if a.kind != "outlier"]
    assert any("1 recording of this model" in n for n in da.notes)


def test_a_drive_under_two_models_is_assessed_per_model() -> None:
    """Its recordings under a second model (other effects: other values) are not
    compared with the first model's: no alert from the switch, a note saying so."""
    recs, d = _healthy()
    mine = sorted((r for r in recs if r.drive == d), key=lambda r: r.t_start)
    other = [dataclasses.replace(r, model_key="e" * 64, model="inertia,viscous,coulomb",
                                 parameters=tuple(dataclasses.replace(p, value=p.value * 2)
                                                  for p in r.parameters))
             for r in mine[5:]]
    recs = [r for r in recs if r not in mine[5:]] + other
    fa = assess(recs)
    for key in ("e" * 64, mine[0].model_key):
        da = fa.drive(d, key)
        assert not da.alerts and any("under 2 models" in n for n in da.notes)


def test_recordings_out_of_order_or_at_the_same_time_raise_no_alert() -> None:
    recs, d = _healthy(0.0)
    base = assess(recs).drive(d)
    assert not base.alerts
    mine = [r for r in recs if r.drive == d]
    # stored in reverse order: the same assessment
    shuffled = [r for r in recs if r.drive != d] + [
        dataclasses.replace(r, id=10 ** 6 - k) for k, r in enumerate(mine)]
    again = assess(shuffled).drive(d)
    assert not again.alerts and again.scatter == pytest.approx(base.scatter)
    assert any("out of time order" in n for n in again.notes)
    # two recordings with the same start time, one a near copy of the other
    twin = dataclasses.replace(mine[4], id=10 ** 7, content_hash="c" * 64)
    da = assess([*recs, twin]).drive(d)
    assert not da.alerts and any("share a start time" in n for n in da.notes)


def test_a_drive_renamed_in_the_manifest_is_said_not_alerted() -> None:
    """A drive's later recordings under a new name: the old name has no recent
    recording, the new one none early (both said); neither is alerted."""
    recs, d = _healthy()
    mine = sorted((r for r in recs if r.drive == d), key=lambda r: r.t_start)
    renamed = [dataclasses.replace(r, drive=d + "-new") for r in mine[5:]]
    recs = [r for r in recs if r not in mine[5:]] + renamed
    fa = assess(recs)
    old, new = fa.drive(d), fa.drive(d + "-new")
    assert not old.alerts and not new.alerts
    assert any("no recording since" in n and "renamed" in n for n in old.notes)
    assert any("recorded since" in n and "renamed" in n for n in new.notes)


def test_changes_are_named_in_the_words_of_the_effect_library() -> None:
    from canrls.estimation.effects import library

    for cls in library():
        cause, check = detect._cause(f"{cls.NAME}.x", True)
        assert cause == cls.CHANGE_CAUSE[0] and check == cls.CHANGE_CHECK
    assert detect._cause("coulomb.Tc", False)[0].startswith("less Coulomb friction")
    assert set(CHANGES) >= {"coulomb.Tc", "inertia.J", "viscous.B"}


# ------------------------------------------------------------------ real fits
def test_wear_and_weather_on_real_fits(tmp_path: Path) -> None:
    """The same conclusion on estimates of the real pipeline: 8 simulated drives x 8
    weekly logs (``canrls.sim.fleet_plan``: friction jittering ±3 % / ±2 % a week), each
    log with its own excitation (standard, steps, prbs, chirp) and length (5 or 10 s),
    fitted through ``canrls.fleet.ingest`` into a SQLite history: the drive whose load
    changes (inertia x1.3) and the drive whose Coulomb friction rises 8 % a week are
    alerted with that parameter, no healthy drive is."""
    pytest.importorskip("sqlalchemy")
    pytest.importorskip("alembic")
    import numpy as np

    from canrls.fleet.history import History
    from canrls.fleet.ingest import JobConfig, ingest
    from canrls.fleet.sources import LogSource
    from canrls.sim.excitation import excitation
    from canrls.sim.fleet_plan import FLEET_EFFECTS, FLEET_KT, make_fleet, write_recording

    rng = np.random.default_rng(33)
    plan = make_fleet(8, 8, 5.0, seed=33)
    healthy = [d for d in plan.drives if d.cls == "healthy"]
    assert len(healthy) >= 8 - 2
    load, wear = healthy[0], healthy[1]
    sources = []
    for d in healthy:
        (tmp_path / d.name).mkdir()
        for k, r in enumerate(d.recordings):
            p = dict(r.params)
            if d is load and k >= 4:
                p["inertia.J"] *= 1.3
            if d is wear and k >= 2:
                p["coulomb.Tc"] *= 1.0 + 0.08 * (k - 1)
            rec = dataclasses.replace(r, params=p)
            prof = excitation(str(rng.choice(["standard", "steps", "prbs", "chirp"])),
                              seed=r.seed)
            path = tmp_path / d.name / f"{k + 1:02d}.log"
            write_recording(path, d, rec, float(rng.choice([5.0, 10.0])), profile=prof)
            sources.append(LogSource(str(path), d.name, d.type))
    with History.open(tmp_path / "fleet.db") as h:
        summary = ingest(sources, JobConfig(effects=FLEET_EFFECTS, kt=FLEET_KT), h)
        recs = h.recordings()
    assert summary.errors == 0 and summary.stored == len(sources)
    fa = assess(recs)
    alerted = {d.drive: d.headline for d in fa.drives if d.headline is not None}
    print("\n" + "\n".join(f"{d}: {a.message}" for d, a in alerted.items()))
    assert alerted[load.name].series == "inertia.J" and alerted[load.name].relative > 0.2
    assert alerted[wear.name].series == "coulomb.Tc" and alerted[wear.name].relative > 0.2
    assert set(alerted) == {load.name, wear.name}
    assert detect.when(alerted[load.name].since) in alerted[load.name].message


# ------------------------------------------------------------------ the command line
def test_report_reads_fleet_settings_and_refuses_a_bad_one(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``canrls fleet report --config`` takes what counts as an alert from ``[fleet]``;
    a bad key is one ``error:`` line naming the file and the key, exit 1."""
    pytest.importorskip("sqlalchemy")
    pytest.importorskip("alembic")
    import json

    from canrls.cli.main import main
    from canrls.fleet.history import History

    f = simulated_fleet(SEEDS[0], 0.02)
    db = tmp_path / "fleet.db"
    with History.open(db) as h:
        h.store(dataclasses.replace(r, id=None) for r in f.recordings)
    assert main(["fleet", "report", "--db", str(db), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    first = out["drives"][0]["alerts"][0]
    assert first["since_date"] and first["check"] and out["settings"]["min_change"]["coulomb"]
    alerted = {d["drive"] for d in out["drives"] if d["alerts"]}
    assert alerted == set(f.changing)
    cfg = tmp_path / "plant.toml"
    cfg.write_text("[fleet]\nmin_times_usual = 1e6\n")
    assert main(["fleet", "report", "--db", str(db), "--json", "--config", str(cfg)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {a["kind"] for d in out["drives"] for a in d["alerts"]} <= {"outlier"}
    cfg.write_text("[fleet]\nmin_chnage = 0.1\n")
    assert main(["fleet", "report", "--db", str(db), "--json", "--config", str(cfg)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"error: {cfg}: unknown key fleet.min_chnage = 0.1")
    assert err.count("\n") == 1
