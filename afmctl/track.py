"""The tracking experiment of the paper's Section 6, as pure planning and scoring.

Planning turns a desired displacement trajectory into a voltage waveform per filter:

* Every waveform starts by **conditioning** the stage: one slow excursion from the present output to
  the upper and lower voltage limits and back. By the wiping-out property of the model (and of the
  material) this erases the memory of whatever the stage did before, so the model's state at the
  start of tracking is known rather than assumed. With a model's validity envelope (the voltage
  range it was identified on, :class:`afmctl.modelfile.Envelope`) the excursion stays inside it:
  a wider one could repole the material into a state the model never saw. A waveform whose
  tracking part leaves the envelope by more than 5 % of its span is refused
  (:class:`EnvelopeError`) unless extrapolation is asked for.
* ``inverse``: Algorithm 3 through the model. After conditioning, a ramp in displacement from the
  stage's output to the trajectory's first point (so the inverse carries the hysteresis state
  through it), the tracking part, then a raised-cosine ramp of the voltage back to the output.
  The inversion horizon ``d`` is searched upward from the smallest non-chattering one until the
  waveform passes the guard: a larger horizon rounds the triangle's corners instead of asking the
  amplifier for an impulse. A model with effects (:mod:`afmctl.effects`, from ``afmctl
  diagnose``) has the plant's inverted around Algorithm 3: the second mode on the target, the
  amplifier's lag on the voltage (its exact inverse, each step clamped to 95 % of the usable slew
  rate). Its sensor effects (delay, gauge error) do not move the stage: they correct the readings
  before scoring (:func:`afmctl.effects.sensor_correct`).
* ``linear``: the paper's baseline, a straight line fitted to the model's quasi-static
  voltage-displacement response over the same voltage range, with the same kind of ramps.

Timing: voltage sample k is held over [t_k, t_{k+1}); displacement sample k is read at t_k. So the
error at sample k is ``displacement[k] - desired[k]`` and sample k's voltage aims at ``desired[k+d]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.signal import sawtooth

from afmctl import effects as fx
from afmctl import guard
from afmctl import inverse as inv
from afmctl import rod as rd
from afmctl import transducer as tr
from afmctl.modelfile import Envelope
from afmctl.tomlfile import InputError

FloatArray = NDArray[np.float64]
HORIZONS = (1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 20, 24, 32, 48, 64)
FINE = 8  # sub-samples per sample when judging between samples
#: The amplifier-lag inverse may use this fraction of the usable slew rate.
LAG_STEP = 0.95
REACH_TOL_UM = 1e-3  # an inverse that misses its target by more hit the voltage limit


@dataclass(frozen=True)
class Desired:
    """A desired displacement trajectory sampled every ``dt_s`` seconds.

    Attributes
    ----------
    u_um : ndarray, shape (N,)
        Desired displacement at t = 0, dt, ..., um.
    period_s : float or None
        Period of a periodic trajectory (the first period is reported separately), s.
    amplitude_um : float
        Peak-to-peak amplitude, um: the scale of the % errors.
    label : str
    """

    dt_s: float
    u_um: FloatArray
    period_s: float | None
    amplitude_um: float
    label: str


def _samples(freq_hz: float, periods: float, dt_s: float) -> FloatArray:
    if not (freq_hz > 0 and periods > 0 and dt_s > 0):
        raise ValueError("frequency, periods and sample period must be > 0")
    return np.arange(int(round(periods / freq_hz / dt_s)) + 1) * dt_s


def triangle(freq_hz: float, amplitude_um: float, offset_um: float, periods: float,
             dt_s: float) -> Desired:
    """Triangle of peak-to-peak ``amplitude_um`` about ``offset_um``, starting at its minimum."""
    t = _samples(freq_hz, periods, dt_s)
    u = offset_um + 0.5 * amplitude_um * sawtooth(2 * np.pi * freq_hz * t, 0.5)
    return Desired(dt_s, u, 1 / freq_hz, amplitude_um,
                   f"triangle {freq_hz:g} Hz, {amplitude_um:g} um")


def sine(freq_hz: float, amplitude_um: float, offset_um: float, periods: float,
         dt_s: float) -> Desired:
    """Sine of peak-to-peak ``amplitude_um`` about ``offset_um``, starting at its minimum."""
    t = _samples(freq_hz, periods, dt_s)
    u = offset_um - 0.5 * amplitude_um * np.cos(2 * np.pi * freq_hz * t)
    return Desired(dt_s, u, 1 / freq_hz, amplitude_um, f"sine {freq_hz:g} Hz, {amplitude_um:g} um")


def from_samples(time_s: FloatArray, u_um: FloatArray, dt_s: float, label: str) -> Desired:
    """Any desired trajectory, linearly resampled onto the stage's clock."""
    t = np.arange(0.0, time_s[-1] - time_s[0] + dt_s / 2, dt_s)
    u = np.interp(t + time_s[0], time_s, u_um)
    return Desired(dt_s, u, None, float(np.ptp(u)), label)


