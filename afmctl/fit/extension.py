"""Candidate model extensions: the paper's model plus one physical effect, fitted by least squares.

Each candidate cause of a model discrepancy (``afmctl diagnose``; the catalogue, its parameters
and bounds are :mod:`afmctl.fit.candidates`) is the identified model of :mod:`afmctl.fit.parametrization`
plus a few parameters ``phi`` of one effect; its residual is
:class:`afmctl.fit.candidate_space.ExtendedSpace`. This module fits it (:func:`fit`: starts,
the joint fit, the polish on the fine grid, the refit of the paper's model through the effect)
and holds the fitted candidate (:class:`Extended`).
Pure numerics: no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy import optimize

from afmctl.fit import identify as idf
from afmctl.fit import noise as ns
from afmctl.fit import parametrization as pz
from afmctl.fit.candidate_space import ExtendedSpace, physical
from afmctl.fit.candidates import INPUT_SIDE
from afmctl.fit.relaxation import THERMAL_COARSE, THERMAL_FINE, THERMAL_JOINT, density_starts
from afmctl.model import transducer as td

FloatArray = NDArray[np.float64]
#: Candidates whose multi-start result refits the paper's model through the effect (:func:`_rebase`).
REBASED = ("amplifier-lag", "sensor-delay", "sensor-nonlinearity")
#: The refit through the effect is tried only when the multi-start's effect has already brought
#: the cost below this fraction of the base model's (on a clean stage it would cost a whole
#: identification for nothing).
REBASE_GAIN = 0.8
#: The polish on the fine grid gets this fraction (1/FINE_SHARE) of a fit's evaluations.
FINE_SHARE = 12


@dataclass(frozen=True)
class Extended:
    """A fitted candidate: the model (with its effect), per-sweep applied-voltage gains, initial
    hysteresis states and sensor zeros (um), and the solver's word."""

    name: str
    model: td.Transducer
    gains: tuple[float | FloatArray, ...]
    parameters: dict[str, float]
    success: bool
    nfev: int
    x: FloatArray
    starts: tuple[str, ...]
    offsets_um: tuple[float, ...]
    beta: FloatArray

    @property
    def present(self) -> td.Transducer:
        """The model as the record left the stage, for ``track``: a gain that drifted in time
        (an array per sample: a warm-up) folded in at its last value ``g``, the field's
        thickness and the amplifier's rails divided by it (what ``g v`` through the rails does
        to a command ``v``); the model itself otherwise. A gain drawn per run (a float per
        sweep, log mean 0) is the next run's too: nothing is folded."""
        last = self.gains[-1] if self.gains else 1.0
        if np.ndim(last) == 0:
            return self.model
        g = float(np.asarray(last)[-1])
        rails = self.model.effects.amplifier_rails_v
        effects = (self.model.effects if rails is None else replace(
            self.model.effects, amplifier_rails_v=(rails[0] / g, rails[1] / g)))
        return replace(self.model, thickness_um=self.model.thickness_um / g, effects=effects)


def _stage(space: ExtendedSpace, text: str) -> None:
    if space.progress is not None:
        space.progress.stage(text)


def _rebase(space: ExtendedSpace, z: FloatArray, settings: idf.Settings,
            globally: bool = True) -> tuple[ExtendedSpace, FloatArray]:
    """``x`` and each sweep's start fitted afresh with the effect of ``z`` held
    (:meth:`~afmctl.fit.candidate_space.ExtendedSpace.through`): the base fit had distorted ``x`` and the starts to absorb
    the effect (a rod slowed to a third of its resonance under a strong amplifier lag; loops
    widened by a sensor's latency, bent by a gauge error). Through an amplifier with identify's
    global fit (its grid of starting points, restarts while a sweep stays off its noise): too
    far for a local fit to come back from; through a sensor effect with identify's local round
    from ``x`` (solve, re-choose the starts, solve again if one changed) and, if ``globally``,
    the global fit too, the lower cost kept: a strong gauge (the in-family bench's index 114,
    20x the noise on the paper's model) had bent the base too far for the local round, 5.2x the
    noise after it against 1.01x after the global fit."""
    n_x = z.size - space.candidate.n_params
    _stage(space, "the paper's model refitted through the effect")
    base = space.through(z[n_x:])
    noise = np.array([max(ns.sensor_noise_um(p.y), 1e-12) for p in base.preps])
    prob = idf.Problem((), base.preps, np.concatenate([p.y for p in base.preps]), noise,
                       settings, lambda _m: None)
    fits = []
    if space.candidate.name not in INPUT_SIDE:
        fits.append(idf.solve_round(base, z[:n_x], prob))
    if globally or not fits:
        fits.append(idf.global_fit(prob)[:2])
    found, sol = min(fits, key=lambda f: float(f[1].cost))
    return space.with_starts(found.starts), np.concatenate((sol.x, z[n_x:]))


