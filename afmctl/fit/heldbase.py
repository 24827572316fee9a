"""Diagnose's causes on identify's model: its hysteresis held, each effect fitted around it.

The catalogue's candidates (:mod:`afmctl.fit.extension`) extend the paper's model with the
lognormal / normal densities. On a stage of the paper's family whose coercive density is of
another shape (a separable Preisach density), that base is 2.6-10.5x the noise before any
effect, and no one-effect extension of it reaches the floor, while identify's general coercive
density (``density = "discrete"``) is at 1.00-1.13x on the same stages with the effect off
(docs/results/diagnose.md, stop 36). So when the catalogue leaves the sweeps ``unexplained``,
:func:`judge` fits that density on the first halves (:func:`afmctl.fit.identify.fit`) and tries
the causes around it:

- **output side** (the effect acts after the hysteresis): the hysteresis's static displacement
  ``g`` held, the rod (16) and the effect refitted by variable projection
  (:mod:`afmctl.fit.heldfit`): ``second-mode`` (:class:`afmctl.model.effects.SecondMode` after
  the rod; a mode *beside* the rod, rod + residue x mode, is the same thing: the rod followed by
  a biquad with the mode's poles; up to twice the Nyquist frequency), ``sensor-delay`` (the
  readings late by a time and averaged over a window: an integrating converter),
  ``sensor-nonlinearity`` (the gauge of :func:`afmctl.model.effects.gauge`, fitted on the
  positions its inverse gives) and its twin ``actuator-nonlinearity`` (``L[g^2]`` and ``L[g^3]``:
  the same polynomial before the rod's dynamics, never named, fitted on the gauge's base);
  identify's density took a gauge's static part up, so on that base the gauge's form is
  ``gauge(L[ungauge(g)])``, which differs from the base only through the rod's lag, and a gauge
  that takes a fifth off the base's cost has the density identified again on the positions it
  gives (:func:`rebases`; a gauge left on the first base is refused: :func:`refusal`). On the
  other-form gap-law stage other-sensor-nonlinearity-0 with eight full-range ramps at 0.95 of
  the usable slew added to the triangles: 1.49x the noise held out without it, 1.05x with it,
  its twin 1.35x (1.95x on the ramps; docs/results/diagnose.md, stop 64);
- **input side** (the effect changes the field): the hysteresis re-run on the effect's field
  and the rod refitted: ``amplifier-lag`` (a second-order amplifier) and
  ``voltage-gain-drift`` (each sweep's applied-voltage gain, their log mean 0, times a warm-up
  ``1 + delta (1 - exp(-t / tau))`` in the record's time: a gain that drifts by sweep or in
  time; the amplifier's output clipped at rails at or beyond the commands' range, for a gain
  above 1 flattens the top of every sweep that spans it: other-voltage-gain-drift-0, 2.2 %
  over 16.5 s, at 1.12 / 2.85 / 5.57x the noise with the true warm-up, 1.00 / 1.00 / 0.95x
  with the rails). identify's
  density absorbed part of what the effect does to the field, so an effect that takes a fifth
  off the base's cost has the density identified again on the effect's field, and the cause
  refitted on it from that identification's rod (kept if it fits the first halves better; in
  turn up to three times while each round takes a fifth off: :func:`rebased`);
- ``none``: identify's model with its rod refitted alone.

Thermal relaxation changes the kernel (10) itself and is left to the catalogue. Every fit is
judged on the second halves, as the catalogue's are, and read by the same verdict
(:func:`afmctl.fit.verdict.decide`). Pure numerics: no I/O.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl.files.sweepfile import Sweep
from afmctl.fit import candidate_space as cs
from afmctl.fit import candidates as cd
from afmctl.fit import extension as ext
from afmctl.fit import heldfit as hf
from afmctl.fit import identify as idf
from afmctl.fit import parametrization as pz
from afmctl.fit import verdict as vd
from afmctl.fit.diagnosis import HELD_BASE, Judged
from afmctl.fit.rod_response import rod_filter
from afmctl.model import effects as fx
from afmctl.model import transducer as td

FloatArray = NDArray[np.float64]
#: A fit of a cause (:meth:`Held.fit`): ``z``, the linear parameters, the solver's word, its
#: evaluations and its cost.
Fit = tuple[FloatArray, FloatArray, bool, int, float]
#: Polished from this many of the best seeds of each rod seed (each a least-squares run; one
#: for an input-side cause, whose every evaluation runs the hysteresis again).
POLISHED = 2
#: An input-side cause whose fit costs less than this share of the base's has its density
#: identified again through the effect (:meth:`Held.through`), and keeps that if it fits better;
#: again while a round takes as much off (:func:`rebased`).
REBASE_GAIN = 0.8
#: At most this many such identifications per cause (:func:`rebased`).
REBASES = 3
#: Bounds of the rod's resonance and damping ratio about identify's, as factors (the resonance
#: may also rise to the readings' Nyquist frequency: an effect the identification's rod took up
#: made it slower and more damped, e.g. a sensor's averaging).
ROD_SPAN = ((0.5, 2.0), (0.1, 10.0))
#: The rod seeds of the causes that alter what the rod took up (``free_rod``): identify's, and
#: this factor faster (to at most 0.9 of the Nyquist frequency) with this damping ratio.
FREE_ROD_SEED = (4.0, 0.1)
#: A second mode may lie up to this many times the Nyquist frequency: it does not ring in the
#: readings there, but its zeros still shape the response below it (a stiff stage's second
#: mode, 9.6 kHz at 10 kHz sampling, left a fast triangle at 4.5x the noise).
MODE_ABOVE = 2.0
#: Bounds of a second mode's damping ratio: a resonance, not a filter's corner (a fit that
#: ends on the upper bound stands in for something else and is refused: :func:`refusal`).
MODE_DAMPING = (0.003, 0.15)
#: Warm-up time constants the gain drift's fit starts from, s.
WARMUP_TIMES_S = (1.0, 10.0, 100.0)
#: The gain drift's amplifier rails: each beyond its end of the commands' range by at most this
#: share of the range, started there (clipping wherever the gain exceeds 1) and well beyond.
RAIL_MARGINS = (0.0, 0.05)
RAIL_MARGIN_MAX = 0.1
#: Mode frequencies tried, as fractions of the rod's resonance (:mod:`afmctl.fit.modes`'s).
MODE_FRACTIONS = (0.35, 0.5, 0.7, 1.4, 2.0, 3.0)


@dataclass(frozen=True)
class Cause:
    """One cause on the held base: the effect's parameters (internal units), their seeds and
    bounds, the side it acts on and how many parameters it adds (with its projected gains)."""

    name: str
    labels: tuple[str, ...]
    seeds: tuple[tuple[float, ...], ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    n_added: int
    input_side: bool = False
    free_rod: bool = False


def causes(n_sweeps: int, rod_hz: float, nyquist_hz: float) -> dict[str, Cause]:
    """The causes tried on ``n_sweeps`` sweeps (gain drift needs two) about a rod of ``rod_hz``
    (Hz) with the readings' Nyquist frequency ``nyquist_hz`` (Hz)."""
    lf, ln = math.log, math.log(nyquist_hz)
    modes = tuple((lf(f * rod_hz), lf(z)) for f in MODE_FRACTIONS for z in (0.02, 0.06)
                  if 2.0 < f * rod_hz < MODE_ABOVE * nyquist_hz) or ((ln - 1.0, lf(0.03)),)
    k = n_sweeps - 1
    out = [
        Cause("none", (), ((),), (), (), 0),
        Cause("second-mode", ("log_frequency_Hz", "log_damping_ratio"), modes,
              (lf(2.0), lf(MODE_DAMPING[0])), (ln + lf(MODE_ABOVE), lf(MODE_DAMPING[1])), 4,
              free_rod=True),
        Cause("sensor-delay", ("delay_fastest_samples", "window_fastest_samples"),
              tuple((d, 0.0) for d in (0.0, 0.5, 2.0, 5.0, 10.0, 25.0))
              + tuple((0.0, w) for w in (2.0, 5.0, 10.0, 20.0)),
              (0.0, 0.0), (60.0, 60.0), 2, free_rod=True),
        Cause("sensor-nonlinearity", ("quadratic_times_range", "cubic_times_range2"),
              cd.GAUGE_STARTS, (-cd.GAUGE_BOUND, -cd.GAUGE_BOUND),
              (cd.GAUGE_BOUND, cd.GAUGE_BOUND), 2),
        Cause("actuator-nonlinearity", (), ((),), (), (), 2),
        Cause("amplifier-lag", ("log_bandwidth_Hz", "log_damping_ratio"),
              ((ln + 2.9, lf(0.7)),) + tuple((lf(f * rod_hz), lf(0.7)) for f in (0.3, 1.0, 3.0))
              + ((ln, lf(0.7)),), (lf(1.0), lf(0.05)), (ln + 3.0, lf(10.0)), 2,
              input_side=True, free_rod=True),
    ]
    if k >= 1:
        lt = tuple(lf(t) for t in WARMUP_TIMES_S)
        drifts = ((0.0, lt[1]),) + tuple((d, t) for d in (-0.02, 0.02) for t in lt)
        out.append(Cause("voltage-gain-drift", tuple(f"log_gain_{i + 1}" for i in range(k))
                         + ("warmup_fraction", "log_warmup_time_s", "rail_low_margin",
                            "rail_high_margin"),
                         tuple((0.0,) * k + d + (m, m) for d in drifts for m in RAIL_MARGINS),
                         (-0.3,) * k + (-0.1, lf(0.1), 0.0, 0.0),
                         (0.3,) * k + (0.1, lf(1000.0), RAIL_MARGIN_MAX, RAIL_MARGIN_MAX), k + 4,
                         input_side=True))
    return {c.name: c for c in out}