@dataclass(frozen=True)
class Waveform:
    """A precomputed, guard-checked voltage waveform for one filter.

    ``desired_um`` is NaN on the conditioning and the ramps; ``tracking`` selects the tracking part.
    """

    filter: str
    dt_s: float
    voltage_v: FloatArray
    desired_um: FloatArray
    horizon: int | None
    tracking: slice = field(repr=False)

    @property
    def time_s(self) -> FloatArray:
        return np.arange(self.voltage_v.size) * self.dt_s

    @property
    def max_slew_v_per_ms(self) -> float:
        return float(guard.slew_v_per_ms(self.voltage_v, self.dt_s).max())


def raised_cosine(a: float, b: float, n: int) -> FloatArray:
    """``n`` samples from ``a`` (exclusive) to ``b`` (inclusive) along a half cosine."""
    s = np.arange(1, n + 1) / n
    return a + (b - a) * 0.5 * (1 - np.cos(np.pi * s))


def ramp_samples(delta: float, rate_per_s: float, dt_s: float, minimum_s: float = 0.05) -> int:
    """Samples for a raised-cosine ramp over ``delta`` whose peak rate is ``rate_per_s``."""
    return int(np.ceil(max(minimum_s, np.pi / 2 * abs(delta) / rate_per_s) / dt_s))


def conditioning(limits: guard.Limits, start_v: float, dt_s: float) -> FloatArray:
    """Slow raised-cosine excursion start -> v_max -> v_min -> start (V), at a quarter of the
    usable slew rate and at least 0.2 s a leg: it wipes out the hysteresis memory."""
    rate = 0.25 * limits.max_rate_v_per_ms * 1e3
    legs = ((start_v, limits.v_max), (limits.v_max, limits.v_min), (limits.v_min, start_v))
    return np.concatenate([raised_cosine(a, b, ramp_samples(b - a, rate, dt_s, 0.2))
                           for a, b in legs])


def _assemble(name: str, desired: Desired, ramp_in: FloatArray, v_track: FloatArray,
              ramp_out: FloatArray, horizon: int | None) -> Waveform:
    n_in, n_tr = ramp_in.size, v_track.size
    v = np.concatenate([ramp_in, v_track, ramp_out])
    d = np.full(v.size, np.nan)
    d[n_in:n_in + n_tr] = desired.u_um
    return Waveform(name, desired.dt_s, v, d, horizon, slice(n_in, n_in + n_tr))


