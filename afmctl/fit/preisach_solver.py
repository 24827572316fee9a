"""The Preisach grid's solver (:mod:`afmctl.fit.preisach`): the smoothness penalty, the bounded
linear step, Gauss-Newton on the problem of :mod:`afmctl.fit.preisach_problem`, the rod's own
search, and the held-out error that chooses the smoothing.

Each Gauss-Newton step linearizes the model about the last point and solves the linear problem
exactly: the free variables (``s``, ``t``, the rod, one offset per sweep) eliminated from the
normal equations, then :func:`scipy.optimize.nnls` on the bounded ones (``w, r, c >= 0``). A step
that does not lower the true cost is damped more (:func:`gauss_newton`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import optimize

from afmctl.fit.preisach_basis import Grid
from afmctl.fit.preisach_problem import FOLDS, MAP, Problem, Theta

FloatArray = NDArray[np.float64]
#: :meth:`Problem.linearize`'s designs and known terms, per sweep.
Linearized = tuple[list[FloatArray], list[FloatArray]]
#: A Gauss-Newton fit has converged once a step lowers the cost by less than this share of the
#: noise's sum of squares (the RMS over the noise then moves by less than 5e-4 of itself).
TOL_SHARE = 1e-3
#: Levenberg damping a Gauss-Newton fit starts with (a share of ``diag(G)``).
MU_START = 1e-4
#: Largest change of log f_n or log zeta in one Gauss-Newton step (a trust region).
MAX_LOG_STEP = 0.5
#: Levenberg damping of each held-out fold's fit toward the full fit (``mu diag(G)``, the least
#: :func:`gauss_newton` uses): the model has a valley the linearization cannot see (a constant
#: added to ``Q`` is undone by a new gain and ``s``, exactly), along which an undamped fold fit
#: slides to where the exact model is 100x the noise off.
HELDOUT_DAMPING = 1e-6
#: The rod's coarse search (:func:`rod_rivals`): natural frequencies x damping ratios, log-spaced.
ROD_GRID = (24, 8)
#: A rod :func:`rod_rivals` weighed (the one it started from, or a polish) this many times away in
#: natural frequency from the best is a rival, fitted from too, if its sum of squares with the
#: hysteresis held is within ``ROD_RIVAL_SSE`` times the best's. Measured: pi-b-creep's true rod
#: 1.4 % above the 8.76 kHz one its weights were fitted with, the independent Preisach plant's
#: (700 Hz) 1.3x above a 9.3 kHz one (tests/fit/test_preisach_rod.py): both won once the weights
#: followed them; a rival 5x above lost (161 against 48).
ROD_RIVAL_RATIO = 1.5
ROD_RIVAL_SSE = 2.0
#: Bounds of the rod's damping ratio (those of the parametric fit).
ZETA_BOUNDS = (0.003, 5.0)


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
                 max_iter: int, mu0: float = MU_START, *, gain_ratio: bool = False) -> Run:
    """Fit ``prob`` from ``th`` by Levenberg-Marquardt steps of the bounded linear problem: the
    linearization is good only near ``th`` (the map's ``s Q^2 + t Q^3`` and the creep multiply the
    weights), so each step is damped by ``mu diag(G)`` (and the rod by at least a prior: a step
    of 0.3 in its logs must buy the noise's sum of squares).

    ``mu`` starts at ``mu0`` and is raised (x8) until the step lowers the true cost; after it
    does, it is quartered (the fixed rule, the default: diagnose's grid). With ``gain_ratio``,
    Nielsen's rule instead (identify's grid, :attr:`Settings.gain_ratio_damping`): raised x2, x4,
    x8 ..., and after a step multiplied by ``max(1/3, 1 - (2 rho - 1)^3)``, ``rho`` the true fall
    over the linearized one (:func:`_nielsen`)."""
    dtd = pen.T @ pen
    k = th.w.size
    n_bounded = k + 1 + (th.c.size if creep else 0)
    th = th.copy()
    th.d = np.zeros(sum(prob.n_trans)) if creep else np.zeros(0)
    lam = 0.0
    cost = math.inf
    mu, nu, it, converged = mu0, 2.0 if gain_ratio else 8.0, 0, False
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
            mu = max(mu * nu, 1e-6)
            nu = 2.0 * nu if gain_ratio else nu
            fresh = False
        if not accepted:
            converged = True  # no step lowers the cost: a (local) minimum
            break
        gain = cost - c_new
        if gain_ratio:
            mu, nu = _nielsen(mu, gain, _pack(trial, creep, rod) - x0, x0, g, h), 2.0
        else:
            mu = max(mu / 4.0, 1e-9)
        th, cost = trial, c_new
        if gain < TOL_SHARE * prob.noise_sse:  # the RMS / noise moves by < 1e-4 of itself
            converged = True
            break
    return Run(th, cost, it, converged)


def _nielsen(mu: float, gain: float, dx: FloatArray, x0: FloatArray, g: FloatArray,
             h: FloatArray) -> float:
    """Nielsen's update of the damping after a step ``dx`` from ``x0`` that lowered the cost by
    ``gain``: ``mu max(1/3, 1 - (2 rho - 1)^3)``, ``rho`` the gain over the linearized cost's fall
    ``dx' (2 h - G (2 x0 + dx))`` (``x' G x - 2 h' x`` at the start less at the end, without
    subtracting the two). A fall the linearization does not foresee (a step the rod's clamp
    bent) leaves ``mu`` as it was."""
    fall = float(dx @ (2.0 * h - g @ (2.0 * x0 + dx)))
    if fall <= 0.0:
        return mu
    rho = min(gain / fall, 1.0)
    return max(mu * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 1e-9)


def refit_rod(prob: Problem, th: Theta) -> Theta:
    """The rod's natural frequency and damping, and each sweep's offset, by least squares with the
    hysteresis and creep held at ``th``: the first of :func:`rod_rivals`."""
    return rod_rivals(prob, th)[0]


def rod_rivals(prob: Problem, th: Theta) -> list[Theta]:
    """The rod's natural frequency and damping, and each sweep's offset, by least squares with the
    hysteresis and creep held at ``th``: ``g(Q~)`` does not depend on the rod, so each trial is
    one filter pass per sweep. A coarse grid over the frequency bounds and damping ratios first
    (Gauss-Newton's rod prior, a trust region sized to the whole set's noise, cannot walk far
    on the fast sweep's evidence alone), then a local least-squares polish from the best point
    and from ``th``'s.

    Parameters
    ----------
    prob : Problem
    th : Theta
        The fit whose hysteresis and creep are held (its rod is weighed as it is and polished).

    Returns
    -------
    list of Theta
        The best of the two polishes and ``th`` itself, each sweep's offset fitted to it; then,
        if another of the three is at a natural frequency :data:`ROD_RIVAL_RATIO` or more away
        and misses by at most :data:`ROD_RIVAL_SSE` times as much, that one (the rival: with
        the hysteresis held, the true rod can lose to the one the weights were fitted with,
        pi-b-creep's 1.25 kHz to 8.76 kHz; :func:`afmctl.fit.preisach._crept` fits from both).
    """
    forces = prob.forces(th)

    def residual(x: FloatArray) -> FloatArray:
        fn, zeta = math.exp(float(x[0])), math.exp(float(x[1]))
        out = []
        for i, (g, m, y) in enumerate(zip(forces, prob.data.masks, prob.data.y, strict=True)):
            r = y - prob.rod(i, g, fn, zeta)[m]
            out.append(math.sqrt(prob.weights[i]) * (r - np.mean(r)))
        return np.concatenate(out)

    lo = np.log([prob.fn_bounds[0], ZETA_BOUNDS[0]])
    hi = np.log([prob.fn_bounds[1], ZETA_BOUNDS[1]])
    coarse = [np.array([f, z]) for f in np.linspace(math.log(50.0), hi[0], ROD_GRID[0])
              for z in np.linspace(math.log(0.01), math.log(2.0), ROD_GRID[1])]
    here = np.array([th.log_fn, th.log_zeta])
    sse = [float(np.sum(residual(x) ** 2)) for x in coarse]
    found = [(float(np.sum(residual(here) ** 2)), here)]
    for x0 in (coarse[int(np.argmin(sse))], here):
        sol = optimize.least_squares(residual, np.clip(x0, lo + 1e-9, hi - 1e-9),
                                     bounds=(lo, hi), x_scale=0.1, max_nfev=60)
        found.append((2.0 * float(sol.cost), sol.x))
    found.sort(key=lambda f: f[0])
    best_sse, best = found[0]
    rivals = [x for c, x in found[1:] if c <= ROD_RIVAL_SSE * best_sse
              and abs(float(x[0] - best[0])) >= math.log(ROD_RIVAL_RATIO)]
    return [_with_rod(prob, th, forces, x) for x in [best] + rivals[:1]]


def _with_rod(prob: Problem, th: Theta, forces: list[FloatArray], x: FloatArray) -> Theta:
    """``th`` with the rod's log natural frequency and damping ``x`` and each sweep's offset
    fitted to it (``forces``: ``prob.forces(th)``)."""
    out = th.copy()
    out.log_fn, out.log_zeta = float(x[0]), float(x[1])
    fn, zeta = math.exp(out.log_fn), math.exp(out.log_zeta)
    out.offsets = np.array([float(np.mean(y - prob.rod(i, g, fn, zeta)[m]))
                            for i, (g, m, y) in enumerate(zip(forces, prob.data.masks,
                                                              prob.data.y, strict=True))])
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
            creep: bool, linearized: Linearized | None = None) -> dict[float, FloatArray]:
    """Held-out RMS per sweep (um) at each relative smoothing in ``lam_rel``: the weights, the
    reversible slope and the offsets fitted on all folds but one, judged on that one with the
    exact model, each fold in turn. The few scalars (``s``, creep weights and transients, rod)
    stay at the full fit's ``th``: refitted without the damping of :func:`gauss_newton` they
    would slide along the valleys they share with the weights, and their own optimism is that
    of a handful of parameters. The problem is linearized at ``th`` (a step of the size of the
    folds' difference); ``linearized``: that linearization (``prob.linearize(th, creep)``, not
    checked), if the caller has it already."""
    designs, rhs = prob.linearize(th, creep) if linearized is None else linearized
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
