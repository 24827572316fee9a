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
does not lower the true cost is halved.

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
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import optimize
from threadpoolctl import threadpool_limits

from afmctl.files.sweepfile import Sweep
from afmctl.fit import parametrization as pz
from afmctl.fit import uncertainty as unc
from afmctl.fit.preisach_problem import (
    BLOCKS,
    CREEP_TAUS_S,
    CREEP_THRESHOLDS,
    FOLDS,
    MAP,
    SMOOTHING,
    TRANSIENT_SPAN,
    Data,
    Grid,
    Problem,
    Settings,
    Theta,
    basis,
    hat_matrix,
    make_grid,
    rod_filter,
)
from afmctl.model import creep as cr
from afmctl.model import preisach as pr
from afmctl.model import rod as rd
from afmctl.model import transducer as td

FloatArray = NDArray[np.float64]
#: A Gauss-Newton fit has converged once a step lowers the cost by less than this share of the
#: noise's sum of squares (the RMS over the noise then moves by less than 5e-4 of itself).
TOL_SHARE = 1e-3
#: Largest change of log f_n or log zeta in one Gauss-Newton step (a trust region).
MAX_LOG_STEP = 0.5
#: Levenberg damping of each held-out fold's fit toward the full fit (``mu diag(G)``, the least
#: :func:`gauss_newton` uses): the model has a valley the linearization cannot see (a constant
#: added to ``Q`` is undone by a new gain and ``s``, exactly), along which an undamped fold fit
#: slides to where the exact model is 100x the noise off.
HELDOUT_DAMPING = 1e-6
#: The rod's coarse search (:func:`refit_rod`): natural frequencies x damping ratios, log-spaced.
ROD_GRID = (24, 8)
#: Bounds of the rod's damping ratio (those of the parametric fit).
ZETA_BOUNDS = (0.003, 5.0)

__all__ = ["CREEP_TAUS_S", "CREEP_THRESHOLDS", "SMOOTHING", "BLOCKS", "FOLDS", "TRANSIENT_SPAN",
           "Settings", "hat_matrix", "Grid", "make_grid", "basis", "Data", "rod_filter", "Theta",
           "Problem", "PreisachFit", "Runs", "fit", "runs", "gauss_newton", "heldout",
           "bounded_solve", "penalty", "start_candidates", "sweep_data"]


# ----------------------------------------------------------------------------------------------
# the linear step: free variables eliminated, NNLS on the bounded ones
# ----------------------------------------------------------------------------------------------


def penalty(ni: int, nj: int, active: NDArray[np.intp]) -> FloatArray:
    """Second differences of the coefficients along both grid directions, on the active ones only
    (a difference that involves one no sweep can move is left out), shape (rows, active)."""
    idx = -np.ones(ni * nj, dtype=np.intp)
    idx[active] = np.arange(active.size)
    rows = []
    for i in range(ni):
        for j in range(nj):
            for di, dj in ((1, 0), (0, 1)):
                if i + 2 * di >= ni or j + 2 * dj >= nj:
                    continue
                cells = [idx[(i + k * di) * nj + j + k * dj] for k in range(3)]
                if min(cells) < 0:
                    continue
                r = np.zeros(active.size)
                r[cells] = (1.0, -2.0, 1.0)
                rows.append(r)
    return np.array(rows).reshape(-1, active.size)


def grid_penalty(grid: Grid) -> FloatArray:
    """:func:`penalty` on the coefficient grid and, with plays, second differences of the plays
    along the coercive field, shape (rows, active)."""
    na, nb = grid.mi.shape[1], grid.mj.shape[1]
    smooth = grid.active < na * nb
    pen = penalty(na, nb, grid.active[smooth])
    if not grid.plays:
        return pen
    lines = penalty(grid.coercive.size, 1, grid.active[~smooth] - na * nb)
    out = np.zeros((pen.shape[0] + lines.shape[0], grid.active.size))
    out[:pen.shape[0], smooth] = pen
    out[pen.shape[0]:, ~smooth] = lines
    return out


