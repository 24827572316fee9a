"""The tracking experiment of the paper's Section 6, as pure planning and scoring.

Planning turns a desired displacement trajectory into a voltage waveform per filter:

* Every waveform starts by **conditioning** the stage: one slow excursion from the present output to
  the upper and lower voltage limits and back. By the wiping-out property of the model (and of the
  material) this erases the memory of whatever the stage did before, so the model's state at the
  start of tracking is known rather than assumed. With a model's validity envelope (the voltage
  range it was identified on, :class:`afmctl.files.modelfile.Envelope`) the excursion stays inside it:
  a wider one could repole the material into a state the model never saw. A waveform whose
  tracking part leaves the envelope by more than 5 % of its span is refused
  (:class:`EnvelopeError`) unless extrapolation is asked for.
* ``inverse``: Algorithm 3 through the model. After conditioning, a ramp in displacement from the
  stage's output to the trajectory's first point (so the inverse carries the hysteresis state
  through it), the tracking part, then a raised-cosine ramp of the voltage back to the output.
  The inversion horizon ``d`` starts at the smallest non-chattering one and is lengthened stretch by
  stretch (each corner of a periodic trajectory, and the smooth parts between) only where the
  waveform would not pass the guard: a larger horizon rounds that corner instead of asking the
  amplifier for an impulse, and the rest of the run keeps the accurate short horizon. A model
  with effects (:mod:`afmctl.model.effects`, from ``afmctl diagnose``) has the plant's inverted around
  Algorithm 3: the second mode on the target, the amplifier's lag on the voltage (its exact
  inverse, each step clamped to 95 % of the usable slew rate; one horizon for the whole run, the
  one the model predicts tracks best). Its sensor effects (delay, gauge error) do not move the
  stage: they correct the readings before scoring (:func:`afmctl.model.effects.sensor_correct`).
* ``linear``: the paper's baseline, a straight line fitted to the model's quasi-static
  voltage-displacement response over the same voltage range, with the same kind of ramps.

Timing: voltage sample k is held over [t_k, t_{k+1}); displacement sample k is read at t_k. So the
error at sample k is ``displacement[k] - desired[k]`` and sample k's voltage aims at ``desired[k+d]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, NoReturn

import numpy as np
from numpy.typing import NDArray
from scipy.signal import butter, filtfilt, sawtooth

from afmctl import guard
from afmctl.errors import EnvelopeError, ReachError
from afmctl.files.modelfile import Envelope
from afmctl.model import effects as fx
from afmctl.model import frame as fr
from afmctl.model import inverse as inv
from afmctl.model import rod as rd
from afmctl.model import transducer as tr

FloatArray = NDArray[np.float64]
HORIZONS = (1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 20, 24, 32, 48, 64)
FINE = 8  # sub-samples per sample when judging between samples
#: Refinements of the inverse through the model's own simulation (:func:`_refined`), and the
#: largest miss (um, the rod's) below which none is made.
REFINE = 2
REFINE_TOL_UM = 1e-3
#: The amplifier-lag inverse may use this fraction of the usable slew rate.
LAG_STEP = 0.95
REACH_TOL_UM = 1e-3  # an inverse that misses its target by more hit the voltage limit
#: Samples per stretch of a non-periodic trajectory (each stretch gets its own horizon).
BLOCK = 64
#: Samples on each side of a corner in the corner's own stretch (tried: 4 leaves corners no
#: horizon can fix from the committed stretch before; 8 tracks best on the 27.9 Hz triangle).
CORNER = 8


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
    ``horizons`` are the inversion horizons (samples) of the inverse's stretches (empty for the
    linear filter), :attr:`horizon` the one most of them use.
    """

    filter: str
    dt_s: float
    voltage_v: FloatArray
    desired_um: FloatArray
    tracking: slice = field(repr=False)
    horizons: tuple[int, ...] = ()

    @property
    def horizon(self) -> int | None:
        """The inversion horizon of most stretches, samples (None for the linear filter)."""
        if not self.horizons:
            return None
        values, counts = np.unique(self.horizons, return_counts=True)
        return int(values[np.argmax(counts)])

    def horizon_text(self) -> str:
        """E.g. ``horizon 4 samples (5 on 2 of 13 stretches)``; "" for the linear filter."""
        main = self.horizon
        if main is None:
            return ""
        other = [h for h in self.horizons if h != main]
        if not other:
            return f"horizon {main} samples"
        return (f"horizon {main} samples ({', '.join(str(h) for h in sorted(set(other)))} on "
                f"{len(other)} of {len(self.horizons)} stretches)")

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
              ramp_out: FloatArray, horizons: tuple[int, ...] = ()) -> Waveform:
    n_in, n_tr = ramp_in.size, v_track.size
    v = np.concatenate([ramp_in, v_track, ramp_out])
    d = np.full(v.size, np.nan)
    d[n_in:n_in + n_tr] = desired.u_um
    return Waveform(name, desired.dt_s, v, d, slice(n_in, n_in + n_tr), horizons)


