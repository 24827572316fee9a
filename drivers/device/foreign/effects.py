"""Hidden effects of the foreign plant: each a frozen dataclass, each off unless a stage carries it.

Every effect is made by a formula family other than the one a naive candidate would fit
(a first-order amplifier, an integer sample shift, the relay kernel with a drifting threshold, a
single added resonance, a quadratic gauge, one gain per sweep).

==========================  =======================  ==========================================
cause                       dataclass                physics
==========================  =======================  ==========================================
``amplifier-lag``           :class:`Amplifier`       2nd-order low-pass with a slew-rate limit
``sensor-delay``            :class:`SensorLatency`   2nd-order anti-alias filter + continuous delay
``thermal-relaxation``      :class:`Thermal`         Arrhenius switching (6)-(10) per hysteron
``second-mode``             :class:`SecondMass`      a second mass coupled to the rod (2 DOF)
``sensor-nonlinearity``     :class:`GaugePolynomial` quadratic and cubic gauge error
``voltage-gain-drift``      :class:`GainDrift`       random per-run gain and a systematic drift
``backlash``                :class:`Backlash`        play (dead band) in the stage linkage
``gauge-saturation``        :class:`GaugeSaturation` soft clipping of the gauge past a knee
``interference``            :class:`Interference`    mains hum + harmonics, periodic spikes
==========================  =======================  ==========================================

The last three are outside afmctl's diagnosis vocabulary (``OUT_OF_VOCABULARY``).

Strength
--------
``random_effect`` draws an effect at a strength ``s`` in [0, 1], every parameter interpolated
log-linearly between its two ends. ``s = 0`` was calibrated to be barely detectable, ``s = 1`` is
strong. Measured as an ideal refit: the clean plant itself (material, rod and an offset, started
at the truth) fitted by least squares to the three standard sweeps of a random stage carrying the
effect; worst sweep's RMS over the sensor noise, two stages at ``s = 0``, one at ``s = 1``:

======================  ==========  =====  ======================  ==========  =====
cause                   s = 0       s = 1  cause                   s = 0       s = 1
======================  ==========  =====  ======================  ==========  =====
amplifier-lag           4.1, 3.4    172    voltage-gain-drift      1.3, 1.7    58
sensor-delay            2.6, 1.8    134    backlash                2.3, 2.0    28
thermal-relaxation      1.6, 3.3    105    gauge-saturation        2.1, 4.6    51
second-mode             1.9, 1.0    13     interference            2.8, 3.0    29
sensor-nonlinearity     1.9, 1.2    18
======================  ==========  =====  ======================  ==========  =====

(A real identification, which does not start at the truth, will not do better.) The ends, with
sigma the sensor noise and ``tau_3`` the lag that shifts the fast standard triangle (27.9 Hz over
the static span) by 3 sigma:

- amplifier-lag: low-pass lag ``2 zeta / w`` from ``tau_3`` or the lag at 3x the rod's
  resonance, whichever is longer (the issue's bandwidths: 0.2-3x the resonance), to the lag at
  0.2x the rod's resonance; slew limit 300 -> 60 x the drive span per second;
- sensor-delay: total latency (filter + delay) from ``tau_3`` to 3 ms (30 samples at 10 kHz); the
  anti-alias cut-off takes half of it (1.5-100 kHz), the pure delay the rest;
- thermal-relaxation: E_T from 0.002 to 0.08 x the median coercive field; attempt rate
  10^3-10^5 /s (drawn);
- second-mode: secondary mass 0.03 -> 0.5 x the rod's, its damping 0.1 -> 0.02; its own frequency
  1.5-4 x the rod's resonance (drawn);
- sensor-nonlinearity: error at the range end 15 -> 300 sigma, split at random between the
  quadratic and cubic terms, random signs;
- voltage-gain-drift: per-run sigma from 3 sigma over the static span (0.01-0.4 %) to 3 %,
  systematic drift 0.5-1 x that per run;
- backlash: play 6 -> 100 sigma;
- gauge-saturation: compression at the range end 8 -> 300 sigma, knee at 60-85 % of the half range;
- interference: hum 3 -> 30 sigma (harmonics 2 and 3 at 20-60 % and 10-40 %), half the draws with
  spikes of 10x the hum every 50-330 ms.

The issue's physical ranges hold at the strong end; to be barely detectable the amplifier's
bandwidth goes above 3x the resonance and the latency below one sample at ``s`` near 0.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from afmctl.drivers.device.foreign import kernel as fk

if TYPE_CHECKING:
    from afmctl.drivers.device.foreign.stage import Stage


@dataclass(frozen=True)
class Amplifier:
    """Voltage amplifier: a second-order low-pass whose output slews at most ``slew_V_per_s``.

    ``v' = S tanh(w_v / S)``, ``w_v' = w^2 (g V - v) - 2 zeta w w_v`` with
    ``w = 2 pi bandwidth_hz``: the textbook low-pass while ``|w_v| << S``, a ramp at rate ``S``
    after a large step.

    Parameters
    ----------
    bandwidth_hz : float
        Natural frequency of the low-pass, Hz.
    damping : float
        Its damping ratio (0.5-0.9).
    slew_V_per_s : float
        Slew-rate limit of the output, V/s.
    """

    bandwidth_hz: float
    damping: float
    slew_V_per_s: float


@dataclass(frozen=True)
class SensorLatency:
    """Sensor electronics: a second-order Butterworth anti-alias filter, then a pure delay.

    Parameters
    ----------
    delay_s : float
        Continuous latency, s (any fraction of a sample).
    antialias_hz : float
        Cut-off of the anti-alias filter, Hz (0: no filter).
    """

    delay_s: float
    antialias_hz: float


@dataclass(frozen=True)
class Thermal:
    """Thermally activated switching of every hysteron (paper (6)-(10)).

    Parameters
    ----------
    thermal_field_MVm : float
        ``E_T = sqrt(eta k T / V)``, MV/m: the width over which a hysteron switches ahead of its
        coercive field; the energy barrier is ``(E_c - E_e)^2 / (2 eta)``, i.e. ``z^2/2`` in
        units of ``kT/V`` with ``z = (E_c - E_e) / E_T``.
    attempt_rate_hz : float
        ``nu0``, 1/s: the prefactor of the switching likelihoods (8).
    """

    thermal_field_MVm: float
    attempt_rate_hz: float


@dataclass(frozen=True)
class SecondMass:
    """A secondary mass ``mass_ratio * m`` (a sample holder, the next axis, the frame) joined to
    the rod's end by a spring and a damper: a second mechanical mode.

    The sensor reads (and the stage positions) the rod's end; the secondary mass acts on it
    through the coupling. Alone on its spring it would resonate at ``frequency_ratio`` times the
    rod's resonance with damping ratio ``damping``; coupled, the two modes split
    (see :func:`mode_frequencies_hz`), the more the heavier the mass.
    """

    mass_ratio: float
    frequency_ratio: float
    damping: float


@dataclass(frozen=True)
class GaugePolynomial:
    """Gauge error ``s = x + R (q2 y^2 + q3 y^3)`` with ``y = (x - center_um) / R``.

    ``R = half_range_um``; ``quadratic`` (q2) and ``cubic`` (q3) are the errors at the range
    end as fractions of ``R``.
    """

    center_um: float
    half_range_um: float
    quadratic: float
    cubic: float


@dataclass(frozen=True)
class GainDrift:
    """The applied voltage is ``g V`` with ``g = (1 + per_run n)(1 + sigma N(0,1))(1 + per_second t)``.

    ``n`` counts runs started with :func:`afmctl.drivers.device.foreign.stage.start_run`, the normal draw is
    made there (one per run), ``t`` is the device time, s.
    """

    sigma: float
    per_run: float
    per_second: float = 0.0


@dataclass(frozen=True)
class Backlash:
    """Play of ``gap_um`` in the linkage: the platform follows the rod only when pushed."""

    gap_um: float


@dataclass(frozen=True)
class GaugeSaturation:
    """The gauge compresses past ``knee_um`` from ``center_um``:
    ``s = c + sign(d) (K + W tanh((|d| - K) / W))`` for ``|d| > K`` (``d = x - c``)."""

    center_um: float
    knee_um: float
    softness_um: float


@dataclass(frozen=True)
class Interference:
    """Pick-up on the sensor line, added to the reading as a function of device time.

    ``sum_h A_h sin(2 pi h f t + phi_h)`` over harmonics ``h = 1, 2, ...`` of the mains
    frequency ``f``, plus spikes ``A_s exp(-(t - t_n) / tau)`` at ``t_n = phase + n T``.
    """

    mains_hz: float
    amplitudes_um: tuple[float, ...]
    phases_rad: tuple[float, ...]
    spike_um: float = 0.0
    spike_period_s: float = 1.0
    spike_decay_s: float = 2e-4
    spike_phase_s: float = 0.0


Effect = (Amplifier | SensorLatency | Thermal | SecondMass | GaugePolynomial | GainDrift
          | Backlash | GaugeSaturation | Interference)

CAUSES = {
    "amplifier-lag": Amplifier, "sensor-delay": SensorLatency, "thermal-relaxation": Thermal,
    "second-mode": SecondMass, "sensor-nonlinearity": GaugePolynomial,
    "voltage-gain-drift": GainDrift, "backlash": Backlash, "gauge-saturation": GaugeSaturation,
    "interference": Interference,
}
OUT_OF_VOCABULARY = ("backlash", "gauge-saturation", "interference")


def cause_of(effect: Effect) -> str:
    """The cause name of an effect instance."""
    return next(name for name, cls in CAUSES.items() if isinstance(effect, cls))


def _span(lo: float, hi: float, s: float) -> float:
    """Log-linear interpolation from ``lo`` (s = 0) to ``hi`` (s = 1)."""
    return float(lo * (hi / lo) ** s)


def mode_frequencies_hz(stage: Stage, mode: SecondMass) -> tuple[float, float]:
    """Undamped natural frequencies of the rod coupled to the second mass, Hz (lower, upper)."""
    m1, k1 = stage.rod.mass_kg, stage.rod.stiffness_N_m
    m2 = mode.mass_ratio * m1
    k2 = m2 * (2 * math.pi * mode.frequency_ratio * stage.rod.resonance_hz) ** 2
    mass = np.diag([m1, m2])
    stiff = np.array([[k1 + k2, -k2], [-k2, k2]])
    w2 = np.sort(np.linalg.eigvals(np.linalg.solve(mass, stiff)).real)
    return float(np.sqrt(w2[0]) / (2 * math.pi)), float(np.sqrt(w2[1]) / (2 * math.pi))


FAST_SWEEP_HZ = 27.9  # the fast standard triangle, on which lags show first
MAX_AMPLIFIER_HZ = 25_000.0  # fastest amplifier drawn (it costs substeps)
MAX_ANTIALIAS_HZ = 100_000.0  # (integrated exactly: costs nothing)


def _weak_lag_s(stage: Stage) -> float:
    """A lag that shifts the fast standard triangle's reading by ~3 sensor noise sigmas, s."""
    lo, hi = stage.static_range_um
    return 3.0 * stage.sensor.noise_um / ((hi - lo) * 2.0 * FAST_SWEEP_HZ)