def bounded_solve(g: FloatArray, h: FloatArray, n_bounded: int) -> FloatArray:
    """``argmin x^T G x / 2 - h^T x`` with ``x[:n_bounded] >= 0`` and the rest free: the free
    block eliminated (Schur complement), then non-negative least squares on a Cholesky factor.
    Columns are equilibrated first (the weights are in um, ``s`` in 1/um, the rod in logs)."""
    d = np.sqrt(np.maximum(np.diag(g), 1e-300))
    gs, hs = g / np.outer(d, d), h / d
    b, f = slice(0, n_bounded), slice(n_bounded, g.shape[0])
    # the free block may be (nearly) singular, e.g. the rod on quasi-static sweeps alone: the
    # minimum-norm solution leaves such directions where they are
    sol_h = np.linalg.lstsq(gs[f, f], np.column_stack((gs[f, b], hs[f])), rcond=1e-10)[0]
    hred = gs[b, b] - gs[b, f] @ sol_h[:, :-1]
    dred = hs[b] - gs[b, f] @ sol_h[:, -1]
    hred = 0.5 * (hred + hred.T) + 1e-10 * np.eye(n_bounded)
    try:
        r = np.linalg.cholesky(hred).T
        rhs = np.linalg.solve(r.T, dred)
    except np.linalg.LinAlgError:  # round-off made it indefinite: its PSD part, by eigenvalues
        lam, vec = np.linalg.eigh(hred)
        lam = np.maximum(lam, 1e-12 * max(float(lam[-1]), 1e-300))
        r = np.sqrt(lam)[:, None] * vec.T
        rhs = (vec.T @ dred) / np.sqrt(lam)
    xb, _ = optimize.nnls(r, rhs, maxiter=50 * n_bounded)
    xf = sol_h[:, -1] - sol_h[:, :-1] @ xb
    return np.concatenate((xb, xf)) / d


def _unpack(x: FloatArray, th: Theta, creep: bool, rod: bool) -> Theta:
    k, nc = th.w.size, th.c.size if creep else 0
    i = k + 1 + nc
    out = Theta(x[:k].copy(), float(x[k]), x[k + 1:i].copy() if creep else th.c * 0.0,
                float(x[i]), float(x[i + 1]), th.log_fn, th.log_zeta, th.offsets.copy())
    i += MAP
    if rod:
        out.log_fn, out.log_zeta = float(x[i]), float(x[i + 1])
        i += 2
    n_s = th.offsets.size
    out.offsets = x[i:i + n_s].copy()
    out.d = x[i + n_s:].copy()
    return out


def _system(designs: list[FloatArray], rhs: list[FloatArray], th: Theta, creep: bool,
            rod: bool, rows: list[NDArray[np.bool_]] | None = None) -> tuple[FloatArray, FloatArray]:
    """Normal equations of the linearized problem (rod columns moved to absolute values, or
    dropped with the rod frozen) over the selected rows of each sweep."""
    k, nc = th.w.size, th.c.size if creep else 0
    rod_at = k + 1 + nc + MAP
    g = h = None
    for i, (a, b) in enumerate(zip(designs, rhs, strict=True)):
        if rows is not None:
            a, b = a[rows[i]], b[rows[i]]
        if rod:
            b = b + a[:, rod_at] * th.log_fn + a[:, rod_at + 1] * th.log_zeta
        else:
            a = np.delete(a, [rod_at, rod_at + 1], axis=1)
        gi, hi = a.T @ a, a.T @ b
        g, h = (gi, hi) if g is None else (g + gi, h + hi)
    assert g is not None and h is not None
    return g, h


# ----------------------------------------------------------------------------------------------
# Gauss-Newton and the held-out choice
# ----------------------------------------------------------------------------------------------


@dataclass
class Run:
    """A converged (or stopped) Gauss-Newton fit."""

    theta: Theta
    cost: float
    iterations: int
    converged: bool


