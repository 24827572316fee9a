"""Effects a real stage adds to the paper's model: amplifier, sensor, structure, run-to-run gain.

The paper's model (13)+(16) maps the voltage on the stack to the displacement of the rod. Between
the DAQ's commanded sample and the recorded displacement a lab stage adds more, and the paper itself
names some of it (dynamics at high frequency, variation of the true applied voltage between
experiments). One signal chain serves three users: the emulated stage carries these effects as its
hidden truth (profile ``[emulator.effects.*]``), ``afmctl diagnose`` fits them as model extensions
and writes them into a model file (``[effects.*]``), and ``afmctl track`` inverts the ones it can.

Chain of one run, sample period ``dt`` (all units: V, um, s, Hz):

1. ``voltage_gain``: the stack sees ``g v_cmd`` with ``g = 1 + N(0, sigma)`` drawn once per run;
2. ``amplifier_lag``: first order (``v' = w (g v_cmd - v)``) or second order
   (``v'' + 2 zeta w v' + w^2 v = w^2 g v_cmd``), ``w = 2 pi f_a``, each command held over its
   sample (exact ZOH); the stack sees the output's mean over each sample (what the rod's ZOH
   model takes as held). Either with its own slew limit ``S``: the output rate saturates
   smoothly, ``v' = d / sqrt(1 + (d / S)^2)`` for the drive ``d`` the linear amplifier would
   slew at (an output stage's current limit into the stack's capacitance, reached gradually).
   With ``amplifier_rails`` the output never leaves its supply rails: a gain above 1 (a warm-up)
   flattens the top of a sweep that spans the range;
3. the transducer (the paper's model) gives the rod displacement ``u``;
4. ``second_mode``: ``x'' + 2 zeta w x' + w^2 x = w^2 gain u + 2 w rate_gain u'``,
   ``w = 2 pi f_2``; ``w = u + x``;
5. ``sensor_nonlinearity``: the gauge reads ``w + c w^2 + c3 w^3`` (about a centre, with the
   linear trend taken out, for a fitted one: :func:`gauge`);
6. ``sensor_delay``: the recorder holds the reading of ``d = d_samples + d_s / dt`` samples
   earlier (fractional ``d`` by linear interpolation): a latency counted in samples (a digital
   pipeline) and one in seconds (the gauge's electronics), the same at any sample rate; with
   an averaging window ``w`` (an integrating converter), the mean over ``[t - d - w, t - d]``.

Steps 2 and 4 move the stage (the *plant*); steps 5 and 6 only misreport where it is (the
*sensor*). ``track`` therefore aims the stage's true position (rod plus second mode) through the
plant's inverse, and corrects the sensor's readings before it scores them.

Everything here is a pure function of its arguments; the emulator carries the filter states.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy import linalg, signal

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SecondMode:
    """A second mechanical mode driven by the main displacement.

    ``x'' + 2 zeta w x' + w^2 x = w^2 gain u + 2 w rate_gain u'`` with ``w = 2 pi frequency_hz``;
    ``x`` (um) is added. The displacement's transfer function is then the rod's times
    ``(s^2 + 2 (zeta + rate_gain) w s + (1 + gain) w^2) / (s^2 + 2 zeta w s + w^2)``: a pole pair
    (the mode) and a zero pair (an anti-resonance) of their own frequencies and dampings, as a
    second mass coupled to the rod's end makes them (its reaction through spring and damper);
    ``rate_gain = 0`` is a mode driven through a spring alone (a base-excited mode).
    """

    frequency_hz: float
    damping_ratio: float
    gain: float
    rate_gain: float = 0.0


@dataclass(frozen=True)
class Effects:
    """Effects the base model lacks; each is off at its default.

    Parameters
    ----------
    amplifier_bandwidth_hz : float or None
        Amplifier lag: -3 dB frequency of the first order, or natural frequency of the second, Hz.
    amplifier_damping_ratio : float or None
        None: a first-order amplifier; else the damping ratio of a second-order one.
    amplifier_slew_v_per_s : float or None
        The amplifier's own slew limit, V/s (None: none).
    amplifier_rails_v : tuple of float or None
        The amplifier's output range ``(low, high)``, V: what reaches the stack is clipped there
        (None: no limit). With or without a lag.
    sensor_delay_samples : float
        Pure latency of the sensor readback, samples (fractional: linear interpolation).
    sensor_delay_s : float
        Latency of the sensor readback in time, s (adds ``sensor_delay_s / dt`` samples).
    sensor_window_s : float
        The sensor averages the position over this window, s (an integrating converter): the
        reading at ``t`` is the mean over ``[t - d - w, t - d]`` of the position (linear between
        samples), ``d`` the latency (:func:`late`).
    sensor_quadratic_per_um : float
        Gauge nonlinearity, quadratic term ``c`` (1/um): measured = ``w + c ((w - m)^2 - R^2/3)
        + c3 ((w - m)^3 - 3/5 R^2 (w - m))`` (:func:`gauge`).
    sensor_cubic_per_um2 : float
        Its cubic term c3, 1/um^2 (with ``c``, any smooth gauge error to third order about any
        point: the offset and the gain are the model's own).
    sensor_center_um, sensor_half_range_um : float
        Centre ``m`` and half width ``R`` (um) of the range the gauge was fitted on. The error terms
        are Legendre polynomials there: over ``m +- R`` they have no mean and no linear trend, so
        the best straight line through the readings against ``w`` is ``w`` itself (a lab's linear
        calibration of its gauge), and ``w`` is the position in that calibration's frame. With
        ``R = 0`` and ``m = 0``, ``w + c w^2 + c3 w^3``.
    sensor_third_moment_um3, sensor_fourth_moment_um4 : float
        Third and fourth central moments (um^3, um^4) of the positions the gauge was calibrated
        on, about ``m`` (their mean) with variance ``R^2/3``; ``0`` for the fourth: a uniform
        spread over ``m +- R`` (the Legendre terms above). With them the error terms are
        ``x^2 - mu2 - (mu3/mu2) x`` and ``x^3 - mu3 - (mu4/mu2) x`` (``x = w - m``): no mean and
        no linear trend over that very spread, so ``w`` is the frame of a least-squares line of
        the readings over the calibration sweep, whatever the sweep's distribution of positions.
    second_mode : SecondMode or None
    voltage_gain_sigma : float
        Applied-voltage gain is ``1 + N(0, sigma)``, drawn once per run. A model cannot know the
        gain of a future run: for a fitted model this is the spread seen between sweeps.

    Thermal relaxation is not here: it is the polarization kernel (``Polarization.thermal``).
    """

    amplifier_bandwidth_hz: float | None = None
    amplifier_damping_ratio: float | None = None
    amplifier_slew_v_per_s: float | None = None
    amplifier_rails_v: tuple[float, float] | None = None
    sensor_delay_samples: float = 0.0
    sensor_delay_s: float = 0.0
    sensor_window_s: float = 0.0
    sensor_quadratic_per_um: float = 0.0
    sensor_cubic_per_um2: float = 0.0
    sensor_center_um: float = 0.0
    sensor_half_range_um: float = 0.0
    sensor_third_moment_um3: float = 0.0
    sensor_fourth_moment_um4: float = 0.0
    second_mode: SecondMode | None = None
    voltage_gain_sigma: float = 0.0


@dataclass(frozen=True)
class Chain:
    """:class:`Effects` prepared for one sample period: filter coefficients.

    ``amp_ad``, ``amp_bd``: the amplifier's state ``(v, r)`` from one sample instant to the next
    under a held command; ``amp_ca``, ``amp_da``: the mean output over that interval (exact ZOH,
    the linear amplifier)."""

    effects: Effects
    dt: float
    lag_a: float
    mode_b: FloatArray
    mode_a: FloatArray
    amp_ad: FloatArray
    amp_bd: FloatArray
    amp_ca: FloatArray
    amp_da: float

    @property
    def has_amplifier(self) -> bool:
        return self.effects.amplifier_bandwidth_hz is not None

    @property
    def has_mode(self) -> bool:
        return self.mode_b.size > 0

    @property
    def delay_samples(self) -> float:
        """Sensor latency at this sample period, samples."""
        return self.effects.sensor_delay_samples + self.effects.sensor_delay_s / self.dt

    @property
    def window_samples(self) -> float:
        """The sensor's averaging window at this sample period, samples."""
        return self.effects.sensor_window_s / self.dt

    @property
    def history(self) -> int:
        """Samples of sensor history the delay line keeps."""
        d = self.delay_samples + self.window_samples
        return math.ceil(d) + 1 if d > 0 else 0


def _amplifier_matrix(effects: Effects) -> tuple[FloatArray, FloatArray]:
    """Continuous ``(A, B)`` of the linear amplifier on the state ``(v, r)``: ``v' = r``,
    ``r' = w^2 (u - v) - 2 zeta w r``; a first order (``v' = w (u - v)``) keeps ``r = 0``."""
    w = 2 * math.pi * float(effects.amplifier_bandwidth_hz or 0.0)
    zeta = effects.amplifier_damping_ratio
    if zeta is None:
        return np.array([[-w, 0.0], [0.0, 0.0]]), np.array([w, 0.0])
    return np.array([[0.0, 1.0], [-w * w, -2 * zeta * w]]), np.array([0.0, w * w])


def _amplifier_ss(effects: Effects, dt: float) -> tuple[FloatArray, FloatArray, FloatArray,
                                                        float]:
    """Exact ZOH of the linear amplifier over ``dt``: ``x[k+1] = Ad x[k] + Bd u[k]`` and the mean
    output over the interval ``Ca x[k] + Da u[k]`` (one matrix exponential of the system
    augmented with the held input and the output's integral)."""
    if effects.amplifier_bandwidth_hz is None:
        return np.eye(2), np.zeros(2), np.array([1.0, 0.0]), 0.0
    a, b = _amplifier_matrix(effects)
    m = np.zeros((4, 4))
    m[:2, :2], m[:2, 2], m[3, 0] = a, b, 1.0
    e = linalg.expm(m * dt)
    return e[:2, :2], e[:2, 2], e[3, :2] / dt, float(e[3, 2] / dt)


def compile_chain(effects: Effects, dt: float) -> Chain:
    """Coefficients of the amplifier lag and the second mode (exact ZOH) at period ``dt`` (s)."""
    bw = effects.amplifier_bandwidth_hz
    lag_a = 0.0 if bw is None else math.exp(-2 * math.pi * bw * dt)
    b, a = np.zeros(0), np.zeros(0)
    if effects.second_mode is not None:
        m = effects.second_mode
        w = 2 * math.pi * m.frequency_hz
        den = [1.0, 2 * m.damping_ratio * w, w * w]
        # ZOH is linear in the numerator: the spring and the damper terms discretized apart
        # (a numerator with a vanishing leading term is ill-conditioned for cont2discrete)
        b_u, ad, _ = signal.cont2discrete(([w * w], den), dt, method="zoh")
        b_du, _, _ = signal.cont2discrete(([2 * w, 0.0], den), dt, method="zoh")
        b = m.gain * np.ravel(b_u) + m.rate_gain * np.ravel(b_du)
        a = np.asarray(ad, dtype=float)
    return Chain(effects, dt, lag_a, b, a, *_amplifier_ss(effects, dt))


#: Most integration substeps per sample of a slew-limited amplifier; an amplifier that would need
#: more is so fast against the sample rate that its slew limit is treated as linear (its lag,
#: which the limit lengthens, is far below a sample).
MAX_SUBSTEPS = 48


@nb.njit(cache=True, nogil=True)
def _linear(ad: FloatArray, bd: FloatArray, ca: FloatArray, da: float, v: FloatArray,
            x0: float, x1: float) -> tuple[FloatArray, float]:  # pragma: no cover - compiled
    y = np.empty(v.size)
    for k in range(v.size):
        y[k] = ca[0] * x0 + ca[1] * x1 + da * v[k]
        x0, x1 = (ad[0, 0] * x0 + ad[0, 1] * x1 + bd[0] * v[k],
                  ad[1, 0] * x0 + ad[1, 1] * x1 + bd[1] * v[k])
    return y, x0


@nb.njit(cache=True, nogil=True)
def _slope(v: float, r: float, u: float, w: float, zeta: float, second: bool,
           slew: float) -> tuple[float, float]:  # pragma: no cover - compiled
    drive = r if second else w * (u - v)
    q = drive / slew
    dv = drive / math.sqrt(1.0 + q * q)
    dr = w * w * (u - v) - 2.0 * zeta * w * r if second else 0.0
    return dv, dr


@nb.njit(cache=True, nogil=True)
def _slewed(v: FloatArray, v0: float, w: float, zeta: float, second: bool, slew: float,
            dt: float, n_sub: int) -> tuple[FloatArray, float]:  # pragma: no cover - compiled
    y = np.empty(v.size)
    x, r, h = v0, 0.0, dt / n_sub
    for k in range(v.size):
        u, area = v[k], 0.0
        for _ in range(n_sub):  # RK4 on (v, r, integral of v)
            a0, b0 = _slope(x, r, u, w, zeta, second, slew)
            a1, b1 = _slope(x + 0.5 * h * a0, r + 0.5 * h * b0, u, w, zeta, second, slew)
            a2, b2 = _slope(x + 0.5 * h * a1, r + 0.5 * h * b1, u, w, zeta, second, slew)
            a3, b3 = _slope(x + h * a2, r + h * b2, u, w, zeta, second, slew)
            area += h * x + h * h / 6.0 * (a0 + a1 + a2)
            x += h / 6.0 * (a0 + 2.0 * a1 + 2.0 * a2 + a3)
            r += h / 6.0 * (b0 + 2.0 * b1 + 2.0 * b2 + b3)
        y[k] = area / dt
    return y, x


def _substeps(effects: Effects, dt: float) -> int:
    """RK4 substeps per sample for the slew-limited amplifier (0: too fast, treat as linear)."""
    w = 2 * math.pi * float(effects.amplifier_bandwidth_hz or 0.0)
    stiff = w * dt * max(1.0, 2.0 * (effects.amplifier_damping_ratio or 0.5))
    n = max(1, math.ceil(stiff / 0.5))
    return n if n <= MAX_SUBSTEPS else 0


def lag(chain: Chain, v: FloatArray, v_prev: float) -> tuple[FloatArray, float]:
    """Voltage on the stack (V) during each sample for commanded ``v`` (V), each command held
    over its sample: the amplifier's mean output over the interval (the rod's ZOH input), from
    rest at output ``v_prev``. Returns the voltages and the output at the end.

    With a slew limit ``S`` the output moves at ``v' = d / sqrt(1 + (d / S)^2)`` for a drive
    ``d`` (the rate the linear amplifier would have): a smooth current limit, linear for
    ``|d| << S``, never faster than ``S``. A second-order amplifier starts at rest (no rate) on
    every call: call it once per run. The output is clipped to the rails, if any (the state
    returned is the amplifier's own, before its output stage clips it)."""
    v = np.asarray(v, dtype=float)
    if not chain.has_amplifier or v.size == 0:
        return railed(chain.effects, v), float(v[-1]) if v.size else v_prev
    e = chain.effects
    n_sub = _substeps(e, chain.dt) if e.amplifier_slew_v_per_s is not None else 0
    if n_sub == 0:
        out, end = _linear(chain.amp_ad, chain.amp_bd, chain.amp_ca, chain.amp_da, v,
                           float(v_prev), 0.0)
    else:
        zeta = e.amplifier_damping_ratio
        out, end = _slewed(v, float(v_prev), 2 * math.pi * float(e.amplifier_bandwidth_hz),
                           zeta or 0.0, zeta is not None, float(e.amplifier_slew_v_per_s),
                           chain.dt, n_sub)
    return railed(e, out), end


def railed(effects: Effects, v: FloatArray) -> FloatArray:
    """``v`` (V) clipped to the amplifier's rails (unchanged without them)."""
    rails = effects.amplifier_rails_v
    return v if rails is None else np.clip(v, *rails)


def _rate_drive(rate: FloatArray, slew: float | None) -> FloatArray:
    """The drive ``d`` whose limited rate (:func:`lag`) is ``rate`` (V/s); rates beyond 99 % of
    the limit are out of reach and ask for the drive at 99 %."""
    if slew is None:
        return rate
    q = np.clip(rate / slew, -0.99, 0.99)
    return slew * q / np.sqrt(1 - q * q)


def unlag_limited(chain: Chain, v_app: FloatArray, v_prev: float, max_step: float,
                  v_range: tuple[float, float] = (-math.inf, math.inf)) -> FloatArray:
    """Commands (V) whose amplifier output (:func:`lag`) follows ``v_app`` as closely as steps of
    at most ``max_step`` (V per sample) and the voltage range ``v_range`` (V) allow, each command
    clamped (an inverse lag leads a corner by overshooting it: near the range's end that
    overshoot is cut, and the output rounds the corner instead).

    The amplifier is inverted in continuous time on the target (known in advance; central
    differences): ``v + d / w`` for a first order, ``v + (d' + 2 zeta w d) / w^2`` for a second,
    with ``d`` the drive that gives the target's rate through the slew limit (``d = v'`` without
    one). ``v_app[k]`` is the mean over sample ``k``'s interval, so the command held over it is
    the inverse at its middle, i.e. at ``k``. A first order without slew limit is inverted
    exactly, sample by sample (the amplifier state following the clamped command, so it
    catches up after a corner). A target beyond the rails is out of the amplifier's reach: it
    asks for the rail."""
    v_app = railed(chain.effects, np.asarray(v_app, dtype=float))
    if not chain.has_amplifier:
        return v_app
    e = chain.effects
    zeta = e.amplifier_damping_ratio
    if zeta is not None or e.amplifier_slew_v_per_s is not None:
        w = 2 * math.pi * float(e.amplifier_bandwidth_hz)  # type: ignore[arg-type]
        padded = np.concatenate(([v_prev], v_app, v_app[-1:]))
        drive = _rate_drive(np.gradient(padded, chain.dt), e.amplifier_slew_v_per_s)
        ideal = padded + (drive / w if zeta is None
                          else (np.gradient(drive, chain.dt) + 2 * zeta * w * drive) / (w * w))
        return _clamp_steps(ideal[1:-1], v_prev, max_step, v_range)
    a, c = chain.lag_a, float(chain.amp_ca[0])  # mean over a sample: c x[k] + (1 - c) v[k]
    out = np.empty_like(v_app)
    cmd = x = v_prev
    for k, target in enumerate(v_app):
        ideal = (target - c * x) / (1 - c)
        cmd = min(max(ideal, cmd - max_step, v_range[0]), cmd + max_step, v_range[1])
        x = a * x + (1 - a) * cmd
        out[k] = cmd
    return out


def _clamp_steps(v: FloatArray, v_prev: float, max_step: float,
                 v_range: tuple[float, float]) -> FloatArray:
    out = np.empty_like(v)
    cmd = v_prev
    for k, target in enumerate(v):
        cmd = min(max(float(target), cmd - max_step, v_range[0]), cmd + max_step, v_range[1])
        out[k] = cmd
    return out


def mode_rest(chain: Chain, u0: float) -> FloatArray:
    """Second-mode filter state at rest under a constant displacement ``u0`` (um)."""
    if not chain.has_mode:
        return np.zeros(2)
    return signal.lfilter_zi(chain.mode_b, chain.mode_a) * u0


def add_mode(chain: Chain, u: FloatArray, zi: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``u`` plus the second mode's displacement, and the filter state after it."""
    if not chain.has_mode:
        return u, zi
    x, zf = signal.lfilter(chain.mode_b, chain.mode_a, u, zi=zi)
    return u + x, zf


def remove_mode(chain: Chain, w: FloatArray) -> FloatArray:
    """The rod displacement whose sum with its second mode is ``w`` (um), from rest.

    The exact inverse of :func:`add_mode` is the filter ``a / (a + b)``. Sampling a lightly
    damped mode can put the zeros of ``a + b`` just outside the unit circle (600 Hz, damping
    0.03, gain 0.4 at 10 kHz), where that inverse grows without bound; such zeros ``z`` are
    replaced by ``1 / conj(z)`` (same DC gain): the magnitude response is kept exactly, the phase
    errs only near the mode's own frequency.
    """
    if not chain.has_mode:
        return w
    b = np.concatenate((np.zeros(chain.mode_a.size - chain.mode_b.size), chain.mode_b))
    den = chain.mode_a + b
    zeros = np.roots(den)
    outside = np.abs(zeros) >= 1.0
    if outside.any():
        zeros[outside] = 1.0 / np.conj(zeros[outside])
        stable = np.real(np.poly(zeros))
        den = stable * (np.sum(den) / np.sum(stable))
    zi = signal.lfilter_zi(chain.mode_a, den) * w[0]
    return signal.lfilter(chain.mode_a, den, w, zi=zi)[0]


def _gauge_terms(effects: Effects) -> tuple[float, float, float, FloatArray]:
    """``(c, c3, m, k)``: the gauge's coefficients, centre (um) and the frame's constants
    ``k = (k2, l2, k3, l3)`` of its terms ``x^2 - k2 - l2 x`` and ``x^3 - k3 - l3 x``."""
    r2 = effects.sensor_half_range_um ** 2
    mu2, mu3 = r2 / 3, effects.sensor_third_moment_um3
    mu4 = effects.sensor_fourth_moment_um4 or r2 * r2 / 5
    k = (np.array([mu2, mu3 / mu2, mu3, mu4 / mu2]) if mu2 > 0 else np.zeros(4))
    return (effects.sensor_quadratic_per_um, effects.sensor_cubic_per_um2,
            effects.sensor_center_um, k)


def gauge_terms(effects: Effects, w: FloatArray) -> FloatArray:
    """The gauge's two error terms at displacement ``w`` (um), shape (N, 2): ``x^2 - k2 - l2 x``
    (um^2) and ``x^3 - k3 - l3 x`` (um^3) with ``x = w - m``, orthogonal to a constant and to
    ``x`` over the calibration's spread (Legendre polynomials for a uniform one), which
    :func:`gauge` weighs by ``c`` and ``c3``."""
    _, _, m, (k2, l2, k3, l3) = _gauge_terms(effects)
    x = np.asarray(w, dtype=float) - m
    return np.column_stack((x * x - k2 - l2 * x, x * x * x - k3 - l3 * x))


def gauge(effects: Effects, w: FloatArray) -> FloatArray:
    """Sensor reading of displacement ``w`` (um): ``w + c P2(w - m) + c3 P3(w - m)``
    (:func:`gauge_terms`; for a uniform spread ``P2 = x^2 - R^2/3``, ``P3 = x^3 - 3/5 R^2 x``)."""
    c, c3, _, _ = _gauge_terms(effects)
    if not c and not c3:
        return w
    return w + gauge_terms(effects, w) @ np.array([c, c3])


def position_frame(effects: Effects, readings_um: FloatArray) -> tuple[float, float, Effects]:
    """The gauge of ``effects`` restated in the frame of a lab's linear calibration.

    A lab calibrates its gauge by the least-squares line of readings against position over a
    sweep. A gauge whose error terms are orthogonal to a line over the *readings*
    (:func:`gauge_terms` with the readings' moments, the frame a fit can state before it knows
    the positions) is off that frame at first order in the error (the gauge skews the readings'
    third moment). With the positions ``w = ungauge(y)`` of ``readings_um`` and the line
    ``y = A + B w`` over them, the positions ``w' = A + B w`` are the calibrated ones: the same
    readings come from ``gauge'(w') = gauge((w' - A) / B)``, a cubic whose error is orthogonal to
    1 and ``w'`` over those positions, so it is ``w' + c' P2 + c3' P3`` with ``P2``, ``P3`` of
    the positions' own moments and ``c'``, ``c3'`` its coefficients of ``x^2`` and ``x^3``.

    Parameters
    ----------
    effects : Effects
        With a gauge error.
    readings_um : ndarray
        The calibration sweep's readings, um.

    Returns
    -------
    offset_um, gain : float
        ``A`` (um) and ``B``: a displacement ``w`` of the old frame is ``A + B w`` in the new.
    effects : Effects
        ``effects`` with the gauge restated.
    """
    y = np.asarray(readings_um, dtype=float)
    w = ungauge(effects, y)
    gain, offset = (float(v) for v in np.polyfit(w, y, 1))
    x = offset + gain * w
    m = float(np.mean(x))
    mu2, mu3, mu4 = (float(np.mean((x - m) ** k)) for k in (2, 3, 4))
    pts = np.linspace(-2.0, 2.0, 9) * math.sqrt(mu2)  # a cubic: fitted exactly
    k3, k2, _, _ = np.polyfit(pts, gauge(effects, (m + pts - offset) / gain), 3)
    return offset, gain, replace(effects, sensor_quadratic_per_um=float(k2),
                                 sensor_cubic_per_um2=float(k3), sensor_center_um=m,
                                 sensor_half_range_um=math.sqrt(3 * mu2),
                                 sensor_third_moment_um3=mu3, sensor_fourth_moment_um4=mu4)


#: Newton steps of :func:`ungauge` with a cubic term (quadratic convergence from the quadratic root).
UNGAUGE_STEPS = 6


def ungauge(effects: Effects, y: FloatArray) -> FloatArray:
    """Displacement (um) whose reading is ``y``: the root of :func:`gauge` ``= y`` nearest ``y``
    (closed form without a cubic term; else Newton from the quadratic's root)."""
    c, c3, m, (k2, l2, k3, l3) = _gauge_terms(effects)
    if not c and not c3:
        return y
    yc = y - m + c * k2 + c3 * k3  # x + c (x^2 - l2 x) + c3 (x^3 - l3 x) = yc
    b = 1.0 - c * l2
    x = 2.0 * yc / (b + np.sqrt(np.maximum(b * b + 4.0 * c * yc, 0.0)))
    if c3:
        for _ in range(UNGAUGE_STEPS):
            slope = b + 2.0 * c * x + c3 * (3.0 * x * x - l3)
            x = x - (b * x + c * x * x + c3 * x * (x * x - l3) - yc) / np.where(
                np.abs(slope) > 1e-3, slope, 1e-3)
    return m + x


def delay(x: FloatArray, d: float, history: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``x`` seen ``d`` samples late; ``history`` holds the samples before ``x[0]`` (oldest first,
    length :attr:`Chain.history`). Returns the delayed signal and the new history."""
    if d <= 0:
        return x, history
    n = history.size
    full = np.concatenate((history, x))
    k = np.arange(n, full.size) - d
    lo = np.floor(k).astype(int)
    f = k - lo
    out = (1 - f) * full[lo] + f * full[np.minimum(lo + 1, full.size - 1)]
    return out, full[full.size - n:]


#: The shortest averaging window :func:`late` integrates over, samples.
MIN_WINDOW = 0.01


def late(x: FloatArray, d: float, window: float,
         history: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``x`` averaged over the ``window`` samples before ``d`` samples ago (``x`` linear between
    samples; the integral exact); ``history`` as for :func:`delay` (at least ``d + window + 1``
    samples). A window under :data:`MIN_WINDOW` samples is its mean delay, ``d + window / 2``
    (:func:`delay`: the difference of two running integrals would lose every digit to rounding;
    the mean delay is off by ``window^2 x'' / 24``). Returns the readings and the new history."""
    if window < MIN_WINDOW:
        return delay(x, d + 0.5 * max(window, 0.0), history)
    n = history.size
    full = np.concatenate((history, x))
    area = np.concatenate(([0.0], np.cumsum(0.5 * (full[1:] + full[:-1]))))

    def integral(k: FloatArray) -> FloatArray:  # of the linear interpolant, from sample 0 to k
        lo = np.minimum(np.floor(k).astype(int), full.size - 2)
        f = k - lo
        return area[lo] + f * full[lo] + 0.5 * f * f * (full[lo + 1] - full[lo])

    k = np.arange(n, full.size) - d
    return (integral(k) - integral(k - window)) / window, full[full.size - n:]


def advance(y: FloatArray, d: float) -> FloatArray:
    """``y`` seen ``d`` samples early (the last sample held): the inverse of :func:`delay` for
    a trajectory known in advance."""
    if d <= 0:
        return y
    k = np.arange(y.size) + d
    return np.interp(k, np.arange(y.size), y)


def rest(chain: Chain, u0: float) -> tuple[FloatArray, FloatArray]:
    """Second-mode state and delay history of a stage at rest at rod displacement ``u0`` (um)."""
    zi = mode_rest(chain, u0)
    w0, _ = add_mode(chain, np.array([u0]), zi)
    return zi, np.full(chain.history, float(gauge(chain.effects, w0)[0]))


def measure(chain: Chain, u: FloatArray, mode_zi: FloatArray,
            history: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Steps 4-6 of the chain: rod displacement ``u`` (um) to the recorded reading (um).

    Returns the reading, the second-mode state and the delay history after the last sample.
    """
    w, zf = add_mode(chain, u, mode_zi)
    y, hist = late(gauge(chain.effects, w), chain.delay_samples, chain.window_samples, history)
    return y, zf, hist


def sensor_part(e: Effects) -> Effects:
    """Only the effects that misreport the position (delay, gauge: the ``sensor_`` fields), not
    those that move it."""
    return Effects(**{f.name: getattr(e, f.name) for f in fields(Effects)
                      if f.name.startswith("sensor_")})


def sensor_correct(chain: Chain, reading_um: FloatArray) -> FloatArray:
    """The stage's position (um) from recorded readings: steps 6 and 5 inverted (the delay by a
    time advance, the gauge by its root; an averaging window by an advance of half its width,
    its mean delay: its smoothing is not undone). The readings themselves are never altered on
    disk."""
    return ungauge(chain.effects, advance(reading_um, chain.delay_samples
                                          + 0.5 * chain.window_samples))


def position(chain: Chain, u: FloatArray) -> FloatArray:
    """The stage's position (um): the rod displacement ``u`` plus its second mode, from rest."""
    return add_mode(chain, u, mode_rest(chain, float(u[0])))[0]