def _amplifier(rng, stage, s):
    zeta = float(rng.uniform(0.5, 0.9))
    strong, weak = (2 * zeta / (2 * math.pi * r * stage.rod.resonance_hz) for r in (0.2, 3.0))
    lag = _span(max(_weak_lag_s(stage), weak), strong, s)  # bandwidth 3x -> 0.2x the resonance
    span = stage.drive_range_V[1] - stage.drive_range_V[0]
    return Amplifier(bandwidth_hz=min(MAX_AMPLIFIER_HZ, 2 * zeta / (2 * math.pi * lag)),
                     damping=zeta, slew_V_per_s=span * _span(300.0, 60.0, s))


def _latency(rng, stage, s):
    total = _span(_weak_lag_s(stage), 3e-3, s)  # up to 30 samples at 10 kHz
    f_aa = min(MAX_ANTIALIAS_HZ, max(1500.0, math.sqrt(2) / (2 * math.pi * 0.5 * total)))
    return SensorLatency(delay_s=max(0.0, total - math.sqrt(2) / (2 * math.pi * f_aa)),
                         antialias_hz=f_aa)


def _thermal(rng, stage, s):
    return Thermal(thermal_field_MVm=stage.material.coercive_median_MVm * _span(0.002, 0.08, s),
                   attempt_rate_hz=float(10 ** rng.uniform(3.0, 5.0)))


