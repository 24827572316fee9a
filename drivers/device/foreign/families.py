"""Hysteresis operators of other families than the paper's, written from the literature.

Independent of afmctl's model code (no import of :mod:`afmctl.model`): the out-of-family plants of
:mod:`afmctl.drivers.device.foreign.family_stage` are built on these. Every operator acts on a
normalized input ``w`` (0 and 1 are the ends of the stage's drive range) and returns a
dimensionless output; state goes in and comes out.

Classical Preisach operator (Mayergoyz, *Mathematical Models of Hysteresis*, 1991, ch. 1)
    ``y(t) = integral over alpha >= beta of mu(alpha, beta) R_ab[w](t)``, relays ``R_ab`` switching
    up at ``alpha`` and down at ``beta`` (0/1 here). Evaluated exactly through the Everett function
    ``F(alpha, beta) = mass of {beta <= b <= a <= alpha}`` and the memory of alternating dominant
    extrema ``L = s_0 < s_1 > s_2 < ...`` (the last entry is the present input):
    ``y = sum over maxima s_i of F(s_i, s_{i-1}) - F(s_i, s_{i+1})``. The wiping-out property is
    the stack update of :func:`preisach_step`. ``F`` is tabulated on a square grid
    (:func:`everett_table`) and interpolated bilinearly, so the operator is continuous.
Prandtl-Ishlinskii (Krasnosel'skii & Pokrovskii 1989; Kuhnen, *Eur. J. Control* 9 (2003) 407)
    A weighted sum of play operators ``z_r = max(w - r, min(w + r, z_r))`` (:func:`play_step`).
    Its inverse is again of PI type, with the closed-form weights and thresholds of
    :func:`pi_inverse` (Kuhnen 2003, eq. 14-15). The "modified" PI of the stages adds an
    asymmetric polynomial output map (:mod:`~afmctl.drivers.device.foreign.family_stage`).
Bouc-Wen (Bouc 1971, Wen 1976; Low et al., piezo stages, and Ismail et al., *Arch. Comput.
Methods Eng.* 16 (2009) 161)
    ``dz/dt = A dw/dt - beta |dw/dt| |z|^(n-1) z - gamma dw/dt |z|^n``: rate independent, so it is
    integrated in ``w`` (RK4, :func:`bouc_wen_step`); it has no wiping-out property and its minor
    loops do not close.
Log-time creep (Krejci & Kuhnen, *IEE Proc. Control Theory Appl.* 148 (2001) 185)
    Linear creep operators ``dz_i/dt = (y - z_i) / tau_i`` driven by the hysteretic output ``y``,
    output ``sum c_i z_i``: with ``tau_i`` spaced evenly in ``log tau`` (``k`` per decade, weights
    ``c_i = gamma / k``) a step of ``y`` creeps by ``gamma`` of the step per time decade
    between the smallest and largest ``tau`` (PI Ceramic's piezo tutorial: 1-2 % per decade)
    (:func:`creep_constants`, :func:`creep_step`).

Example
-------
>>> import numpy as np
>>> grid = np.linspace(-0.3, 1.0, 131)
>>> F = everett_table(lambda a, b: np.ones_like(a), grid)
>>> stack, n = preisach_start(grid[0], 0.0)
>>> ys = [preisach_output(F, grid[0], grid[1] - grid[0], *preisach_step(stack, n, w))
...       for w in (0.5, 1.0, 0.2)]
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numba
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: Entries of the Preisach memory stack (alternating extrema); more than a stage ever keeps.
MAX_STACK = 256
#: Largest input step of one Bouc-Wen RK4 substep.
BW_STEP = 0.002

__all__ = ["MAX_STACK", "everett_table", "preisach_start", "preisach_step", "preisach_output",
           "play_step", "pi_inverse", "bouc_wen_step", "creep_constants", "creep_step"]


# -- Preisach ----------------------------------------------------------------------------------
def everett_table(density: Callable[[FloatArray, FloatArray], FloatArray],
                  grid: FloatArray) -> FloatArray:
    """Everett function of ``density`` on ``grid`` (both thresholds), shape (N, N).

    Parameters
    ----------
    density : callable
        ``mu(alpha, beta)`` (>= 0, arrays of equal shape), per unit area of the
        (alpha, beta) half-plane; evaluated at cell centres (midpoint rule, diagonal cells halved).
    grid : ndarray, shape (N,)
        Evenly spaced thresholds; inputs must stay within ``grid[0] .. grid[-1]``.

    Returns
    -------
    F : ndarray, shape (N, N)
        ``F[i, j]`` = mass of ``{grid[j] <= b <= a <= grid[i]}`` (0 where ``i <= j``).
    """
    h = float(grid[1] - grid[0])
    c = 0.5 * (grid[:-1] + grid[1:])
    a, b = np.meshgrid(c, c, indexing="ij")  # a: row (alpha), b: column (beta)
    m = np.clip(density(a, b), 0.0, None) * h * h
    m = np.where(a > b, m, 0.0) + np.where(a == b, 0.5 * m, 0.0)
    n = grid.size
    F = np.zeros((n, n))
    # F[i, j] = sum over rows p < i, columns q >= j
    inner = np.cumsum(np.cumsum(m[:, ::-1], axis=1)[:, ::-1], axis=0)
    F[1:, :-1] = inner
    return F


def preisach_start(low: float, w0: float) -> tuple[FloatArray, int]:
    """Memory at negative saturation (``low``, every relay down), then the input raised to
    ``w0``: the stack and its length."""
    stack = np.zeros(MAX_STACK)
    stack[0] = low
    n = 1
    return preisach_step(stack, n, w0)


@numba.njit(cache=True)
def preisach_step(stack: FloatArray, n: int, w: float) -> tuple[FloatArray, int]:
    """Update the memory ``stack[:n]`` with the input ``w`` (in place; wiping-out property).

    ``stack[0]`` is the lower end of the thresholds (a minimum); odd entries are maxima, even ones
    minima; the last entry is the present input.
    """
    if w < stack[0]:
        w = stack[0]
    if n == 1:
        if w > stack[0]:
            stack[1] = w
            n = 2
        return stack, n
    rising = (n - 1) % 2 == 1
    last = stack[n - 1]
    if not (rising and w >= last or (not rising) and w <= last):  # a reversal: a new extremum
        if n < stack.size:  # (full: never with stage inputs; the innermost loop is merged)
            n += 1
            rising = not rising
    stack[n - 1] = w
    # wipe out every earlier extremum of the same kind that the input has passed
    while n >= 4 and ((rising and w >= stack[n - 3]) or ((not rising) and w <= stack[n - 3])):
        n -= 2
        stack[n - 1] = w
    if (not rising) and n == 3 and w <= stack[0]:
        n = 1
    return stack, n


@numba.njit(cache=True)
def _everett(F: FloatArray, low: float, h: float, a: float, b: float) -> float:
    """Bilinear interpolation of the Everett table at (alpha=a, beta=b)."""
    n = F.shape[0]
    x = (a - low) / h
    y = (b - low) / h
    i = min(max(int(math.floor(x)), 0), n - 2)
    j = min(max(int(math.floor(y)), 0), n - 2)
    fx = min(max(x - i, 0.0), 1.0)
    fy = min(max(y - j, 0.0), 1.0)
    return ((1 - fx) * (1 - fy) * F[i, j] + fx * (1 - fy) * F[i + 1, j]
            + (1 - fx) * fy * F[i, j + 1] + fx * fy * F[i + 1, j + 1])


@numba.njit(cache=True)
def preisach_output(F: FloatArray, low: float, h: float, stack: FloatArray, n: int) -> float:
    """Mass of the relays that are up, for the memory ``stack[:n]``."""
    y = 0.0
    for i in range(1, n, 2):
        y += _everett(F, low, h, stack[i], stack[i - 1])
        if i + 1 < n:
            y -= _everett(F, low, h, stack[i], stack[i + 1])
    return y


# -- Prandtl-Ishlinskii ------------------------------------------------------------------------
@numba.njit(cache=True)
def play_step(z: FloatArray, r: FloatArray, w: float) -> None:
    """Advance the play operators (thresholds ``r``) to input ``w``, in place."""
    for i in range(z.size):
        z[i] = max(w - r[i], min(w + r[i], z[i]))


def pi_inverse(r: FloatArray, p: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Thresholds and weights of the inverse of the PI operator ``sum p_i play_{r_i}``.

    Parameters
    ----------
    r : ndarray, shape (m,)
        Increasing thresholds, ``r[0] = 0``.
    p : ndarray, shape (m,)
        Weights, ``p[0] > 0`` and every partial sum ``p[0] + ... + p[i] > 0``.

    Returns
    -------
    r_inv, p_inv : ndarray, shape (m,)
        ``r'_i = sum_{j<=i} p_j (r_i - r_j)``, ``p'_0 = 1 / p_0``,
        ``p'_i = -p_i / ((p_0 + ... + p_i)(p_0 + ... + p_{i-1}))`` (Kuhnen 2003): the PI operator
        with these inverts the first, both started from zero play states.
    """
    r, p = np.asarray(r, float), np.asarray(p, float)
    cum = np.cumsum(p)
    r_inv = np.array([np.sum(p[:i + 1] * (r[i] - r[:i + 1])) for i in range(r.size)])
    p_inv = np.empty_like(p)
    p_inv[0] = 1.0 / p[0]
    p_inv[1:] = -p[1:] / (cum[1:] * cum[:-1])
    return r_inv, p_inv


