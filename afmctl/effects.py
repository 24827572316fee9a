"""Effects a real stage adds to the paper's model: amplifier, sensor, structure, run-to-run gain.

The paper's model (13)+(16) maps the voltage on the stack to the displacement of the rod. Between
the DAQ's commanded sample and the recorded displacement a lab stage adds more, and the paper itself
names some of it (dynamics at high frequency, variation of the true applied voltage between
experiments). One signal chain serves three users: the emulated stage carries these effects as its
hidden truth (profile ``[emulator.effects.*]``), ``afmctl diagnose`` fits them as model extensions
and writes them into a model file (``[effects.*]``), and ``afmctl track`` inverts the ones it can.

Chain of one run, sample period ``dt`` (all units: V, um, s, Hz):

1. ``voltage_gain``: the stack sees ``g v_cmd`` with ``g = 1 + N(0, sigma)`` drawn once per run;
2. ``amplifier_lag``: first order, exact ZOH, ``v[k] = a v[k-1] + (1 - a) g v_cmd[k]``,
   ``a = exp(-2 pi f_a dt)``; or second order (``v'' + 2 zeta w v' + w^2 v = w^2 g v_cmd``,
   ``w = 2 pi f_a``, the same ZOH convention); either with its own slew limit (the output moves
   at most ``S dt`` per sample: an amplifier's current limit into the stack's capacitance);
3. the transducer (the paper's model) gives the rod displacement ``u``;
4. ``second_mode``: ``x'' + 2 zeta w x' + w^2 x = w^2 gain u``, ``w = 2 pi f_2``; ``w = u + x``;
5. ``sensor_nonlinearity``: the gauge reads ``w + c w^2 + c3 w^3`` (about a centre, with the
   linear trend taken out, for a fitted one: :func:`gauge`);
6. ``sensor_delay``: the recorder holds the reading of ``d = d_samples + d_s / dt`` samples
   earlier (fractional ``d`` by linear interpolation): a latency counted in samples (a digital
   pipeline) and one in seconds (the gauge's electronics), the same at any sample rate.

Steps 2 and 4 move the stage (the *plant*); steps 5 and 6 only misreport where it is (the
*sensor*). ``track`` therefore aims the stage's true position (rod plus second mode) through the
plant's inverse, and corrects the sensor's readings before it scores them.

Everything here is a pure function of its arguments; the emulator carries the filter states.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy import linalg, signal

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SecondMode:
    """A second mechanical mode driven by the main displacement.

    ``x'' + 2 zeta w x' + w^2 x = w^2 gain u`` with ``w = 2 pi frequency_hz``; ``x`` (um) is added.
    """

    frequency_hz: float
    damping_ratio: float
    gain: float


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
    sensor_delay_samples : float
        Pure latency of the sensor readback, samples (fractional: linear interpolation).
    sensor_delay_s : float
        Latency of the sensor readback in time, s (adds ``sensor_delay_s / dt`` samples).
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
    second_mode : SecondMode or None
    voltage_gain_sigma : float
        Applied-voltage gain is ``1 + N(0, sigma)``, drawn once per run. A model cannot know the
        gain of a future run: for a fitted model this is the spread seen between sweeps.

    Thermal relaxation is not here: it is the polarization kernel (``Polarization.thermal``).
    """

    amplifier_bandwidth_hz: float | None = None
    amplifier_damping_ratio: float | None = None
    amplifier_slew_v_per_s: float | None = None
    sensor_delay_samples: float = 0.0
    sensor_delay_s: float = 0.0
    sensor_quadratic_per_um: float = 0.0
    sensor_cubic_per_um2: float = 0.0
    sensor_center_um: float = 0.0
    sensor_half_range_um: float = 0.0
    second_mode: SecondMode | None = None
    voltage_gain_sigma: float = 0.0


@dataclass(frozen=True)
class Chain:
    """:class:`Effects` prepared for one sample period: filter coefficients."""

    effects: Effects
    dt: float
    lag_a: float
    mode_b: FloatArray
    mode_a: FloatArray
    amp_ad: FloatArray
    amp_bd: FloatArray

    @property
    def has_amplifier(self) -> bool:
        return self.effects.amplifier_bandwidth_hz is not None

    @property
    def amp_simple(self) -> bool:
        """A first-order amplifier without slew limit (an exact linear filter)."""
        e = self.effects
        return e.amplifier_damping_ratio is None and e.amplifier_slew_v_per_s is None

    @property
    def has_mode(self) -> bool:
        return self.mode_b.size > 0

    @property
    def delay_samples(self) -> float:
        """Sensor latency at this sample period, samples."""
        return self.effects.sensor_delay_samples + self.effects.sensor_delay_s / self.dt

    @property
    def history(self) -> int:
        """Samples of sensor history the delay line keeps."""
        d = self.delay_samples
        return math.ceil(d) + 1 if d > 0 else 0


