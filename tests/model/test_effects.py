"""The effects chain (afmctl.model.effects): each operator against its inverse, its analytic limit, and
the emulator that runs it."""

import math

import numpy as np
import pytest

from afmctl.model import effects as fx

DT = 1e-4


def _signal(n: int = 3000) -> np.ndarray:
    t = np.arange(n) * DT
    return 20 * np.sin(2 * np.pi * 27.9 * t) + 5 * np.sin(2 * np.pi * 130 * t) + 3.0


def fine_mean(v_cmd: np.ndarray, bw: float, v_prev: float, n_fine: int = 400) -> np.ndarray:
    """Oracle: a first-order amplifier's output (exact exponential steps on a grid ``n_fine``
    times finer, each command held over its sample) averaged over each sample (trapezoids)."""
    h = DT / n_fine
    a = math.exp(-2 * math.pi * bw * h)
    out, x = np.empty(v_cmd.size), v_prev
    for k, u in enumerate(v_cmd):
        xs = np.empty(n_fine + 1)
        xs[0] = x
        for j in range(n_fine):
            xs[j + 1] = a * xs[j] + (1 - a) * u
        out[k] = float(np.mean(0.5 * (xs[1:] + xs[:-1])))
        x = xs[-1]
    return out


def test_lag_is_the_mean_output_over_each_held_sample() -> None:
    chain = fx.compile_chain(fx.Effects(amplifier_bandwidth_hz=400.0), DT)
    v = _signal(300)
    np.testing.assert_allclose(fx.lag(chain, v, 1.0)[0], fine_mean(v, 400.0, 1.0), atol=1e-5)


def test_unlag_inverts_lag_exactly() -> None:
    chain = fx.compile_chain(fx.Effects(amplifier_bandwidth_hz=400.0), DT)
    v = _signal()
    out, _ = fx.lag(chain, fx.unlag_limited(chain, v, 1.0, np.inf), 1.0)
    np.testing.assert_allclose(out, v, atol=1e-9)


def test_lag_step_response_is_first_order() -> None:
    """The mean of ``1 - exp(-w t)`` over each sample ``[k dt, (k + 1) dt]``."""
    bw = 250.0
    chain = fx.compile_chain(fx.Effects(amplifier_bandwidth_hz=bw), DT)
    y, _ = fx.lag(chain, np.ones(400), 0.0)
    wdt = 2 * np.pi * bw * DT
    k = np.arange(400)
    np.testing.assert_allclose(y, 1 - np.exp(-wdt * k) * (1 - np.exp(-wdt)) / wdt, atol=1e-12)


def _step_2nd(t: np.ndarray, w: float, zeta: float) -> np.ndarray:
    if zeta < 1:
        wd = w * np.sqrt(1 - zeta ** 2)
        return 1 - np.exp(-zeta * w * t) * (np.cos(wd * t) + zeta * w / wd * np.sin(wd * t))
    r1, r2 = -w * (zeta - np.sqrt(zeta ** 2 - 1)), -w * (zeta + np.sqrt(zeta ** 2 - 1))
    return 1 + (r2 * np.exp(r1 * t) - r1 * np.exp(r2 * t)) / (r1 - r2)


@pytest.mark.parametrize("zeta", [0.3, 0.7, 2.0])
def test_second_order_amplifier_step_response(zeta: float) -> None:
    """The closed-form step response of ``v'' + 2 zeta w v' + w^2 v = w^2`` from rest, averaged
    over each sample (Simpson's rule on 65 points); with a slew limit far beyond the step's rate
    (integrated numerically: RK4, one step per sample here) the same to the method's error."""
    f = 300.0
    w = 2 * np.pi * f
    t = (np.arange(400)[:, None] + np.linspace(0.0, 1.0, 65)[None, :]) * DT
    wts = np.ones(65)
    wts[1:-1:2], wts[2:-1:2] = 4.0, 2.0
    exact = _step_2nd(t, w, zeta) @ wts / wts.sum()
    for slew in (None, 1e12):
        e = fx.Effects(amplifier_bandwidth_hz=f, amplifier_damping_ratio=zeta,
                       amplifier_slew_v_per_s=slew)
        y, _ = fx.lag(fx.compile_chain(e, DT), np.ones(400), 0.0)
        np.testing.assert_allclose(y, exact, atol=1e-9 if slew is None else 3e-5)