def _segments(desired: Desired, n_in: int, n: int) -> list[int]:
    """Boundaries of the stretches that each get their own inversion horizon: the ramp in, then
    a stretch of ``2 CORNER + 1`` samples around each corner of a periodic trajectory (every half
    period from its start at the minimum) with the smooth parts between, or blocks of ``BLOCK``
    samples for a trajectory without a period."""
    if desired.period_s is not None:
        half = 0.5 * desired.period_s / desired.dt_s
        corners = np.arange(half, n - n_in, half)
        marks = n_in + np.round(np.concatenate([corners - CORNER, corners + CORNER + 1]))
    else:
        marks = np.arange(n_in + BLOCK, n, BLOCK)
    return sorted({0, n_in, n, *(int(m) for m in marks if n_in < m < n)})


def _reach(res: inv.Inversion, n: int, first: int) -> None:
    short = int(np.argmax(res.error[:n]))
    if res.error[short] > REACH_TOL_UM:
        raise ReachError(f"at sample {first + short} the model falls {res.error[short]:.3f} um "
                         f"short at the voltage limit")


def _invert_stretches(cm: tr.Compiled, target: FloatArray, state: tr.StageState, start_v: float,
                      limits: guard.Limits, bounds: list[int], e_lim: tuple[float, float],
                      fixed: tuple[int, ...] | None = None
                      ) -> tuple[FloatArray, tuple[int, ...]]:
    """Algorithm 3 stretch by stretch, each with the smallest horizon (from the smooth one up)
    whose voltage passes the guard: one hard corner lengthens the horizon of its own stretch only.
    ``fixed`` gives each stretch the horizon to start the search from instead.

    Returns the voltage (V) and the horizon of each stretch.
    """
    thick, dt = cm.model.thickness_um, cm.dt
    d0 = rd.smooth_horizon(cm.disc)
    stable = _stable(cm.disc)
    parts, horizons = [], []
    st, v_prev = state, start_v
    for i, (s, e) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
        last: guard.LimitError | None = None
        for d in _ladder(stable, max(d0, fixed[i]) if fixed else d0):
            res = inv.algorithm3(cm, target[s:e + d - 1], st, e_init=v_prev / thick, horizon=d,
                                 e_min=e_lim[0], e_max=e_lim[1], keep=e - s)
            v = res.voltage(thick)[:e - s]
            try:  # a longer horizon rounds a corner the limit cuts off
                _reach(res, e - s, s)
                guard.check(v, dt, limits, v_prev, "inverse waveform")
            except guard.LimitError as exc:
                last = exc
                continue
            break
        else:
            _no_horizon(last)
        parts.append(v)
        horizons.append(d)
        st = res.kept  # the model's state after the stretch's own fields
        v_prev = float(v[-1])
    return np.concatenate(parts), tuple(horizons)


def _stable(disc: rd.Discrete) -> tuple[int, ...]:
    """The :data:`HORIZONS` whose inverse is stable (:func:`afmctl.model.rod.horizon_radius`
    below 1): an unstable one rails at the limits or, mildly unstable, passes the guard and
    chatters."""
    return tuple(h for h in HORIZONS if rd.horizon_radius(disc, h) < 1.0)


