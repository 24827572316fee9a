"""Identification of the Preisach grid (:mod:`afmctl.model.preisach`) with creep, from sweeps.

The classic identification of a Preisach density is a convex problem: the output is linear in the
density's weights, which are non-negative, and a smoothness penalty on the grid makes the problem
well posed (non-negative least squares with Tikhonov regularization). Here the output is not the
polarization but the displacement of the rod (16), ``u = L[a1 P + a2 P^2 + a3 P^3] / k`` (the
paper's force with a cubic term, see :func:`~afmctl.fit.preisach_problem.output_map`), with ``L``
the rod's unit-DC-gain dynamics; in the frame of :mod:`afmctl.fit.parametrization`::

    u = L[g(Q~)] + offset_s,    g(Q) = Q + s Q^2 + t Q^3,    Q~ = Q + sum_j c_j Z_j[Q],
    Q = r E + sum_ij w_ij erf((y_i + E_I,j) / (sqrt(2) spread))      (um),

with ``y_i`` the play output of coercive row ``i`` (fixed by the field history and the start
state, not by any parameter), ``Z_j`` the creep elements of :mod:`afmctl.model.creep`, and the
gain fixed by convention in ``g``. The weights ``w, r, c >= 0`` enter linearly but for the
map's ``s Q^2 + t Q^3`` (the ``a2 P^2`` of (16) and its cubic) and the product of creep and
hysteresis. The fit is Gauss-Newton on that structure: at each step the model is linearized in
``(w, r, c, s, t)`` about the last point (exact in ``s`` and ``t``; the columns are
``L[g'(Q~) C[basis]]``), with the rod's natural frequency and damping as two more columns (their
finite-difference derivatives, Levenberg-damped), and the linear problem (bounded: ``w, r, c >=
0``; free: ``s, t``, the rod, one offset per sweep) is solved exactly: the free variables
eliminated from the normal equations, then :func:`scipy.optimize.nnls` on the rest. A step that
does not lower the true cost is halved (the solver: :mod:`afmctl.fit.preisach_solver`).

The creep may act on the force instead (:attr:`afmctl.model.creep.Creep.acts_on`):
``u = L[g(Q) + sum_j c_j Z_j[g(Q)]] + offset_s``, the columns ``L[C[g'(Q) basis]]``; both are fitted
(:func:`runs`).

The penalty weight (and whether creep is kept, and on what) is chosen by held-out error: the residual rows are
cut into blocks, dealt in turn to four folds; each candidate is fitted on three folds (linearized
at the full fit, rod frozen) and judged on the fourth with the exact model, each fold in turn.
Identify compares that held-out error, against each sweep's sensor noise, with the parametric
HEM's (:mod:`afmctl.fit.representation`).
"""

from __future__ import annotations

import copy
import functools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from afmctl.files.sweepfile import Sweep, holds_s
from afmctl.fit import cores
from afmctl.fit import parametrization as pz
from afmctl.fit import preisach_coarse as pc
from afmctl.fit import preisach_problem as pp
from afmctl.fit import uncertainty as unc
from afmctl.fit.preisach_basis import Grid, basis, hat_matrix
from afmctl.fit.preisach_problem import (
    BLOCKS,
    CREEP_TAUS_S,
    CREEP_THRESHOLDS,
    FOLDS,
    SMOOTHING,
    TRANSIENT_SPAN,
    Data,
    Problem,
    Settings,
    Theta,
    make_grid,
)
from afmctl.fit.preisach_solver import (
    Linearized,
    Run,
    bounded_solve,
    gauss_newton,
    grid_penalty,
    heldout,
    penalty,
    refit_rod,
    rod_rivals,
)
from afmctl.fit.rod_response import rod_filter
from afmctl.model import creep as cr
from afmctl.model import preisach as pr
from afmctl.model import rod as rd
from afmctl.model import transducer as td