def test_amplifier_slew_limit_caps_the_output_rate() -> None:
    """A 10 V step into an amplifier with a 20 V/ms limit: a ramp just under the limit (the drive
    is several times the limit), then the approach to 10 V; first and second order alike."""
    for zeta in (None, 0.5):
        e = fx.Effects(amplifier_bandwidth_hz=2000.0, amplifier_damping_ratio=zeta,
                       amplifier_slew_v_per_s=2e4)
        y, _ = fx.lag(fx.compile_chain(e, DT), np.full(300, 10.0), 0.0)
        steps = np.diff(y)
        assert np.max(np.abs(steps)) <= 2e4 * DT * (1 + 1e-12)
        assert np.all(steps[:3] > 0.9 * 2e4 * DT)
        assert y[-1] == pytest.approx(10.0, abs=1e-6)


@pytest.mark.parametrize("slew", [None, 3e4])
def test_second_order_unlag_follows_a_smooth_target(slew: float | None) -> None:
    """The continuous-time inverse (through the slew limit too, the fastest ramp here at 0.6 of
    it) leaves under 1 % of the plain lag's error."""
    chain = fx.compile_chain(fx.Effects(amplifier_bandwidth_hz=300.0, amplifier_damping_ratio=0.6,
                                        amplifier_slew_v_per_s=slew), DT)
    v = 1.0 + 20 * np.sin(2 * np.pi * 27.9 * np.arange(2000) * DT) ** 2
    out, _ = fx.lag(chain, fx.unlag_limited(chain, v, 1.0, np.inf), 1.0)
    plain, _ = fx.lag(chain, v, 1.0)
    inner = slice(0, -5)  # the target's rate after its end is unknown
    assert np.max(np.abs(out - v)[inner]) < 0.01 * np.max(np.abs(plain - v))


def test_slew_limited_unlag() -> None:
    """At a step it ramps at the step limit, then the amplifier output catches up with the
    target and follows it exactly again."""
    chain = fx.compile_chain(fx.Effects(amplifier_bandwidth_hz=500.0), DT)
    step = np.concatenate((np.zeros(50), np.full(400, 10.0)))
    cmd = fx.unlag_limited(chain, step, 0.0, 2.0)
    assert np.max(np.abs(np.diff(cmd, prepend=0.0))) <= 2.0 + 1e-12
    out, _ = fx.lag(chain, cmd, 0.0)
    np.testing.assert_allclose(out[200:], 10.0, atol=1e-9)


def test_remove_mode_inverts_add_mode() -> None:
    chain = fx.compile_chain(fx.Effects(second_mode=fx.SecondMode(600.0, 0.1, 0.4)), DT)
    u = _signal()
    w, _ = fx.add_mode(chain, u, fx.mode_rest(chain, u[0]))
    np.testing.assert_allclose(fx.remove_mode(chain, w), u, atol=1e-9)


@pytest.mark.parametrize("mode", [(600.0, 0.03, 0.4), (700.0, 0.03, 0.5)])
def test_remove_mode_stays_bounded_when_the_exact_inverse_is_unstable(
        mode: tuple[float, float, float]) -> None:
    """Lightly damped modes whose sampled 1 + mode has zeros outside the unit circle: the
    reflected inverse is bounded over 3 s and within 0.5 % of the range for content far below
    the mode (the exact inverse's error grows by |z|^n: 1e15 after 3 s)."""
    chain = fx.compile_chain(fx.Effects(second_mode=fx.SecondMode(*mode)), DT)
    b = np.concatenate((np.zeros(chain.mode_a.size - chain.mode_b.size), chain.mode_b))
    assert np.max(np.abs(np.roots(chain.mode_a + b))) > 1.0
    t = np.arange(30_000) * DT
    u = 20 * np.sin(2 * np.pi * 27.9 * t) + 5 * np.sin(2 * np.pi * 130 * t) + 3.0
    w, _ = fx.add_mode(chain, u, fx.mode_rest(chain, u[0]))
    assert np.max(np.abs(fx.remove_mode(chain, w) - u)) < 0.005 * np.ptp(u)


