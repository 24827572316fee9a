"""Compiled thermally activated kernel (6)-(10) of the homogenized energy model (Section 2.1).

Every hysteron of the grid carries the fraction ``x_+`` of positively oriented dipoles; over a
sample held ``dt`` s at a frozen field it relaxes exactly towards ``p_-+ / (p_+- + p_-+)``:

``x_+ <- x_eq + (x_+ - x_eq) exp(-(p_+- + p_-+) dt)``,

the solution of the rate equations after (8) at constant rates. The rates (7)-(8) in the
inflection-point form are ``p = nu0 / erfcx(z)`` with ``z = -(E + E_I + E_c) / E_th`` (``+ -> -``)
and ``z = (E + E_I - E_c) / E_th`` (``- -> +``) (:func:`afmctl.model.hysteresis.switching_rates`
derives them).

Speed (issue 27): the kernel visits only the hysterons that can move (:func:`thermal_step`), takes
``1 / erfcx`` from a cubic Hermite table with exact slopes (:data:`RATE_TABLE`; relative error
below :data:`RATE_REL_ERROR`; the direct formula is used outside the table) and,
along a row, stops evaluating rates past the first hysteron that switches completely within the
sample (every hysteron further on switches faster: its ``x_+`` is exactly 1 or 0 after the snap,
as the direct update would give it). Pure numerics: no I/O.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy import special

FloatArray = NDArray[np.float64]

#: A hysteron within this of a settled orientation (no rate back) is settled.
SNAP = 1e-12
#: ``rate * dt`` beyond which the exact update leaves less than ``exp(-30) < SNAP`` unswitched.
FULL_SWITCH = 30.0
#: The rate table spans ``RATE_Z_LO <= z < RATE_Z_HI`` at ``RATE_PER_UNIT`` intervals per unit of
#: ``z``. Below it the rates are under ``nu0 * 2e-21`` (``1 / erfcx(-6.5)``): a sample's cut-off
#: ``zcut`` lies above it unless ``nu0 dt`` exceeds ``1e6`` s/s ... then the formula is used.
RATE_Z_LO, RATE_Z_HI, RATE_PER_UNIT = -6.5, 25.0, 256
#: Largest relative error of the table's ``1 / erfcx`` over its span (checked by the tests): 1.6e-8
#: at its low end, where a rate moves x_+ by under ``1e-11 nu0 dt`` per sample; below 1e-13 for
#: ``z >= 0``, where the rates matter.
RATE_REL_ERROR = 2e-8


@nb.njit(cache=True, nogil=True)
def erfcx(z: float) -> float:
    """Scaled complementary error function exp(z^2) erfc(z), stable for all real z."""
    if z < 25.0:
        if z < -26.0:
            return math.inf
        return math.exp(z * z) * math.erfc(z)
    iz2 = 1.0 / (z * z)
    return (1.0 - 0.5 * iz2 + 0.75 * iz2 * iz2 - 1.875 * iz2 * iz2 * iz2) / (z * math.sqrt(math.pi))


def _rate_table() -> FloatArray:
    """Cubic coefficients ``(a, b, c, d)`` of ``1 / erfcx`` per interval of the table: on interval
    ``k``, ``1 / erfcx(z_k + t h) = a + t (b + t (c + t d))`` for ``0 <= t < 1`` (Hermite with the
    exact slope ``(1 / erfcx)' = 2 r^2 / sqrt(pi) - 2 z r``, ``r = 1 / erfcx``)."""
    h = 1.0 / RATE_PER_UNIT
    n = int(round((RATE_Z_HI - RATE_Z_LO) * RATE_PER_UNIT))
    z = RATE_Z_LO + h * np.arange(n + 1)
    r = 1.0 / special.erfcx(z)
    slope = h * (2.0 * r * r / math.sqrt(math.pi) - 2.0 * z * r)
    y0, y1, d0, d1 = r[:-1], r[1:], slope[:-1], slope[1:]
    return np.ascontiguousarray(np.column_stack((
        y0, d0, 3.0 * (y1 - y0) - 2.0 * d0 - d1, 2.0 * (y0 - y1) + d0 + d1)))


#: :func:`_rate_table`: shape (intervals, 4).
RATE_TABLE = _rate_table()


@nb.njit(cache=True, nogil=True)
def rate(z: float, nu0: float, table: np.ndarray) -> float:
    """``nu0 / erfcx(z)`` (1/s): the switching likelihood (7)-(8) at the scaled field ``z``, from
    ``table`` (:data:`RATE_TABLE`) inside its span, from the formula outside."""
    if z < RATE_Z_LO or z >= RATE_Z_HI:
        return nu0 / erfcx(z)
    u = (z - RATE_Z_LO) * RATE_PER_UNIT
    k = int(u)
    t = u - k
    return nu0 * (table[k, 0] + t * (table[k, 1] + t * (table[k, 2] + t * table[k, 3])))


@nb.njit(cache=True, nogil=True)
def _cell(x: float, ee: float, ec: float, dt: float, s: float, zcut: float, nu0: float,
          table: np.ndarray) -> tuple[float, float, float]:
    """New ``x_+`` of a hysteron (effective field ``ee``, coercive field ``ec``; MV/m) held
    ``dt`` s: the exact exponential update at the frozen rates (7)-(8), a rate whose scaled field
    is at most ``zcut`` being 0. Also returns the rates ``(p_+-, p_-+)`` (1/s) it evaluated (0 for
    one it did not need: a hysteron settled at 1 or 0 with no rate back does not move)."""
    zm = -s * (ee + ec)  # + -> - switching (7)-(8)
    zp = s * (ee - ec)   # - -> + switching
    if zm <= zcut:  # towards x_eq = 1 (as pp / (0 + pp) is, exactly)
        if x == 1.0 or zp <= zcut:
            return x, 0.0, 0.0
        pp = rate(zp, nu0, table)
        x = 1.0 + (x - 1.0) * math.exp(-pp * dt)
        if x > 1.0 - SNAP:  # settled up: a fraction below 1e-12 is none
            x = 1.0
        return x, 0.0, pp
    if zp <= zcut:  # towards x_eq = 0
        if x == 0.0:
            return x, 0.0, 0.0
        pm = rate(zm, nu0, table)
        x = x * math.exp(-pm * dt)
        if x < SNAP:
            x = 0.0
        return x, pm, 0.0
    pm, pp = rate(zm, nu0, table), rate(zp, nu0, table)
    xeq = pp / (pm + pp)
    return xeq + (x - xeq) * math.exp(-(pm + pp) * dt), pm, pp


@nb.njit(cache=True, nogil=True)
def thermal_step(e: float, dt: float, st: np.ndarray, out: np.ndarray, ec: np.ndarray,
                 wc: np.ndarray, ei: np.ndarray, cw: np.ndarray, fscale: float,
                 nu0: float) -> float:
    """Kernel (10) over the grid: advance x_+ of every hysteron at field ``e`` (MV/m) held ``dt``
    s from ``st`` into ``out`` (which may alias it) and return the switched total
    ``sum w (2 x_+ - 1)``, kept in the state's last slot.

    ``ec`` (increasing coercive nodes, weights ``wc``) are the rows, ``ei`` (increasing
    interaction nodes, cumulative weights ``cw``) the columns; ``st`` holds x_+ row-major, then
    the total. A hysteron moves only near its switching fields ``E + E_I = +-E_c`` (rates
    (7)-(8) below ``1e-12 / dt`` elsewhere), so each row is visited from ``zcut`` field scales
    ahead of each switching field on, and on past it while x_+ is not yet exactly 1 (up) or 0
    (down): a state made by this kernel from a relay state is monotone in ``E_I``, so past a
    hysteron that was and stays fully switched the rest of the row cannot move. Along a pass the
    rate of switching grows; once a hysteron switches completely within ``dt`` (rate times
    ``dt`` at least :data:`FULL_SWITCH`, no rate back) the rest of the pass is set switched
    without evaluating rates. The result equals the sweep of every hysteron to 1e-12 and the
    rates' table error; the cost is the bands'.
    """
    ni, nj = ec.size, ei.size
    n = ni * nj
    if out is not st:
        out[:] = st
    table = RATE_TABLE
    s = 1.0 / fscale
    zcut = -math.sqrt(max(math.log(max(nu0 * dt, 1e-300) * 1e12), 1.0))
    band = -zcut * fscale
    full = FULL_SWITCH / dt
    acc = st[n]
    for i in range(ni):
        base = i * nj
        d_acc = 0.0
        # up-switching: E_I >= ec - e - band, on while inside the band or not yet fully up
        j = np.searchsorted(ei, ec[i] - e - band)
        first_up = j
        beyond = ec[i] - e + band  # E_I past which a fully switched hysteron ends the pass
        done = False  # a hysteron before switched up completely: so do the rest
        pure = False  # no rate back (p_+- = 0) here, so neither further on
        while j < nj:
            old = st[base + j]
            if pure and old == 1.0:  # fully up and cannot leave: unchanged
                if ei[j] > beyond:
                    break
                j += 1
                continue
            if done:
                x = 1.0
            else:
                x, pm, pp = _cell(old, e + ei[j], ec[i], dt, s, zcut, nu0, table)
                done = pm == 0.0 and pp >= full  # (0 when not evaluated: x_+ was already 1)
                pure = -s * (e + ei[j] + ec[i]) <= zcut
            if x != old:
                out[base + j] = x
                d_acc += (cw[j + 1] - cw[j]) * (x - old)
            if old == 1.0 and x == 1.0 and ei[j] > beyond:
                break
            j += 1
        # down-switching: E_I <= -ec - e + band, below the hysterons the up pass visited
        j = min(np.searchsorted(ei, -ec[i] - e + band, side="right"), first_up) - 1
        beyond = -ec[i] - e - band
        done = False
        pure = False  # no rate back (p_-+ = 0)
        while j >= 0:
            old = st[base + j]
            if pure and old == 0.0:
                if ei[j] < beyond:
                    break
                j -= 1
                continue
            if done:
                x = 0.0
            else:
                x, pm, pp = _cell(old, e + ei[j], ec[i], dt, s, zcut, nu0, table)
                done = pp == 0.0 and pm >= full
                pure = s * (e + ei[j] - ec[i]) <= zcut
            if x != old:
                out[base + j] = x
                d_acc += (cw[j + 1] - cw[j]) * (x - old)
            if old == 0.0 and x == 0.0 and ei[j] < beyond:
                break
            j -= 1
        acc += 2.0 * wc[i] * d_acc
    out[n] = acc
    return acc