def gauss_newton(prob: Problem, th: Theta, pen: FloatArray, lam_rel: float, creep: bool,
                 max_iter: int) -> Run:
    """Fit ``prob`` from ``th`` by Levenberg-Marquardt steps of the bounded linear problem: the
    linearization is good only near ``th`` (the map's ``s Q^2 + t Q^3`` and the creep multiply the
    weights), so each step is damped by ``mu diag(G)`` (and the rod by at least a prior: a step
    of 0.3 in its logs must buy the noise's sum of squares), ``mu`` raised until the step lowers
    the true cost and lowered after it does."""
    dtd = pen.T @ pen
    k = th.w.size
    n_bounded = k + 1 + (th.c.size if creep else 0)
    th = th.copy()
    th.d = np.zeros(sum(prob.n_trans)) if creep else np.zeros(0)
    lam = 0.0
    cost = math.inf
    mu, it, converged = 1e-4, 0, False
    for it in range(1, max_iter + 1):  # noqa: B007 (returned)
        designs, rhs = prob.linearize(th, creep)
        rod = bool(th.w.any() or th.r > 0)  # from nothing the rod has no derivative yet
        g, h = _system(designs, rhs, th, creep, rod)
        if lam == 0.0:  # scale the penalty to the weights' columns once
            lam = lam_rel * float(np.trace(g[:k, :k])) / max(float(np.trace(dtd)), 1e-300)
            cost = prob.cost(th, pen, lam)
        g[:k, :k] += lam * dtd
        x0 = _pack(th, creep, rod)
        diag = np.diag(g).copy()
        if rod:
            at = slice(n_bounded + MAP, n_bounded + MAP + 2)
            diag[at] = np.maximum(diag[at], prob.noise_sse / 0.3 ** 2 / max(mu, 1e-12))
        fresh = not (th.w.any() or th.r > 0)
        accepted = False
        for _ in range(12):
            damp = 0.0 if fresh else mu
            trial = _unpack(bounded_solve(g + damp * np.diag(diag), h + damp * diag * x0,
                                          n_bounded), th, creep, rod)
            trial.t = trial.t if prob.cubic else 0.0  # its column is 0 (CUBIC_LOOPS)
            trial.log_fn = _clamp(trial.log_fn, th.log_fn, prob.fn_bounds)
            trial.log_zeta = _clamp(trial.log_zeta, th.log_zeta, ZETA_BOUNDS)
            c_new = prob.cost(trial, pen, lam)
            if c_new < cost:
                accepted = True
                break
            mu = max(mu * 8.0, 1e-6)
            fresh = False
        if not accepted:
            converged = True  # no step lowers the cost: a (local) minimum
            break
        gain = cost - c_new
        th, cost, mu = trial, c_new, max(mu / 4.0, 1e-9)
        if gain < TOL_SHARE * prob.noise_sse:  # the RMS / noise moves by < 1e-4 of itself
            converged = True
            break
    return Run(th, cost, it, converged)


def refit_rod(prob: Problem, th: Theta) -> Theta:
    """The rod's natural frequency and damping, and each sweep's offset, by least squares with the
    hysteresis and creep held at ``th``: ``g(Q~)`` does not depend on the rod, so each trial is
    one filter pass per sweep. A coarse grid over the frequency bounds and damping ratios first
    (Gauss-Newton's rod prior, a trust region sized to the whole set's noise, cannot walk far
    on the fast sweep's evidence alone), then a local least-squares polish from the best point
    and from ``th``'s; the better of that and ``th`` is returned."""
    forces = prob.forces(th)

    def residual(x: FloatArray) -> FloatArray:
        fn, zeta = math.exp(float(x[0])), math.exp(float(x[1]))
        out = []
        for g, dt, m, y in zip(forces, prob.data.dts, prob.data.masks, prob.data.y, strict=True):
            r = y - rod_filter(g, fn, zeta, dt)[m]
            out.append(r - np.mean(r))
        return np.concatenate(out)

    lo = np.log([prob.fn_bounds[0], ZETA_BOUNDS[0]])
    hi = np.log([prob.fn_bounds[1], ZETA_BOUNDS[1]])
    coarse = [np.array([f, z]) for f in np.linspace(math.log(50.0), hi[0], ROD_GRID[0])
              for z in np.linspace(math.log(0.01), math.log(2.0), ROD_GRID[1])]
    here = np.array([th.log_fn, th.log_zeta])
    sse = [float(np.sum(residual(x) ** 2)) for x in coarse]
    best, best_sse = here, float(np.sum(residual(here) ** 2))
    for x0 in (coarse[int(np.argmin(sse))], here):
        sol = optimize.least_squares(residual, np.clip(x0, lo + 1e-9, hi - 1e-9),
                                     bounds=(lo, hi), x_scale=0.1, max_nfev=60)
        if 2 * sol.cost < best_sse:
            best, best_sse = sol.x, 2 * float(sol.cost)
    out = th.copy()
    out.log_fn, out.log_zeta = float(best[0]), float(best[1])
    fn, zeta = math.exp(out.log_fn), math.exp(out.log_zeta)
    out.offsets = np.array([float(np.mean(y - rod_filter(g, fn, zeta, dt)[m]))
                            for g, dt, m, y in zip(forces, prob.data.dts, prob.data.masks,
                                                   prob.data.y, strict=True)])
    return out