def test_second_mode_static_gain_and_resonance() -> None:
    f, zeta, g = 700.0, 0.02, 0.3
    chain = fx.compile_chain(fx.Effects(second_mode=fx.SecondMode(f, zeta, g)), DT)
    w, _ = fx.add_mode(chain, np.ones(20000), fx.mode_rest(chain, 0.0))
    assert w[-1] == pytest.approx(1 + g, rel=1e-9)  # x'' + ... = w^2 g u: static gain g
    ring = w[:4000] - (1 + g)
    peaks = np.flatnonzero((ring[1:-1] > ring[:-2]) & (ring[1:-1] > ring[2:])) + 1
    period = np.mean(np.diff(peaks[:6])) * DT
    assert 1 / period == pytest.approx(f * math.sqrt(1 - zeta ** 2), rel=0.01)


@pytest.mark.parametrize("e", [fx.Effects(sensor_quadratic_per_um=-2.5e-3),
                               fx.Effects(sensor_quadratic_per_um=1e-3, sensor_cubic_per_um2=-4e-5),
                               fx.Effects(sensor_cubic_per_um2=6e-5),
                               fx.Effects(sensor_quadratic_per_um=3e-3, sensor_cubic_per_um2=-5e-5,
                                          sensor_center_um=10.0, sensor_half_range_um=40.0)],
                         ids=["quadratic", "quadratic+cubic", "cubic", "centred"])
def test_ungauge_inverts_gauge(e: fx.Effects) -> None:
    w = np.linspace(-45, 50, 101)
    assert np.all(np.diff(fx.gauge(e, w)) > 0)  # a monotone gauge over this range
    np.testing.assert_allclose(fx.ungauge(e, fx.gauge(e, w)), w, atol=1e-10)


def test_a_centred_gauge_has_the_identity_as_its_linear_calibration() -> None:
    """Over the fitted range m +- R the error terms are Legendre polynomials: a straight line
    fitted through the readings against the position is the identity (a lab's linear gauge
    calibration), while the gauge is still curved (its error at the ends is c 2R^2/3 +- ...)."""
    m, r, c, c3 = -120.0, 35.0, 4e-3, -6e-5
    e = fx.Effects(sensor_quadratic_per_um=c, sensor_cubic_per_um2=c3, sensor_center_um=m,
                   sensor_half_range_um=r)
    w = np.linspace(m - r, m + r, 20001)
    slope, intercept = np.polyfit(w, fx.gauge(e, w), 1)
    assert slope == pytest.approx(1.0, abs=1e-4)  # uncentred: 1 + 3/5 c3 R^2 = 0.956
    assert intercept - m * (1 - slope) == pytest.approx(0.0, abs=1e-2)  # uncentred: 1.6 um
    ends = fx.gauge(e, np.array([m - r, m + r])) - np.array([m - r, m + r])
    np.testing.assert_allclose(ends, [c * 2 * r * r / 3 - c3 * 0.4 * r ** 3,
                                      c * 2 * r * r / 3 + c3 * 0.4 * r ** 3], rtol=1e-12)


@pytest.mark.parametrize(("d", "tol"), [(0.0, 1e-12), (3.0, 1e-12), (2.4, 0.02)])
def test_delay_is_a_shift_and_advance_undoes_it(d: float, tol: float) -> None:
    """Whole samples shift exactly; a fractional delay interpolates linearly (twice, there and
    back: error <= f (1 - f) max|x''| / 2 per pass, 0.01 um for this signal)."""
    chain = fx.compile_chain(fx.Effects(sensor_delay_samples=d), DT)
    x = _signal()
    _, hist = fx.rest(chain, float(x[0]))
    late, _ = fx.delay(x, d, hist)
    k = np.arange(x.size) - d
    np.testing.assert_allclose(late[5:], np.interp(k, np.arange(x.size), x)[5:], atol=1e-12)
    np.testing.assert_allclose(fx.advance(late, d)[5:-5], x[5:-5], atol=tol)