def _amplifier_ss(effects: Effects, lag_a: float, dt: float) -> tuple[FloatArray, FloatArray]:
    """State update ``x[k] = Ad x[k-1] + Bd v_cmd[k]`` of the amplifier, ``x = (v, v')``."""
    zeta = effects.amplifier_damping_ratio
    if effects.amplifier_bandwidth_hz is None or zeta is None:
        return np.array([[lag_a, 0.0], [0.0, 0.0]]), np.array([1.0 - lag_a, 0.0])
    w = 2 * math.pi * effects.amplifier_bandwidth_hz
    m = np.zeros((3, 3))
    m[0, 1], m[1, 0], m[1, 1], m[1, 2] = 1.0, -w * w, -2 * zeta * w, w * w
    e = linalg.expm(m * dt)
    return e[:2, :2], e[:2, 2]


def compile_chain(effects: Effects, dt: float) -> Chain:
    """Coefficients of the amplifier lag and the second mode (exact ZOH) at period ``dt`` (s)."""
    bw = effects.amplifier_bandwidth_hz
    lag_a = 0.0 if bw is None else math.exp(-2 * math.pi * bw * dt)
    b, a = np.zeros(0), np.zeros(0)
    if effects.second_mode is not None:
        m = effects.second_mode
        w = 2 * math.pi * m.frequency_hz
        bd, ad, _ = signal.cont2discrete(([m.gain * w * w], [1.0, 2 * m.damping_ratio * w, w * w]),
                                         dt, method="zoh")
        b, a = np.ravel(bd), np.asarray(ad, dtype=float)
    return Chain(effects, dt, lag_a, b, a, *_amplifier_ss(effects, lag_a, dt))


@nb.njit(cache=True)
def _amplify(ad: FloatArray, bd: FloatArray, v: FloatArray, v0: float, max_step: float,
             rate: float) -> FloatArray:  # pragma: no cover - compiled
    y = np.empty(v.size)
    x0, x1 = v0, 0.0
    for k in range(v.size):
        n0 = ad[0, 0] * x0 + ad[0, 1] * x1 + bd[0] * v[k]
        n1 = ad[1, 0] * x0 + ad[1, 1] * x1 + bd[1] * v[k]
        if n0 - x0 > max_step:
            n0, n1 = x0 + max_step, rate
        elif x0 - n0 > max_step:
            n0, n1 = x0 - max_step, -rate
        x0, x1 = n0, n1
        y[k] = x0
    return y


def lag(chain: Chain, v: FloatArray, v_prev: float) -> tuple[FloatArray, float]:
    """Amplifier output for commanded ``v`` (V), from rest at output ``v_prev``; returns (v, last).

    A second-order amplifier starts at rest (no rate) on every call: call it once per run."""
    v = np.asarray(v, dtype=float)
    if not chain.has_amplifier or v.size == 0:
        return v, float(v[-1]) if v.size else v_prev
    if chain.amp_simple:
        a = chain.lag_a
        y, _ = signal.lfilter([1 - a], [1.0, -a], v, zi=[a * v_prev])
        return y, float(y[-1])
    slew = chain.effects.amplifier_slew_v_per_s
    rate = math.inf if slew is None else slew
    y = _amplify(chain.amp_ad, chain.amp_bd, v, float(v_prev), rate * chain.dt, rate)
    return y, float(y[-1])


