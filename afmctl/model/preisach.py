"""A Preisach-type polarization with a general (non-separable) density on a grid.

The homogenized energy model with relay hysterons and no thermal activation is a Preisach model
(Section 2.2 of the paper): the relay (4) of coercive field ``E_c`` and interaction field ``E_I``
switches up at ``E = E_c - E_I`` and down at ``E = -E_c - E_I``, and (11) averages it over the
separable density ``nu_1(E_c) nu_2(E_I)``; Algorithm 1 writes the discretized (13) as
``P_k = V^T Pbar_k W``, an outer product of the two densities' weights. A stage whose hysteresis
is of the Preisach family but whose density is not separable (or not centred) is out of reach of
that product. :class:`PreisachGrid` replaces it by a full weight matrix on the grid::

    P_k = E_k / eta_r + sum_ij w_ij  Pbar_ij(E_k),       w_ij >= 0,

that is Algorithm 1 with a matrix ``w`` in place of ``V W^T`` (and the reversible part ``E / eta``
as its own term). Each cell's relays are spread normally in ``E_I`` about the node ``E_I,j`` with
the grid's ``spread`` (the closed form of the ``normal`` kernel of :mod:`afmctl.model.hysteresis`,
per cell): all relays of a coercive row ``i`` see the same play operator of half-width ``E_c,i``,
whose output ``y_i`` turns the row into ``sum_j w_ij erf((y_i + E_I,j) / (sqrt(2) spread))``. So the
output is smooth in the field (no staircase of a bare relay grid) while keeping the Preisach
properties exactly: wiping-out (a play operator forgets every reversal a larger one wipes out) and
congruency of minor loops between the same input extremes (every row's output depends only on the
reversal points).

The state is the play output per row, as for the ``normal`` kernel; the compiled kernel is
:data:`afmctl.model.hysteresis.KIND_MATRIX`, so :func:`afmctl.model.hysteresis.run`, the transducer,
Algorithm 3 (:mod:`afmctl.model.inverse`) and everything built on them take it as they take (13).
The weights are fitted by non-negative least squares (:mod:`afmctl.fit.preisach`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy import special

from afmctl.model import hysteresis as hy

FloatArray = NDArray[np.float64]
#: Table steps per interaction spread (:func:`row_tables`).
TABLE_STEPS = 16
#: Half-width of the band where a cell is still switching, in spreads: ``5 sqrt(2)``.
CUT = 5.0 * math.sqrt(2.0)
#: Most interaction spreads in the nodes' span (so a row's table is at most ~16,000 long).
MAX_SPAN_SPREADS = 1000


@dataclass(frozen=True)
class PreisachGrid:
    """A general non-negative density on a (coercive, interaction) grid.

    Parameters
    ----------
    coercive : tuple of float
        Coercive-field nodes ``E_c,i`` (play half-widths), MV/m, increasing, >= 0 (0: a row
        without hysteresis, the anhysteretic part).
    interaction : tuple of float
        Interaction-field nodes ``E_I,j``, MV/m, strictly increasing.
    spread : float
        Standard deviation of each cell's interaction field about its node, MV/m (> 0 and at
        least ``1/MAX_SPAN_SPREADS`` of the nodes' span; about the node spacing).
    weights : tuple of tuple of float
        ``w_ij >= 0``, C/m^2: polarization switched by the cell's relays (row ``i`` = coercive
        node, column ``j`` = interaction node).
    reversible : float
        Slope of the reversible part ``E / eta``, (C/m^2)/(MV/m), >= 0.

    Examples
    --------
    >>> g = PreisachGrid((0.2, 0.5), (-0.5, 0.0, 0.5), 0.25, ((0.1, 0.2, 0.1), (0.0, 0.3, 0.0)),
    ...                  0.05)
    >>> p, s = hy.run(g, [0.0, 1.0, 0.0], hy.initial_state(g))  # remanence after poling
    >>> bool(p[1] > p[2] > p[0])
    True
    """

    coercive: tuple[float, ...]
    interaction: tuple[float, ...]
    spread: float
    weights: tuple[tuple[float, ...], ...]
    reversible: float

    #: The Preisach grid has no thermal activation (kernel (4) spread, not (10)).
    thermal = None
    kernel: Literal["preisach"] = "preisach"

    def __post_init__(self) -> None:
        ec, ei = np.asarray(self.coercive, float), np.asarray(self.interaction, float)
        w = np.asarray(self.weights, float)
        if ec.ndim != 1 or ei.ndim != 1 or ec.size < 1 or ei.size < 1:
            raise ValueError("the Preisach grid needs at least one coercive and one interaction node")
        if w.shape != (ec.size, ei.size):
            raise ValueError(f"Preisach weights must be {ec.size} x {ei.size} (coercive x "
                             f"interaction), got {w.shape}")
        values = np.concatenate((ec, ei, w.ravel(), [self.spread, self.reversible]))
        if not np.all(np.isfinite(values)):
            raise ValueError("Preisach grid nodes, weights, spread and slope must be finite")
        if np.any(ec < 0) or np.any(np.diff(ec) < 0):
            raise ValueError("coercive nodes must be >= 0 and increasing")
        if np.any(np.diff(ei) <= 0):
            raise ValueError("interaction nodes must be strictly increasing")
        if np.any(w < 0) or self.reversible < 0:
            raise ValueError("Preisach weights and the reversible slope must be >= 0")
        if not self.spread > 0:
            raise ValueError("the interaction spread must be > 0")
        if self.spread < np.ptp(ei) / MAX_SPAN_SPREADS:
            raise ValueError(f"the interaction spread must be at least 1/{MAX_SPAN_SPREADS} of the "
                             "interaction nodes' span (the kernel tabulates each row at "
                             f"1/{TABLE_STEPS} of it)")

    @property
    def matrix(self) -> FloatArray:
        """The weights as an (N_i, N_j) array, C/m^2."""
        return np.asarray(self.weights, float)

    @property
    def n_coercive(self) -> int:
        return len(self.coercive)

    @property
    def n_interaction(self) -> int:
        return len(self.interaction)

    @property
    def kind(self) -> int:
        return hy.KIND_MATRIX

    @property
    def eta(self) -> float:
        """Reciprocal of the smallest slope dP/dE the model can have, (MV/m)/(C/m^2): that of the
        reversible part, or (without one) a thousandth of the mean hysteretic slope over the
        grid's field range (Algorithm 3 uses it as a lower bound of the slope)."""
        span = float(np.ptp(self.interaction) + 2 * max(self.coercive) + 6 * self.spread)
        mean = 2.0 * float(self.matrix.sum()) / max(span, 1e-12)
        return 1.0 / max(self.reversible, 1e-3 * mean, 1e-300)

    def build_kernel(self) -> hy.Kernel:
        """Packed arrays of the ``KIND_MATRIX`` kernel: each row's table of
        :func:`row_tables` (see :func:`afmctl.model.hysteresis._matrix_step`). Built once per
        grid (a 64 x 48 grid's tables take about 30 ms; setting up and planning one raster frame
        asked for them 36 times) and shared: no kernel writes its arrays."""
        return self._kernel

    @functools.cached_property
    def _kernel(self) -> hy.Kernel:
        y0, h, g, slope = row_tables(self)
        pairs = np.stack((g, h * slope), axis=2).ravel()
        cw = np.ascontiguousarray(np.concatenate(([y0, 1.0 / h, g.shape[1]], pairs)))
        scal = np.array([1.0, 1.0, self.spread, 0.0, 0.0, self.reversible, 0.0])
        return hy.Kernel(hy.KIND_MATRIX, np.asarray(self.coercive, float),
                         np.ones(len(self.coercive)), np.asarray(self.interaction, float),
                         np.ones(len(self.interaction)), cw, scal)

    def hysteretic_range(self) -> float:
        """Polarization between the states all down and all up, ``2 sum w``, C/m^2."""
        return 2.0 * float(self.matrix.sum())