FloatArray = NDArray[np.float64]
#: identify fits creep only if the grid without it is above this many times some sweep's noise:
#: below, creep has nothing left to explain (on the family plant's pi-u, at 1.02-1.07x without
#: it, the two creep fits took 281 of the grid's 438 s).
CREEP_ABOVE = 1.1
#: A creep fit that explains most of the misfit (less than half the sum of squares left) but
#: leaves a sweep above this many times its noise is fitted again from the start assignment
#: whose first linear step came second: that step, taken without creep, ranks the start states
#: poorly on a creeping stage (the family plant's preisach-b-creep: "positive" first, its creep
#: fit stuck at 5.3x the noise).
RETRY_ABOVE = 1.5
#: Levenberg damping the last Gauss-Newton steps (on the full problem, from the coarse
#: problem's fit) start with, a share of ``diag(G)`` (:func:`gauss_newton`'s ``mu0``): the fit
#: starts near the full problem's minimum, where its linearization foresees each step (on pi-u
#: the five steps from the usual 1e-4 each fell as foreseen to 1 %, held back only by the
#: damping); from 1e-6 they took two, to the same errors within 1e-3 of the noise (both with
#: the fixed rule, stop 60; the last steps now follow Nielsen's, stop 61).
POLISH_MU = 1e-6
#: Lighter smoothings are tried only while some sweep is above this many times its noise held
#: out (:func:`_finer`): below, there is nothing left for them to gain, and each costs a fit.
FINER_ABOVE = 1.1
#: ... and a lighter one is kept only if it lowers the held-out sum of squares by this share.
FINER_GAIN = 0.01

__all__ = ["CREEP_TAUS_S", "CREEP_THRESHOLDS", "SMOOTHING", "BLOCKS", "FOLDS", "TRANSIENT_SPAN",
           "Settings", "hat_matrix", "Grid", "make_grid", "basis", "Data", "rod_filter", "Theta",
           "Problem", "PreisachFit", "Runs", "fit", "runs", "gauss_newton", "heldout",
           "bounded_solve", "penalty", "grid_penalty", "refit_rod", "start_candidates",
           "sweep_data", "POLISH_MU", "scalar_uncertainty"]


# ----------------------------------------------------------------------------------------------
# the fit
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PreisachFit:
    """Outcome of :func:`fit`.

    Attributes
    ----------
    model : transducer.Transducer
        The Preisach grid (with creep if kept), the rod, the last sweep's sensor zero.
    starts : tuple of str
        Each sweep's start state.
    offsets : ndarray
        Each sweep's sensor zero, um.
    heldout_rms_um : ndarray
        Per sweep, the RMS on samples the fit did not see (two folds of blocks), um.
    smoothing : float
        The relative smoothing chosen by held-out error.
    creep : bool
        Whether creep was kept (it lowered the held-out error).
    candidates : dict
        Held-out sum of squares over noise variance of every (creep, smoothing) tried, and of
        the chosen fit refitted at its smoothing and the lighter ones (``..., refitted``:
        :func:`_finer`).
    iterations, converged, seconds
        Gauss-Newton iterations of the final fit, whether it converged, wall time (s).
    insample_over_noise : ndarray
        Per sweep, the final fit's RMS over its noise on all judged samples.
    n_coefficients : int
        Coefficients the sweeps move (the fitted weights).
    uncertainty : dict
        :func:`afmctl.fit.uncertainty.summary` of the scalar parameters (reversible slope, creep
        weights, ``s``, rod, offsets), the density's weights held.
    p_scale : float
        The polarization scale convention, C/m^2.
    predicted : list of ndarray
        The fit's readings on every sample of each sweep (um): the model's, with the sweep's
        sensor zero and its creep transient (the history before the sweep).
    interior_loops : int
        The sweeps' loops with both ends inside their range
        (:func:`afmctl.fit.preisach_problem.interior_loops`).
    cubic : bool
        Whether the force's cubic was fitted (else held at 0: too few interior loops).
    """

    model: td.Transducer
    starts: tuple[str, ...]
    offsets: FloatArray
    heldout_rms_um: FloatArray
    smoothing: float
    creep: bool
    candidates: dict[str, float]
    iterations: int
    converged: bool
    seconds: float
    insample_over_noise: FloatArray
    n_coefficients: int
    uncertainty: dict[str, Any]
    p_scale: float
    predicted: list[FloatArray]
    interior_loops: int
    cubic: bool

    @property
    def how(self) -> str:
        """How the final Gauss-Newton fit ended (as :attr:`BoucWenFit.how
        <afmctl.fit.boucwen.BoucWenFit.how>`)."""
        return "converged" if self.converged else "stopped on its budget"


