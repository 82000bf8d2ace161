"""``canrls.fleet.multiplicity``: the tails of one test and of correlated tests (the
family-wise p of a drive against a Monte Carlo of its series: ``test_fleet_detect.py``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from canrls.fleet import multiplicity


def test_two_tests_reach_a_z_together_as_the_bivariate_normal_says() -> None:
    """P(|z1| >= c, |z2| >= c) of two correlated tests against scipy's bivariate normal."""
    stats = pytest.importorskip("scipy.stats")
    rho = np.array([0.0, 0.5, 0.9, 0.999])
    for c in (2.0, 4.0):
        ref = [sum(stats.multivariate_normal([0, 0], [[1, s * r], [s * r, 1]]).cdf([-c, -c])
                   for s in (1, 1, -1, -1)) for r in rho]
        assert multiplicity.both_beyond(c, rho) == pytest.approx(ref, rel=1e-5)


def test_a_t_has_heavier_tails_than_a_normal() -> None:
    assert math.isfinite(multiplicity.t_tail(4.0, 20.0))
    assert multiplicity.t_tail(4.0, 20.0) > multiplicity.phi_tail(4.0)
    assert multiplicity.t_tail(4.0, math.inf) == multiplicity.phi_tail(4.0)


def test_one_test_alone_is_its_own_family() -> None:
    """A series of one test: the family's p is that test's."""
    q = multiplicity.phi_tail(3.0)
    assert multiplicity.family_p(3.0, [(1, np.empty(0))]) == pytest.approx(q, rel=1e-12)
