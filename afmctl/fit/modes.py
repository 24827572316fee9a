"""A second mechanical mode of an axis, identified with its hysteresis held.

An axis of an x/y stage moves mostly through its own resonance (the rod (16)), and a little
through a structural mode the axes share: the coupling fit finds that mode's frequency
(:attr:`afmctl.model.coupling.Coupling.mode_hz`), which may lie below the axis's own. A one-mode
rod cannot follow it: after every turning point of a fast triangle the shared mode rings, and the
axis's fit stays far above its noise on that sweep alone (foreign-xy-1: a 150 Hz mode carrying
4.4 % of x's stroke, 32x the noise on the 23 Hz triangle, 2.8x on the slowest).

The hysteresis and its static displacement ``g`` (um: the rod's force over its stiffness) are
held; the rod and the mode are fitted to the readings by variable projection::

    y_s = a (L[g_s] + g2 M1[L[g_s]] + r2 M2[L[g_s]]) + offset_s,

``L`` the rod (16) at unit DC gain, ``M1`` and ``M2`` the spring and damper parts of the mode of
:class:`afmctl.model.effects.SecondMode` (its ``gain`` ``g2`` and ``rate_gain`` ``r2``), ``a`` a
common scale (the mode's DC gain ``1 + g2`` is absorbed so that slow sweeps stay where they were).
The nonlinear parameters are the rod's and the mode's frequencies and dampings
(:mod:`afmctl.fit.heldfit`), started at the given frequencies (the coupling's modes) and at
fractions of the rod's.

The hysteresis so held was identified without the mode, while the mode's ringing (32x the noise
on foreign-xy-1's 23 Hz triangle) was the largest misfit: the density bent to it, and every
sweep stayed at 1.7-2.5x the noise once the mode was found. :func:`reidentified` therefore
identifies the axis again on the readings with the found mode taken out (its exact inverse,
:func:`afmctl.model.effects.remove_mode`), then fits the mode again on the readings as recorded
with that hysteresis held, and keeps whichever misses its worst sweep less. Pure numerics: no I/O.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from afmctl.files.sweepfile import Sweep
from afmctl.fit import heldfit as hf
from afmctl.fit import identify as idf
from afmctl.fit import openloops
from afmctl.fit import parametrization as pz
from afmctl.fit import uncertainty as unc
from afmctl.fit.rod_response import rod_filter
from afmctl.model import effects as fx
from afmctl.model import transducer as td

FloatArray = NDArray[np.float64]
#: Mode frequencies tried when none are given, as fractions of the rod's resonance.
SEED_FRACTIONS = (0.35, 0.5, 0.7, 1.4, 2.0)
#: Mode damping ratios tried at every seed frequency.
SEED_DAMPINGS = (0.02, 0.06)
#: Polished from this many of the best seeds.
POLISHED = 3
#: Evaluations of each least-squares run.
MAX_NFEV = 60
#: The mode is kept only if it brings the worst sweep's RMS (over its noise) below this share of
#: the fit without it (a ringing mode shows on the fast sweeps, far above the noise), or to
#: identify's floor from above it (foreign-xy-4's x: its 23 Hz triangle 1.56 -> 1.05x, the worst
#: sweep then the 3.3 Hz one the mode does not touch, 1.27x).
KEEP_BELOW = 0.8
#: ... and leaves no sweep worse than this times identify's own fit (a "mode" that trades the
#: slow sweeps for the fast one stands in for something else: an amplifier lag, a latency).
NO_WORSE = 1.05
#: The mode's frequency is searched within these factors of the given seeds (Hz).
SEED_SPAN = (0.7, 1.4)
#: Bounds of the mode's damping ratio.
DAMPING_BOUNDS = (0.005, 0.3)
#: Gains of a physical mode (:data:`afmctl.fit.heldfit.GAIN_BOUNDS`).
GAIN_BOUNDS = hf.GAIN_BOUNDS


@dataclass(frozen=True)
class ModeFit:
    """The rod and mode found (:class:`afmctl.model.effects.SecondMode`), the common scale ``a``,
    each sweep's rod zero (um; the readings' zero over ``1 + gain``) and RMS over its noise
    without the mode (``before``: the rod refitted alone) and with it (``after``)."""

    mode: fx.SecondMode
    natural_hz: float
    damping_ratio: float
    scale: float
    offsets_um: tuple[float, ...]
    before: tuple[float, ...]
    after: tuple[float, ...]
    identified: tuple[float, ...]
    converged: bool

    @property
    def physical(self) -> bool:
        """The mode's gain within :data:`GAIN_BOUNDS` and its zeros (the anti-resonance) in the
        left half-plane (``damping_ratio + rate_gain > 0``): its inverse is then exact."""
        m = self.mode
        return GAIN_BOUNDS[0] < m.gain < GAIN_BOUNDS[1] and m.damping_ratio + m.rate_gain > 0

    @property
    def kept(self) -> bool:
        """A :attr:`physical` mode that lowers the worst sweep's RMS below :data:`KEEP_BELOW` of
        the fit without it, or to identify's floor (:data:`afmctl.fit.identify.FLOOR`) from
        above it, and leaves no sweep worse than :data:`NO_WORSE` times identify's."""
        worst, before = max(self.after), max(self.before)
        return (self.physical and (worst < KEEP_BELOW * before or worst <= idf.FLOOR < before)
                and all(a <= NO_WORSE * i for a, i in zip(self.after, self.identified,
                                                          strict=True)))

    def to_dict(self) -> dict[str, object]:
        """JSON-ready: ``kept``, the mode's and the rod's parameters, the solver's word and each
        sweep's RMS over its noise in identify's fit, without the mode and with it."""
        m = self.mode
        return {"kept": self.kept, "physical": self.physical, "converged": self.converged,
                "frequency_Hz": m.frequency_hz,
                "damping_ratio": m.damping_ratio, "gain": m.gain, "rate_gain": m.rate_gain,
                "rod_natural_Hz": self.natural_hz, "rod_damping_ratio": self.damping_ratio,
                "per_sweep_over_noise_identified": list(self.identified),
                "per_sweep_over_noise_without": list(self.before),
                "per_sweep_over_noise_with": list(self.after)}