class Held:
    """identify's model ``model`` on whole ``sweeps`` (recorded in sequence, each from its start
    in ``starts``): fitted on the rows of ``fit_masks``, judged on those of ``judged_masks``,
    every sweep in units of its ``noise`` (um); a gauge error stated about ``frame`` (the
    calibration readings' centre, half width and third and fourth moments:
    :func:`afmctl.fit.candidates.reading_frame`)."""

    def __init__(self, model: td.Transducer, sweeps: Sequence[Sweep], starts: Sequence[str],
                 fit_masks: Sequence[NDArray[np.bool_]],
                 judged_masks: Sequence[NDArray[np.bool_]], noise: FloatArray,
                 frame: tuple[float, float, float, float], gauge_in_base: bool = True,
                 offsets: Sequence[float] | None = None) -> None:
        self.model, self.sweeps, self.starts = model, list(sweeps), list(starts)
        self.gauge_in_base = gauge_in_base
        # each sweep's sensor zero as identified (um): the static output in the readings' frame
        self.offsets = np.nan_to_num(np.zeros(len(self.sweeps)) if offsets is None
                                     else np.asarray(offsets, dtype=float))
        self.fit_masks, self.judged_masks = list(fit_masks), list(judged_masks)
        self.noise, self.frame = np.asarray(noise, dtype=float), frame
        self.g = hf.static_um(model, sweeps, starts)
        # the fits see each sweep up to its last fitted row (an input-side cause re-runs that)
        self.fit_sweeps = [s.head(int(np.flatnonzero(m)[-1]) + 1) for s, m in zip(
            sweeps, fit_masks, strict=True)]
        self.dt_min = min(s.dt for s in sweeps)
        # each sweep's start in the record's time, s (taken back to back)
        self.t0 = np.concatenate(([0.0], np.cumsum([s.time_s[-1] - s.time_s[0] + s.dt
                                                    for s in sweeps])))[:-1]
        self.rod = np.log([model.rod.natural_hz, model.rod.damping_ratio])
        self.commands = (min(float(np.min(s.voltage_v)) for s in sweeps),
                         max(float(np.max(s.voltage_v)) for s in sweeps))  # V
        self.nyquist_hz = 0.5 / max(s.dt for s in sweeps)
        self.causes = causes(len(sweeps), model.rod.natural_hz, self.nyquist_hz)
        # the last input-side statics, by (cause, phi, fitted): a Jacobian's rod columns reuse it
        self._last: tuple[tuple[str, bytes, bool], list[FloatArray]] | None = None

    @classmethod
    def identified(cls, res: idf.FitResult, sweeps: Sequence[Sweep],
                   fit_masks: Sequence[NDArray[np.bool_]],
                   judged_masks: Sequence[NDArray[np.bool_]], noise: FloatArray,
                   frame: tuple[float, float, float, float], gauge_in_base: bool) -> Held:
        """The Held of an identification ``res`` (its model, each sweep's start and sensor
        zero) on whole ``sweeps``."""
        return cls(res.model, sweeps, [e.start for e in res.sweeps], fit_masks, judged_masks,
                   noise, frame, gauge_in_base, [e.offset_um for e in res.sweeps])

    # -- the model of each cause ------------------------------------------------------------

    def effects(self, name: str, phi: FloatArray) -> fx.Effects:
        """The effect of cause ``name`` at ``phi`` (a mode's gains are linear: not here)."""
        if name == "sensor-delay":
            return fx.Effects(sensor_delay_s=float(phi[0]) * self.dt_min,
                              sensor_window_s=float(phi[1]) * self.dt_min)
        if name == "sensor-nonlinearity":
            m, r, mu3, mu4 = self.frame
            return fx.Effects(sensor_quadratic_per_um=float(phi[0]) / r,
                              sensor_cubic_per_um2=float(phi[1]) / r ** 2, sensor_center_um=m,
                              sensor_half_range_um=r, sensor_third_moment_um3=mu3,
                              sensor_fourth_moment_um4=mu4)
        if name == "amplifier-lag":
            return fx.Effects(amplifier_bandwidth_hz=float(np.exp(phi[0])),
                              amplifier_damping_ratio=float(np.exp(phi[1])))
        if name == "voltage-gain-drift":
            (lo, hi), (a, b) = self.commands, phi[-2:]
            return fx.Effects(amplifier_rails_v=(lo - float(a) * (hi - lo),
                                                 hi + float(b) * (hi - lo)))
        return fx.Effects()

    def gains(self, name: str, phi: FloatArray, sweeps: Sequence[Sweep] | None = None
              ) -> tuple[float | FloatArray, ...]:
        """Each sweep's applied-voltage gain under cause ``name``: one per sweep, times a
        warm-up ``1 + delta (1 - exp(-t / tau))`` in the record's time ``t`` (the sweeps taken
        back to back) when ``delta`` is not 0 (then an array: one gain per sample of ``sweeps``,
        default the whole ones)."""
        sweeps = self.sweeps if sweeps is None else sweeps
        if name != "voltage-gain-drift":
            return tuple([1.0] * len(sweeps))
        k = len(self.sweeps) - 1
        g = np.exp(cs.log_gains(phi[:k]))
        delta, tau = float(phi[k]), float(np.exp(phi[k + 1]))
        if delta == 0.0:
            return tuple(float(v) for v in g)
        return tuple(gs * (1.0 + delta * (1.0 - np.exp(-(t0 + s.time_s - s.time_s[0]) / tau)))
                     for gs, t0, s in zip(g, self.t0, sweeps, strict=True))

    def statics(self, name: str, phi: FloatArray, fitted: bool = False) -> list[FloatArray]:
        """The static displacement (um) of every sweep (``fitted``: of its fitted part only)
        under cause ``name``: held, or re-run on the effect's field (input side; the last such run
        is kept, so that a finite-difference step in the rod's parameters alone does not re-run
        the hysteresis)."""
        sweeps = self.fit_sweeps if fitted else self.sweeps
        if not self.causes[name].input_side:
            return [g[:s.time_s.size] for g, s in zip(self.g, sweeps, strict=True)]
        key = (name, np.asarray(phi, dtype=float).tobytes(), fitted)
        if self._last is None or self._last[0] != key:
            model = replace(self.model, effects=self.effects(name, phi))
            self._last = key, hf.static_um(model, sweeps, self.starts,
                                           self.gains(name, phi, sweeps))
        return self._last[1]

    def columns(self, name: str, z: FloatArray, g: Sequence[FloatArray],
                sweeps: Sequence[Sweep], offsets: FloatArray | None = None) -> list[FloatArray]:
        """Per sweep: the design columns (N x k) of cause ``name`` at ``z`` on static
        displacements ``g`` (um; their sensor zeros ``offsets``, default the sweeps')."""
        fn, zn = np.exp(z[:2])
        phi, out = z[2:], []
        offsets = self.offsets if offsets is None else offsets
        for gs, s, o in zip(g, sweeps, offsets, strict=True):
            if name == "actuator-nonlinearity":
                out.append(rod_filter(np.column_stack((gs, gs * gs, gs ** 3)), fn, zn, s.dt))
                continue
            if name == "sensor-nonlinearity" and self.gauge_in_base:  # in the readings' frame
                gs = fx.ungauge(self.effects(name, phi), gs + o) - o
            u = rod_filter(gs, fn, zn, s.dt)
            if name == "second-mode":
                out.append(np.column_stack((u, *hf.mode_parts(u, *np.exp(phi), s.dt))))
            elif name == "sensor-delay":
                d, w = (float(p) * self.dt_min / s.dt for p in phi)
                out.append(fx.late(u, d, w, np.full(int(d + w) + 2, u[0]))[0][:, None])
            else:
                out.append(u[:, None])
        return out

    def design(self, name: str) -> hf.Design:
        """What :class:`afmctl.fit.heldfit.Problem` fits for cause ``name``: its columns, and the
        readings (a gauge's: the positions its inverse gives them)."""
        def design(z: FloatArray) -> list[tuple[FloatArray, FloatArray]]:
            e = self.effects(name, z[2:])
            cols = self.columns(name, z, self.statics(name, z[2:], True), self.fit_sweeps)
            return [(c, fx.ungauge(e, s.displacement_um)) for c, s in zip(cols, self.fit_sweeps,
                                                                          strict=True)]
        return design

    def readings(self, name: str, z: FloatArray, beta: FloatArray,
                 cols: Sequence[FloatArray]) -> list[FloatArray]:
        """What the fit reads (um) on the sweeps of ``cols``: the columns weighed, each sweep's
        zero (``beta``'s last entries, one per column set; a single one: every sweep's), the
        gauge."""
        k, e = cols[0].shape[1], self.effects(name, z[2:])
        zeros = beta[k:]
        return [fx.gauge(e, c @ beta[:k] + zeros[min(i, zeros.size - 1)])
                for i, c in enumerate(cols)]

    # -- fit and judge ------------------------------------------------------------------------

    def fit(self, name: str, max_nfev: int, start: FloatArray | None = None) -> Fit:
        """Cause ``name`` fitted on the fit rows from its seeds (the best of each rod seed
        polished: :data:`POLISHED`) or from ``start``: ``z``, the linear parameters, the solver's
        word, its evaluations and its cost (the weighted sum of squares)."""
        c = self.causes[name]
        prob = hf.Problem(self.design(name), [m[:s.time_s.size] for m, s in zip(
            self.fit_masks, self.fit_sweeps, strict=True)], self.noise)
        (flo, fhi), (zlo, zhi) = ROD_SPAN
        lo = np.concatenate((self.rod + np.log([flo, zlo]), c.lower))
        hi = np.concatenate((self.rod + np.log([fhi, zhi]), c.upper))
        hi[0] = max(hi[0], math.log(self.nyquist_hz))
        lo[1], hi[1] = max(lo[1], math.log(0.002)), min(hi[1], 0.0)
        rods = [self.rod]
        if c.free_rod:
            f, z = FREE_ROD_SEED
            rods.append(np.log([min(f * math.exp(self.rod[0]), 0.9 * self.nyquist_hz), z]))
        # the best POLISHED seeds of each rod (a rod moved with the effect starts off worse)
        runs = ([sorted((np.clip(np.concatenate((r, s)), lo, hi) for s in c.seeds),
                        key=prob.cost)[:1 if c.input_side else POLISHED] for r in rods]
                if start is None else [[start]])
        best = prob.polish([z for run in runs for z in run], lo, hi, max_nfev)
        beta = prob.solve(best.x)[0]
        cost = (self.reading_cost(name, best.x, beta, prob.w) if name == "sensor-nonlinearity"
                else 2.0 * float(best.cost))
        return best.x, beta, bool(best.success and best.status > 0), best.nfev, cost

    def reading_cost(self, name: str, z: FloatArray, beta: FloatArray, w: FloatArray) -> float:
        """The weighted sum of squares (each sweep's weight ``w``) of the fit on its rows in the
        readings' units: a gauge's solver weighs the positions its inverse gives the readings,
        whose scale moves with the gauge (its cost would not compare with the base's)."""
        cols = self.columns(name, z, self.statics(name, z[2:], True), self.fit_sweeps)
        got = self.readings(name, z, beta, cols)
        return float(sum(np.sum((ws * (s.displacement_um - u))[m[:s.time_s.size]] ** 2)
                         for ws, s, u, m in zip(w, self.fit_sweeps, got, self.fit_masks,
                                                strict=True)))

    def through(self, name: str, phi: FloatArray, halves: Sequence[Sweep],
                settings: idf.Settings) -> Held:
        """This context with the hysteresis identified again through cause ``name`` at ``phi``:
        on the field an input-side cause makes (the sweeps' first ``halves`` with the effect's
        voltages), or on the positions the gauge's inverse gives the readings (then the base no
        longer carries the gauge). The identification had absorbed what the effect does into its
        density."""
        effects, gains = self.effects(name, phi), self.gains(name, phi, halves)
        again = []
        for s, g in zip(halves, gains, strict=True):
            if name == "sensor-nonlinearity":
                again.append(replace(s, displacement_um=fx.ungauge(effects, s.displacement_um)))
                continue
            v = g * np.asarray(s.voltage_v, dtype=float)
            again.append(replace(s, voltage_v=fx.lag(fx.compile_chain(effects, s.dt), v,
                                                     float(v[0]))[0]))
        res = idf.fit(again, replace(settings, representation="hem", density="discrete"))
        return Held.identified(res, self.sweeps, self.fit_masks, self.judged_masks, self.noise,
                               self.frame, self.gauge_in_base and name != "sensor-nonlinearity")

    def heldout(self, name: str, z: FloatArray, beta: FloatArray
                ) -> tuple[float, tuple[float, ...], float]:
        """RMS of the fit on the judged rows (um: the root mean of the per-sweep mean squares),
        each sweep's, and the same root mean on the rows it was fitted on (um)."""
        cols = self.columns(name, z, self.statics(name, z[2:]), self.sweeps)
        sq = [(s.displacement_um - u) ** 2 for s, u in
              zip(self.sweeps, self.readings(name, z, beta, cols), strict=True)]
        rms, per = vd.judged_rms(sq, self.judged_masks)
        return rms, per, vd.judged_rms(sq, self.fit_masks)[0]

    def extended(self, name: str, z: FloatArray, beta: FloatArray, success: bool,
                 nfev: int) -> ext.Extended:
        """The fit as a model with its effect, its per-sweep gains, starts and sensor zeros:
        :func:`afmctl.fit.identify.predict_set` of it gives the fit's readings (the twin
        ``actuator-nonlinearity``, never named, is stated by its gains only: its model is the
        rod's)."""
        fn, zn = (float(v) for v in np.exp(z[:2]))
        phi, n_cols = z[2:], beta.size - len(self.sweeps)
        a, zeros = float(beta[0]), beta[n_cols:]
        effects, params = self.effects(name, phi), {"rod_natural_Hz": fn, "rod_damping_ratio": zn}
        if name == "second-mode":
            mode = fx.SecondMode(*(float(v) for v in np.exp(phi)), float(beta[1]) / a,
                                 float(beta[2]) / a)
            effects, zeros = fx.Effects(second_mode=mode), zeros / (1.0 + mode.gain)
        elif name == "actuator-nonlinearity":
            params |= {"quadratic_gain": float(beta[1]) / a, "cubic_gain": float(beta[2]) / a}
        elif name == "voltage-gain-drift":
            k = len(self.sweeps) - 1
            params |= {"warmup_fraction": float(phi[k]),
                       "warmup_time_s": float(np.exp(phi[k + 1]))}
        gains = self.gains(name, phi)
        model = replace(hf.with_rod(self.model, fn, zn, a,
                                    float(zeros[pz.zero_sweep(self.starts)])), effects=effects)
        return ext.Extended(name, model, gains, params | cs.physical(name, model, gains),
                            success, nfev, z, tuple(self.starts), tuple(float(v) for v in zeros),
                            beta)

    def readings_on(self, name: str, fitted: ext.Extended, sweep: Sweep) -> FloatArray:
        """What fitted cause ``name`` reads (um) on a sweep never recorded, from the state the
        first sweep started in (depoled if that carried on from an earlier history), with the
        last sweep's sensor zero and the sweeps' mean gain."""
        start = fitted.starts[0] if fitted.starts[0] != "previous" else "depoled"
        z, beta = fitted.x, fitted.beta
        g = hf.static_um(replace(self.model, effects=self.effects(name, z[2:])), [sweep], [start])
        cols = self.columns(name, z, g, [sweep], self.offsets[-1:])
        k = cols[0].shape[1]
        return self.readings(name, z, np.concatenate((beta[:k], beta[-1:])), cols)[0]