def build(th: Theta, prob: Problem, scales_mass: float, thickness_um: float,
          p_scale: float, creep: bool) -> td.Transducer:
    """The physical model of ``th``: ``P = kappa Q`` with ``kappa`` making the largest ``|Q|`` over
    the sweeps ``p_scale`` (C/m^2, a convention like P_R), ``k = m (2 pi f_n)^2``, and the force
    ``a1 P + a2 P^2 + a3 P^3`` giving ``g(Q)`` in um: ``a1 = 1e-6 k / kappa``, ``a2 = 1e-6 k s /
    kappa^2``, ``a3 = 1e-6 k t / kappa^3``."""
    q_max = max(float(np.max(np.abs(q))) for q in prob.hysteretic(th)) or 1.0
    kappa = p_scale / q_max
    g = prob.grid
    w = np.maximum(g.weights(th.w) * kappa, 0.0)
    grid = pr.PreisachGrid(tuple(g.coercive), tuple(g.interaction), g.spread,
                           tuple(map(tuple, w)), th.r * kappa)
    fn, zeta = math.exp(th.log_fn), math.exp(th.log_zeta)
    k = scales_mass * (2 * math.pi * fn) ** 2
    rod = rd.Rod(m=scales_mass, c=2 * zeta * math.sqrt(k * scales_mass), k=k,
                 a1=1e-6 * k / kappa, a2=1e-6 * k * th.s / kappa ** 2,
                 a3=1e-6 * k * th.t / kappa ** 3,
                 offset_um=float(th.offsets[pz.zero_sweep(prob.starts)]))
    unit = 1e-6 * k if prob.creep_on_force else kappa  # um of g(Q) -> N, um of Q -> C/m^2
    on = "force" if prob.creep_on_force else "polarization"
    cp = cr.Creep(tuple(float(t) for t in prob.el_tau), tuple(float(c) for c in th.c),
                  tuple(float(r) * unit for r in prob.el_thr), on) if creep and th.c.any() else None
    first = prob.starts[0] if prob.starts[0] != "previous" else "depoled"
    return td.Transducer(grid, rod, thickness_um, initial=first, creep=cp)  # type: ignore[arg-type]


def _active(data: Data, ec: FloatArray, ei: FloatArray, spread: float, mi: FloatArray,
            mj: FloatArray, starts_list: Sequence[Sequence[str]], plays: bool = False
            ) -> NDArray[np.intp]:
    """Coefficients that move some cell whose erf varies on the judged samples of some sweep
    (under some of the start assignments); with ``plays``, then each row's play that does."""
    var = np.zeros((ec.size, ei.size), dtype=bool)
    for starts in starts_list:
        y_end = None
        for e, m, start in zip(data.fields, data.masks, starts, strict=True):
            y0 = (y_end if start == "previous" and y_end is not None else
                  pr.start_outputs(ec, "depoled" if start == "previous" else start))
            y = pr.play(e, ec, y0)
            y_end = y[-1]
            ym = y[m]
            lo, hi = ym.min(axis=0), ym.max(axis=0)  # per row
            var |= ((-ei[None, :] > lo[:, None] - pr.CUT * spread) &
                    (-ei[None, :] < hi[:, None] + pr.CUT * spread) &
                    (hi - lo > 1e-12)[:, None])
    coarse = (mi.T @ var.astype(float) @ mj) > 0
    moved = np.concatenate((coarse.ravel(), var.any(axis=1) if plays else np.zeros(0, bool)))
    return np.flatnonzero(moved)


def sweep_data(sweeps: Sequence[Sweep], thickness_um: float, noise_um: Sequence[float],
               window_s: tuple[float, float] | None = None) -> Data:
    """``sweeps`` as the fit sees them: fields (MV/m), the readings (um) on each sweep's judged
    samples (after its first excursion, within ``window_s``), sample periods and each sweep's
    sensor noise (um)."""
    return Data([s.voltage_v / thickness_um for s in sweeps], [s.mask(window_s) for s in sweeps],
                [s.displacement_um[s.mask(window_s)] for s in sweeps], [s.dt for s in sweeps],
                np.asarray(noise_um, float), gaps_s=holds_s(sweeps))