def _second(rng, stage, s):
    return SecondMass(mass_ratio=_span(0.03, 0.5, s),
                      frequency_ratio=float(rng.uniform(1.5, 4.0)), damping=_span(0.1, 0.02, s))


def _gauge_range(stage):
    lo, hi = stage.static_range_um
    return 0.5 * (lo + hi), 0.5 * (hi - lo)


def _polynomial(rng, stage, s):
    center, half = _gauge_range(stage)
    eps = stage.sensor.noise_um * _span(15.0, 300.0, s) / half  # error at the range end / R
    frac = float(rng.uniform(0.3, 0.7))
    sign = rng.choice([-1.0, 1.0], size=2)
    return GaugePolynomial(center_um=center, half_range_um=half,
                           quadratic=float(sign[0] * eps * frac),
                           cubic=float(sign[1] * eps * (1 - frac)))


def _gain(rng, stage, s):
    lo, hi = stage.static_range_um
    sigma = _span(3.0 * stage.sensor.noise_um / (hi - lo), 0.03, s)
    return GainDrift(sigma=sigma, per_run=float(rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 1.0)
                                                 * sigma))


def _backlash(rng, stage, s):
    return Backlash(gap_um=stage.sensor.noise_um * _span(6.0, 100.0, s))


def _softness(excess: float, compression: float) -> float:
    """W with ``excess - W tanh(excess / W) = compression`` (0 < compression < excess)."""
    lo, hi = 1e-6 * excess, 1e6 * excess
    for _ in range(200):
        mid = math.sqrt(lo * hi)
        if excess - mid * math.tanh(excess / mid) > compression:
            lo = mid
        else:
            hi = mid
    return math.sqrt(lo * hi)