def refusal(fitted: ext.Extended, gauge_in_base: bool = False) -> str | None:
    """Why a fitted cause cannot be what it says (None: it can): a gauge still fitted on a base
    that carries it (``gauge_in_base``: its density was not identified again through the gauge,
    :func:`rebased`: no model states the hysteresis and the gauge apart), a second mode whose
    damping ends on its upper bound (:data:`MODE_DAMPING`: a filter's corner, not a resonance)
    or whose gain is beyond :data:`afmctl.fit.heldfit.GAIN_BOUNDS` (a "mode" carrying as much
    of the stroke as the rod)."""
    if fitted.name == "sensor-nonlinearity" and gauge_in_base:
        return ("the gauge was not identified apart from the density, which carries its static "
                "part (it took less than a fifth off the base's cost, or the density identified "
                "again through it fitted the first halves worse)")
    mode = fitted.model.effects.second_mode
    if fitted.name != "second-mode" or mode is None:
        return None
    if mode.damping_ratio >= 0.98 * MODE_DAMPING[1]:
        return (f"its damping ratio {mode.damping_ratio:.3g} sits on the bound of a resonance "
                f"({MODE_DAMPING[1]:g}): a filter's corner stands in for another effect")
    lo, hi = hf.GAIN_BOUNDS
    if not lo < mode.gain < hi:
        return f"its gain {mode.gain:.3g} is beyond a second mode's ({lo:g} to {hi:g})"
    return None