def start_candidates(starts: Sequence[str]) -> list[tuple[str, ...]]:
    """The start assignments a grid fit tries: ``starts`` (the paper's model's) and every sweep
    alike from ``positive``, ``depoled`` and ``negative``."""
    n = len(starts)
    return [tuple(starts)] + [(s,) * n for s in ("positive", "depoled", "negative")]


def fit(data: Data, starts_candidates: Sequence[Sequence[str]], rod0: tuple[float, float],
        thickness_um: float, mass_kg: float, settings: Settings | None = None,
        say: Callable[[str], None] | None = None) -> PreisachFit:
    """Fit the Preisach grid (and creep) to ``data``.

    Parameters
    ----------
    data : Data
    starts_candidates : sequence of sequences of str
        Start assignments to try (one start per sweep); the best (plain linear fit) is kept.
    rod0 : (float, float)
        Starting natural frequency (Hz) and damping ratio of the rod (e.g. the HEM fit's).
    thickness_um, mass_kg : float
        Layer thickness (um) and the fixed effective mass (kg, a scale convention).
    """
    # small dense algebra: more BLAS threads only contend (seconds per call on a busy host)
    with threadpool_limits(1):
        return _fit(data, starts_candidates, rod0, thickness_um, mass_kg, settings or Settings(),
                    say or (lambda _m: None))


@dataclass(frozen=True)
class Runs:
    """The grid fitted with and without its creep elements at the middle smoothing: the problem
    (its start assignment chosen, the elements' thresholds set), the penalty, both fits."""

    problem: Problem
    penalty: FloatArray
    smoothing: float
    plain: Run
    #: None when the fit without creep left nothing for it (``runs``' ``creep_above``)
    crept: Run | None
    #: the creep on the force (:attr:`afmctl.fit.preisach_problem.Problem.creep_on_force`): its
    #: problem (elements' thresholds set on ``g(Q)``'s range) and its fit
    force_problem: Problem | None
    crept_force: Run | None
    #: what ``runs``' ``judge`` said of each fit: without creep, with it, with it on the force
    #: (as many as were fitted; empty without a judge)
    judged: tuple[Any, ...] = ()


