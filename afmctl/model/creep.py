"""Log-time creep of the polarization: Krejci-Kuhnen creep operators.

A piezo stack held at a constant voltage keeps moving in the direction of its last motion, by about
1-2 % of the step per decade of time (PI's tutorial; Kuhnen's creep operators). afmctl describes it
as a bank of first-order creep elements driven by the hysteretic output ``P_h`` of the polarization
model ((13) or the Preisach grid of :mod:`afmctl.model.preisach`)::

    P(t) = P_h(t) + sum_j c_j z_j(t),      tau_j z_j' = play_{r_j}[P_h] - z_j,      c_j >= 0,

with time constants ``tau_j`` log-spaced over the decades the stage creeps over (10 ms ... 1000 s
by default). ``P`` then forces the rod (16) in place of ``P_h``. After a step ``Delta P_h`` from rest,
``P(t) - P_h = Delta P_h sum_j c_j (1 - exp(-t / tau_j))``: with equal ``c`` per element and ``n``
elements per decade, each element settles in turn, so between the first and the last time constant
this grows by close to ``n c`` per decade, a straight line against log time (:func:`step_response`).
A thermal relaxation (kernel (10)) instead settles with an exponential knee.

The weights enter the displacement linearly once the hysteretic output is known, so they are fitted
by non-negative least squares together with the Preisach weights (:mod:`afmctl.fit.preisach`).

Discretization (zero-order hold, sample period ``dt``): ``y_{j,k}`` the play output after sample
``k``, ``z_{j,k+1} = a_j z_{j,k} + (1 - a_j) y_{j,k}`` with ``a_j = exp(-dt / tau_j)``, and
``P_k = P_{h,k} + sum_j c_j z_{j,k}``: the creep part of sample ``k`` depends only on the samples
before it, so the inverse (Algorithm 3) sees it as a known offset of the polarization at each
sample. The state is ``(z_1 ... z_n, y_1 ... y_n)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: Default creep time constants: two per decade from 10 ms to 1000 s.
DEFAULT_TAUS_S = tuple(float(t) for t in np.logspace(-2, 3, 11))


#: What the creep elements are driven by and added to (:attr:`Creep.acts_on`).
ACTS_ON = ("polarization", "force")


@dataclass(frozen=True)
class Creep:
    """Creep operators on the polarization, or on the rod's force.

    Parameters
    ----------
    tau_s : tuple of float
        Time constants of the creep elements, s (> 0).
    weights : tuple of float
        Weight ``c_j`` of each element (dimensionless, >= 0): the share of a step in ``P_h``
        that element ``j`` adds once settled.
    thresholds : tuple of float, optional
        Play half-width ``r_j`` in front of each element, C/m^2 (N when :attr:`acts_on` is
        ``force``; >= 0; default all 0: linear creep elements).
    acts_on : str
        ``polarization`` (default): the elements are driven by the hysteretic output ``P_h`` and
        ``P = P_h + sum c_j z_j`` forces the rod (16), so the force's ``a2 P^2`` bends the creep
        too. ``force``: driven by the force ``F_h = F(P_h)`` of (16), ``F = F_h + sum c_j z_j``
        (the stack or its flexure creeping under load, after the force's nonlinearity): the two
        differ where the force is not linear in ``P`` and the elements are fast (on a stage with
        a cubic output map and creep after it, a 27.9 Hz triangle was fitted at 7.4x the noise
        with creep on the polarization, 1.6x with creep on the force from an earlier fit's rod,
        6.8x through ``afmctl identify``: the fit's basin, not the model, limits there).
    """

    tau_s: tuple[float, ...]
    weights: tuple[float, ...]
    thresholds: tuple[float, ...] = ()
    acts_on: str = "polarization"

    def __post_init__(self) -> None:
        if self.acts_on not in ACTS_ON:
            raise ValueError(f"creep acts on one of {', '.join(ACTS_ON)}, not {self.acts_on!r}")
        t, c = np.asarray(self.tau_s, float), np.asarray(self.weights, float)
        if not self.thresholds:
            object.__setattr__(self, "thresholds", (0.0,) * t.size)
        r = np.asarray(self.thresholds, float)
        if t.ndim != 1 or t.shape != c.shape or t.shape != r.shape or t.size < 1:
            raise ValueError("creep needs equally long, non-empty tau_s, weights and thresholds")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(c)) and np.all(np.isfinite(r))):
            raise ValueError("creep time constants, weights and thresholds must be finite")
        if np.any(t <= 0) or np.any(c < 0) or np.any(r < 0):
            raise ValueError("creep time constants must be > 0, weights and thresholds >= 0")

    @property
    def size(self) -> int:
        return len(self.tau_s)

    @property
    def total(self) -> float:
        """``sum c_j``: the share of a step added once every element has settled."""
        return float(np.sum(self.weights))

    def factors(self, dt: float) -> FloatArray:
        """``a_j = exp(-dt / tau_j)`` for sample period ``dt`` (s)."""
        return np.exp(-float(dt) / np.asarray(self.tau_s, float))

    def per_decade(self, t_lo: float = 0.1, t_hi: float = 100.0) -> float:
        """Mean creep per decade of time between ``t_lo`` and ``t_hi`` (s) after a unit step
        (one much larger than every threshold)."""
        lo, hi = step_response(self, np.array([t_lo, t_hi]))
        return float((hi - lo) / np.log10(t_hi / t_lo))


def rest_state(creep: Creep | None, p_h: float) -> FloatArray:
    """Creep state after a long rest at hysteretic output ``p_h``: every element settled."""
    return np.zeros(0) if creep is None else np.full(2 * creep.size, float(p_h))


def held(creep: Creep | None, z: FloatArray, hold_s: float) -> FloatArray:
    """Creep state ``z`` (:func:`run`'s) after its last input is held ``hold_s`` seconds more:
    each element relaxes toward its play's output, ``z_j -> y_j + (z_j - y_j) exp(-hold / tau_j)``,
    the plays (their input unchanged) hold theirs.

    Examples
    --------
    >>> c = Creep((1.0,), (0.1,))
    >>> [round(float(v), 4) for v in held(c, np.array([0.0, 1.0]), 1.0)]
    [0.6321, 1.0]
    """
    if creep is None:
        return np.asarray(z, float).copy()
    n, zz = creep.size, np.asarray(z, float)
    y = zz[n:]
    return np.concatenate((y + (zz[:n] - y) * np.exp(-float(hold_s) / np.asarray(creep.tau_s)),
                           y))


def offset(creep: Creep | None, z: FloatArray) -> float:
    """Creep part ``sum c_j z_j`` of the polarization in state ``z``."""
    if creep is None or z.size == 0:
        return 0.0
    return float(np.dot(creep.weights, z[:creep.size]))


@nb.njit(cache=True, nogil=True)
def _update(p: float, a: np.ndarray, r: np.ndarray, z: np.ndarray) -> None:
    """Advance the state ``z = (z_j, y_j)`` by one sample of hysteretic output ``p``."""
    n = a.size
    for j in range(n):
        y = z[n + j]
        if y < p - r[j]:
            y = p - r[j]
        elif y > p + r[j]:
            y = p + r[j]
        z[n + j] = y
        z[j] = a[j] * z[j] + (1.0 - a[j]) * y


@nb.njit(cache=True, nogil=True)
def _run(p_h: np.ndarray, a: np.ndarray, c: np.ndarray, r: np.ndarray,
         z: np.ndarray) -> np.ndarray:
    out = np.empty(p_h.size)
    for k in range(p_h.size):
        acc = 0.0
        for j in range(a.size):
            acc += c[j] * z[j]
        out[k] = p_h[k] + acc
        _update(p_h[k], a, r, z)
    return out


def run(creep: Creep | None, p_h: FloatArray, dt: float,
        z: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Polarization with creep for the hysteretic output ``p_h`` (held ``dt`` s per sample).

    Parameters
    ----------
    creep : Creep or None
        None: no creep (``p_h`` is returned as it is).
    p_h : ndarray, shape (N,)
        Hysteretic output per sample, C/m^2.
    dt : float
        Sample period, s.
    z : ndarray, shape (2 n_elements,)
        Creep state before the first sample (:func:`rest_state`); not modified.

    Returns
    -------
    p : ndarray, shape (N,)
        ``P_k = P_{h,k} + sum_j c_j z_{j,k}``, C/m^2.
    z : ndarray
        State after the last sample.

    Examples
    --------
    >>> c = Creep((1.0,), (0.1,))
    >>> p, z = run(c, np.ones(3), 1.0, rest_state(c, 0.0))
    >>> [round(float(v), 4) for v in p]
    [1.0, 1.0632, 1.0865]
    """
    p_h = np.ascontiguousarray(p_h, dtype=float)
    if creep is None:
        return p_h.copy(), np.zeros(0)
    zz = np.array(z, dtype=float)
    out = _run(p_h, creep.factors(dt), np.asarray(creep.weights, float),
               np.asarray(creep.thresholds, float), zz)
    return out, zz


def step_response(creep: Creep, t_s: FloatArray) -> FloatArray:
    """Creep after a unit step of ``P_h`` from rest: ``sum_j c_j (1 - exp(-t / tau_j))``."""
    t = np.asarray(t_s, float)[..., None]
    return np.sum(np.asarray(creep.weights) * -np.expm1(-t / np.asarray(creep.tau_s)), axis=-1)


def lagged(x: FloatArray, tau_s: FloatArray, dt: float, z0: FloatArray) -> FloatArray:
    """Each element's state ``z_j`` before every sample for the input ``x`` (N,) (one element per
    time constant, unit weight), shape (N, n_elements), from ``z_{j,0} = z0[j]``: the columns whose
    combination ``sum c_j z_j`` the fit weighs. ``z_{j,k+1} = a_j z_{j,k} + (1 - a_j) x_k``,
    ``a_j = exp(-dt / tau_j)``: the first-order filter ``scipy.signal.lfilter`` computes, to the
    last bit (``tests/model/test_creep.py``)."""
    a = np.array([math.exp(-float(dt) / float(tau)) for tau in tau_s])
    if len(z0) < a.size:  # the compiled loop checks no bounds
        raise ValueError(f"lagged: {len(z0)} start states for {a.size} time constants")
    return _lagged(np.ascontiguousarray(x, dtype=float), a,
                   np.array([float(v) for v in z0[:a.size]]))


@nb.njit(cache=True, nogil=True)
def _lagged(x: np.ndarray, a: np.ndarray, z0: np.ndarray) -> np.ndarray:
    out = np.empty((x.size, a.size))
    z = z0.copy()
    for t in range(x.size):
        for j in range(a.size):
            out[t, j] = z[j]
            z[j] = (1.0 - a[j]) * x[t] + a[j] * z[j]  # lfilter's step, term for term
    return out


@nb.njit(cache=True, nogil=True)
def _add_columns(out: np.ndarray, x: np.ndarray, idx: np.ndarray, a: np.ndarray,
                 c: np.ndarray, group: np.ndarray, z: np.ndarray, x0: np.ndarray) -> None:
    """:func:`add_lag_columns`: ``out[t] = x[t] + acc_0 + acc_1 + ...`` (in that order),
    ``acc_g`` group ``g``'s elements' weighted states before sample ``t``, summed in the
    elements' order; the states ``z`` (elements, K: element-major, the inner loops run along the
    columns, contiguous) stepped in place. A single pass over ``out`` for all the groups."""
    m = out.shape[1]
    acc = np.empty((idx.shape[0], m))
    for t in range(out.shape[0]):
        acc[:, :] = 0.0
        for j in range(a.size):
            g = group[j]
            row = idx[g, t]
            xv = x[row] if row >= 0 else x0[g]  # 1-D views: the loops vectorize (4x)
            ag, zj = acc[g], z[j]
            cj, aj, bj = c[j], a[j], 1.0 - a[j]
            for i in range(m):
                ag[i] += cj * zj[i]
                zj[i] = aj * zj[i] + bj * xv[i]
        ot, xt = out[t], x[t]
        for i in range(m):
            ot[i] = xt[i]
        for g in range(idx.shape[0]):
            ag = acc[g]
            for i in range(m):
                ot[i] += ag[i]


@dataclass(frozen=True, eq=False)
class Lags:
    """A group of linear creep elements on the columns of a basis (:func:`add_lag_columns`):
    time constants ``tau_s`` (s) and ``weights``; ``idx``, the sample each column is held at,
    at every sample (a play's last move, :func:`play_hold`; -1: the play still holds what it
    held before the first sample); ``start``, where the elements start: (states (K, elements),
    held (K,)), or None: from rest at the first sample (then ``idx[0]`` is a sample)."""

    tau_s: FloatArray
    weights: FloatArray
    idx: NDArray[np.int64]
    start: tuple[FloatArray, FloatArray] | None = None


def add_lag_columns(x: FloatArray, groups: Sequence[Lags], dt: float
                    ) -> tuple[FloatArray, list[tuple[FloatArray, FloatArray]]]:
    """``x + sum_g sum_j c_gj z_gj`` for linear elements in groups (:class:`Lags`) on every
    column of ``x[idx_g]`` (``x``: N samples by K columns; ``dt``, the sample period, s): the
    creep of every basis column of a fit, each group's held where its play says. ``x[idx]`` is
    never copied (for a fit's basis it is hundreds of MB, and the copy took as long as the
    filtering), and the sum is written in a single pass for all the groups (a pass per group,
    after a copy of ``x`` to add to, took half the time).

    Returns the sum (a new array) and, per group, the elements' states after the last sample
    and what the play then holds, per column: the ``start`` of a record that follows this one.
    """
    xs = np.ascontiguousarray(x, dtype=float)
    if xs.ndim != 2 or not groups:
        raise ValueError("add_lag_columns: x is (samples, columns), with at least one group")
    for g in groups:  # the compiled loop checks no bounds
        if len(g.weights) != len(g.tau_s) or len(g.idx) != xs.shape[0]:
            raise ValueError(f"add_lag_columns: {len(g.weights)} weights for {len(g.tau_s)} "
                             f"time constants, {len(g.idx)} held samples for {xs.shape[0]}")
        if g.start is None and g.idx[0] < 0:
            raise ValueError("add_lag_columns: a group from rest starts at a sample (idx[0] >= 0)")
    sizes = [len(g.tau_s) for g in groups]
    rows = [slice(b - n, b) for n, b in zip(sizes, np.cumsum(sizes), strict=True)]  # of z
    idx = np.ascontiguousarray(np.stack([np.asarray(g.idx, np.int64) for g in groups]))
    a = np.concatenate([np.exp(-float(dt) / np.asarray(g.tau_s, float)) for g in groups])
    z = np.empty((a.size, xs.shape[1]))
    x0 = np.zeros((len(groups), xs.shape[1]))
    for i, (g, at) in enumerate(zip(groups, rows, strict=True)):
        if g.start is None:
            z[at] = xs[g.idx[0]][None, :]
        else:  # copies: stepped in place
            z[at] = np.asarray(g.start[0], dtype=float).T
            x0[i] = g.start[1]
    result = np.empty(xs.shape)
    _add_columns(result, xs, idx, a,
                 np.concatenate([np.asarray(g.weights, dtype=float) for g in groups]),
                 np.repeat(np.arange(len(groups), dtype=np.int64), sizes), z, x0)
    return result, [(z[at].T.copy(), xs[g.idx[-1]].copy() if g.idx[-1] >= 0 else x0[i].copy())
                    for i, (g, at) in enumerate(zip(groups, rows, strict=True))]


@nb.njit(cache=True, nogil=True)
def _held(x: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
    y = np.empty(x.size)
    idx = np.empty(x.size, dtype=np.int64)
    yy, last = x[0], 0
    for k in range(x.size):
        if yy < x[k] - r:
            yy, last = x[k] - r, k
        elif yy > x[k] + r:
            yy, last = x[k] + r, k
        elif r == 0.0:
            last = k
        y[k] = yy
        idx[k] = last
    return y, idx


def play_hold(x: FloatArray, r: float) -> tuple[FloatArray, NDArray[np.int64]]:
    """The play operator of half-width ``r`` on ``x`` (from rest at ``x[0]``) and, per sample, the
    last sample at which it moved: its derivative with respect to ``x`` is that sample's
    (``play(x + dx)[k] = play(x)[k] + dx[idx[k]]`` for a small ``dx``)."""
    return _held(np.ascontiguousarray(x, dtype=float), float(r))
