"""Identification of the Preisach grid (:mod:`afmctl.model.preisach`) with creep, from sweeps.

The classic identification of a Preisach density is a convex problem: the output is linear in the
density's weights, which are non-negative, and a smoothness penalty on the grid makes the problem
well posed (non-negative least squares with Tikhonov regularization). Here the output is not the
polarization but the displacement of the rod (16), ``u = L[a1 P + a2 P^2] / k``, with ``L`` the rod's
unit-DC-gain dynamics; in the frame of :mod:`afmctl.fit.parametrization`::

    u = L[g(Q~)] + offset_s,    g(Q) = Q + s Q^2,    Q~ = Q + sum_j c_j Z_j[Q],
    Q = r E + sum_ij w_ij erf((y_i + E_I,j) / (sqrt(2) spread))      (um),

with ``y_i`` the play output of coercive row ``i`` (fixed by the field history and the start
state, not by any parameter), ``Z_j`` the creep elements of :mod:`afmctl.model.creep`, and the
gain fixed by convention in ``g``. The weights ``w, r, c >= 0`` enter linearly but for the
quadratic ``s Q^2`` (the ``a2 P^2`` of (16)) and the product of creep and hysteresis. The fit is
Gauss-Newton on that structure: at each step the model is linearized in ``(w, r, c, s)`` about the
last point (exact in ``s``; the columns are ``L[(1 + 2 s Q~) C[basis]]``), with the rod's natural
frequency and damping as two more columns (their finite-difference derivatives, Levenberg-damped),
and the linear problem (bounded: ``w, r, c >= 0``; free: ``s``, the rod, one offset per sweep) is
solved exactly: the free variables eliminated from the normal equations, then
:func:`scipy.optimize.nnls` on the rest. A step that does not lower the true cost is halved.

The penalty weight (and whether creep is kept) is chosen by held-out error: the residual rows are
cut into blocks, dealt in turn to four folds; each candidate is fitted on three folds (linearized
at the full fit, rod frozen) and judged on the fourth with the exact model, each fold in turn.
Identify compares that held-out error, against each sweep's sensor noise, with the parametric
HEM's (:mod:`afmctl.fit.representation`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy import optimize
from threadpoolctl import threadpool_limits

from afmctl.fit import parametrization as pz
from afmctl.fit import uncertainty as unc
from afmctl.model import creep as cr
from afmctl.model import preisach as pr
from afmctl.model import rod as rd
from afmctl.model import transducer as td

FloatArray = NDArray[np.float64]
#: Two creep elements per decade, 10 ms ... 1000 s (one per decade left a ripple at the
#: reversals of the other-family creep set: 1.33 / 1.29 / 1.60x its noise, against 1.31 / 1.07 /
#: 1.17x with two).
CREEP_TAUS_S = tuple(float(t) for t in np.logspace(-2, 3, 11))
#: Play half-widths in front of the creep elements, shares of the hysteretic output's range: 0 is
#: linear creep; wider plays keep creeping the old way through small reversals (the Krejci-Kuhnen
#: operators; on the other-family creep set they take the slow sweep from 1.26 to 1.11x its noise).
CREEP_THRESHOLDS = (0.0, 0.02, 0.05, 0.1)
#: Relative smoothing weights tried (times tr(J_w^T J_w) / tr(D^T D)).
SMOOTHING = (1e-6, 1e-5, 1e-4, 1e-3)
#: Residual blocks per sweep for the held-out folds, and the folds (blocks dealt in turn).
BLOCKS = 24
FOLDS = 4
#: A Gauss-Newton fit has converged once a step lowers the cost by less than this share of the
#: noise's sum of squares (the RMS over the noise then moves by less than 5e-4 of itself).
TOL_SHARE = 1e-3
#: A sweep's creep transient is fitted for the elements up to this many times its length: 0, off.
#: Free transients (tried at 3) fitted the other-family creep set's misfit instead of a history
#: (the model alone, which track uses, was then 70x the noise where the fit said 1.2x): each sweep
#: is taken to start with its creep at rest.
TRANSIENT_SPAN = 0.0
#: Largest change of log f_n or log zeta in one Gauss-Newton step (a trust region).
MAX_LOG_STEP = 0.5
#: Bounds of the rod's damping ratio (those of the parametric fit).
ZETA_BOUNDS = (0.003, 5.0)


@dataclass(frozen=True)
class Settings:
    """Options of :func:`fit`.

    The model's grid (``n_coercive x n_interaction`` cells, the kernel's resolution) is finer
    than the fitted coefficients (``coef_coercive x coef_interaction``, non-negative), from which
    the weights are interpolated bilinearly: the kernel needs fine rows to follow a smooth density
    without kinks, the data do not need one free weight per cell (measured on the other-family
    Preisach set: a 16 x 24 grid fitted cell by cell stays at 1.75x the noise on the slow sweep,
    a 32 x 48 grid from 12 x 18 coefficients reaches 1.08x with fewer unknowns).
    """

    n_coercive: int = 32
    n_interaction: int = 48
    coef_coercive: int = 12
    coef_interaction: int = 18
    creep_taus_s: tuple[float, ...] = CREEP_TAUS_S
    creep_thresholds: tuple[float, ...] = CREEP_THRESHOLDS
    smoothing: tuple[float, ...] = SMOOTHING
    max_iter: int = 40
    p_scale: float = 0.3  # |P| over the sweeps is scaled to this, C/m^2 (a convention, like P_R)


def hat_matrix(n_fine: int, n_coarse: int) -> FloatArray:
    """Linear interpolation from ``n_coarse`` equally spaced nodes to ``n_fine`` ones, spanning
    the same interval, shape (n_fine, n_coarse); rows sum to 1, entries >= 0."""
    x = np.linspace(0.0, n_coarse - 1.0, n_fine)
    j = np.minimum(np.floor(x).astype(int), n_coarse - 2)
    t = x - j
    m = np.zeros((n_fine, n_coarse))
    m[np.arange(n_fine), j] = 1.0 - t
    m[np.arange(n_fine), j + 1] = t
    return m


@dataclass(frozen=True)
class Grid:
    """Nodes of the model's grid (MV/m), the interpolation from the coefficients (``mi``, ``mj``)
    and which coefficients the sweeps can move (``active``, flat row-major indices into the
    ``coef_coercive x coef_interaction`` array)."""

    coercive: FloatArray
    interaction: FloatArray
    spread: float
    mi: FloatArray
    mj: FloatArray
    active: NDArray[np.intp]

    def weights(self, coef: FloatArray) -> FloatArray:
        """The cell weights (N_i, N_j) of the active coefficients ``coef``."""
        full = np.zeros(self.mi.shape[1] * self.mj.shape[1])
        full[self.active] = coef
        return self.mi @ full.reshape(self.mi.shape[1], -1) @ self.mj.T


def make_grid(fields: Sequence[FloatArray], settings: Settings) -> tuple[FloatArray, FloatArray,
                                                                           float]:
    """Coercive nodes ``0 ... span/2`` (rows that the field's span can switch) and interaction
    nodes with ``-E_I`` over the field range padded by two spacings; the spread is the spacing."""
    lo = min(float(np.min(e)) for e in fields)
    hi = max(float(np.max(e)) for e in fields)
    span = max(hi - lo, 1e-9)
    ec = np.linspace(0.0, 0.5 * span, settings.n_coercive)
    h = span / (settings.n_interaction - 5)
    ei = np.sort(-np.linspace(lo - 2 * h, hi + 2 * h, settings.n_interaction))
    return ec, ei, h


@nb.njit(cache=True)
def _coef_columns(y: np.ndarray, ei: np.ndarray, inv: float, mi: np.ndarray,
                  mj: np.ndarray) -> np.ndarray:
    """``sum_ij mi[i, a] mj[j, b] erf((y_i + E_I,j) inv)`` per sample, shape (N, A B)."""
    n, ni = y.shape
    nj, na, nb_ = ei.size, mi.shape[1], mj.shape[1]
    out = np.zeros((n, na * nb_))
    row = np.empty(nb_)
    for t in range(n):
        for i in range(ni):
            for b in range(nb_):
                row[b] = 0.0
            for j in range(nj):
                z = (y[t, i] + ei[j]) * inv
                v = 1.0 if z > 5.0 else (-1.0 if z < -5.0 else math.erf(z))
                for b in range(nb_):
                    if mj[j, b] != 0.0:
                        row[b] += mj[j, b] * v
            for a in range(na):
                if mi[i, a] != 0.0:
                    for b in range(nb_):
                        out[t, a * nb_ + b] += mi[i, a] * row[b]
    return out


def basis(field: FloatArray, grid: Grid, y0: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Columns of every coefficient (row-major over the coefficient grid), shape (N, A B): the
    polarization the interpolated cells ``erf((y_i + E_I,j) / (sqrt(2) spread))`` give with that
    coefficient 1 and the others 0; and the play outputs after the sweep (its end state)."""
    y = pr.play(field, grid.coercive, y0)
    cols = _coef_columns(y, grid.interaction, 1.0 / (math.sqrt(2.0) * grid.spread), grid.mi,
                         grid.mj)
    return cols, y[-1]


@dataclass
class Data:
    """The sweeps as the fit sees them: fields (MV/m), readings (um) on their judged samples,
    noise (um), sample periods and a fold label per judged sample."""

    fields: list[FloatArray]
    masks: list[NDArray[np.bool_]]
    y: list[FloatArray]
    dts: list[float]
    noise: FloatArray
    folds: list[NDArray[np.intp]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.folds:
            for y in self.y:
                block = np.minimum(np.arange(y.size) * BLOCKS // max(y.size, 1), BLOCKS - 1)
                self.folds.append((block % FOLDS).astype(np.intp))


@nb.njit(cache=True)
def _rod_columns(phi: np.ndarray, gam: np.ndarray, x: np.ndarray) -> np.ndarray:
    n, k = x.shape
    out = np.empty((n, k))
    p = x[0].copy()
    v = np.zeros(k)
    for t in range(n):
        for j in range(k):
            out[t, j] = p[j]
            f = x[t, j]
            p_new = phi[0, 0] * p[j] + phi[0, 1] * v[j] + gam[0] * f
            v[j] = phi[1, 0] * p[j] + phi[1, 1] * v[j] + gam[1] * f
            p[j] = p_new
    return out


def rod_filter(x: FloatArray, fn: float, zeta: float, dt: float) -> FloatArray:
    """``L[x]`` along axis 0 (each column): the rod (16) normalized to unit DC gain (exact ZOH,
    (18)), at rest with the first sample; :func:`afmctl.fit.parametrization.unit_filter` for
    many columns at once."""
    d = pz.unit_oscillator_zoh(fn, zeta, dt)
    w2 = (2 * math.pi * fn) ** 2
    x2 = np.ascontiguousarray(x, dtype=float).reshape(x.shape[0], -1)
    return _rod_columns(d.phi, d.gamma * w2, x2).reshape(x.shape)


@dataclass
class Theta:
    """A point of the fit: weights (um), reversible slope (um per MV/m), creep weights, the
    quadratic ``s`` (1/um), rod ``log f_n``, ``log zeta``, one offset per sweep (um) and, with
    creep, each sweep's creep transients ``d`` (um; see :class:`Problem`)."""

    w: FloatArray
    r: float
    c: FloatArray
    s: float
    log_fn: float
    log_zeta: float
    offsets: FloatArray
    d: FloatArray = field(default_factory=lambda: np.zeros(0))

    def copy(self) -> Theta:
        return Theta(self.w.copy(), self.r, self.c.copy(), self.s, self.log_fn, self.log_zeta,
                     self.offsets.copy(), self.d.copy())


class Problem:
    """The basis of one start assignment and the exact model and its linearization.

    A sweep need not start with the creep at rest: recorded after others (or after poling), its
    slow elements still remember them. The fit can give each sweep free transients (the elements'
    departure from rest decaying as ``exp(-t / tau_j)``, for time constants up to
    :data:`TRANSIENT_SPAN` times the sweep's length; a slower one would only add a straight line
    in time, a drift, which the fit must not absorb), but does not by default (see there): each
    sweep starts with its creep at rest.
    """

    def __init__(self, data: Data, grid: Grid, starts: Sequence[str], taus: Sequence[float]):
        self.data, self.grid, self.starts = data, grid, tuple(starts)
        self.taus = np.asarray(taus, float)
        self.set_thresholds((0.0,))
        self.trans = []
        for e, dt in zip(data.fields, data.dts, strict=True):
            t = np.arange(e.size) * dt
            cols = [np.exp(-t / tau) for tau in self.taus if tau <= TRANSIENT_SPAN * t[-1]]
            self.trans.append(np.column_stack(cols) if cols else np.zeros((e.size, 0)))
        self.n_trans = [a.shape[1] for a in self.trans]
        self.fn_bounds = (0.5, 10.0 / min(data.dts))  # up to 20x the Nyquist frequency
        self.noise_sse = float(sum(y.size * n * n for y, n in zip(data.y, data.noise,
                                                                   strict=True)))
        self.phi: list[FloatArray] = []
        y_end: FloatArray | None = None
        for e, start in zip(data.fields, self.starts, strict=True):
            if start == "previous" and y_end is not None:
                y0 = y_end
            else:
                y0 = pr.start_outputs(grid.coercive, "depoled" if start == "previous" else start)
            cols, y_end = basis(e, grid, y0)
            self.phi.append(np.ascontiguousarray(cols[:, grid.active]))

    def hysteretic(self, th: Theta) -> list[FloatArray]:
        return [p @ th.w + th.r * e for p, e in zip(self.phi, self.data.fields, strict=True)]

    def set_thresholds(self, thresholds_um: Sequence[float]) -> None:
        """Creep elements: every time constant behind a play of each half-width (um of ``Q``)."""
        self.thresholds = tuple(float(r) for r in thresholds_um)
        self.el_tau = np.tile(self.taus, len(self.thresholds))
        self.el_thr = np.repeat(self.thresholds, self.taus.size)

    def lags(self, q: FloatArray, dt: float) -> FloatArray:
        """Each creep element's state before every sample for the hysteretic output ``q`` (um),
        shape (N, elements), from rest at the first sample."""
        out = []
        for r in self.thresholds:
            y = cr.play_hold(q, r)[0]
            out.append(cr.lagged(y, self.taus, dt, np.full(self.taus.size, y[0])))
        return np.hstack(out)

    def crept(self, x: FloatArray, q: FloatArray, c: FloatArray, dt: float) -> FloatArray:
        """``sum_j c_j Z_j`` linearized in the hysteresis: each element's play held where it
        last moved on ``q``, applied to the columns of ``x`` (N, K) (or to ``x`` (N,))."""
        out = np.zeros(x.shape)
        n_tau = self.taus.size
        for i, r in enumerate(self.thresholds):
            ci = c[i * n_tau:(i + 1) * n_tau]
            on = ci > 0  # (non-negative least squares leaves many at 0)
            if on.any():
                idx = cr.play_hold(q, r)[1]
                out += cr.lag_columns(self.taus[on], ci[on], x[idx], dt)
        return out

    def transients(self, th: Theta) -> list[FloatArray]:
        """Each sweep's creep transient (um, full rate; zeros without)."""
        if not th.d.size:
            return [np.zeros(a.shape[0]) for a in self.trans]
        parts = np.split(th.d, np.cumsum(self.n_trans)[:-1])
        return [a @ d for a, d in zip(self.trans, parts, strict=True)]

    def predict(self, th: Theta, full: bool = False) -> list[FloatArray]:
        """Readings on each sweep's judged samples (``full``: on all its samples), um."""
        out = []
        fn, zeta = math.exp(th.log_fn), math.exp(th.log_zeta)
        for q, dt, m, off, tr in zip(self.hysteretic(th), self.data.dts, self.data.masks,
                                     th.offsets, self.transients(th), strict=True):
            qt = q + self.lags(q, dt) @ th.c + tr if th.c.any() else q
            u = rod_filter(qt + th.s * qt * qt, fn, zeta, dt) + off
            out.append(u if full else u[m])
        return out

    def ratios(self, th: Theta) -> FloatArray:
        """RMS over noise per sweep on the judged samples."""
        return np.array([float(np.sqrt(np.mean((y - u) ** 2))) / n for y, u, n in
                         zip(self.data.y, self.predict(th), self.data.noise, strict=True)])

    def cost(self, th: Theta, pen: FloatArray, lam: float) -> float:
        res = sum(float(np.sum((y - u) ** 2)) for y, u in zip(self.data.y, self.predict(th),
                                                               strict=True))
        return res + lam * float(np.sum((pen @ th.w) ** 2))

    def linearize(self, th: Theta, creep: bool) -> tuple[list[FloatArray], list[FloatArray]]:
        """Per sweep: the design ``[w | r | c | s | log f_n | log zeta | offsets | d]`` on the
        judged samples and the known term ``y - b0`` (see the module docstring)."""
        fn, zeta = math.exp(th.log_fn), math.exp(th.log_zeta)
        n_s, step = len(self.phi), 1e-4
        n_d = sum(self.n_trans) if creep else 0
        d_at = np.concatenate(([0], np.cumsum(self.n_trans)))
        designs, rhs = [], []
        for i, (p, e, dt, m, y, tr) in enumerate(zip(self.phi, self.data.fields, self.data.dts,
                                                     self.data.masks, self.data.y,
                                                     self.transients(th), strict=True)):
            q = p @ th.w + th.r * e
            z = self.lags(q, dt) if creep else np.zeros((q.size, 0))
            tr = tr if creep else np.zeros(q.size)
            qt = q + z @ th.c + tr if creep else q
            m0 = 1.0 + 2.0 * th.s * qt
            cp, ce, held = p, e, 0.0
            if creep and th.c.any():
                cp = p + self.crept(p, q, th.c, dt)
                ce = e + self.crept(e, q, th.c, dt)
                held = self.crept(q, q, th.c, dt)
            g = qt + th.s * qt * qt
            lg = rod_filter(g, fn, zeta, dt)
            cols = [rod_filter(m0[:, None] * cp, fn, zeta, dt)[m],
                    rod_filter(m0 * ce, fn, zeta, dt)[m, None]]
            if creep:
                cols.append(rod_filter(m0[:, None] * z, fn, zeta, dt)[m])
            cols += [rod_filter(qt * qt, fn, zeta, dt)[m, None],
                     ((rod_filter(g, fn * math.exp(step), zeta, dt) - lg) / step)[m, None],
                     ((rod_filter(g, fn, zeta * math.exp(step), dt) - lg) / step)[m, None]]
            ind = np.zeros((int(m.sum()), n_s + n_d))
            ind[:, i] = 1.0
            if creep and self.n_trans[i]:
                ind[:, n_s + d_at[i]:n_s + d_at[i + 1]] = rod_filter(
                    m0[:, None] * self.trans[i], fn, zeta, dt)[m]
            designs.append(np.hstack(cols + [ind]))
            rhs.append(y - rod_filter(qt - m0 * (qt + held), fn, zeta, dt)[m])
        return designs, rhs


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
                float(x[i]), th.log_fn, th.log_zeta, th.offsets.copy())
    i += 1
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
    rod_at = k + 1 + nc + 1
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
    linearization is good only near ``th`` (the quadratic ``s Q^2`` and the creep multiply the
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
            diag[n_bounded + 1:n_bounded + 3] = np.maximum(diag[n_bounded + 1:n_bounded + 3],
                                                           prob.noise_sse / 0.3 ** 2 / max(mu, 1e-12))
        fresh = not (th.w.any() or th.r > 0)
        accepted = False
        for _ in range(12):
            damp = 0.0 if fresh else mu
            trial = _unpack(bounded_solve(g + damp * np.diag(diag), h + damp * diag * x0,
                                          n_bounded), th, creep, rod)
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


def _pack(th: Theta, creep: bool, rod: bool) -> FloatArray:
    """The inverse of :func:`_unpack`."""
    parts = [th.w, [th.r], th.c if creep else [], [th.s]]
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
    fixed = np.concatenate((th.c if creep else [], [th.s]))
    at_d = k + 1 + nc + 3 + n_s
    keep = np.r_[np.arange(k + 1), np.arange(k + 1 + nc + 3, at_d)]
    rhs = [b - a[:, k + 1:k + 2 + nc] @ fixed - a[:, at_d:] @ th.d[:a.shape[1] - at_d]
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
    dtd = pen.T @ pen
    scale = float(np.trace(g_all[:k, :k])) / max(float(np.trace(dtd)), 1e-300)
    out: dict[float, FloatArray] = {}
    for lam_r in lam_rel:
        sse = np.zeros(n_s)
        count = np.zeros(n_s)
        for q in range(FOLDS):
            g = g_all - parts[q][0]  # fit on the other folds
            g[:k, :k] += lam_r * scale * dtd
            x = bounded_solve(g, h_all - parts[q][1], k + 1)
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


def build(th: Theta, prob: Problem, scales_mass: float, thickness_um: float,
          p_scale: float, creep: bool) -> td.Transducer:
    """The physical model of ``th``: ``P = kappa Q`` with ``kappa`` making the largest ``|Q|`` over
    the sweeps ``p_scale`` (C/m^2, a convention like P_R), ``k = m (2 pi f_n)^2``, and the force
    ``a1 P + a2 P^2`` giving ``g(Q)`` in um: ``a1 = 1e-6 k / kappa``, ``a2 = 1e-6 k s / kappa^2``."""
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
                 offset_um=float(th.offsets[-1]))
    cp = cr.Creep(tuple(float(t) for t in prob.el_tau), tuple(float(c) for c in th.c),
                  tuple(float(r) * kappa for r in prob.el_thr)) if creep and th.c.any() else None
    first = prob.starts[0] if prob.starts[0] != "previous" else "depoled"
    return td.Transducer(grid, rod, thickness_um, initial=first, creep=cp)  # type: ignore[arg-type]


def _active(data: Data, ec: FloatArray, ei: FloatArray, spread: float, mi: FloatArray,
            mj: FloatArray, starts_list: Sequence[Sequence[str]]) -> NDArray[np.intp]:
    """Coefficients that move some cell whose erf varies on the judged samples of some sweep
    (under some of the start assignments)."""
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
    return np.flatnonzero(coarse.ravel())


def fit(data: Data, starts_candidates: Sequence[Sequence[str]], rod0: tuple[float, float],
        thickness_um: float, mass_kg: float, settings: Settings = Settings(),
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
    with threadpool_limits(1):  # small dense algebra: threads only contend (seconds per call
        return _fit(data, starts_candidates, rod0, thickness_um, mass_kg, settings,  # on a
                    say or (lambda _m: None))                                      # busy host)


def _fit(data: Data, starts_candidates: Sequence[Sequence[str]], rod0: tuple[float, float],
         thickness_um: float, mass_kg: float, settings: Settings,
         say: Callable[[str], None]) -> PreisachFit:
    t0 = time.perf_counter()
    ec, ei, spread = make_grid(data.fields, settings)
    cands = [tuple(s) for s in dict.fromkeys(tuple(s) for s in starts_candidates)]
    mi = hat_matrix(ec.size, settings.coef_coercive)
    mj = hat_matrix(ei.size, settings.coef_interaction)
    grid = Grid(ec, ei, spread, mi, mj, _active(data, ec, ei, spread, mi, mj, cands))
    pen = penalty(settings.coef_coercive, settings.coef_interaction, grid.active)
    lam0 = settings.smoothing[len(settings.smoothing) // 2]

    def start_theta() -> Theta:
        return Theta(np.zeros(grid.active.size), 0.0, np.zeros(len(settings.creep_taus_s)), 0.0,
                     math.log(rod0[0]), math.log(rod0[1]),
                     np.array([float(np.mean(y)) for y in data.y]))

    def with_elements(th: Theta) -> Theta:
        out = th.copy()
        out.c = np.zeros(prob.el_tau.size)
        return out

    best: tuple[float, Problem, Theta] | None = None
    for starts in cands:  # the start states: one linear step each, the cheapest to compare
        prob = Problem(data, grid, starts, settings.creep_taus_s)
        run = gauss_newton(prob, start_theta(), pen, lam0, False, 1)
        if best is None or run.cost < best[0]:
            best = (run.cost, prob, run.theta)
    assert best is not None
    _, prob, th = best
    say(f"Preisach grid {ec.size} x {ei.size} from {settings.coef_coercive} x "
        f"{settings.coef_interaction} coefficients ({grid.active.size} the sweeps move), "
        f"starts {', '.join(prob.starts)}")
    plain = gauss_newton(prob, th, pen, lam0, False, settings.max_iter // 4)
    q_range = max(float(np.ptp(q)) for q in prob.hysteretic(plain.theta))
    prob.set_thresholds([f * q_range for f in settings.creep_thresholds])
    runs = {False: plain, True: gauss_newton(prob, with_elements(plain.theta), pen, lam0, True,
                                             settings.max_iter)}
    for creep, run in runs.items():
        say(f"  {'with' if creep else 'without'} creep: RMS / noise per sweep "
            + " / ".join(f"{r:.2f}" for r in prob.ratios(run.theta))
            + f" ({run.iterations} steps{'' if run.converged else ', stopped on its budget'})")
    scores: dict[str, float] = {}
    choice: tuple[float, bool, float, FloatArray] | None = None
    for creep, run in runs.items():
        per = heldout(prob, run.theta, pen, settings.smoothing, creep)
        for lam in per:
            score = float(np.sum(per[lam] ** 2 / data.noise ** 2))
            scores[f"{'creep' if creep else 'no creep'}, smoothing {lam:g}"] = score
            if choice is None or score < choice[0]:
                choice = (score, creep, float(lam), per[lam])
    assert choice is not None
    _, creep, lam, per = choice
    final = gauss_newton(prob, runs[creep].theta, pen, lam, creep, settings.max_iter)
    say("  held-out RMS / noise per sweep "
        + " / ".join(f"{r:.2f}" for r in per / data.noise)
        + f" ({'with' if creep else 'without'} creep, smoothing {lam:g}; "
        f"{final.iterations} Gauss-Newton steps)")
    model = build(final.theta, prob, mass_kg, thickness_um, settings.p_scale, creep)
    return PreisachFit(model, prob.starts, final.theta.offsets, per, lam, creep, scores,
                       final.iterations, final.converged, time.perf_counter() - t0,
                       prob.ratios(final.theta), grid.active.size,
                       scalar_uncertainty(prob, final.theta, creep), settings.p_scale,
                       prob.predict(final.theta, full=True))


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
             + ["s_per_um", "log_fn", "log_zeta"]
             + [f"offset_{i + 1}_um" for i in range(len(prob.phi))]
             + ([f"offset_{i + 1}_creep_transient@{t:g}s_um" for i, n in enumerate(prob.n_trans)
                 for t in prob.taus[:n]] if creep else []))
    p = np.concatenate(([th.r], th.c if creep else [], [th.s, th.log_fn, th.log_zeta],
                        th.offsets, th.d if creep else []))
    s2 = float(res @ res) / max(1, res.size - k - p.size)
    cov = s2 * np.linalg.pinv(a.T @ a)
    out = unc.summary(names, p, cov)
    out["method"] = ("Gauss-Newton s^2 (J^T J)^+ of the scalar parameters at the solution, the "
                     "Preisach weights held (non-negative: judged by held-out error instead)")
    return out
