"""Rod model (16)-(18): exact discretization, static gain 1/k, resonance sqrt(k/m)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from afmctl.model import rod as rd

ROD = rd.Rod(m=0.05, c=39.27, k=123370.0, a1=3.8, a2=0.5, offset_um=1.5)


def test_discretization_matches_scipy_zero_order_hold() -> None:
    a = np.array([[0.0, 1.0], [-ROD.k / ROD.m, -ROD.c / ROD.m]])
    b = np.array([[0.0], [1.0 / ROD.m]])
    phi, gamma, *_ = signal.cont2discrete((a, b, np.eye(2), np.zeros((2, 1))), 1e-4, "zoh")
    disc = rd.discretize(ROD, 1e-4)
    np.testing.assert_allclose(disc.phi, phi, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(disc.gamma, gamma[:, 0], rtol=1e-12, atol=1e-18)


def test_static_gain_is_one_over_k() -> None:
    disc = rd.discretize(ROD, 1e-4)
    u, _ = rd.simulate(ROD, disc, np.full(20_000, 2.0))
    assert u[-1] - ROD.offset_um == pytest.approx(2.0 / ROD.k * 1e6, rel=1e-9)


def test_free_vibration_rings_at_the_damped_resonance() -> None:
    light = rd.Rod(m=0.05, c=2.0, k=123370.0, a1=1.0)
    dt = 1e-5
    u, _ = rd.simulate(light, rd.discretize(light, dt), np.zeros(40_000), np.array([1e-6, 0.0]))
    crossings = np.flatnonzero(np.diff(np.sign(u)) != 0)
    period = 2 * np.mean(np.diff(crossings)) * dt
    zeta = light.damping_ratio
    assert 1 / period == pytest.approx(light.natural_hz * np.sqrt(1 - zeta**2), rel=1e-3)
    assert light.natural_hz == pytest.approx(np.sqrt(light.k / light.m) / (2 * np.pi))


def test_alpha1_of_the_semigroup_is_positive_inequalities_19() -> None:
    """The (1,2) entry of e^{At} is > 0 for real and complex eigenvalues: the basis of (19)."""
    for c in (2.0, 39.27, 5000.0):  # under-, moderately and over-damped
        r = rd.Rod(m=0.05, c=c, k=123370.0, a1=1.0)
        for dt in (1e-5, 1e-4, 1e-3):
            assert rd.discretize(r, dt).gamma[0] > 0
            row, gain = rd.discretize(r, dt).horizon(3)
            assert gain > 0


def test_smooth_horizon_avoids_the_alternating_sampling_zero() -> None:
    disc = rd.discretize(ROD, 1e-4)
    d = rd.smooth_horizon(disc)
    row1, g1 = disc.horizon(1)
    ev1 = np.linalg.eigvals(disc.phi - np.outer(disc.gamma, row1) / g1)
    assert ev1.real.min() < -0.9  # the one-step inverse has the sampling zero near -1
    row, g = disc.horizon(d)
    ev = np.linalg.eigvals(disc.phi - np.outer(disc.gamma, row) / g)
    assert d > 1 and np.all(ev.real > 0) and np.all(np.abs(ev) < 1)