def _ladder(stable: tuple[int, ...], start: int) -> list[int]:
    """The horizons a waveform tries, in turn: ``start`` (the smooth one, which need not be one of
    :data:`HORIZONS`), then each of the ``stable`` ones above it (:func:`_stable`). On a rod
    resonating above a quarter of the sample rate the smooth horizon can be 7 and the next of
    HORIZONS, 8, unstable."""
    return [start] + [h for h in stable if h > start]


def _invert_lagged(cm: tr.Compiled, chain: fx.Chain, target: FloatArray, state: tr.StageState,
                   start_v: float, limits: guard.Limits, e_lim: tuple[float, float],
                   build: Any, fixed: tuple[int, ...] | None = None) -> Waveform:
    """With an amplifier lag the slew limit clamps the lead at the corners: a longer horizon asks
    for less of it but rounds the corners; keep the (uniform) one the model says tracks best."""
    dt = cm.dt
    last: guard.LimitError | None = None
    best: tuple[float, Waveform] | None = None
    for d in _ladder(_stable(cm.disc), max((rd.smooth_horizon(cm.disc), *(fixed or ())))):
        res = inv.algorithm3(cm, target, state, e_init=start_v / cm.model.thickness_um,
                             horizon=d, e_min=e_lim[0], e_max=e_lim[1])
        v = fx.unlag_limited(chain, res.voltage(cm.model.thickness_um), start_v,
                             LAG_STEP * limits.max_rate_v_per_ms * 1e3 * dt,
                             (limits.v_min, limits.v_max))
        try:
            _reach(res, target.size, 0)
            wf = build(v, (d,))
        except guard.LimitError as exc:
            last = exc
            continue
        u = tr.simulate(cm, fx.lag(chain, v, start_v)[0], state)[0]
        err = _rms(u[1:] - target[:-1])  # target[k] is for sample k + 1
        if best is not None and err >= best[0]:
            return best[1]
        best = (err, wf)
    if best is not None:
        return best[1]
    _no_horizon(last)


def _no_horizon(last: guard.LimitError | None) -> NoReturn:
    """Raise why no horizon gave a waveform: the reach if the last one fell short of it, else
    the limit the last one broke."""
    if isinstance(last, ReachError):
        raise last
    raise guard.LimitError(f"no inversion horizon up to {HORIZONS[-1]} samples keeps the "
                           f"waveform within limits; last: {last}")


def plan_inverse(cm: tr.Compiled, desired: Desired, limits: guard.Limits, start_v: float,
                 state: tr.StageState, prefix_v: FloatArray,
                 horizons: tuple[int, ...] | None = None,
                 frame: fr.Frame = fr.Frame()) -> Waveform:
    """Algorithm 3 waveform, each stretch with the smallest horizon that passes the guard.

    ``prefix_v`` (the conditioning) is played first; ``state`` is the model state after it.
    ``frame`` is where the readings will sit from the model (from the waveform's first sample):
    the model is aimed at the trajectory less it.
    ``horizons`` (those of an earlier plan of the same trajectory) are the stretches' shortest
    horizons: learning starts each iteration's search from the last one's, so the horizons (and
    the plant it learns through) only change where a corrected stretch would break the guard.

    Raises
    ------
    guard.LimitError
        If the trajectory is out of reach, or no horizon up to 64 samples gives a waveform
        within the limits.
    """
    dt = desired.dt_s
    rate = 0.25 * limits.max_rate_v_per_ms * 1e3  # V/s for the ramps
    chain = fx.compile_chain(cm.model.effects, dt)
    rod0 = float(tr.simulate(cm, np.array([start_v]), state)[0][0])
    u0 = float(fx.position(chain, np.array([rod0]))[0])  # rod plus second mode
    gain = _linear_from_model(cm, state, limits).gain_um_per_v
    n_in = ramp_samples(desired.u_um[0] - u0, rate * abs(gain), dt)
    aim = desired.u_um - frame.along(prefix_v.size + n_in, desired.u_um.size, dt)
    target = np.concatenate([raised_cosine(u0, aim[0], n_in), aim[1:], aim[-1:]])
    target = fx.remove_mode(chain, target)  # what the rod must do for the stage to be there
    e_lim = (limits.v_min / cm.model.thickness_um, limits.v_max / cm.model.thickness_um)

    def build(v: FloatArray, horizons: tuple[int, ...]) -> Waveform:
        v_in, v_tr = np.concatenate([prefix_v, v[:n_in]]), v[n_in:]
        out = raised_cosine(v_tr[-1], start_v, ramp_samples(v_tr[-1] - start_v, rate, dt))
        wf = _assemble("inverse", desired, v_in, v_tr, out, horizons)
        guard.check(wf.voltage_v, dt, limits, start_v, "inverse waveform")
        return wf

    try:
        bounds = _segments(desired, n_in, target.size)
        wf = _inverted(cm, chain, target, state, start_v, limits, e_lim, build, horizons, bounds)
        return _refined(cm, chain, target, state, start_v, limits, e_lim, build, bounds, wf,
                        prefix_v.size)
    except ReachError as exc:
        lo, hi = reach(cm.model, limits)
        raise ReachError(
            f"the trajectory ({float(np.min(desired.u_um)):.4g} ... "
            f"{float(np.max(desired.u_um)):.4g} um) is out of the stage's reach: the model "
            f"reaches {lo:.4g} ... {hi:.4g} um on {limits.v_min:g} ... {limits.v_max:g} V "
            f"(as afmctl reach shows), and {exc}; reduce the amplitude or move the offset") from None