def test_a_delay_in_seconds_is_the_same_time_at_any_rate() -> None:
    """0.6 ms of latency: 6 samples at 10 kHz, 3 at 5 kHz; added to a latency in samples."""
    e = fx.Effects(sensor_delay_samples=1.0, sensor_delay_s=6e-4)
    assert fx.compile_chain(e, 1e-4).delay_samples == pytest.approx(7.0)
    assert fx.compile_chain(e, 2e-4).delay_samples == pytest.approx(4.0)
    chain = fx.compile_chain(e, 2e-4)
    u = np.sin(np.arange(200) * 0.05)
    y, _, _ = fx.measure(chain, u, *fx.rest(chain, float(u[0])))
    np.testing.assert_allclose(y[4:], u[:-4], atol=1e-12)


@pytest.mark.parametrize(("d", "w"), [(0.0, 4.0), (2.3, 7.6)])
def test_an_averaging_window_is_the_mean_over_it(d: float, w: float) -> None:
    """An integrating converter: the reading is the mean of the (linearly interpolated) position
    over ``[t - d - w, t - d]``, against the closed form for a sine; in pieces it equals at
    once, and sensor_correct advances it by its mean delay ``d + w / 2``."""
    dt, f = 1e-4, 37.0
    e = fx.Effects(sensor_delay_s=d * dt, sensor_window_s=w * dt)
    chain = fx.compile_chain(e, dt)
    assert chain.history >= d + w + 1
    t = np.arange(3000) * dt
    u = np.sin(2 * np.pi * f * t)
    y, _, _ = fx.measure(chain, u, *fx.rest(chain, float(u[0])))
    a, b = 2 * np.pi * f * (t - d * dt - w * dt), 2 * np.pi * f * (t - d * dt)
    exact = (np.cos(a) - np.cos(b)) / (2 * np.pi * f * w * dt)
    np.testing.assert_allclose(y[20:], exact[20:], atol=1e-4)  # the interpolant: w^2 dt^2 / 8
    hist = fx.rest(chain, float(u[0]))[1]
    first, h = fx.late(u[:1111], chain.delay_samples, chain.window_samples, hist)
    rest, _ = fx.late(u[1111:], chain.delay_samples, chain.window_samples, h)
    np.testing.assert_allclose(np.concatenate((first, rest)), y, atol=1e-12)
    back = fx.sensor_correct(chain, y)
    assert np.max(np.abs(back - u)[50:-50]) < 0.01  # the window's smoothing stays


def test_a_vanishing_window_is_a_delay() -> None:
    """Windows down to nothing join the pure delay smoothly (no rounding blow-up of the two
    running integrals' difference)."""
    x = _signal()
    hist = np.full(8, float(x[0]))
    pure, _ = fx.delay(x, 2.5, hist)
    for w in (1e-12, 1e-3, 0.02):
        np.testing.assert_allclose(fx.late(x, 2.5 - w / 2, w, hist)[0], pure, atol=1e-6)


def test_delay_in_pieces_equals_delay_at_once() -> None:
    chain = fx.compile_chain(fx.Effects(sensor_delay_samples=2.5), DT)
    x = _signal()
    _, hist = fx.rest(chain, float(x[0]))
    whole, _ = fx.delay(x, 2.5, hist)
    a, h = fx.delay(x[:1234], 2.5, hist)
    b, _ = fx.delay(x[1234:], 2.5, h)
    np.testing.assert_allclose(np.concatenate((a, b)), whole, atol=1e-12)