def _design(g: Sequence[FloatArray], sweeps: Sequence[Sweep]) -> hf.Design:
    """Per sweep: ``L[g]`` for the rod ``exp(z[:2])`` (Hz, damping ratio), and with a mode
    ``exp(z[2:])`` also ``M1[L[g]]`` and ``M2[L[g]]``; the readings as recorded."""
    def design(z: FloatArray) -> list[tuple[FloatArray, FloatArray]]:
        fn, zn = np.exp(z[:2])
        out = []
        for gs, s in zip(g, sweeps, strict=True):
            u = rod_filter(gs, fn, zn, s.dt)
            cols = [u, *hf.mode_parts(u, *np.exp(z[2:]), s.dt)] if z.size > 2 else [u]
            out.append((np.column_stack(cols), s.displacement_um))
        return out
    return design


def fit(model: td.Transducer, sweeps: Sequence[Sweep], starts: Sequence[str], noise: FloatArray,
        identified: Sequence[float], seeds_hz: Sequence[float] = (),
        window_s: idf.Window = None) -> ModeFit:
    """Fit the rod and a second mode to ``sweeps`` with ``model``'s hysteresis held.

    Parameters
    ----------
    model : Transducer
        An identified model of the paper's form, without effects (:func:`refined` checks).
    sweeps : sequence of Sweep
        In the order they were recorded; ``starts`` their hysteresis states
        (:data:`afmctl.fit.parametrization.STARTS`), ``noise`` their sensor noise (um).
    identified : sequence of float
        Each sweep's RMS over its noise in the fit that made ``model`` (what :attr:`ModeFit.kept`
        may not make worse).
    seeds_hz : sequence of float
        Mode frequencies to start from (Hz), e.g. the coupling's shared modes: the mode is then
        searched within :data:`SEED_SPAN` of them; without them, at fractions of the rod's
        resonance (:data:`SEED_FRACTIONS`), anywhere from 2 Hz to 0.9 of the Nyquist frequency.
    window_s : Window
        The samples each sweep is judged on (as identify's).

    Returns
    -------
    ModeFit
        The best mode found, kept or not (:attr:`ModeFit.kept`).
    """
    g = hf.static_um(model, sweeps, starts)
    prob = hf.Problem(_design(g, sweeps), [s.mask(window_s) for s in sweeps],
                      np.asarray(noise, float))
    rod = np.log([model.rod.natural_hz, model.rod.damping_ratio])
    nyquist = 0.5 / max(s.dt for s in sweeps)
    given = [f for f in seeds_hz if 2.0 < f < 0.9 * nyquist]
    span = (SEED_SPAN[0] * min(given), SEED_SPAN[1] * max(given)) if given else (2.0, nyquist)
    lo = np.concatenate((rod + np.log([0.5, 0.1]),
                         np.log([max(span[0], 2.0), DAMPING_BOUNDS[0]])))
    hi = np.concatenate((rod + np.log([2.0, 10.0]),
                         np.log([min(span[1], 0.9 * nyquist), DAMPING_BOUNDS[1]])))
    lo[1], hi[1] = max(lo[1], math.log(0.002)), min(hi[1], 0.0)
    freqs = given or [f for f in (k * model.rod.natural_hz for k in SEED_FRACTIONS)
                      if lo[2] < math.log(f) < hi[2]]
    seeds = [np.clip(np.concatenate((rod, np.log([f, z]))), lo, hi) for f in freqs
             for z in SEED_DAMPINGS]
    plain = prob.polish([rod], lo[:2], hi[:2], MAX_NFEV)
    ranked = sorted(seeds, key=prob.cost)[:POLISHED]
    best = prob.polish(ranked, lo, hi, MAX_NFEV)
    beta, _, per = prob.solve(best.x)
    fn, zn, f2, z2 = (float(v) for v in np.exp(best.x))
    a, g2 = float(beta[0]), float(beta[1] / beta[0])
    zeros = tuple(float(b) / (1.0 + g2) for b in beta[3:])  # the mode moves the rod's zero too
    return ModeFit(fx.SecondMode(f2, z2, g2, float(beta[2]) / a), fn, zn, a, zeros,
                   prob.ratios(prob.solve(plain.x)[2]), prob.ratios(per), tuple(identified),
                   bool(best.success and best.status > 0))