def _refined(cm: tr.Compiled, chain: fx.Chain, target: FloatArray, state: tr.StageState,
             start_v: float, limits: guard.Limits, e_lim: tuple[float, float], build: Any,
             bounds: list[int], wf: Waveform, n_prefix: int) -> Waveform:
    """``wf`` re-inverted (same horizons) for the target moved by what the model's own
    simulation of ``wf`` misses, up to :data:`REFINE` times while that exceeds
    :data:`REFINE_TOL_UM`: the horizon-``d`` inversion holds the force ``d`` samples ahead and
    re-solves every sample, which on a fast, lightly damped rod leaves the model itself a fraction
    of a sample behind a ramp (0.145 um RMS on a 27.9 Hz triangle over 48 um through a 1.8 kHz,
    12 %-damped rod: 0.0037 um after; 0.011 um through the emulated stage's 250 Hz rod). Where
    the whole miss makes the re-inversion miss more, its part the rod can follow
    (:func:`followable`) is added instead: the rest excites the horizon-``d`` inverse (a 418 Hz,
    4.5 %-damped rod on a 30 Hz raster line: 0.161 um RMS, 0.38 of a sample ahead; the whole miss
    0.93 um, the followable part 0.041 um), and the refinement ends there: each try is a whole
    inversion. A refinement the guard refuses, or that misses more, is not kept. First, a plan
    whose simulation runs whole samples ahead of its target (:func:`model_lead`) is aimed that
    many samples later, kept on the same rule. Not with an amplifier lag (its own inversion)."""
    if chain.lag_a != 0.0:
        return wf
    goal = target

    def missed(w: Waveform) -> FloatArray:  # goal[j]: the rod at sample j + 1
        return goal[:-1] - tr.simulate(cm, w.voltage_v[n_prefix:], state)[0][1:goal.size]

    def better(step: FloatArray) -> tuple[Waveform, FloatArray, FloatArray] | None:
        moved = target + np.append(step, 0.0)
        try:
            trial = _inverted(cm, chain, moved, state, start_v, limits, e_lim, build,
                              best.horizons, bounds)
        except guard.LimitError:
            return None
        trial_miss = missed(trial)
        return (trial, trial_miss, moved) if np.sum(trial_miss ** 2) < np.sum(miss ** 2) else None

    best, miss = wf, missed(wf)
    lead = model_lead(goal[:-1], goal[:-1] - miss, max(best.horizons, default=1) - 1)
    if lead:  # aim that many samples later: the whole samples first, the rest as below
        found = better(np.concatenate([np.full(lead, target[0]), target[:-lead]])[:-1]
                       - target[:-1])
        if found is not None:
            best, miss, target = found
    for _ in range(REFINE):
        if float(np.max(np.abs(miss))) <= REFINE_TOL_UM:
            break
        found = better(miss)
        if found is None:  # the last step: a second one gains little (0.0409 -> 0.0394 um)
            part = followable(miss, cm.model.rod.natural_hz, cm.dt)
            found = None if part is miss else better(part)  # the whole miss failed already
            return best if found is None else found[0]
        best, miss, target = found
    return best