def _saturation(rng, stage, s):
    center, half = _gauge_range(stage)
    knee = half * float(rng.uniform(0.6, 0.85))
    squeeze = min(stage.sensor.noise_um * _span(8.0, 300.0, s), 0.6 * (half - knee))
    return GaugeSaturation(center_um=center, knee_um=knee,
                           softness_um=_softness(half - knee, squeeze))


def _interference(rng, stage, s):
    amp = stage.sensor.noise_um * _span(3.0, 30.0, s)
    amps = (amp, amp * float(rng.uniform(0.2, 0.6)), amp * float(rng.uniform(0.1, 0.4)))
    spiky = bool(rng.random() < 0.5)
    return Interference(mains_hz=float(rng.choice([50.0, 60.0])), amplitudes_um=amps,
                        phases_rad=tuple(float(p) for p in rng.uniform(0, 2 * math.pi, 3)),
                        spike_um=10.0 * amp if spiky else 0.0,
                        spike_period_s=float(1.0 / rng.uniform(3.0, 20.0)),
                        spike_phase_s=float(rng.uniform(0.0, 0.05)))


_DRAW = {
    "amplifier-lag": _amplifier, "sensor-delay": _latency, "thermal-relaxation": _thermal,
    "second-mode": _second, "sensor-nonlinearity": _polynomial, "voltage-gain-drift": _gain,
    "backlash": _backlash, "gauge-saturation": _saturation, "interference": _interference,
}


