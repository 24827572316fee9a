"""The cross-coupling operator against analytic limits: DC gain, the steady sine response equal to
|H(j w)| and its phase, the mode's resonance written by hand, and rest at the reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmctl.model.coupling import Coupling, caused, frf, own_motion


def test_static_only_is_a_gain_about_the_reference() -> None:
    c = Coupling(static=-0.012, reference_um=40.0)
    x = np.linspace(0.0, 80.0, 11)
    assert np.allclose(caused(c, x, 1e-4), -0.012 * (x - 40.0))
    assert c.static_db == pytest.approx(20 * math.log10(0.012))


def test_an_arc_is_zero_at_the_reference_with_the_static_slope_at_its_centre() -> None:
    """y = static (x - r) + q ((x - c)^2 - (r - c)^2), written out by hand; a mode does not
    change the settled value (it vanishes at DC)."""
    x = np.linspace(0.0, 100.0, 401)
    for mode_hz in (0.0, 300.0):
        c = Coupling(static=0.05, mode_hz=mode_hz, reference_um=40.0, quadratic=-2e-5,
                     centre_um=55.0)
        held = np.repeat(x, 200)  # each level held 20 ms: the mode (tau < 10 ms) dies away
        y = caused(c, held, 1e-4)[199::200]
        assert np.allclose(y, 0.05 * (x - 40.0) - 2e-5 * ((x - 55.0) ** 2 - 15.0 ** 2), atol=1e-9)
        assert y[160] == pytest.approx(0.0, abs=1e-12)  # x = 40: the reference
        slope = np.gradient(y, x)
        assert slope[220] == pytest.approx(0.05, rel=1e-9)  # x = 55: the centre


def test_frf_at_dc_resonance_and_high_frequency() -> None:
    c = Coupling(static=0.01, mode_hz=400.0, damping=0.04, gain_hp=0.02, gain_bp=0.03)
    h = frf(c, [0.0, 400.0, 4e6])
    assert h[0] == pytest.approx(0.01)
    # at s = j w: (s/w)^2 = -1, 2 zeta s/w = 2 zeta j, denominator 2 zeta j
    assert h[1] == pytest.approx(0.01 + (-0.02 + 0.03 * 2 * 0.04j) / (2 * 0.04j))
    assert abs(h[2] - 0.03) < 1e-6


@pytest.mark.parametrize("f_hz", [5.0, 120.0, 350.0])
def test_steady_sine_follows_the_frf(f_hz: float) -> None:
    c = Coupling(static=-0.008, mode_hz=300.0, damping=0.06, gain_hp=0.015, gain_bp=-0.01)
    dt = 1e-4
    t = np.arange(int(2.0 / dt)) * dt
    y = caused(c, np.sin(2 * np.pi * f_hz * t), dt)
    tail = t > 1.0  # the mode (tau = 1 / (zeta w) < 10 ms) has died away
    basis = np.column_stack([np.sin(2 * np.pi * f_hz * t[tail]), np.cos(2 * np.pi * f_hz * t[tail])])
    (a, b), *_ = np.linalg.lstsq(basis, y[tail], rcond=None)
    # the hold interpolates the source linearly: a sine's spectrum is weighted by sinc^2(f dt)
    # (0.4 % at 350 Hz); the images at k/dt +- f fold back at the samples, weighted by
    # sinc^2 ~ (f dt)^2: a few 1e-4 of H, hence the tolerance
    h = frf(c, [f_hz])[0] * np.sinc(f_hz * dt) ** 2
    assert a + 1j * b == pytest.approx(h, rel=1e-3)


def test_starts_at_rest_and_settles_to_the_static_gain() -> None:
    c = Coupling(static=0.02, mode_hz=200.0, damping=0.05, gain_hp=0.05, reference_um=10.0)
    x = np.full(4000, 30.0)
    x[2000:] = 50.0
    y = caused(c, x, 1e-4)
    assert np.allclose(y[:2000], 0.02 * 20.0)
    assert y[-1] == pytest.approx(0.02 * 40.0, rel=1e-3)
    assert abs(y[2000:2100] - 0.8).max() > 0.01  # the mode rings after the step


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ValueError):
        Coupling(static=float("nan"))
    with pytest.raises(ValueError):
        Coupling(static=0.0, mode_hz=100.0, damping=0.0)


def test_own_motions_solve_the_loop_of_two_static_couplings() -> None:
    """Readings of own motions X, Y coupled both ways about the references (x = X + c_xy (Y -
    30), y = Y + c_yx (X - 45)): :func:`own_motion` recovers X; its one-round error is ``c_xy^2
    c_yx (Y - 30)`` (worked out by hand) and each further round multiplies it by ``c_xy c_yx``."""
    rng = np.random.default_rng(3)
    own_x, own_y = rng.uniform(0, 80, 500), rng.uniform(0, 100, 500)
    xy, yx = Coupling(0.06, reference_um=30.0), Coupling(-0.05, reference_um=45.0)
    x, y = own_x + 0.06 * (own_y - 30.0), own_y - 0.05 * (own_x - 45.0)
    for rounds in (1, 2, 3):
        error = own_motion(xy, yx, x, y, 1e-4, rounds) - own_x
        expected = 0.06 ** 2 * -0.05 * (0.06 * -0.05) ** (rounds - 1) * (own_y - 30.0)
        assert np.allclose(error, expected, rtol=1e-6, atol=1e-12)