def model_lead(goal: FloatArray, u: FloatArray, most: int) -> int:
    """The whole samples ``L`` (0 ... ``most``) by which ``u`` runs ahead of ``goal`` (um, the
    same samples): ``u[j] ~ goal[j + L]``. A horizon-``d`` inverse holds the force ``d`` samples
    ahead; a rod that settles within a sample then reaches each target up to ``d - 1`` samples
    early (an independent tester's 3.5 kHz Bouc-Wen stage at horizon 4: 3 samples, 0.68 um on a
    27.9 Hz triangle over 40 um, 0.014 um aimed 3 samples later)."""
    rms = [float(np.mean((u[:u.size - m] - goal[m:]) ** 2)) for m in range(min(most, u.size - 1) + 1)]
    return int(np.argmin(rms))


def followable(miss: FloatArray, natural_hz: float, dt_s: float) -> FloatArray:
    """``miss`` (um) below the rod's natural frequency ``natural_hz`` (Hz): a zero-phase
    second-order low-pass (``miss`` itself if that is above 0.9 of the Nyquist frequency)."""
    wn = 2.0 * natural_hz * dt_s
    if wn >= 0.9 or miss.size <= 3 * 3:  # filtfilt's padding needs more samples
        return miss
    b, a = butter(2, wn)
    return np.asarray(filtfilt(b, a, miss), float)


def _inverted(cm: tr.Compiled, chain: fx.Chain, target: FloatArray, state: tr.StageState,
              start_v: float, limits: guard.Limits, e_lim: tuple[float, float], build: Any,
              horizons: tuple[int, ...] | None, bounds: list[int]) -> Waveform:
    """:func:`plan_inverse`'s inversion: lagged, from given horizons, or stretch by stretch."""
    if chain.lag_a != 0.0:
        return _invert_lagged(cm, chain, target, state, start_v, limits, e_lim, build, horizons)
    if horizons:
        fixed = bounds if len(horizons) == len(bounds) - 1 else [0, target.size]
        return build(*_invert_stretches(cm, target, state, start_v, limits, fixed, e_lim,
                                        horizons))
    try:
        v, horizons = _invert_stretches(cm, target, state, start_v, limits, bounds, e_lim)
    except ReachError:
        raise
    except guard.LimitError:
        # a stretch that no horizon fixes after the stretch before it: one horizon throughout
        v, horizons = _invert_stretches(cm, target, state, start_v, limits, [0, target.size],
                                        e_lim)
    return build(v, horizons)


def reach(model: tr.Transducer, limits: guard.Limits, envelope: Envelope | None = None
          ) -> tuple[float, float]:
    """The displacements (um, the sensor's frame) the model reaches within the voltage limits:
    the lowest and highest of its quasi-static response (0.279 Hz) to a triangle over
    ``[v_min, v_max]`` (narrowed to ``envelope``'s voltages, where the model was identified),
    after one period that wipes out the initial state. A trajectory must stay inside it; at
    27.9 Hz the rod's dynamics take a little more near the corners.

    Examples
    --------
    >>> from afmctl.files.profile import default_profile
    >>> lim = guard.Limits(0.0, 150.0, 50.0, 100.0, 2.0)
    >>> lo, hi = reach(default_profile().emulator.model, lim)
    >>> round(lo, 1), round(hi, 1)
    (6.5, 53.6)
    """
    lim = conditioning_limits(limits, envelope)
    cm = tr.compile_model(model, 1e-3)
    _, u = _quasi_static(cm, tr.initial(model, voltage_v=0.0), lim.v_min, lim.v_max)
    return float(np.min(u)), float(np.max(u))


