"""The rod's response (16) at unit DC gain to many columns at once: the fits' design columns.

:func:`rod_filter` runs the rod's exact zero-order-hold recursion (18) down every column of an
array, :func:`rod_rows` writes the scaled columns' responses straight into a design's rows, and
:func:`quasi_static` is the limit of their block means on a sweep slow to the rod (the Preisach
grid's problem in block means, :mod:`afmctl.fit.preisach_coarse`). Used by the Preisach grid,
Bouc-Wen and the fits with a model's hysteresis held. Pure numerics: no I/O.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from afmctl.fit import parametrization as pz

FloatArray = NDArray[np.float64]


@nb.njit(cache=True, nogil=True)
def _rod_rows(phi: np.ndarray, gam: np.ndarray, x: np.ndarray, scale: np.ndarray,
              rows: np.ndarray, out: np.ndarray, col0: int) -> None:
    """:func:`rod_rows` (1-D views: the loops vectorize)."""
    m = x.shape[1]
    p = x[0] * scale[0]
    v = np.zeros(m)
    a00, a01, a10, a11, g0, g1 = phi[0, 0], phi[0, 1], phi[1, 0], phi[1, 1], gam[0], gam[1]
    r = 0
    for t in range(x.shape[0]):
        if r < rows.size and rows[r] == t:
            o = out[r, col0:col0 + m]
            for j in range(m):
                o[j] = p[j]
            r += 1
        xt = x[t]
        st = scale[t]
        for j in range(m):
            f = st * xt[j]
            p_new = a00 * p[j] + a01 * v[j] + g0 * f
            v[j] = a10 * p[j] + a11 * v[j] + g1 * f
            p[j] = p_new


def rod_rows(x: FloatArray, scale: FloatArray, fn: float, zeta: float, dt: float,
             rows: NDArray[np.intp], out: FloatArray, col0: int) -> None:
    """``out[:, col0:col0 + K] = L[scale * x][rows]`` for ``x`` (N, K): :func:`rod_filter` of
    the scaled columns written straight into a design's rows (no full-rate temporaries).
    ``rows`` are sample indices, strictly increasing, within ``x``; ``out`` is float64 with one
    row per index (the compiled loop checks no bounds, so this does)."""
    x2 = np.ascontiguousarray(x, dtype=float).reshape(x.shape[0], -1)
    idx = np.ascontiguousarray(rows, dtype=np.int64)
    n = x2.shape[0]
    if (idx.ndim != 1 or (idx.size and (idx[0] < 0 or idx[-1] >= n or np.any(np.diff(idx) <= 0)))
            or np.shape(scale) != (n,) or out.dtype != np.float64 or out.shape[0] != idx.size
            or not 0 <= col0 <= out.shape[1] - x2.shape[1]):
        raise ValueError("rod_rows: rows must be increasing sample indices within x, scale one "
                         "per sample, out float64 with a row per index and room from col0")
    _rod_rows(*_rod_coefficients(fn, zeta, dt), x2, np.ascontiguousarray(scale, dtype=float),
              idx, out, col0)


def _rod_coefficients(fn: float, zeta: float, dt: float) -> tuple[FloatArray, FloatArray]:
    """The rod's ZOH transition matrix and its input column scaled to unit DC gain."""
    d = pz.unit_oscillator_zoh(fn, zeta, dt)
    return d.phi, d.gamma * (2 * math.pi * fn) ** 2


def rod_filter(x: FloatArray, fn: float, zeta: float, dt: float) -> FloatArray:
    """``L[x]`` along axis 0 (each column): the rod (16) normalized to unit DC gain (exact ZOH,
    (18)), at rest with the first sample; :func:`afmctl.fit.parametrization.unit_filter` for
    many columns at once (:func:`rod_rows` at every sample, unscaled)."""
    x2 = np.ascontiguousarray(x, dtype=float).reshape(x.shape[0], -1)
    n = x2.shape[0]
    out = np.empty(x2.shape)
    _rod_rows(*_rod_coefficients(fn, zeta, dt), x2, np.ones(n), np.arange(n, dtype=np.int64),
              out, 0)
    return out.reshape(x.shape)


def quasi_static(x: FloatArray, fn: float, zeta: float, dt: float, h: float) -> FloatArray:
    """The block means of ``L[x]`` (along axis 0) for ``x`` given as block means ``h`` (s)
    apart, on a sweep slow to the rod (:mod:`afmctl.fit.preisach_coarse`): the force is held
    over each sample ``dt`` (s), half a sample late on average, and the rod lags it by
    ``2 zeta / omega``, so ``x - (dt / 2 + 2 zeta / omega) dx/dt`` (central differences)."""
    lag = 0.5 * dt + 2.0 * zeta / (2.0 * math.pi * fn)
    return x - lag * np.gradient(x, h, axis=0) if x.shape[0] > 1 else x.copy()


__all__ = ["quasi_static", "rod_filter", "rod_rows"]