@dataclass(frozen=True)
class HeldBase:
    """Every cause judged on identify's model with its hysteresis held: the table (``none``
    first), identify's fit on the first halves (each sweep's RMS over its noise), each fit's
    context (for readings on other sweeps: an input-side cause's may hold a hysteresis
    identified through its effect), the wall time (s) and the fits refused as what they say
    (:func:`refusal`: name -> why; they take no part in the verdict)."""

    table: dict[str, Judged]
    identified_over_noise: tuple[float, ...]
    helds: dict[str, Held]
    seconds: float
    refused: dict[str, str]

    @property
    def judged(self) -> dict[str, Judged]:
        """The table without the refused fits: what the verdict reads."""
        return {k: j for k, j in self.table.items() if k not in self.refused}

    def readings(self, name: str, sweep: Sweep) -> FloatArray:
        """What fitted cause ``name`` reads on ``sweep`` (um; :meth:`Held.readings_on`)."""
        return self.helds[name].readings_on(name, self.table[name].fitted, sweep)

    def as_dict(self, floor_um: float) -> dict[str, Any]:
        """JSON-ready: the base, identify's fit and every cause's held-out figures."""
        base = self.table["none"].heldout_rms_um
        return {"model": HELD_BASE, "identified_over_noise": list(self.identified_over_noise),
                "candidates": {k: j.as_dict(base, floor_um) for k, j in self.table.items()},
                "refused": dict(self.refused), "seconds": round(self.seconds, 2)}