def test_sensor_correct_inverts_the_sensor_and_position_adds_the_mode() -> None:
    e = fx.Effects(sensor_delay_samples=3.0, sensor_quadratic_per_um=1e-3,
                   second_mode=fx.SecondMode(800.0, 0.03, 0.2))
    chain = fx.compile_chain(e, DT)
    u = _signal()
    read, _, _ = fx.measure(chain, u, *fx.rest(chain, float(u[0])))
    where = fx.position(chain, u)  # where the stage is: rod plus mode
    np.testing.assert_allclose(fx.sensor_correct(chain, read)[10:-10], where[10:-10], atol=1e-9)
    assert fx.sensor_part(e) == fx.Effects(sensor_delay_samples=3.0, sensor_quadratic_per_um=1e-3)


def test_gauge_about_a_centre_is_inverted() -> None:
    """``w + c (w - w_c)^2 + c3 (w - w_c)^3`` read back by :func:`afmctl.model.effects.ungauge` over a
    range centred far from 0 (300-420 um about 360 um; 5 % and 2.7 % errors at the ends)."""
    e = fx.Effects(sensor_quadratic_per_um=-1.5e-3, sensor_cubic_per_um2=-1.4e-5,
                   sensor_center_um=360.0)
    w = np.linspace(300.0, 420.0, 241)
    reading = w - 1.5e-3 * (w - 360.0) ** 2 - 1.4e-5 * (w - 360.0) ** 3
    np.testing.assert_allclose(fx.gauge(e, w), reading, rtol=1e-14)
    np.testing.assert_allclose(fx.ungauge(e, reading), w, atol=1e-9)


@pytest.mark.parametrize("zeta", [None, 0.7])
def test_unlag_keeps_to_the_voltage_range(zeta: float | None) -> None:
    """A triangle turning at 1 V through a 90 Hz amplifier: the exact inverse leads the corner
    below 0 V; within a 0-150 V range the commands stay in it, and the output still turns."""
    chain = fx.compile_chain(fx.Effects(amplifier_bandwidth_hz=90.0, amplifier_damping_ratio=zeta),
                             DT)
    t = np.arange(3000) * DT
    v = 1.0 + 100 * np.abs(2 * ((t * 27.9 + 0.5) % 1.0) - 1)
    free = fx.unlag_limited(chain, v, float(v[0]), np.inf)
    kept = fx.unlag_limited(chain, v, float(v[0]), np.inf, (0.0, 150.0))
    assert free.min() < -1.0
    assert kept.min() >= 0.0 and kept.max() <= 150.0
    out, _ = fx.lag(chain, kept, float(v[0]))
    assert np.max(np.abs(out - v)[:-5]) < 0.5 * np.max(np.abs(fx.lag(chain, v, float(v[0]))[0] - v))


@pytest.mark.parametrize("bw", [None, 400.0])
def test_rails_clip_what_reaches_the_stack(bw: float | None) -> None:
    """A gain of 1.03 on a 0-150 V triangle through rails at 0 and 150 V: the output is the
    unrailed one wherever that stays inside, and the rail wherever it would not; the inverse
    aims at the rail where the target is beyond it."""
    rails = fx.Effects(amplifier_bandwidth_hz=bw, amplifier_rails_v=(0.0, 150.0))
    free = fx.compile_chain(fx.Effects(amplifier_bandwidth_hz=bw), DT)
    chain = fx.compile_chain(rails, DT)
    t = np.arange(3000) * DT
    v = 1.03 * 150 * np.abs(2 * ((t * 27.9 + 0.5) % 1.0) - 1)
    want, _ = fx.lag(free, v, 0.0)
    got, _ = fx.lag(chain, v, 0.0)
    assert want.max() > 150.0 and np.any(got == 150.0) and got.max() == 150.0
    inside = want <= 150.0
    np.testing.assert_array_equal(got[inside], want[inside])
    np.testing.assert_array_equal(got[~inside], 150.0)
    back, _ = fx.lag(chain, fx.unlag_limited(chain, v, 0.0, np.inf), 0.0)
    np.testing.assert_allclose(back, np.clip(v, 0.0, 150.0), atol=1e-9)