def runs(data: Data, starts_candidates: Sequence[Sequence[str]], rod0: tuple[float, float],
         settings: Settings, say: Callable[[str], None], on_force: bool = True,
         creep_above: float = 0.0, coarse: bool = False,
         judge: Callable[[Problem, FloatArray, Run, bool], Any] | None = None) -> Runs:
    """The grid fitted without and with creep at the middle smoothing (and, if ``on_force``,
    with creep on the force).

    Parameters
    ----------
    data : Data
    starts_candidates : sequence of sequences of str
        Start assignments to try; the one whose first linear step fits best is kept.
    rod0 : (float, float)
        Starting natural frequency (Hz) and damping ratio of the rod.
    settings : Settings
    say : callable
        One-line progress messages.
    on_force : bool
        Fit the creep on the force too.
    creep_above : float
        Fit creep only if the fit without it is above this many times some sweep's noise
        (identify: :data:`CREEP_ABOVE`; 0, always: diagnose judges both).
    coarse : bool
        Run the fits on the problem with its slow sweeps in block means and its other sweeps
        judged on every k-th sample (:mod:`afmctl.fit.preisach_coarse`); the runs returned hold
        the full problems (their creep elements set as the fits left them), on which each fit
        is judged and shown, and from which the caller takes its last steps (identify's).
    judge : callable, optional
        Called on each fit (``(problem, penalty, run, with creep)``; identify: its held-out
        errors), the first two side by side with the creep on the force, that one's after it
        (:func:`cores.together`); what it returns is :attr:`Runs.judged`.

    Returns
    -------
    Runs
        The fit without creep (the rod searched twice, ``settings.max_iter // 4`` steps after
        each search), then with creep from there (``settings.max_iter`` steps), the rod searched
        again with the creep found and ``settings.max_iter`` more steps: without creep the
        hysteresis misfit of a creeping stage can hide its rod (pi-b-creep's 1247 Hz rod was
        kept at 8.76 kHz; found at 1250 Hz after); the last steps run from the search's rival
        rod too, if it offers one, and the lower cost is kept (:func:`_crept`). A creep fit
        left above :data:`RETRY_ABOVE` is done again from the runner-up start assignment
        (:func:`_retried`); with ``judge``, what it said of each fit (:attr:`Runs.judged`).
    """
    ec, ei, spread = make_grid(data.fields, settings)
    cands = [tuple(s) for s in dict.fromkeys(tuple(s) for s in starts_candidates)]
    close = pp.interior_loops(data.fields) >= pp.CLOSE_NODES_LOOPS
    mi = hat_matrix(ec.size, settings.coef_coercive, settings.coercive_power if close else 1.0)
    mj = hat_matrix(ei.size, settings.coef_interaction)
    grid = Grid(ec, ei, spread, mi, mj,
                _active(data, ec, ei, spread, mi, mj, cands, settings.plays), settings.plays)
    pen = grid_penalty(grid)
    lam0 = settings.smoothing[len(settings.smoothing) // 2]

    def start_theta() -> Theta:
        return Theta(np.zeros(grid.active.size), 0.0, np.zeros(len(settings.creep_taus_s)), 0.0,
                     0.0, math.log(rod0[0]), math.log(rod0[1]),
                     np.array([float(np.mean(y)) for y in data.y]))

    sizes = pc.blocks(data.fields, data.dts, min(settings.creep_taus_s)) if coarse else None

    def first_step(starts: tuple[str, ...]) -> tuple[float, Fitted, Theta]:
        full = Problem(data, grid, starts, settings.creep_taus_s)
        fitted = Fitted(full, pc.coarse(full, sizes) if sizes is not None else full)
        run = gauss_newton(fitted.fit, start_theta(), pen, lam0, False, 1,
                           gain_ratio=settings.gain_ratio_damping)
        return run.cost, fitted, run.theta

    top: list[tuple[float, Fitted, Theta]] = []  # the best two (each holds its basis columns)
    at_once = cores.workers()
    for at in range(0, len(cands), at_once):  # the start states: one linear step each, the
        firsts = cores.together([functools.partial(first_step, s)  # cheapest to compare
                                 for s in cands[at:at + at_once]])
        top = sorted([*top, *firsts], key=lambda r: r[0])[:2]
    best, runner_up = top[0], (top[1] if len(top) > 1 else None)
    prob = best[1]
    say(f"Preisach grid {ec.size} x {ei.size} from {settings.coef_coercive} x "
        f"{settings.coef_interaction} coefficients{f' and {ec.size} plays' if grid.plays else ''}"
        f" ({grid.active.size} the sweeps move), "
        f"starts {', '.join(prob.full.starts)}"
        + ("" if max(prob.fit.weights) == 1 else
           "; first fitted with each sweep's rows standing for "
           + ", ".join(f"{w}{' (means)' if b > 1 else ''}" for w, b in
                       zip(prob.fit.weights, prob.fit.blocks, strict=True)) + " samples"))
    # the runner-up's fits run only if the retry asks for them (run beside the best's in
    # advance, they slowed it by a fifth: both stream their bases through one memory bus)
    plain = _plain(prob.fit, best[2], pen, lam0, settings)
    crept = forced = crept_force = None
    if float(np.max(prob.full.ratios(plain.theta))) <= creep_above:
        say(f"  no creep fitted: without it every sweep is within {creep_above:g}x its noise")
    else:
        crept = _crept(prob, plain.theta, pen, lam0, settings)
        if runner_up is not None and _retry(prob.full, plain, crept):
            prob, plain, crept = _retried(prob, plain, crept, runner_up, pen, lam0, settings, say)
    shown = [("without creep", prob.full, plain)] + ([("with creep", prob.full, crept)]
                                                      if crept else [])
    del top, best, runner_up  # the other start assignments' bases: freed
    calls: list[Callable[[], Any]] = [] if judge is None else [
        functools.partial(judge, prob.full, pen, run, creep)
        for run, creep in ((plain, False), (crept, True)) if run is not None]
    if on_force and crept is not None:
        forced = prob.forced()
        calls.insert(0, functools.partial(_force, forced, plain.theta, crept.theta, pen, lam0,
                                          settings, judge))
    judged = cores.together(calls)
    if forced is not None:
        crept_force, on_it = judged.pop(0)
        judged.append(on_it)
        shown.append(("with creep on the force", forced.full, crept_force))
    for label, p, run in shown:
        say(f"  {label}: RMS / noise per sweep "
            + " / ".join(f"{r:.2f}" for r in p.ratios(run.theta))
            + f" ({run.iterations} steps{'' if run.converged else ', stopped on its budget'})")
    return Runs(prob.full, pen, lam0, plain, crept, None if forced is None else forced.full,
                crept_force, tuple(judged) if judge is not None else ())


@dataclass(frozen=True)
class Fitted:
    """A start assignment's problem: ``full``, and ``fit``, the one its runs are fitted on (the
    full one, or its copy with the slow sweeps in block means and the others' rows thinned:
    :mod:`afmctl.fit.preisach_coarse`)."""

    full: Problem
    fit: Problem

    def set_thresholds(self, thresholds_um: Sequence[float]) -> None:
        """Both problems' creep elements (:meth:`Problem.set_thresholds`): the full one judges
        and continues the fits with the elements they were fitted with."""
        for p in (self.full, self.fit):  # the same one when not coarse: set alike twice
            p.set_thresholds(thresholds_um)

    def forced(self) -> Fitted:
        """Copies of both with the creep on the force."""
        full, fit = copy.copy(self.full), copy.copy(self.fit)
        full.creep_on_force = fit.creep_on_force = True
        return Fitted(full, fit if self.fit is not self.full else full)


def _plain(prob: Problem, th: Theta, pen: FloatArray, lam: float, settings: Settings) -> Run:
    """The grid without creep from ``th``: the rod searched twice, ``settings.max_iter // 4``
    Gauss-Newton steps after each search."""
    steps = functools.partial(gauss_newton, pen=pen, lam_rel=lam, creep=False,
                              max_iter=settings.max_iter // 4,
                              gain_ratio=settings.gain_ratio_damping)
    return steps(prob, refit_rod(prob, steps(prob, refit_rod(prob, th)).theta))


def _retry(prob: Problem, plain: Run, crept: Run) -> bool:
    """Creep explains most of the misfit and leaves a sweep above :data:`RETRY_ABOVE`."""
    before, after = (prob.ratios(r.theta) for r in (plain, crept))
    return bool(np.max(after) > RETRY_ABOVE and np.sum(after ** 2) < 0.5 * np.sum(before ** 2))


def _retried(prob: Fitted, plain: Run, crept: Run, runner_up: tuple[float, Fitted, Theta],
             pen: FloatArray, lam: float, settings: Settings, say: Callable[[str], None]
             ) -> tuple[Fitted, Run, Run]:
    """The fits without and with creep again from the runner-up start assignment; the pair
    whose creep fit misses the sweeps less (sum of squares over the noise, on the full problems)
    is returned."""
    other = runner_up[1]
    alt_plain = _plain(other.fit, runner_up[2], pen, lam, settings)
    alt = _crept(other, alt_plain.theta, pen, lam, settings)
    miss = [float(np.sum(p.full.ratios(r.theta) ** 2)) for p, r in ((prob, crept), (other, alt))]
    say(f"  creep fit from starts {', '.join(prob.full.starts)} left {miss[0]:.3g}, from "
        f"{', '.join(other.full.starts)} {miss[1]:.3g} (sum of (RMS / noise)^2): "
        f"kept {', '.join((other if miss[1] < miss[0] else prob).full.starts)}")
    return (other, alt_plain, alt) if miss[1] < miss[0] else (prob, plain, crept)


def _crept(fitted: Fitted, plain: Theta, pen: FloatArray, lam: float, settings: Settings,
           warm: Theta | None = None) -> Run:
    """The creep elements fitted on ``fitted.fit`` from the fit without them, both problems'
    thresholds set on the range of what drives them there (``Q``, or ``g(Q)`` with the creep on
    the force), the rod searched again with the creep found and the last ``settings.max_iter``
    steps run from its best rod and from its rival, if it offers one
    (:func:`~afmctl.fit.preisach_solver.rod_rivals`): the lower cost is kept (both at the same
    smoothing; each run scales the penalty from its own start, which differ by about 1e-6).

    ``warm``: start from this fit with creep instead (the other placement's: its weights are
    shares of the same thresholds' fractions, so they start the force's creep near its answer:
    on pi-u-creep the last run took 16 steps where it had stopped on its budget of 40, to about
    the same error), else from ``plain`` with no creep.
    """
    prob = fitted.fit
    drives = prob.forces(plain) if prob.creep_on_force else prob.hysteretic(plain)
    span = max(float(np.ptp(x)) for x in drives)
    fitted.set_thresholds([f * span for f in settings.creep_thresholds])
    if warm is None:
        elements = plain.copy()
        elements.c = np.zeros(prob.el_tau.size)
    else:
        elements = warm.copy()
    steps = functools.partial(gauss_newton, pen=pen, lam_rel=lam, creep=True,
                              max_iter=settings.max_iter, gain_ratio=settings.gain_ratio_damping)
    tries = [steps(prob, th) for th in rod_rivals(prob, steps(prob, elements).theta)]
    return min(tries, key=lambda run: run.cost)


def _force(forced: Fitted, plain: Theta, crept: Theta, pen: FloatArray, lam: float,
           settings: Settings, judge: Callable[[Problem, FloatArray, Run, bool], Any] | None
           ) -> tuple[Run, Any]:
    """The creep on the force fitted from the fit with creep (:func:`_crept`), and ``judge``'s
    word on it (None without a judge)."""
    run = _crept(forced, plain, pen, lam, settings, crept)
    return run, None if judge is None else judge(forced.full, pen, run, True)


def _fit(data: Data, starts_candidates: Sequence[Sequence[str]], rod0: tuple[float, float],
         thickness_um: float, mass_kg: float, settings: Settings,
         say: Callable[[str], None]) -> PreisachFit:
    t0 = time.perf_counter()

    def held(prob: Problem, pen: FloatArray, run: Run, creep: bool) -> dict[float, FloatArray]:
        return heldout(prob, run.theta, pen, settings.smoothing, creep)

    fitted = runs(data, starts_candidates, rod0, settings, say, creep_above=CREEP_ABOVE,
                  coarse=True, judge=held)
    pen = fitted.penalty
    runs_by = {"no creep": (fitted.problem, False, fitted.plain)}
    if fitted.crept is not None:
        runs_by["creep"] = (fitted.problem, True, fitted.crept)
    if fitted.force_problem is not None and fitted.crept_force is not None:
        runs_by["creep on the force"] = (fitted.force_problem, True, fitted.crept_force)
    pers = fitted.judged
    scores: dict[str, float] = {}
    choice: tuple[float, str, float, FloatArray] | None = None
    for label, per in zip(runs_by, pers, strict=True):
        for lam in per:
            score = float(np.sum(per[lam] ** 2 / data.noise ** 2))
            scores[f"{label}, smoothing {lam:g}"] = score
            if choice is None or score < choice[0]:
                choice = (score, label, float(lam), per[lam])
    assert choice is not None
    _, label, lam, per = choice
    prob, creep, run = runs_by[label]
    final, lam, per, refits, at_final = _finer(prob, run.theta, pen, lam, creep, settings, say)
    scores.update({f"{label}, smoothing {k:g}, refitted": v for k, v in refits.items()})
    spread = scalar_uncertainty(prob, final.theta, creep, at_final)
    del at_final
    say("  held-out RMS / noise per sweep "
        + " / ".join(f"{r:.2f}" for r in per / data.noise)
        + f" ({'with ' + label if creep else 'without creep'}, smoothing {lam:g}; "
        f"{final.iterations} Gauss-Newton steps)")
    model = build(final.theta, prob, mass_kg, thickness_um, settings.p_scale, creep)
    return PreisachFit(model, prob.starts, final.theta.offsets, per, lam, creep, scores,
                       final.iterations, final.converged, time.perf_counter() - t0,
                       prob.ratios(final.theta), prob.grid.active.size,
                       spread, settings.p_scale,
                       prob.predict(final.theta, full=True), prob.interior_loops,
                       prob.cubic)


def _polished(prob: Problem, th: Theta, pen: FloatArray, lam: float, creep: bool,
              settings: Settings) -> tuple[Run, FloatArray, Linearized]:
    """The fit at smoothing ``lam`` from ``th`` (Gauss-Newton from :data:`POLISH_MU`), its
    held-out RMS per sweep (um) and the problem linearized there (for its uncertainty too)."""
    run = gauss_newton(prob, th, pen, lam, creep, settings.max_iter, POLISH_MU,
                       gain_ratio=settings.gain_ratio_damping)
    at = prob.linearize(run.theta, creep)
    return run, heldout(prob, run.theta, pen, [lam], creep, at)[lam], at


def _finer(prob: Problem, th: Theta, pen: FloatArray, lam: float, creep: bool,
           settings: Settings, say: Callable[[str], None]
           ) -> tuple[Run, float, FloatArray, dict[float, float], Linearized | None]:
    """The fit at the chosen smoothing ``lam``, then, on a set with the reversal curves
    (:data:`~afmctl.fit.preisach_problem.CLOSE_NODES_LOOPS` interior loops, where it was
    measured), refitted at each lighter one of ``settings.smoothing`` and
    ``settings.finer_smoothing`` in turn while that is better held out by :data:`FINER_GAIN`
    (sum of squares over the noise variance, :func:`_polished`) and some sweep is above
    :data:`FINER_ABOVE` times its noise held out: the fit kept, its smoothing, its held-out RMS
    per sweep (um), every refit's score, and the problem linearized at the fit kept (None if a
    refit was tried after it: one linearization, hundreds of MB, is kept at a time)."""
    def score(per: FloatArray) -> float:
        return float(np.sum(per ** 2 / prob.data.noise ** 2))

    run, per, at = _polished(prob, th, pen, lam, creep, settings)
    scores = {lam: score(per)}
    curves = prob.interior_loops >= pp.CLOSE_NODES_LOOPS
    ladder = sorted({*settings.smoothing, *settings.finer_smoothing}, reverse=True) if curves else []
    for lighter in (x for x in ladder if x < lam):
        if float(np.max(per / prob.data.noise)) <= FINER_ABOVE:
            break
        at = None  # freed before the refit's own
        trial = _polished(prob, run.theta, pen, lighter, creep, settings)
        scores[lighter] = score(trial[1])
        better = scores[lighter] < (1.0 - FINER_GAIN) * scores[lam]
        say(f"  smoothing {lighter:g}: held-out RMS / noise per sweep "
            + " / ".join(f"{r:.2f}" for r in trial[1] / prob.data.noise)
            + ("" if better else f" (kept {lam:g})"))
        if not better:
            break
        (run, per, at), lam = trial, lighter
    return run, lam, per, scores, at


def scalar_uncertainty(prob: Problem, th: Theta, creep: bool,
                       linearized: Linearized | None = None) -> dict[str, Any]:
    """Gauss-Newton ``s^2 (J^T J)^+`` of the scalar parameters at ``th``, the weights held (they
    are bounded; the held-out error judges the density instead); ``linearized``: the problem
    linearized at ``th`` with ``creep`` (:meth:`Problem.linearize`, not checked), if the caller
    has it already."""
    designs, _ = prob.linearize(th, creep) if linearized is None else linearized
    k = th.w.size
    a = np.vstack(designs)[:, k:]
    res = np.concatenate([y - u for y, u in zip(prob.data.y, prob.predict(th), strict=True)])
    names = (["reversible_um_per_MV_per_m"]
             + ([f"creep_c@{t:g}s_r{r:.3g}um" for t, r in zip(prob.el_tau, prob.el_thr,
                                                                 strict=True)] if creep else [])
             + ["s_per_um", "t_per_um2", "log_fn", "log_zeta"]
             + [f"offset_{i + 1}_um" for i in range(len(prob.phi))]
             + ([f"offset_{i + 1}_creep_transient@{t:g}s_um" for i, n in enumerate(prob.n_trans)
                 for t in prob.taus[:n]] if creep else []))
    p = np.concatenate(([th.r], th.c if creep else [], [th.s, th.t, th.log_fn, th.log_zeta],
                        th.offsets, th.d if creep else []))
    if not prob.cubic:  # held at 0, not estimated (CUBIC_LOOPS)
        at = names.index("t_per_um2")
        names, p, a = names[:at] + names[at + 1:], np.delete(p, at), np.delete(a, at, axis=1)
    s2 = float(res @ res) / max(1, res.size - k - p.size)
    cov = s2 * np.linalg.pinv(a.T @ a)
    out = unc.summary(names, p, cov)
    out["method"] = ("Gauss-Newton s^2 (J^T J)^+ of the scalar parameters at the solution, the "
                     "Preisach weights held (non-negative: judged by held-out error instead)")
    return out