def rebases(held: Held, name: str, cost: float, base_cost: float) -> bool:
    """Whether cause ``name``, fitted at ``cost`` on ``held`` (the base's: ``base_cost``), has
    its density identified again through it (:func:`rebased`): an input-side cause, or a gauge
    on a base that carries it, that takes a fifth off the base's cost (:data:`REBASE_GAIN`).
    On such a base the gauge's held form (its inverse before the rod, the gauge after it) sees
    only the rod's dynamics, and its model is written from the density identified on the
    positions the gauge gives; a gauge not identified apart is refused (:func:`refusal`)."""
    gauge = name == "sensor-nonlinearity" and held.gauge_in_base
    return (held.causes[name].input_side or gauge) and cost < REBASE_GAIN * base_cost


def rebased(held: Held, name: str, fit: Fit, halves: Sequence[Sweep], settings: idf.Settings,
            max_nfev: int, say: Callable[[str], None]) -> tuple[Held, Fit]:
    """Cause ``name``'s ``fit`` (:meth:`Held.fit`; an input-side cause, or a gauge on a base that
    carries it: :func:`rebases`) with the density identified again through its effect
    (:meth:`Held.through`) and the cause refitted on it from that
    identification's rod, in turn, up to :data:`REBASES` times while each round takes a fifth
    off the cost (:data:`REBASE_GAIN`); a round that fits the first halves worse is not kept.
    A density identified without the effect had absorbed part of it, and the effect fitted on
    that density is too small: other-voltage-gain-drift-0's warm-up (2.2 % over 16.5 s) was
    fitted at 2.1 % over 95 s, and three rounds took its cost from 0.61 to 0.08 of the base's."""
    on = held
    for k in range(REBASES):
        say(f"  held {name}: identifying the density again through the effect ({k + 1}) ...")
        again = on.through(name, fit[0][2:], halves, settings)
        new = again.fit(name, max_nfev, np.concatenate((again.rod, fit[0][2:])))
        if new[-1] >= fit[-1]:
            break
        gained = new[-1] < REBASE_GAIN * fit[-1]
        on, fit = again, new
        if not gained:
            break
    return on, fit