def random_effect(cause: str, rng: np.random.Generator, stage: Stage,
                  strength: float | None = None) -> Effect:
    """Draw one hidden effect of ``cause`` for ``stage``.

    Parameters
    ----------
    cause : str
        One of :data:`CAUSES`.
    rng : numpy.random.Generator
        Source of the random parameters.
    stage : Stage
        The stage the effect is made for (its resonance, range and noise set the scales).
    strength : float, optional
        0 (barely detectable) ... 1 (strong); drawn uniformly if None.

    Returns
    -------
    Effect
        A frozen dataclass; add it to a stage with ``with_effects``.
    """
    if cause not in _DRAW:
        raise ValueError(f"unknown cause {cause!r} (one of {', '.join(_DRAW)})")
    s = float(rng.uniform(0.0, 1.0)) if strength is None else float(strength)
    if not 0.0 <= s <= 1.0:
        raise ValueError(f"strength must be in [0, 1], got {s}")
    return _DRAW[cause](rng, stage, s)


def _pack_amp(par, eff: Amplifier, stage):
    w = 2 * math.pi * eff.bandwidth_hz
    par[fk.P_AMP], par[fk.P_AW], par[fk.P_AZ] = 1.0, w, eff.damping
    par[fk.P_SLEW] = eff.slew_V_per_s


def _pack_latency(par, eff: SensorLatency, stage):
    par[fk.P_DELAY] = eff.delay_s
    if eff.antialias_hz > 0:
        par[fk.P_AA], par[fk.P_AAW], par[fk.P_AAZ] = 1.0, 2 * math.pi * eff.antialias_hz, \
            1 / math.sqrt(2)


def _pack_thermal(par, eff: Thermal, stage):
    par[fk.P_THERM], par[fk.P_ET], par[fk.P_NU0] = 1.0, eff.thermal_field_MVm, \
        eff.attempt_rate_hz


def _pack_mass(par, eff: SecondMass, stage):
    m2 = eff.mass_ratio * stage.rod.mass_kg
    w2 = 2 * math.pi * eff.frequency_ratio * stage.rod.resonance_hz
    par[fk.P_TWO], par[fk.P_M2], par[fk.P_K2] = 1.0, m2, m2 * w2 * w2
    par[fk.P_C2] = 2 * eff.damping * m2 * w2


def _pack_poly(par, eff: GaugePolynomial, stage):
    par[fk.P_GPOLY], par[fk.P_GC], par[fk.P_GR] = 1.0, eff.center_um, eff.half_range_um
    par[fk.P_Q2], par[fk.P_Q3] = eff.quadratic, eff.cubic


def _pack_sat(par, eff: GaugeSaturation, stage):
    par[fk.P_GSAT], par[fk.P_SC], par[fk.P_SK], par[fk.P_SW] = (1.0, eff.center_um, eff.knee_um,
                                                                 eff.softness_um)


def _pack_drift(par, eff: GainDrift, stage):
    par[fk.P_GRATE] = eff.per_second


def _pack_play(par, eff: Backlash, stage):
    par[fk.P_PLAY] = eff.gap_um


_PACKERS: dict[type, Callable] = {Amplifier: _pack_amp, SensorLatency: _pack_latency, Thermal: _pack_thermal,
            SecondMass: _pack_mass, GaugePolynomial: _pack_poly, GaugeSaturation: _pack_sat,
            GainDrift: _pack_drift, Backlash: _pack_play}


def pack_effect(par: np.ndarray, effect: Effect, stage: Stage) -> None:
    """Write an effect's parameters into the kernel's parameter vector (see
    :mod:`afmctl.drivers.device.foreign.kernel`); interference acts outside the kernel and a run's
    gain through the state, so they write nothing or only their drift rate."""
    packer = _PACKERS.get(type(effect))
    if packer is not None:
        packer(par, effect, stage)


def interference_um(effect: Interference, time_s: np.ndarray) -> np.ndarray:
    """Pick-up added to the reading at the device times ``time_s`` (s), um."""
    out = np.zeros_like(time_s)
    for h, (a, p) in enumerate(zip(effect.amplitudes_um, effect.phases_rad, strict=True), 1):
        out += a * np.sin(2 * math.pi * h * effect.mains_hz * time_s + p)
    if effect.spike_um:
        since = np.mod(time_s - effect.spike_phase_s, effect.spike_period_s)
        out += effect.spike_um * np.exp(-since / effect.spike_decay_s)
    return out