def row_outputs(grid: PreisachGrid, y: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Each row's switched polarization ``g_i(y) = sum_j w_ij erf((y + E_I,j) / (sqrt(2)
    sigma))`` (C/m^2) at play outputs ``y`` (MV/m, shape (M,)) and its slope ``g_i'(y)``
    ((C/m^2)/(MV/m)); both of shape (N_i, M): the closed form of each cell's normal spread."""
    ei = np.asarray(grid.interaction, float)
    scale = math.sqrt(2.0) * grid.spread
    z = (np.asarray(y, float)[:, None] + ei[None, :]) / scale
    gauss = np.exp(-z * z) * (2.0 / (math.sqrt(math.pi) * scale))
    return grid.matrix @ special.erf(z).T, grid.matrix @ gauss.T


def row_tables(grid: PreisachGrid) -> tuple[float, float, FloatArray, FloatArray]:
    """The rows' tables for the compiled kernel: the first output ``y_0`` and the step ``h``
    (MV/m), and :func:`row_outputs` on ``y_0 + h k``, from ``CUT`` spreads below the lowest
    switching output to ``CUT`` above the highest (beyond, every cell is within ``erfc(5) =
    1.5e-12`` of switched). ``h`` is the spread over ``TABLE_STEPS``, so cubic Hermite
    interpolation is within ``h^4 max|g''''| / 384 < 4.4e-8 sum_j w_ij`` of each row's closed
    form (``max|erf''''| = 4.40`` in its own variable)."""
    ei = np.asarray(grid.interaction, float)
    cut = CUT * grid.spread
    h = grid.spread / TABLE_STEPS
    y0 = -ei[-1] - cut
    n = int(math.ceil((ei[-1] - ei[0] + 2.0 * cut) / h)) + 1
    g, slope = row_outputs(grid, y0 + h * np.arange(n))
    return y0, h, g, slope


@nb.njit(cache=True, nogil=True)
def _play(e: np.ndarray, r: np.ndarray, y: np.ndarray) -> np.ndarray:
    out = np.empty((e.size, r.size))
    for k in range(e.size):
        for i in range(r.size):
            if y[i] < e[k] - r[i]:
                y[i] = e[k] - r[i]
            elif y[i] > e[k] + r[i]:
                y[i] = e[k] + r[i]
            out[k, i] = y[i]
    return out


def play(field_mv_m: FloatArray, half_widths: FloatArray, y0: FloatArray) -> FloatArray:
    """Play (backlash) operators of half-widths ``half_widths`` (MV/m) from outputs ``y0``: each
    output stays put until the field is more than its half-width away, then follows it. Returns
    the outputs after each sample, shape (N, n_rows): the rows of the grid, for the fit."""
    return _play(np.ascontiguousarray(field_mv_m, dtype=float),
                 np.ascontiguousarray(half_widths, dtype=float), np.array(y0, dtype=float))


def start_outputs(half_widths: FloatArray, how: str) -> FloatArray:
    """Play outputs of the initial states of :func:`afmctl.model.hysteresis.initial_state`:
    depoled (0), poled positive (+inf: every relay up) or negative (-inf)."""
    value = {"depoled": 0.0, "positive": np.inf, "negative": -np.inf}[how]
    return np.full(np.asarray(half_widths).size, value)
