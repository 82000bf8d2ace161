"""The sigma printed beside a parameter covers the truth as often as it claims.

Simulated drives with known truth and the right model, across seeds and run lengths:
about 95 % of the parameters lie within 2 sigma. The plain RLS formula assumes white
residuals; after the state-variable filter they are coloured, and without the
correction (:mod:`canrls.estimation.sigma_inflation`) far fewer are covered.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from canrls.estimation.model import Model
from canrls.estimation.settings import EstimatorSettings
from canrls.estimation.sigma_inflation import ResidualTail
from canrls.processor import SampleProcessor
from canrls.processor.config import DEFAULT_HELD
from canrls.sim.scenario import scenario, simulate

EFFECTS = "inertia,viscous,coulomb,offset"


def _z_scores(durations: tuple[float, ...], seeds: range
              ) -> tuple[np.ndarray, np.ndarray, list[tuple[float, str]]]:
    """(z with the reported sigma, z with the plain RLS sigma) of every identifiable
    parameter, and (duration, name) of those reported as not identifiable."""
    z, z_plain, weak = [], [], []
    for duration in durations:
        for seed in seeds:
            res = simulate(scenario("standard", effects=EFFECTS, seed=seed,
                                    duration=duration))
            model = Model(EFFECTS.split(","), kt=0.1, held=DEFAULT_HELD)
            proc = SampleProcessor(model, 1e-3, EstimatorSettings())
            proc.run(res.measured)
            est = proc.pipeline.estimators[0]
            kappa = est.sigma_inflation()
            assert kappa > 1.0
            for p in proc.pipeline.estimates().parameters:
                if not p.identifiable:
                    weak.append((duration, p.name))
                    continue
                err = p.value - res.truth.params[p.name]
                z.append(err / p.sigma)
                z_plain.append(err / (p.sigma / np.sqrt(kappa)))
    return np.abs(np.array(z)), np.abs(np.array(z_plain)), weak


@pytest.mark.slow
def test_two_sigma_covers_about_95_percent() -> None:
    # from 2 s: the standard profile first reverses at 2.2 s, so in the 2 s runs
    # Coulomb friction and the offset are one column: no sigma makes their split
    # honest, they must be reported as not identifiable (and are left out of the
    # coverage); inertia and viscous friction are covered at every length
    durations = (2.0, 3.0, 5.0, 20.0)
    seeds = range(1, 9)
    z, z_plain, weak = _z_scores(durations, seeds)
    assert sorted(set(weak)) == [(2.0, "coulomb.Tc"), (2.0, "offset.T0")]
    assert len(weak) == 2 * len(seeds)
    assert len(z) == 4 * len(durations) * len(seeds) - len(weak)
    covered = float(np.mean(z <= 2.0))
    assert 0.88 <= covered <= 0.995, covered
    assert float(np.mean(z <= 3.0)) >= 0.97
    # the plain formula claims far more than it knows
    assert float(np.mean(z_plain <= 2.0)) < 0.75


def test_one_direction_parameters_are_not_identifiable_in_the_fit(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # 2 s of the standard profile never reverse: 'canrls fit' says so beside the values
    from canrls.can.logs import write_candump
    from canrls.cli.main import main

    res = simulate(scenario("standard", effects=EFFECTS, seed=3, duration=2.0))
    log = tmp_path / "two.log"
    write_candump(log, [res.frames])
    argv = ["fit", str(log), "--kt", "0.1", "--effects", EFFECTS, "--quiet"]
    capsys.readouterr()
    assert main([*argv, "--json"]) == 0
    params = json.loads(capsys.readouterr().out)["parameters"]
    assert {n for n, p in params.items() if not p["identifiable"]} == {"coulomb.Tc",
                                                                        "offset.T0"}
    assert params["coulomb.Tc"]["prior_share"] > 0.3
    assert params["inertia.J"]["prior_share"] < 1e-3
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "coulomb.Tc" in out and "NOT IDENTIFIABLE" in out
    assert "not identifiable from these data: coulomb.Tc, offset.T0" in out
    # and the saved model carries it to 'canrls validate'
    m = tmp_path / "two.json"
    assert main([*argv, "--json", "--save-model", str(m)]) == 0
    saved = json.loads(m.read_text())["parameters"]
    assert not saved["offset.T0"]["identifiable"] and saved["inertia.J"]["identifiable"]
    capsys.readouterr()
    assert main(["validate", str(log), "--model", str(m), "--quiet"]) == 0
    out = capsys.readouterr().out
    marked = [ln.split()[0] for ln in out.splitlines() if "NOT IDENTIFIABLE" in ln]
    assert marked == ["coulomb.Tc", "offset.T0"]


def test_inflation_of_white_and_coloured_residuals() -> None:
    rng = np.random.default_rng(3)
    n, rows = 2, 20000
    phi = rng.standard_normal((rows, n))
    theta = np.array([0.5, -0.25])
    white = phi @ theta + 0.1 * rng.standard_normal(rows)
    tail = ResidualTail(n, lags=20, window=rows)
    tail.push(phi, white)
    assert tail.inflation(theta) == pytest.approx(1.0, abs=0.15)
    # moving average of 10 samples: rho_l = 1 - l/10, kappa = 1 + 2 sum = 10
    e = np.convolve(rng.standard_normal(rows + 9), np.ones(10) / 10, mode="valid")
    tail2 = ResidualTail(n, lags=20, window=rows)
    # pushed in uneven blocks: the ring keeps the order
    y = phi @ theta + e
    for a, b in ((0, 7), (7, 5000), (5000, rows)):
        tail2.push(phi[a:b], y[a:b])
    assert tail2.inflation(theta) == pytest.approx(10.0, rel=0.15)
    # a short ring keeps the newest rows only, and survives a state round trip
    tail3 = ResidualTail(n, lags=20, window=1000)
    tail3.push(phi, y)
    st = tail3.state()
    assert np.array_equal(st["y"], y[-1000:])
    tail4 = ResidualTail(n, lags=20, window=1000)
    tail4.restore(st)
    assert tail4.inflation(theta) == tail3.inflation(theta)
    assert ResidualTail(n, lags=20).inflation(theta) == 1.0  # nothing held yet


EXCITATIONS = ("standard", "steps", "prbs", "chirp", "slow")


@pytest.mark.slow
def test_sigma_covers_the_truth_for_every_excitation_and_duration() -> None:
    """Within 2 sigma for at least 90 % of the identifiable parameters, for every
    parameter, excitation and run length from 2 s to 10 min: sigma holds the bound of
    the model's errors (the two filters' difference), which grows no smaller with the
    run, and the parameters the noise could explain are said not identifiable."""
    cases = [(e, d, seed) for e in EXCITATIONS for d, seeds in ((2.0, (1, 2)), (20.0, (1, 2)),
                                                                 (600.0, (1,)))
             for seed in seeds]
    rows = []
    for excitation, duration, seed in cases:
        res = simulate(scenario("standard", excitation=excitation, duration=duration,
                                seed=seed))
        model = Model(["inertia", "viscous", "coulomb"], kt=0.1, held=DEFAULT_HELD)
        proc = SampleProcessor(model, 1e-3, EstimatorSettings())
        proc.run(res.measured)
        for p in proc.pipeline.estimates().parameters:
            z = (p.value - res.truth.params[p.name]) / p.sigma
            rows.append((p.name, excitation, duration, p.identifiable, abs(z) <= 2.0))
    for k in range(3):
        for key in sorted({r[k] for r in rows}, key=str):
            covered = [r[4] for r in rows if r[k] == key and r[3]]
            assert covered and np.mean(covered) >= 0.9, (key, np.mean(covered), len(covered))
    weak = [r for r in rows if not r[3]]
    # only where the data cannot tell: the slow profile's first seconds
    assert all(r[1] == "slow" or r[2] <= 2.0 for r in weak), weak
    assert len(weak) <= 0.2 * len(rows)
