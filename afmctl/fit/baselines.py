"""Reference models the homogenized-energy model is judged against: a linear scaling (the
paper's "linear filter", Section 6) and the classical Prandtl-Ishlinskii operator.

Prandtl-Ishlinskii: ``u(t) = sum_i w_i F_{r_i}[v](t) + offset`` with play (backlash) operators
``F_r`` of thresholds ``r_i = i v_max / n`` (i = 0 ... n-1; ``r_0 = 0`` is the linear term) and
weights ``w_i >= 0``, fitted by nonnegative least squares. Both models are static (rate
independent) and act on the voltage directly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy import optimize

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class Linear:
    """``u = gain v + offset`` (um/V, um)."""

    gain_um_per_v: float
    offset_um: float

    def predict(self, voltage_v: FloatArray) -> FloatArray:
        return self.gain_um_per_v * np.asarray(voltage_v, dtype=float) + self.offset_um


def fit_linear(voltage_v: FloatArray, displacement_um: FloatArray,
               mask: BoolArray | None = None) -> Linear:
    """Least-squares :class:`Linear` on the samples in ``mask`` (all if None)."""
    m = np.ones(len(voltage_v), dtype=bool) if mask is None else mask
    a = np.column_stack((np.asarray(voltage_v)[m], np.ones(int(m.sum()))))
    (g, off), *_ = np.linalg.lstsq(a, np.asarray(displacement_um)[m], rcond=None)
    return Linear(float(g), float(off))


@nb.njit(cache=True, nogil=True)
def _plays(v: np.ndarray, r: np.ndarray) -> np.ndarray:
    out = np.empty((v.size, r.size))
    y = np.zeros(r.size)
    for k in range(v.size):
        for i in range(r.size):
            y[i] = max(v[k] - r[i], min(v[k] + r[i], y[i]))
            out[k, i] = y[i]
    return out


def plays(voltage_v: FloatArray, thresholds_v: FloatArray) -> FloatArray:
    """Play-operator outputs, shape (N, n), each starting at 0 (the history starts at rest).

    Examples
    --------
    >>> plays(np.array([0.0, 2.0, 1.0, -1.0]), np.array([1.0])).ravel().tolist()
    [0.0, 1.0, 1.0, 0.0]
    """
    return _plays(np.ascontiguousarray(voltage_v, dtype=float),
                  np.ascontiguousarray(thresholds_v, dtype=float))


@dataclass(frozen=True)
class PrandtlIshlinskii:
    """Classical PI operator: thresholds (V), nonnegative weights (um/V), offset (um)."""

    thresholds_v: tuple[float, ...]
    weights: tuple[float, ...]
    offset_um: float

    def predict(self, voltage_v: FloatArray) -> FloatArray:
        """Displacement (um) for a voltage history that starts at rest."""
        return plays(voltage_v, np.array(self.thresholds_v)) @ np.array(self.weights) \
            + self.offset_um


def fit_pi(voltage_v: FloatArray, displacement_um: FloatArray, mask: BoolArray | None = None,
           n_plays: int = 24) -> PrandtlIshlinskii:
    """Nonnegative least-squares PI fit on the samples in ``mask``; the plays run over the whole
    history so their state is carried from the start. The offset is free (two columns +-1)."""
    v = np.asarray(voltage_v, dtype=float)
    m = np.ones(v.size, dtype=bool) if mask is None else mask
    r = np.arange(n_plays) * float(np.max(np.abs(v))) / n_plays
    f = plays(v, r)[m]
    ones = np.ones((f.shape[0], 1))
    w, _ = optimize.nnls(np.hstack((f, ones, -ones)), np.asarray(displacement_um)[m],
                         maxiter=50 * (n_plays + 2))
    return PrandtlIshlinskii(tuple(r), tuple(w[:n_plays]), float(w[n_plays] - w[n_plays + 1]))
