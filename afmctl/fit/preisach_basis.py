"""The Preisach grid's nodes and its basis columns (:mod:`afmctl.fit.preisach_problem`).

The weights of the model's ``N_i x N_j`` cells are interpolated bilinearly (:func:`hat_matrix`)
from fewer coefficients (:class:`Grid`); each active coefficient's column is the polarization its
cells give along a sweep's field history (:func:`basis`), fixed by the field and the start state,
never by a parameter. Pure numerics: no I/O.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from afmctl.fit import cores
from afmctl.model import preisach as pr

FloatArray = NDArray[np.float64]

__all__ = ["Grid", "basis", "hat_matrix"]


def hat_matrix(n_fine: int, n_coarse: int, power: float = 1.0) -> FloatArray:
    """Linear interpolation from ``n_coarse`` nodes to ``n_fine`` equally spaced ones, spanning
    the same interval, shape (n_fine, n_coarse); rows sum to 1, entries >= 0. Node ``k`` sits
    at ``(k / (n_coarse - 1))**power`` of the interval: equally spaced with ``power`` 1, closer
    together at the interval's start above 1.

    Examples
    --------
    >>> hat_matrix(5, 3)[:, 1]
    array([0. , 0.5, 1. , 0.5, 0. ])
    >>> np.round(hat_matrix(5, 3, power=2.0)[:, 1], 3)
    array([0.   , 1.   , 0.667, 0.333, 0.   ])
    """
    if n_fine < 2 or n_coarse < 2 or power <= 0.0:
        raise ValueError(f"hat_matrix needs 2 nodes or more each way and a positive power, "
                         f"got {n_fine}, {n_coarse}, {power}")
    nodes = (n_fine - 1.0) * (np.arange(n_coarse) / (n_coarse - 1.0)) ** power
    if nodes[1] < 1.0 or nodes[-1] - nodes[-2] < 1.0:
        raise ValueError(f"hat_matrix: {n_coarse} nodes at power {power} fall less than one of "
                         f"the {n_fine} rows apart")
    x = np.arange(n_fine, dtype=float)
    j = np.clip(np.searchsorted(nodes, x, side="right") - 1, 0, n_coarse - 2)
    t = (x - nodes[j]) / (nodes[j + 1] - nodes[j])
    m = np.zeros((n_fine, n_coarse))
    m[np.arange(n_fine), j] = 1.0 - t
    m[np.arange(n_fine), j + 1] = t
    return m


@dataclass(frozen=True)
class Grid:
    """Nodes of the model's grid (MV/m), the interpolation from the coefficients (``mi``, ``mj``)
    and which coefficients the sweeps can move (``active``, flat indices into the
    ``coef_coercive x coef_interaction`` array, row-major, then, with ``plays``, one per model
    row: that row's play, a line of the density uniform in the interaction field)."""

    coercive: FloatArray
    interaction: FloatArray
    spread: float
    mi: FloatArray
    mj: FloatArray
    active: NDArray[np.intp]
    plays: bool = False

    @property
    def n_coefficients(self) -> int:
        """Size of the coefficient space ``active`` indexes."""
        return self.mi.shape[1] * self.mj.shape[1] + (self.coercive.size if self.plays else 0)

    def weights(self, coef: FloatArray) -> FloatArray:
        """The cell weights (N_i, N_j) of the active coefficients ``coef``."""
        full = np.zeros(self.n_coefficients)
        full[self.active] = coef
        n = self.mi.shape[1] * self.mj.shape[1]
        w = self.mi @ full[:n].reshape(self.mi.shape[1], -1) @ self.mj.T
        return w + full[n:, None] if self.plays else w


@nb.njit(cache=True, nogil=True)
def _nonzeros(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``m`` its nonzero columns (``idx[r, :cnt[r]]``, in order)."""
    idx = np.zeros(m.shape, np.int64)
    cnt = np.zeros(m.shape[0], np.int64)
    for r in range(m.shape[0]):
        for c in range(m.shape[1]):
            if m[r, c] != 0.0:
                idx[r, cnt[r]] = c
                cnt[r] += 1
    return idx, cnt


@nb.njit(cache=True, nogil=True)
def _coef_columns(y: np.ndarray, ei: np.ndarray, inv: float, mi: np.ndarray,
                  mj: np.ndarray, plays: bool, col_of: np.ndarray, out: np.ndarray) -> None:
    """``out[:, col_of[a B + b]] += sum_ij mi[i, a] mj[j, b] erf((y_i + E_I,j) inv)`` per sample
    (a column of -1 is not kept); with ``plays``, then ``out[:, col_of[A B + i]]`` is row ``i``'s
    ``sum_j erf((y_i + E_I,j) inv)``, from the same erfs. Only the interpolations' nonzero
    entries are visited (two per node of a hat); each sample's row depends on its plays' outputs
    alone, so a span of samples is computed alike on its own."""
    n, ni = y.shape
    nj, nb_ = ei.size, mj.shape[1]
    ia, na_ = _nonzeros(mi)
    jb, nbj = _nonzeros(mj)
    rows = np.zeros((ni, nb_))  # each row's erfs, summed per coefficient, at its output ...
    lines = np.zeros(ni)
    at = np.full(ni, np.nan)  # ... ``at``: a held play's are not computed again
    for t in range(n):
        for i in range(ni):
            row = rows[i]
            if y[t, i] != at[i]:
                at[i] = y[t, i]
                row[:] = 0.0
                line = 0.0
                for j in range(nj):
                    z = (y[t, i] + ei[j]) * inv
                    v = 1.0 if z > 5.0 else (-1.0 if z < -5.0 else math.erf(z))
                    line += v
                    for k in range(nbj[j]):
                        b = jb[j, k]
                        row[b] += mj[j, b] * v
                lines[i] = line
            for k in range(na_[i]):
                a = ia[i, k]
                for b in range(nb_):
                    c = col_of[a * nb_ + b]
                    if c >= 0:
                        out[t, c] += mi[i, a] * row[b]
            if plays and col_of[mi.shape[1] * nb_ + i] >= 0:
                out[t, col_of[mi.shape[1] * nb_ + i]] = lines[i]


def basis(field: FloatArray, grid: Grid, y0: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Columns of the grid's active coefficients (``grid.active``, of the coefficient grid
    row-major, then each row's play with ``grid.plays``), shape (N, active): the polarization the
    interpolated cells ``erf((y_i + E_I,j) / (sqrt(2) spread))`` give with that coefficient 1 and
    the others 0; and the play outputs after the sweep (its end state). With a core spare, the
    sweep's two halves are computed side by side (:func:`afmctl.fit.cores.together`)."""
    y = pr.play(field, grid.coercive, y0)
    n_all = grid.mi.shape[1] * grid.mj.shape[1] + (grid.coercive.size if grid.plays else 0)
    col_of = np.full(n_all, -1, dtype=np.int64)
    col_of[grid.active] = np.arange(grid.active.size)
    out = np.zeros((y.shape[0], grid.active.size))
    cuts = np.linspace(0, y.shape[0], cores.workers() + 1).astype(int)
    inv = 1.0 / (math.sqrt(2.0) * grid.spread)
    cores.together([functools.partial(_coef_columns, y[a:b], grid.interaction, inv, grid.mi,
                                      grid.mj, grid.plays, col_of, out[a:b])
                    for a, b in zip(cuts[:-1], cuts[1:], strict=True) if b > a])
    return out, y[-1]