def plan_inverse(cm: tr.Compiled, desired: Desired, limits: guard.Limits, start_v: float,
                 state: tr.StageState, prefix_v: FloatArray) -> Waveform:
    """Algorithm 3 waveform with the smallest horizon that passes the guard.

    ``prefix_v`` (the conditioning) is played first; ``state`` is the model state after it.

    Raises
    ------
    guard.LimitError
        If no horizon up to 64 samples gives a waveform within the limits.
    """
    dt = desired.dt_s
    rate = 0.25 * limits.max_rate_v_per_ms * 1e3  # V/s for the ramps
    chain = fx.compile_chain(cm.model.effects, dt)
    rod0 = float(tr.simulate(cm, np.array([start_v]), state)[0][0])
    u0 = float(fx.position(chain, np.array([rod0]))[0])  # rod plus second mode
    gain = _linear_from_model(cm, state, limits).gain_um_per_v
    n_in = ramp_samples(desired.u_um[0] - u0, rate * abs(gain), dt)
    target = np.concatenate([raised_cosine(u0, desired.u_um[0], n_in), desired.u_um[1:],
                             desired.u_um[-1:]])
    target = fx.remove_mode(chain, target)  # what the rod must do for the stage to be there
    e_max = max(abs(limits.v_min), abs(limits.v_max)) / cm.model.thickness_um
    d0 = rd.smooth_horizon(cm.disc)
    last: guard.LimitError | None = None
    best: tuple[float, Waveform] | None = None
    for d in (h for h in HORIZONS if h >= d0):
        res = inv.algorithm3(cm, target, state, e_init=start_v / cm.model.thickness_um,
                             horizon=d, e_max=e_max)
        short = int(np.argmax(res.error))
        if res.error[short] > REACH_TOL_UM:
            raise guard.LimitError(
                f"the trajectory is out of the stage's reach: at sample {short} the model falls "
                f"{res.error[short]:.3f} um short at the voltage limit; reduce amplitude or offset")
        v = fx.unlag_limited(chain, res.voltage(cm.model.thickness_um), start_v,
                             LAG_STEP * limits.max_rate_v_per_ms * 1e3 * dt)  # amplifier lag
        v_in, v_tr = np.concatenate([prefix_v, v[:n_in]]), v[n_in:]
        out = raised_cosine(v_tr[-1], start_v, ramp_samples(v_tr[-1] - start_v, rate, dt))
        wf = _assemble("inverse", desired, v_in, v_tr, out, d)
        try:
            guard.check(wf.voltage_v, dt, limits, start_v, "inverse waveform")
        except guard.LimitError as exc:
            last = exc
            continue
        if chain.lag_a == 0.0:
            return wf
        # with an amplifier lag the slew limit clamps the lead at the corners: a longer horizon
        # asks for less of it but rounds the corners; keep the one the model says tracks best
        u = tr.simulate(cm, fx.lag(chain, v, start_v)[0], state)[0]
        err = _rms(u[1:] - target[:-1])  # target[k] is for sample k + 1
        if best is not None and err >= best[0]:
            return best[1]
        best = (err, wf)
    if best is not None:
        return best[1]
    raise guard.LimitError(f"no inversion horizon up to {HORIZONS[-1]} samples keeps the "
                           f"waveform within limits; last: {last}")


def _linear_from_model(cm: tr.Compiled, state: tr.StageState, limits: guard.Limits,
                       v_lo: float | None = None, v_hi: float | None = None) -> inv.LinearFilter:
    """Line through the model's quasi-static (0.279 Hz) response over [v_lo, v_hi]."""
    lo = limits.v_min if v_lo is None else v_lo
    hi = limits.v_max if v_hi is None else v_hi
    dt = 1e-3
    t = np.arange(0, 2 / 0.279, dt)
    v = 0.5 * (hi + lo) + 0.5 * (hi - lo) * sawtooth(2 * np.pi * 0.279 * t + np.pi / 2, 0.5)
    slow = tr.compile_model(cm.model, dt)
    u, _, _ = tr.simulate(slow, v, state)
    half = t >= 1 / 0.279  # the second, settled period
    return inv.fit_linear(v[half], u[half])


def plan_linear(cm: tr.Compiled, desired: Desired, limits: guard.Limits, start_v: float,
                state: tr.StageState, v_range: tuple[float, float],
                prefix_v: FloatArray) -> Waveform:
    """The paper's linear filter over the voltage range ``v_range`` the inverse filter needs."""
    lin = _linear_from_model(cm, state, limits, *v_range)
    v_tr = lin.voltage(desired.u_um)
    dt, rate = desired.dt_s, 0.25 * limits.max_rate_v_per_ms * 1e3
    ramp_in = raised_cosine(start_v, v_tr[0], ramp_samples(v_tr[0] - start_v, rate, dt))
    ramp_out = raised_cosine(v_tr[-1], start_v, ramp_samples(v_tr[-1] - start_v, rate, dt))
    wf = _assemble("linear", desired, np.concatenate([prefix_v, ramp_in]), v_tr, ramp_out, None)
    guard.check(wf.voltage_v, dt, limits, start_v, "linear waveform")
    return wf


class EnvelopeError(InputError):
    """The waveform leaves the model's validity envelope (one line naming the envelope)."""


def conditioning_limits(limits: guard.Limits, env: Envelope | None) -> guard.Limits:
    """The profile's limits narrowed to the envelope's voltage range (where they overlap)."""
    if env is None:
        return limits
    lo, hi = max(limits.v_min, env.voltage_min_v), min(limits.v_max, env.voltage_max_v)
    return replace(limits, v_min=lo, v_max=hi) if lo < hi else limits