def _pack(th: Theta, creep: bool, rod: bool) -> FloatArray:
    """The inverse of :func:`_unpack`."""
    parts = [th.w, [th.r], th.c if creep else [], [th.s, th.t]]
    parts += [[th.log_fn, th.log_zeta]] if rod else []
    return np.concatenate(parts + [th.offsets, th.d]).astype(float)


def _clamp(new: float, old: float, bounds: tuple[float, float]) -> float:
    """A log step of at most :data:`MAX_LOG_STEP`, within ``bounds`` (values, not logs)."""
    step = min(max(new - old, -MAX_LOG_STEP), MAX_LOG_STEP)
    return min(max(old + step, math.log(bounds[0])), math.log(bounds[1]))


def heldout(prob: Problem, th: Theta, pen: FloatArray, lam_rel: Sequence[float],
            creep: bool) -> dict[float, FloatArray]:
    """Held-out RMS per sweep (um) at each relative smoothing in ``lam_rel``: the weights, the
    reversible slope and the offsets fitted on all folds but one, judged on that one with the
    exact model, each fold in turn. The few scalars (``s``, creep weights and transients, rod)
    stay at the full fit's ``th``: refitted without the damping of :func:`gauss_newton` they
    would slide along the valleys they share with the weights, and their own optimism is that
    of a handful of parameters. The problem is linearized at ``th`` (a step of the size of the
    folds' difference)."""
    designs, rhs = prob.linearize(th, creep)
    k, nc, n_s = th.w.size, th.c.size if creep else 0, len(prob.phi)
    fixed = np.concatenate((th.c if creep else [], [th.s, th.t]))
    at_d = k + 1 + nc + MAP + 2 + n_s
    keep = np.r_[np.arange(k + 1), np.arange(k + 1 + nc + MAP + 2, at_d)]
    rhs = [b - a[:, k + 1:k + 1 + nc + MAP] @ fixed - a[:, at_d:] @ th.d[:a.shape[1] - at_d]
           for a, b in zip(designs, rhs, strict=True)]
    designs = [a[:, keep] for a in designs]
    folds = prob.data.folds
    parts = []
    for q in range(FOLDS):
        rows = [f == q for f in folds]
        a = np.vstack([d[r] for d, r in zip(designs, rows, strict=True)])
        b = np.concatenate([v[r] for v, r in zip(rhs, rows, strict=True)])
        parts.append((a.T @ a, a.T @ b))
    g_all = sum(p[0] for p in parts)
    h_all = sum(p[1] for p in parts)
    x_th = np.concatenate((th.w, [th.r], th.offsets))
    diag = np.diag(g_all).copy()
    dtd = pen.T @ pen
    scale = float(np.trace(g_all[:k, :k])) / max(float(np.trace(dtd)), 1e-300)
    out: dict[float, FloatArray] = {}
    for lam_r in lam_rel:
        sse = np.zeros(n_s)
        count = np.zeros(n_s)
        for q in range(FOLDS):
            g = g_all - parts[q][0] + HELDOUT_DAMPING * np.diag(diag)  # the other folds
            g[:k, :k] += lam_r * scale * dtd
            x = bounded_solve(g, h_all - parts[q][1] + HELDOUT_DAMPING * diag * x_th, k + 1)
            fitted = th.copy()
            fitted.w, fitted.r, fitted.offsets = x[:k].copy(), float(x[k]), x[k + 1:].copy()
            for i, (y, u, f) in enumerate(zip(prob.data.y, prob.predict(fitted), folds,
                                              strict=True)):
                sel = f == q
                sse[i] += float(np.sum((y[sel] - u[sel]) ** 2))
                count[i] += int(sel.sum())
        out[float(lam_r)] = np.sqrt(sse / np.maximum(count, 1))
    return out


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
        Held-out sum of squares over noise variance of every (creep, smoothing) tried.
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
            var |= ((-ei[None, :] > lo[:, None] - 5 * math.sqrt(2) * spread) &
                    (-ei[None, :] < hi[:, None] + 5 * math.sqrt(2) * spread) &
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
                np.asarray(noise_um, float))


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
    crept: Run
    #: the creep on the force (:attr:`afmctl.fit.preisach_problem.Problem.creep_on_force`): its
    #: problem (elements' thresholds set on ``g(Q)``'s range) and its fit
    force_problem: Problem | None
    crept_force: Run | None