def with_mode(model: td.Transducer, found: ModeFit, starts: Sequence[str]) -> td.Transducer:
    """``model`` with the rod and mode of ``found`` (:func:`afmctl.fit.heldfit.with_rod`), the
    mode among its effects, the sensor zero that of the sweep
    :func:`afmctl.fit.parametrization.zero_sweep` names for ``starts``."""
    out = hf.with_rod(model, found.natural_hz, found.damping_ratio, found.scale,
                      found.offsets_um[pz.zero_sweep(starts)])
    return replace(out, effects=replace(model.effects, second_mode=found.mode))


#: The rod's estimates a mode's fit restates (the rod was refitted with it).
_ROD_ESTIMATES = {"natural_frequency": "natural_hz", "damping_ratio": "damping_ratio", "k": "k",
                  "c": "c", "a1": "a1", "a2": "a2", "offset": "offset_um"}


def _restated(parameters: Sequence[unc.Estimate], model: td.Transducer,
              mode: fx.SecondMode) -> tuple[unc.Estimate, ...]:
    """``parameters`` with the rod's values of ``model`` (no interval: not re-estimated) and the
    mode's four."""
    rod = model.rod
    out = [replace(p, value=float(getattr(rod, _ROD_ESTIMATES[p.name])), stderr=math.nan)
           if p.name in _ROD_ESTIMATES and not p.fixed else p for p in parameters]
    return tuple(out + [unc.Estimate("mode_frequency", mode.frequency_hz, math.nan, "Hz"),
                        unc.Estimate("mode_damping_ratio", mode.damping_ratio, math.nan, "1"),
                        unc.Estimate("mode_gain", mode.gain, math.nan, "1"),
                        unc.Estimate("mode_rate_gain", mode.rate_gain, math.nan, "1")])