def check_envelope(wf: Waveform, env: Envelope | None, extrapolate: bool) -> None:
    """EnvelopeError if the tracking part of ``wf`` leaves ``env`` by more than 5 % of its span."""
    if env is None or extrapolate:
        return
    v = wf.voltage_v[wf.tracking]
    lo, hi = float(v.min()), float(v.max())
    if not env.admits(lo, hi):
        raise EnvelopeError(
            f"the {wf.filter} waveform needs {lo:.1f} ... {hi:.1f} V, outside the model's validity "
            f"envelope ({env.describe()}) by {env.excess_v(lo, hi):.1f} V (> 5 % of its span): "
            f"identify on sweeps that cover it, or pass --extrapolate")


def plan(model: tr.Transducer, desired: Desired, limits: guard.Limits, start_v: float = 0.0,
         filters: tuple[str, ...] = ("inverse", "linear"),
         state: tr.StageState | None = None, condition: bool = True,
         envelope: Envelope | None = None, extrapolate: bool = False) -> dict[str, Waveform]:
    """Guard-checked waveforms for each filter (the inverse one first: it sets the voltage range).

    ``state`` is the model state at the stage's present output ``start_v`` (default: depoled, then
    ``start_v`` applied); the conditioning that starts every waveform makes the result insensitive
    to it for every hysteron the voltage limits can switch. ``condition=False`` leaves it out (no
    full-stroke excursion, e.g. with a tip near the sample): the model then assumes ``state``.
    ``envelope`` (the model's, if known) bounds the conditioning and, unless ``extrapolate``,
    the waveforms (:func:`check_envelope`).
    """
    cm = tr.compile_model(model, desired.dt_s)
    st0 = state if state is not None else tr.initial(model, voltage_v=start_v)
    pre = (conditioning(conditioning_limits(limits, envelope), start_v, desired.dt_s)
           if condition else np.zeros(0))
    _, _, st = tr.simulate(cm, pre, st0)
    wf = plan_inverse(cm, desired, limits, start_v, st, pre)
    check_envelope(wf, envelope, extrapolate)
    out = {"inverse": wf} if "inverse" in filters else {}
    if "linear" in filters:
        track_v = wf.voltage_v[wf.tracking]
        out["linear"] = plan_linear(cm, desired, limits, start_v, st,
                                    (float(track_v.min()), float(track_v.max())), pre)
    return out


@dataclass(frozen=True)
class Score:
    """Tracking errors of one run, um and % of the peak-to-peak amplitude."""

    rms_um: float
    max_um: float
    rms_pct: float
    max_pct: float
    rms_steady_um: float
    rms_between_um: float | None

    def as_dict(self) -> dict[str, float | None]:
        return dict(self.__dict__)


def _rms(x: FloatArray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")


def score(wf: Waveform, desired: Desired, measured_um: FloatArray,
          between_um: FloatArray | None = None) -> Score:
    """Errors on the tracking part; ``between_um`` from :func:`between_samples` if available.

    Missing samples (NaN in ``measured_um``) are left out, never filled in.
    """
    err = measured_um[wf.tracking] - desired.u_um
    steady = err
    if desired.period_s is not None:
        steady = err[int(round(desired.period_s / desired.dt_s)):] if err.size > 1 else err
    amp = desired.amplitude_um
    rms, mx = _rms(err), float(np.nanmax(np.abs(err)))
    between = None
    if between_um is not None:
        between = _rms(between_um)
    return Score(rms, mx, 100 * rms / amp, 100 * mx / amp, _rms(steady), between)


def between_samples(model: tr.Transducer, wf: Waveform, desired: Desired,
                    state: tr.StageState) -> FloatArray:
    """Error of the stage's true position between samples: the plant (with the model's amplifier
    lag and second mode, not its sensor) simulated on a grid ``FINE`` times finer, the voltage
    held (zero-order hold), the desired trajectory linearly interpolated (um)."""
    fine = tr.compile_model(model, wf.dt_s / FINE)
    chain = fx.compile_chain(model.effects, wf.dt_s / FINE)
    v = np.repeat(wf.voltage_v, FINE)
    u, _, _ = tr.simulate(fine, fx.lag(chain, v, float(v[0]))[0], state)
    u = fx.position(chain, u)
    start = wf.tracking.start * FINE
    n = (desired.u_um.size - 1) * FINE + 1
    t_fine = np.arange(n) / FINE
    want = np.interp(t_fine, np.arange(desired.u_um.size), desired.u_um)
    return u[start:start + n] - want