def state_choices(n: int) -> list[tuple[str, ...]]:
    """Initial states of ``n`` sweeps recorded in sequence, each after the one before: the first
    depoled or poled either way, the others where the previous left it (:data:`pz.STARTS`)."""
    return [(first,) + ("previous",) * (n - 1) for first in pz.STARTS[:3]]


def _in_sequence(space: ExtendedSpace, z: FloatArray) -> ExtendedSpace | None:
    """``space`` with the :func:`state_choices` that fits best at ``z``; None if every sweep
    after the first already carries on from the one before (a base fit that restarted only
    some of them from a poled state still gets the sequence)."""
    if all(s == "previous" for s in space.base.starts[1:]) or len(space.preps) < 2:
        return None
    return min((space.with_starts(c) for c in state_choices(len(space.preps))),
               key=lambda s: float(np.sum(s.residual(z) ** 2)))


def _started(space: ExtendedSpace, x_base: FloatArray, max_nfev: int, n_starts: int,
             identify: idf.Settings | None) -> tuple[ExtendedSpace, FloatArray, int]:
    """Multi-start on ``phi`` with ``x_base`` held (see :func:`fit`): the space (with the starts
    a refit through the effect chose), the joint fit's start ``z`` and the evaluations spent."""
    lo, hi = space.bounds()
    n_x = x_base.size
    n_held = 0 if space.candidate.fresh_density else 4 if space.candidate.free_rod else n_x

    def clip(z: FloatArray) -> FloatArray:
        return np.clip(z, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))

    def cost(z: FloatArray) -> float:
        return float(np.sum(space.residual(z) ** 2))

    def with_free(v: FloatArray) -> FloatArray:
        return space.residual(np.concatenate((x_base[:n_held], v)))

    starts = [clip(np.concatenate((x_base, s))) for s in space.candidate.starts]
    cost_off = cost(starts[0])
    ranked = sorted(starts, key=cost)[:max(n_starts, 1)]
    if space.candidate.fresh_density:  # the best of the effect's starts on a fresh density too
        e_max = pz.extent(space.preps)[0]
        fresh = [clip(np.concatenate((x, s))) for x in density_starts(x_base, e_max)
                 for s in space.candidate.starts[1:]]
        ranked = ranked[:max(n_starts - 1, 1)] + [min(fresh, key=cost)]
        starts += fresh
    nfev = len(starts)
    if n_x < ranked[0].size:
        runs = [optimize.least_squares(with_free, z0[n_held:], bounds=(lo[n_held:], hi[n_held:]),
                                       diff_step=1e-6, max_nfev=max_nfev // 2) for z0 in ranked]
        best = min(runs, key=lambda r: float(r.cost))
        if space.candidate.switch:  # the switch (the slew limit) tried the other way too
            other = {s[-1] for s in space.candidate.starts} - {float(best.x[-1])}
            runs += [optimize.least_squares(
                with_free, np.concatenate((best.x[:-1], [v])), bounds=(lo[n_held:], hi[n_held:]),
                diff_step=1e-6, max_nfev=max_nfev // 2) for v in sorted(other)]
            best = min(runs, key=lambda r: float(r.cost))
        nfev += sum(r.nfev for r in runs)
        ranked = [clip(np.concatenate((x_base[:n_held], best.x)))]
        if space.candidate.name in REBASED and 2 * float(best.cost) < REBASE_GAIN * cost_off:
            settings = identify or idf.Settings()
            rebased = [_rebase(space, ranked[0], settings)]
            first, z1 = rebased[0]
            rebased += [_rebase(first, clip(np.concatenate((z1[:n_x], s))), settings, False)
                        for s in first.gauge_seeds(z1[:n_x])]
            scored = [(float(np.sum(s.residual(clip(z)) ** 2)), s, clip(z)) for s, z in rebased]
            found_cost, found, z = min(scored, key=lambda f: f[0])
            if found_cost < cost(ranked[0]):
                space, ranked = found, [z]
    return space, ranked[0], nfev


def _joint(start: tuple[ExtendedSpace, FloatArray, int], max_nfev: int
           ) -> tuple[ExtendedSpace, optimize.OptimizeResult, int]:
    """The joint fit of ``(x, phi)`` in a space from ``z`` (``start``: the space, ``z`` and the
    evaluations so far); the space, solution and evaluations."""
    space, z, nfev = start
    lo, hi = space.bounds()
    sol = optimize.least_squares(space.residual, z, bounds=(lo, hi), diff_step=1e-6,
                                 max_nfev=max_nfev)
    return space, sol, nfev + int(sol.nfev)


def fit(space: ExtendedSpace, x_base: FloatArray, thickness_um: float,
        max_nfev: int, n_starts: int = 1,
        identify: idf.Settings | None = None) -> tuple[Extended, ExtendedSpace]:
    """Fit ``(x, phi)`` from the base parameters ``x_base``; returns the fit and its space (the
    initial hysteresis states and the grid it chose).

    Multi-start on the effect alone: from each of the ``n_starts`` best of the candidate's starting
    ``phi`` (by cost) a short least-squares run moves ``phi`` (and the rod's two parameters, for
    a candidate with ``free_rod``) with the rest of the base model held (a Jacobian of a few
    columns); the best of those then starts the joint fit of ``(x, phi)``. A ``fresh_density``
    candidate (relaxation) runs one of its short runs from the best of its effect's starts on a
    fresh density (:func:`density_starts`), and its short runs move the whole model. The
    amplifier and the sensor effects (:data:`REBASED`) then fit ``x`` and the starts afresh
    through their effect (:func:`_rebase`, with the ``identify`` settings; tried if the effect
    alone already brought the cost below :data:`REBASE_GAIN` of the base model's, kept if it
    lowers the cost). The base model is in every candidate's family (the viscous form's comes
    within a sample's lag of it), so its own cost bounds the result's.

    An ``own_states`` candidate (relaxation: the state a sweep starts from has relaxed with the
    sweeps before it) is also fitted with the sweeps in sequence (:func:`state_choices`, the
    first state chosen at the best start) unless the base's states already are, each
    multi-start with half the budget on a coarse thermal grid (:data:`THERMAL_COARSE`); the
    lower cost's start gets the whole joint fit on a grid that resolves small field scales
    (:data:`THERMAL_JOINT`), polished on the fine one with 1/:data:`FINE_SHARE` of the budget.
    A ``sequenced`` candidate (a gain per run) is fitted, each with the whole budget, from the
    base's states and from every first state of the sweeps in sequence; the lowest cost wins.
    ``max_nfev`` is multiplied by the candidate's :attr:`~afmctl.fit.candidates.Candidate.budget`."""
    max_nfev *= space.candidate.budget
    spaces = [space]
    if space.candidate.own_states:
        spaces = [space.with_grid(THERMAL_COARSE)]
        z0 = np.concatenate((x_base, space.candidate.starts[0]))
        spaces += [s for s in [_in_sequence(spaces[0], z0)] if s is not None]
        _stage(space, f"multi-start on the coarse grid ({THERMAL_COARSE[0]} rows), "
                      f"{len(spaces)} choice(s) of the sweeps' start states")
    elif space.candidate.sequenced and len(space.preps) > 1:
        spaces += [space.with_starts(c) for c in state_choices(len(space.preps))
                   if c != space.base.starts]
    if space.candidate.sequenced:
        fits = [_joint(_started(s, x_base, max_nfev, n_starts, identify), max_nfev)
                for s in spaces]
        nfev = sum(f[2] for f in fits)
        space, sol, _ = min(fits, key=lambda f: float(f[1].cost))
    else:  # the best start of every space gets the whole joint fit
        started = [_started(s, x_base, max_nfev // len(spaces), n_starts, identify)
                   for s in spaces]
        space, z, _ = started[0] if len(started) == 1 else min(
            started, key=lambda f: float(np.sum(f[0].residual(f[1]) ** 2)))
        if space.candidate.own_states:
            space = space.with_grid(THERMAL_JOINT)
            _stage(space, f"joint fit (up to {max_nfev} evaluations, {THERMAL_JOINT[0]} rows)")
        space, sol, nfev = _joint((space, z, sum(f[2] for f in started)), max_nfev)
    if space.candidate.own_states:  # polished on the fine grid
        _stage(space, f"polish on the fine grid ({THERMAL_FINE[0]} rows)")
        space, sol, nfev = _joint((space.with_grid(THERMAL_FINE), sol.x, nfev),
                                  max(max_nfev // FINE_SHARE, 1))
    model, gains, offsets = space.to_model(sol.x, thickness_um)
    beta = pz.project(*space.system(sol.x))[0]
    fitted = physical(space.candidate.name, model, gains)
    for k in range(3, space.n_rod + 1):  # the gains of L[Q^k] (in the fit's units)
        fitted[f"gain_Q{k}"] = float(beta[k - 1])
    return Extended(space.candidate.name, model, gains, fitted,
                    bool(sol.success and sol.status > 0), nfev, sol.x,
                    space.base.starts, offsets, beta), space