# -- Bouc-Wen ----------------------------------------------------------------------------------
@numba.njit(cache=True)
def _bw_slope(z: float, s: float, A: float, beta: float, gamma: float, n: float) -> float:
    az = abs(z)
    return A - beta * s * az ** (n - 1.0) * z - gamma * az ** n


@numba.njit(cache=True)
def bouc_wen_step(z: float, w_from: float, w_to: float, A: float, beta: float, gamma: float,
                  n: float) -> float:
    """``z`` after the input moves monotonically from ``w_from`` to ``w_to`` (RK4 in ``w``)."""
    dw = w_to - w_from
    if dw == 0.0:
        return z
    s = 1.0 if dw > 0 else -1.0
    k = max(1, int(math.ceil(abs(dw) / BW_STEP)))
    h = dw / k
    for _ in range(k):
        k1 = _bw_slope(z, s, A, beta, gamma, n)
        k2 = _bw_slope(z + 0.5 * h * k1, s, A, beta, gamma, n)
        k3 = _bw_slope(z + 0.5 * h * k2, s, A, beta, gamma, n)
        k4 = _bw_slope(z + h * k3, s, A, beta, gamma, n)
        z += h * (k1 + 2 * k2 + 2 * k3 + k4) / 6.0
    return z


# -- creep -------------------------------------------------------------------------------------
def creep_constants(per_decade: float, tau_min_s: float = 0.01, tau_max_s: float = 1000.0,
                    per_decade_elements: int = 2) -> tuple[FloatArray, FloatArray]:
    """Time constants (s) and weights of creep operators creeping ``per_decade`` of a step per
    time decade between ``tau_min_s`` and ``tau_max_s`` (end elements at half weight: the
    trapezoidal rule of ``integral d log tau``)."""
    decades = math.log10(tau_max_s / tau_min_s)
    k = int(round(decades * per_decade_elements)) + 1
    tau = np.logspace(math.log10(tau_min_s), math.log10(tau_max_s), k)
    c = np.full(k, per_decade / per_decade_elements)
    c[0] *= 0.5
    c[-1] *= 0.5
    return tau, c


@numba.njit(cache=True)
def creep_step(z: FloatArray, y: float, decay: FloatArray, mean: FloatArray,
               c: FloatArray) -> float:
    """Advance creep states ``z`` over one interval with the output ``y`` held (exact); returns
    ``sum c_i`` times each state's average over the interval (``decay = exp(-h / tau)``,
    ``mean = tau / h (1 - decay)``)."""
    out = 0.0
    for i in range(z.size):
        out += c[i] * (y + (z[i] - y) * mean[i])
        z[i] = y + (z[i] - y) * decay[i]
    return out