def runs(data: Data, starts_candidates: Sequence[Sequence[str]], rod0: tuple[float, float],
         settings: Settings, say: Callable[[str], None], on_force: bool = True) -> Runs:
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

    Returns
    -------
    Runs
        The fit without creep (the rod searched twice, ``settings.max_iter // 4`` steps after
        each search), then with creep from there (``settings.max_iter`` steps), the rod searched
        again with the creep found and ``settings.max_iter`` more steps: without creep the
        hysteresis misfit of a creeping stage can hide its rod (pi-b-creep's 1247 Hz rod was
        kept at 8.76 kHz; found at 1250 Hz after).
    """
    ec, ei, spread = make_grid(data.fields, settings)
    cands = [tuple(s) for s in dict.fromkeys(tuple(s) for s in starts_candidates)]
    mi = hat_matrix(ec.size, settings.coef_coercive)
    mj = hat_matrix(ei.size, settings.coef_interaction)
    grid = Grid(ec, ei, spread, mi, mj,
                _active(data, ec, ei, spread, mi, mj, cands, settings.plays), settings.plays)
    pen = grid_penalty(grid)
    lam0 = settings.smoothing[len(settings.smoothing) // 2]

    def start_theta() -> Theta:
        return Theta(np.zeros(grid.active.size), 0.0, np.zeros(len(settings.creep_taus_s)), 0.0,
                     0.0, math.log(rod0[0]), math.log(rod0[1]),
                     np.array([float(np.mean(y)) for y in data.y]))

    best: tuple[float, Problem, Theta] | None = None
    for starts in cands:  # the start states: one linear step each, the cheapest to compare
        prob = Problem(data, grid, starts, settings.creep_taus_s)
        run = gauss_newton(prob, start_theta(), pen, lam0, False, 1)
        if best is None or run.cost < best[0]:
            best = (run.cost, prob, run.theta)
    assert best is not None
    _, prob, th = best
    say(f"Preisach grid {ec.size} x {ei.size} from {settings.coef_coercive} x "
        f"{settings.coef_interaction} coefficients{f' and {ec.size} plays' if grid.plays else ''}"
        f" ({grid.active.size} the sweeps move), "
        f"starts {', '.join(prob.starts)}")
    plain = gauss_newton(prob, refit_rod(prob, th), pen, lam0, False, settings.max_iter // 4)
    plain = gauss_newton(prob, refit_rod(prob, plain.theta), pen, lam0, False,
                         settings.max_iter // 4)
    crept = _crept(prob, plain.theta, pen, lam0, settings)
    shown = [("without creep", prob, plain), ("with creep", prob, crept)]
    forced = crept_force = None
    if on_force:
        forced = copy.copy(prob)
        forced.creep_on_force = True
        crept_force = _crept(forced, plain.theta, pen, lam0, settings, crept.theta)
        shown.append(("with creep on the force", forced, crept_force))
    for label, p, run in shown:
        say(f"  {label}: RMS / noise per sweep "
            + " / ".join(f"{r:.2f}" for r in p.ratios(run.theta))
            + f" ({run.iterations} steps{'' if run.converged else ', stopped on its budget'})")
    return Runs(prob, pen, lam0, plain, crept, forced, crept_force)


def _crept(prob: Problem, plain: Theta, pen: FloatArray, lam: float, settings: Settings,
           warm: Theta | None = None) -> Run:
    """The creep elements fitted from the fit without them, ``prob``'s thresholds set on the
    range of what drives them (``Q``, or ``g(Q)`` with the creep on the force), the rod searched
    again with the creep found.

    ``warm``: start from this fit with creep instead (the other placement's: its weights are
    shares of the same thresholds' fractions, so they start the force's creep near its answer:
    on pi-u-creep the last run took 16 steps where it had stopped on its budget of 40, to about
    the same error), else from ``plain`` with no creep.
    """
    drives = prob.forces(plain) if prob.creep_on_force else prob.hysteretic(plain)
    span = max(float(np.ptp(x)) for x in drives)
    prob.set_thresholds([f * span for f in settings.creep_thresholds])
    if warm is None:
        elements = plain.copy()
        elements.c = np.zeros(prob.el_tau.size)
    else:
        elements = warm.copy()
    run = gauss_newton(prob, elements, pen, lam, True, settings.max_iter)
    return gauss_newton(prob, refit_rod(prob, run.theta), pen, lam, True, settings.max_iter)


def _fit(data: Data, starts_candidates: Sequence[Sequence[str]], rod0: tuple[float, float],
         thickness_um: float, mass_kg: float, settings: Settings,
         say: Callable[[str], None]) -> PreisachFit:
    t0 = time.perf_counter()
    fitted = runs(data, starts_candidates, rod0, settings, say)
    pen = fitted.penalty
    runs_by = {"no creep": (fitted.problem, False, fitted.plain),
               "creep": (fitted.problem, True, fitted.crept)}
    if fitted.force_problem is not None and fitted.crept_force is not None:
        runs_by["creep on the force"] = (fitted.force_problem, True, fitted.crept_force)
    scores: dict[str, float] = {}
    choice: tuple[float, str, float, FloatArray] | None = None
    for label, (p, creep, run) in runs_by.items():
        per = heldout(p, run.theta, pen, settings.smoothing, creep)
        for lam in per:
            score = float(np.sum(per[lam] ** 2 / data.noise ** 2))
            scores[f"{label}, smoothing {lam:g}"] = score
            if choice is None or score < choice[0]:
                choice = (score, label, float(lam), per[lam])
    assert choice is not None
    _, label, lam, per = choice
    prob, creep, run = runs_by[label]
    final = gauss_newton(prob, run.theta, pen, lam, creep, settings.max_iter)
    say("  held-out RMS / noise per sweep "
        + " / ".join(f"{r:.2f}" for r in per / data.noise)
        + f" ({'with ' + label if creep else 'without creep'}, smoothing {lam:g}; "
        f"{final.iterations} Gauss-Newton steps)")
    model = build(final.theta, prob, mass_kg, thickness_um, settings.p_scale, creep)
    return PreisachFit(model, prob.starts, final.theta.offsets, per, lam, creep, scores,
                       final.iterations, final.converged, time.perf_counter() - t0,
                       prob.ratios(final.theta), prob.grid.active.size,
                       scalar_uncertainty(prob, final.theta, creep), settings.p_scale,
                       prob.predict(final.theta, full=True), prob.interior_loops,
                       prob.cubic)


def scalar_uncertainty(prob: Problem, th: Theta, creep: bool) -> dict[str, Any]:
    """Gauss-Newton ``s^2 (J^T J)^+`` of the scalar parameters at ``th``, the weights held (they
    are bounded; the held-out error judges the density instead)."""
    designs, _ = prob.linearize(th, creep)
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