def unlag_limited(chain: Chain, v_app: FloatArray, v_prev: float, max_step: float) -> FloatArray:
    """Commands (V) whose amplifier output follows ``v_app`` as closely as steps of at most
    ``max_step`` (V per sample) allow: the exact inverse of :func:`lag` sample by sample, each
    step clamped, the amplifier state following the clamped command (so it catches up after a
    corner). With an unbounded ``max_step`` it is the exact inverse.

    A second-order amplifier is inverted in continuous time, ``v + 2 zeta v' / w + v'' / w^2`` of
    the target (central differences; the target is known in advance) half a sample back (the
    middle of the held command's interval), each step clamped: not
    exact, but free of the sampled inverse's ringing (its zero near -1)."""
    v_app = np.asarray(v_app, dtype=float)
    if not chain.has_amplifier:
        return v_app
    zeta = chain.effects.amplifier_damping_ratio
    if zeta is not None:
        w = 2 * math.pi * float(chain.effects.amplifier_bandwidth_hz)  # type: ignore[arg-type]
        padded = np.concatenate(([v_prev], v_app, v_app[-1:]))
        d1 = np.gradient(padded, chain.dt)
        ideal = padded + 2 * zeta * d1 / w + np.gradient(d1, chain.dt) / (w * w)
        # the command held over (k-1, k] is the continuous inverse at its middle
        return _clamp_steps(0.5 * (ideal[1:-1] + ideal[:-2]), v_prev, max_step)
    a = chain.lag_a
    out = np.empty_like(v_app)
    cmd = out_prev = v_prev
    for k, target in enumerate(v_app):
        ideal = (target - a * out_prev) / (1 - a)
        cmd = min(max(ideal, cmd - max_step), cmd + max_step)
        out_prev = a * out_prev + (1 - a) * cmd
        out[k] = cmd
    return out


def _clamp_steps(v: FloatArray, v_prev: float, max_step: float) -> FloatArray:
    out = np.empty_like(v)
    cmd = v_prev
    for k, target in enumerate(v):
        cmd = min(max(float(target), cmd - max_step), cmd + max_step)
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


def _gauge_terms(effects: Effects) -> tuple[float, float, float, float]:
    """``(c, c3, m, r2)``: the gauge's coefficients, centre (um) and squared half range (um^2)."""
    return (effects.sensor_quadratic_per_um, effects.sensor_cubic_per_um2,
            effects.sensor_center_um, effects.sensor_half_range_um ** 2)


def gauge(effects: Effects, w: FloatArray) -> FloatArray:
    """Sensor reading of displacement ``w`` (um):
    ``w + c ((w - m)^2 - R^2/3) + c3 ((w - m)^3 - 3/5 R^2 (w - m))``."""
    c, c3, m, r2 = _gauge_terms(effects)
    if not c and not c3:
        return w
    x = w - m
    return w + c * (x * x - r2 / 3) + c3 * x * (x * x - 0.6 * r2)


#: Newton steps of :func:`ungauge` with a cubic term (quadratic convergence from the quadratic root).
UNGAUGE_STEPS = 6


def ungauge(effects: Effects, y: FloatArray) -> FloatArray:
    """Displacement (um) whose reading is ``y``: the root of :func:`gauge` ``= y`` nearest ``y``
    (closed form without a cubic term; else Newton from the quadratic's root)."""
    c, c3, m, r2 = _gauge_terms(effects)
    if not c and not c3:
        return y
    yc = y - m + c * r2 / 3
    x = 2.0 * yc / (1.0 + np.sqrt(np.maximum(1.0 + 4.0 * c * yc, 0.0)))
    if c3:
        for _ in range(UNGAUGE_STEPS):
            slope = 1.0 + 2.0 * c * x + c3 * (3.0 * x * x - 0.6 * r2)
            x = x - (x + c * x * x + c3 * x * (x * x - 0.6 * r2) - yc) / np.where(
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
    y, hist = delay(gauge(chain.effects, w), chain.delay_samples, history)
    return y, zf, hist


def sensor_part(e: Effects) -> Effects:
    """Only the effects that misreport the position (delay, gauge), not those that move it."""
    return Effects(sensor_delay_samples=e.sensor_delay_samples, sensor_delay_s=e.sensor_delay_s,
                   sensor_quadratic_per_um=e.sensor_quadratic_per_um,
                   sensor_cubic_per_um2=e.sensor_cubic_per_um2)


def sensor_correct(chain: Chain, reading_um: FloatArray) -> FloatArray:
    """The stage's position (um) from recorded readings: steps 6 and 5 inverted (the delay by a
    time advance, the gauge by its root). The readings themselves are never altered on disk."""
    return ungauge(chain.effects, advance(reading_um, chain.delay_samples))


def position(chain: Chain, u: FloatArray) -> FloatArray:
    """The stage's position (um): the rod displacement ``u`` plus its second mode, from rest."""
    return add_mode(chain, u, mode_rest(chain, float(u[0])))[0]