def _quasi_static(cm: tr.Compiled, state: tr.StageState, lo: float, hi: float
                  ) -> tuple[FloatArray, FloatArray]:
    """Voltage and the model's displacement over the second period of a 0.279 Hz triangle over
    ``[lo, hi]`` (V) from ``state`` (the first period settles it)."""
    dt = 1e-3
    t = np.arange(0, 2 / 0.279, dt)
    v = 0.5 * (hi + lo) + 0.5 * (hi - lo) * sawtooth(2 * np.pi * 0.279 * t + np.pi / 2, 0.5)
    u, _, _ = tr.simulate(tr.compile_model(cm.model, dt), v, state)
    half = t >= 1 / 0.279  # the second, settled period
    return v[half], u[half]


def _linear_from_model(cm: tr.Compiled, state: tr.StageState, limits: guard.Limits,
                       v_lo: float | None = None, v_hi: float | None = None) -> inv.LinearFilter:
    """Line through the model's quasi-static (0.279 Hz) response over [v_lo, v_hi]."""
    lo = limits.v_min if v_lo is None else v_lo
    hi = limits.v_max if v_hi is None else v_hi
    return inv.fit_linear(*_quasi_static(cm, state, lo, hi))


def plan_linear(cm: tr.Compiled, desired: Desired, limits: guard.Limits, start_v: float,
                state: tr.StageState, v_range: tuple[float, float],
                prefix_v: FloatArray, frame: fr.Frame = fr.Frame()) -> Waveform:
    """The paper's linear filter over the voltage range ``v_range`` the inverse filter needs,
    aimed at the trajectory less ``frame`` (as :func:`plan_inverse`)."""
    lin = _linear_from_model(cm, state, limits, *v_range)
    dt, rate = desired.dt_s, 0.25 * limits.max_rate_v_per_ms * 1e3
    n_in = ramp_samples(float(lin.voltage(desired.u_um[:1])[0]) - start_v, rate, dt)
    v_tr = lin.voltage(desired.u_um - frame.along(prefix_v.size + n_in, desired.u_um.size, dt))
    ramp_in = raised_cosine(start_v, v_tr[0], n_in)  # as long as the frame was placed for
    ramp_out = raised_cosine(v_tr[-1], start_v, ramp_samples(v_tr[-1] - start_v, rate, dt))
    wf = _assemble("linear", desired, np.concatenate([prefix_v, ramp_in]), v_tr, ramp_out)
    guard.check(wf.voltage_v, dt, limits, start_v, "linear waveform")
    return wf


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
         envelope: Envelope | None = None, extrapolate: bool = False,
         frame: fr.Frame = fr.Frame()) -> dict[str, Waveform]:
    """Guard-checked waveforms for each filter (the inverse one first: it sets the voltage range).

    ``state`` is the model state at the stage's present output ``start_v`` (default: depoled, then
    ``start_v`` applied); the conditioning that starts every waveform makes the result insensitive
    to it for every hysteron the voltage limits can switch. ``condition=False`` leaves it out (no
    full-stroke excursion, e.g. with a tip near the sample): the model then assumes ``state``.
    ``envelope`` (the model's, if known) bounds the conditioning and, unless ``extrapolate``,
    the waveforms (:func:`check_envelope`). ``frame`` is where the readings will sit from the
    model from the waveforms' first sample (:meth:`afmctl.experiment.twin.Twin.frame`; default:
    the model's zero): both filters aim the model at the trajectory less it.
    """
    cm = tr.compile_model(model, desired.dt_s)
    st0 = state if state is not None else tr.initial(model, voltage_v=start_v)
    pre = (conditioning(conditioning_limits(limits, envelope), start_v, desired.dt_s)
           if condition else np.zeros(0))
    _, _, st = tr.simulate(cm, pre, st0)
    wf = plan_inverse(cm, desired, limits, start_v, st, pre, frame=frame)
    check_envelope(wf, envelope, extrapolate)
    out = {"inverse": wf} if "inverse" in filters else {}
    if "linear" in filters:
        track_v = wf.voltage_v[wf.tracking]
        out["linear"] = plan_linear(cm, desired, limits, start_v, st,
                                    (float(track_v.min()), float(track_v.max())), pre, frame)
    return out