def refined(result: idf.FitResult, sweeps: Sequence[Sweep], seeds_hz: Sequence[float] = (),
            window_s: idf.Window = None, at_floor_too: bool = False) -> idf.FitResult:
    """``result`` (identify's, on ``sweeps``) with a second mode (:func:`fit`) where it is kept
    (:attr:`ModeFit.kept`): the model, its parameters and every sweep's error restated (the
    uncertainty's intervals, computed without the mode, are marked so); the mode's figures under
    ``representations["second_mode"]`` either way. Not tried on a fit already at its noise floor
    (:attr:`afmctl.fit.identify.FitResult.at_noise_floor`: nothing is left for a mode to
    explain; ``at_floor_too``: tried there as well), on a fit that is not finite, or on a model
    with effects of its own."""
    why = ("every sweep at its noise floor" if result.at_noise_floor and not at_floor_too else
           "the fit is not finite" if not result.finite else
           "the model has effects of its own" if result.model.effects != fx.Effects() else None)
    if why is not None:
        return replace(result, representations={**result.representations, "second_mode": {
            "kept": False, "skipped": why}})
    t0 = time.perf_counter()
    on = [i for i in range(len(sweeps)) if i not in result.held_out]  # what the model was fitted on
    used = [sweeps[i] for i in on]
    starts = [result.sweeps[i].start for i in on]
    with threadpool_limits(limits=1, user_api="blas"):  # small dense algebra, as identify's
        found = fit(result.model, used, starts,
                    np.array([result.sweeps[i].noise_um for i in on]),
                    [result.sweeps[i].rms_over_noise for i in on], seeds_hz, window_s)
    figures = {**result.representations, "second_mode": found.to_dict()}
    seconds = result.seconds + time.perf_counter() - t0
    if not found.kept:
        return replace(result, representations=figures, seconds=seconds)
    model = with_mode(result.model, found, starts)
    note = (f"computed before the rod was refitted with a second mode at "
            f"{found.mode.frequency_hz:.4g} Hz: they hold for the model without it")
    return replace(result, model=model,
                   sweeps=openloops.judged(model, sweeps, result.held_out, starts,
                                           found.offsets_um, window_s),
                   parameters=_restated(result.parameters, model, found.mode),
                   uncertainty={**result.uncertainty, "note": note} if result.uncertainty else {},
                   message=f"{result.message}; a second mode at {found.mode.frequency_hz:.4g} Hz",
                   seconds=seconds, representations=figures)


def without_mode(sweeps: Sequence[Sweep], mode: fx.SecondMode) -> list[Sweep]:
    """``sweeps`` with ``mode``'s motion taken out of the readings (the exact inverse of the
    model's mode, :func:`afmctl.model.effects.remove_mode`), scaled by the mode's DC gain
    ``1 + gain`` so that a held reading stays where it was (um)."""
    effects = fx.Effects(second_mode=mode)
    return [replace(s, displacement_um=(1.0 + mode.gain) * fx.remove_mode(
        fx.compile_chain(effects, s.dt), s.displacement_um)) for s in sweeps]


def reidentified(result: idf.FitResult, sweeps: Sequence[Sweep], seeds_hz: Sequence[float],
                 settings: idf.Settings, say: Callable[[str], None] | None = None
                 ) -> idf.FitResult:
    """``result`` (:func:`refined`'s, on ``sweeps``) identified again without its mode's ringing.

    Where ``result`` kept a mode: :func:`afmctl.fit.identify.fit` on the readings with that mode
    taken out (:func:`without_mode`), then :func:`refined` on the readings as recorded, seeded at
    the mode found. That second result is returned if it keeps a mode too and misses its worst
    sweep less than ``result`` (RMS over noise, on the recorded readings); else ``result``. The
    figures of the second identification are under ``representations["second_mode"]
    ["reidentified"]`` either way.
    """
    mode = result.model.effects.second_mode  # set by :func:`refined` when it keeps one
    if mode is None:
        return result
    (say or (lambda _m: None))(f"identifying again with the {mode.frequency_hz:.4g} Hz mode "
                               "taken out of the readings ...")
    t0 = time.perf_counter()
    again = refined(idf.fit(without_mode(sweeps, mode), settings), sweeps,
                    (mode.frequency_hz, *seeds_hz), settings.window_s, at_floor_too=True)
    kept = again.model.effects.second_mode is not None
    worst = [max(s.rms_over_noise for s in r.sweeps) for r in (result, again)]
    better = kept and worst[1] < worst[0]
    figures = {"kept": better, "mode_kept": kept, "seconds": time.perf_counter() - t0,
               "per_sweep_over_noise": [s.rms_over_noise for s in again.sweeps] if kept else None,
               "worst_over_noise_before": worst[0]}
    chosen = again if better else result
    modes_figures = {**chosen.representations["second_mode"], "reidentified": figures}
    return replace(chosen, representations={**chosen.representations,
                                            "second_mode": modes_figures},
                   seconds=result.seconds + figures["seconds"])