def judge(sweeps: Sequence[Sweep], halves: Sequence[Sweep], noise: Sequence[float],
          settings: idf.Settings, names: Sequence[str], max_nfev: int,
          say: Callable[[str], None]) -> HeldBase:
    """identify's general coercive density on the first ``halves`` of ``sweeps``, then ``none``
    and every cause of ``names`` (those :func:`causes` has) fitted around it on the first halves
    and judged on the second halves.

    Parameters
    ----------
    sweeps, halves : sequence of Sweep
        The whole sweeps, recorded in sequence, and their first halves.
    noise : sequence of float
        Each sweep's sensor noise, um.
    settings : identify's Settings
        The identification's (its representation and density are set here).
    names : sequence of str
        The causes to try (diagnose's candidates; the twin is added with its sensor cause).
    max_nfev : int
        Evaluations of each least-squares run.
    say : callable
        One-line progress messages.
    """
    t0 = time.perf_counter()
    say("identifying the general coercive density on the first halves ...")
    res = idf.fit(halves, replace(settings, representation="hem", density="discrete"))
    ratios = tuple(e.rms_over_noise for e in res.sweeps)
    say("  general density: RMS / noise per half " + " / ".join(f"{r:.2f}" for r in ratios))
    masks = [s.mask(None) for s in sweeps]
    half = [np.arange(s.time_s.size) < s.time_s.size // 2 for s in sweeps]
    held = Held.identified(res, sweeps, [m & h for m, h in zip(masks, half, strict=True)],
                           [m & ~h for m, h in zip(masks, half, strict=True)],
                           np.asarray(noise, float),
                           cd.reading_frame(cd.recorded_calibration(sweeps)), True)
    tried = [n for n in held.causes if n == "none" or n in names
             or (n in cd.TWIN_ONLY and any(cd.TWINS.get(s) == n for s in names))]
    table, helds, base_cost = {}, {}, math.inf
    for name in tried:
        t1 = time.perf_counter()
        # a twin is fitted on its sensor cause's base: the two then differ only in the side
        on = next((helds[s] for s, t in cd.TWINS.items() if t == name and s in helds), held)
        z, beta, ok, nfev, cost = on.fit(name, max_nfev)
        base_cost = cost if name == "none" else base_cost
        if rebases(on, name, cost, base_cost):
            on, (z, beta, ok, nfev, cost) = rebased(on, name, (z, beta, ok, nfev, cost),
                                                    halves, settings, max_nfev, say)
        rms, per, fit_rms = on.heldout(name, z, beta)
        table[name] = Judged(on.extended(name, z, beta, ok, nfev), on.causes[name].n_added,
                             rms, per, time.perf_counter() - t1, fit_rms)
        helds[name] = on
        say(f"  held {name:20s} held-out RMS {rms:.4f} um ({table[name].fit_seconds:.1f} s)")
    refused = {n: why for n, j in table.items()
               if (why := refusal(j.fitted, helds[n].gauge_in_base)) is not None}
    for n, why in refused.items():
        say(f"  held {n} refused: {why}")
    return HeldBase(table, ratios, helds, time.perf_counter() - t0, refused)