@dataclass(frozen=True)
class Score:
    """Tracking errors of one run, um and % of the peak-to-peak amplitude.

    The headline figures (``rms_um``, ``max_um`` and their %) are over the steady part: from one
    period after the start of a periodic trajectory, as the benchmarks judge it (the first period
    carries the transient of the ramp in). ``steady`` is False when that leaves less than a full
    period (or the trajectory has no period): the headline is then over the whole run. The first
    period is reported apart (``rms_transient_um``), and ``rms_all_um`` covers everything.
    ``rms_between_um`` is the error between samples over the same part as the headline.
    """

    rms_um: float
    max_um: float
    rms_pct: float
    max_pct: float
    steady: bool
    steady_from_s: float
    rms_transient_um: float | None
    rms_all_um: float
    rms_between_um: float | None

    def as_dict(self) -> dict[str, float | bool | None]:
        return dict(self.__dict__)


def _rms(x: FloatArray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")


def steady_start(desired: Desired) -> int:
    """First sample of the steady part: one period in, if a full period follows; else 0."""
    if desired.period_s is None:
        return 0
    n_period = int(round(desired.period_s / desired.dt_s))
    return n_period if desired.u_um.size >= 2 * n_period else 0


def score(wf: Waveform, desired: Desired, measured_um: FloatArray,
          between_um: FloatArray | None = None) -> Score:
    """Errors on the tracking part; ``between_um`` from :func:`between_samples` if available.

    Missing samples (NaN in ``measured_um``) are left out, never filled in.
    """
    err = measured_um[wf.tracking] - desired.u_um
    k0 = steady_start(desired)
    steady = err[k0:]
    amp = desired.amplitude_um
    rms = _rms(steady)
    mx = float(np.nanmax(np.abs(steady))) if np.isfinite(steady).any() else float("nan")
    between = None if between_um is None else _rms(between_um[k0 * FINE:])
    return Score(rms, mx, 100 * rms / amp, 100 * mx / amp, k0 > 0, k0 * desired.dt_s,
                 _rms(err[:k0]) if k0 else None, _rms(err), between)


def between_samples(model: tr.Transducer, wf: Waveform, desired: Desired,
                    state: tr.StageState, measured_um: FloatArray | None = None) -> FloatArray:
    """Error of the stage's true position between samples: the plant (with the model's amplifier
    lag and second mode, not its sensor) simulated on a grid ``FINE`` times finer, the voltage
    held (zero-order hold), the desired trajectory linearly interpolated (um).

    ``measured_um`` (the run's readings, corrected for the model's sensor effects, on the whole
    waveform) makes it an estimate that carries the model's misfit: when ``model`` is the fitted
    model rather than the stage's truth, its own simulation between the samples is only as good
    as the model (issue 23: on a stage off the model's family it understated the true error
    10-40x). The misfit at the samples, reading minus the model's simulation there, is added
    between them by linear interpolation, so at every sample the estimate is the measured error
    and between samples it is the model's shape moved by what the model got wrong nearby.
    """
    fine = tr.compile_model(model, wf.dt_s / FINE)
    chain = fx.compile_chain(model.effects, wf.dt_s / FINE)
    v = np.repeat(wf.voltage_v, FINE)
    u, _, _ = tr.simulate(fine, fx.lag(chain, v, float(v[0]))[0], state)
    u = fx.position(chain, u)
    start = wf.tracking.start * FINE
    n = (desired.u_um.size - 1) * FINE + 1
    t_fine = np.arange(n) / FINE
    want = np.interp(t_fine, np.arange(desired.u_um.size), desired.u_um)
    err = u[start:start + n] - want
    if measured_um is not None:
        k = np.arange(desired.u_um.size)
        misfit = np.asarray(measured_um, float)[wf.tracking] - u[start + k * FINE]
        ok = np.isfinite(misfit)
        if ok.any():
            err = err + np.interp(t_fine, k[ok], misfit[ok])
    return err
