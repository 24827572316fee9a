"""The coupling estimator against linear systems written out by hand and simulated by
scipy.signal.lsim (not by afmctl.model.coupling.caused)."""

import math

import numpy as np
import pytest
from scipy import signal

from afmctl.errors import FitInputError
from afmctl.fit import coupling as fc

RATE_HZ = 10_000.0


def _two_dof(static: float, mode_hz: float, damping: float, inertial: float) -> signal.lti:
    """Target mass on a spring, pulled by the source's position (k_c) and acceleration (m_c):
    ``m y'' + c y' + k y = k_c x + m_c x''`` with m = 1: ``H = (m_c s^2 + k_c) / (s^2 + c s + k)``."""
    w = 2 * math.pi * mode_hz
    return signal.lti([inertial, 0.0, static * w * w], [1.0, 2 * damping * w, w * w])


def _two_modes(static: float) -> signal.lti:
    """A static path plus two resonances (300 Hz and 900 Hz): outside the one-mode form."""
    w1, w2 = 2 * math.pi * 300.0, 2 * math.pi * 900.0
    m1 = np.polymul([0.02, 0.0, 0.0], [1.0, 2 * 0.1 * w2, w2 * w2])
    m2 = np.polymul([-0.01, 0.0, 0.0], [1.0, 2 * 0.05 * w1, w1 * w1])
    den = np.polymul([1.0, 2 * 0.05 * w1, w1 * w1], [1.0, 2 * 0.1 * w2, w2 * w2])
    num = np.polyadd(np.polyadd(static * den, m1), m2)
    return signal.lti(num, den)


def _records(system: signal.lti, rng: np.random.Generator, noise_um: float = 0.02,
             arc: float = 0.0, chirp_centre: float = 0.0, slow: bool = True) -> list[fc.Record]:
    """Triangles over -50..50 um (0.3 Hz, 6 Hz) and a log chirp to 150 Hz about
    ``chirp_centre``; the target reads the system's response plus ``arc (x - 0)^2``, an offset
    and Gaussian noise; the source reads its position plus noise."""
    out = []
    waves = [(0.3, 7.0), (6.0, 1.0)] if slow else [(6.0, 1.0)]
    for f, seconds in waves:
        t = np.arange(int(seconds * RATE_HZ)) / RATE_HZ
        out.append((t, 50 * signal.sawtooth(2 * np.pi * f * t + np.pi / 2, 0.5)))
    t = np.arange(int(4 * RATE_HZ)) / RATE_HZ
    out.append((t, chirp_centre + 15 * signal.chirp(t, 1.0, t[-1], 150.0, method="logarithmic")))
    recs = []
    for k, (t, x) in enumerate(out):
        _, y, _ = signal.lsim(system, x - x[0], t)
        y = y + system.num[-1] / system.den[-1] * x[0] + arc * x ** 2 + 3.0 + 0.01 * t
        recs.append(fc.Record(x + noise_um * rng.standard_normal(x.size),
                              y + noise_um * rng.standard_normal(x.size), 1 / RATE_HZ, f"f{k}"))
    return recs


def _errors(fit: fc.CouplingFit, system: signal.lti, f_max: float) -> tuple[float, float]:
    f = np.geomspace(1.0, f_max, 25)
    h = fit.response(f)[0]
    true = system.freqresp(2 * np.pi * f)[1]
    ratio = h / true
    return float(np.max(np.abs(20 * np.log10(np.abs(ratio))))), \
        float(np.max(np.abs(np.degrees(np.angle(ratio)))))


def test_two_dof_is_recovered_with_its_mode() -> None:
    system = _two_dof(-0.012, 300.0, 0.08, 0.03)
    fit = fc.identify(_records(system, np.random.default_rng(1)))
    assert fit.coupling.static == pytest.approx(-0.012, rel=0.01)
    assert fit.static == pytest.approx(-0.012, rel=0.02)  # the low-passed regression alone
    db, deg = _errors(fit, system, 150.0)
    assert db < 0.25 and deg < 2.0
    # excited to half the mode: the mode is fixed to within its stated 1-sigma, not exactly
    assert abs(math.log(fit.coupling.mode_hz / 300.0)) < 4 * fit.stderr[1] + 0.02
    assert fit.stderr[1] < 0.3
    # the 1-sigma is honest: the static error within 4 sigma, and not absurdly large
    assert abs(fit.coupling.static + 0.012) < 4 * fit.stderr[0] + 1e-6
    assert fit.stderr[0] < 0.05 * 0.012


def test_two_modes_outside_the_form_are_followed_below_the_first() -> None:
    system = _two_modes(0.006)
    fit = fc.identify(_records(system, np.random.default_rng(2)))
    assert fit.coupling.quadratic == 0.0  # no arc: none significant, none kept
    db, deg = _errors(fit, system, 60.0)  # 0.2 of the first mode
    assert db < 0.5 and deg < 3.0
    assert fit.coupling.static == pytest.approx(0.006, rel=0.03)


def test_an_arc_off_centre_keeps_the_mid_range_static_gain() -> None:
    """y = H x + a x^2: full-range triangles about 0 see the slope at 0 (the secant), a chirp
    about x = 30 um the local slope H(0) + 2 a 30; the static gain is the mid-range one."""
    system = _two_dof(0.01, 400.0, 0.05, -0.02)
    fit = fc.identify(_records(system, np.random.default_rng(3), arc=4e-5, chirp_centre=30.0))
    assert fit.coupling.static == pytest.approx(0.01, rel=0.02)
    # the arc itself, about the middle of the triangles' range
    assert fit.coupling.quadratic == pytest.approx(4e-5, rel=0.03)
    assert abs(fit.coupling.quadratic - 4e-5) < 4 * fit.quadratic_stderr + 1e-7
    assert abs(fit.coupling.centre_um) < 0.5
    db, deg = _errors(fit, system, 80.0)
    assert db < 0.3 and deg < 2.0


def test_without_a_slow_file_the_response_fixes_the_static_gain() -> None:
    system = _two_dof(0.02, 250.0, 0.1, 0.005)
    fit = fc.identify(_records(system, np.random.default_rng(4), slow=False))
    assert math.isnan(fit.static)
    assert fit.coupling.static == pytest.approx(0.02, rel=0.03)


def test_refusals() -> None:
    with pytest.raises(FitInputError, match="no file"):
        fc.identify([])
    rng = np.random.default_rng(5)
    x = rng.standard_normal(20000)
    unrelated = fc.Record(x, rng.standard_normal(20000), 1e-3, "noise")
    with pytest.raises(FitInputError, match="too few frequencies"):
        fc.identify([unrelated])
