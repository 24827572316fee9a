"""The Preisach grid's problem with its slow sweeps in block means and the others' rows thinned:
the first fits' cheap copy.

A Gauss-Newton step of the grid costs in proportion to the rows it fits, and most of a standard
set's rows are its slowest sweep's (the 0.279 Hz triangle: 54k of the 82k judged samples at
10 kHz), over which the field moves by 0.006 % of its range per sample: far finer than the
density, the creep's fastest element or the rod can tell. :func:`coarse` gives the same problem
with such a sweep seen as the means of blocks of samples (:func:`blocks`): the basis columns, the
field and the readings averaged over each block (the hysteresis's memory is the full rate's:
its columns are), the creep stepped block by block, the rod in its quasi-static limit
(:func:`afmctl.fit.rod_response.quasi_static`), each row weighed by its block's samples. A
sweep seen at its own rate is judged on every k-th sample down to about :data:`THIN_ROWS` rows,
each weighed by k (:func:`afmctl.fit.parametrization.every_kth`): still simulated on every
sample (the rod, the creep), only the rows summed are fewer, so the cost and its Gauss-Newton
step are the full problem's with ``k`` times the noise's variance. It
has the same parameters as the full problem, so a fit on it is a start for the full one: the
grid's first fits run on it, and the full problem judges them and takes the last steps
(:func:`afmctl.fit.preisach.runs`). Pure numerics: no I/O.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from afmctl.fit.parametrization import every_kth
from afmctl.fit.preisach_problem import Data, Problem

FloatArray = NDArray[np.float64]
#: A sweep is seen in block means only if its field moves at most this share as fast as the
#: set's fastest sweep's (a slow sweep, which the rod follows quasi-statically) ...
SLOW_RATE = 0.05
#: ... in blocks over which its field moves by at most this share of the set's field range
#: (35 samples of the standard 0.279 Hz triangle at 10 kHz; at 0.5 %, 89 samples, the bipolar
#: creep stages' fits ended off their full fits' minima: preisach-b-creep 1.00 -> 1.19x the noise
#: on its slow sweep, pi-b-creep 1.08 -> 1.23x, under load; at 0.2 % scratch runs of both ended
#: where the full fits had) ...
BLOCK_SHARE = 0.002
#: ... no longer than the creep's fastest time constant, and of at least this many samples.
BLOCK_MIN = 4
#: A sweep at its own rate is judged on every k-th sample down to about this many rows (the
#: standard 27.9 Hz triangle's 3,300 at 10 kHz are kept; on a bipolar stage the reversal
#: curves' 15,500 by 4 and the 5.58 Hz triangle's 7,600 by 2, on a unipolar one 16,800 by 5 and
#: 8,100 by 3: the rows the slow sweep's blocks left are most of a step's cost).
THIN_ROWS = 4000


def blocks(fields: Sequence[FloatArray], dts: Sequence[float], fastest_tau_s: float
           ) -> list[int]:
    """Samples per block of each sweep (1: seen at its own rate) for fields (MV/m) sampled
    every ``dts`` (s), by :data:`SLOW_RATE`, :data:`BLOCK_SHARE` and :data:`BLOCK_MIN`."""
    rates = [float(np.max(np.abs(np.diff(e)))) / dt if e.size > 1 else 0.0
             for e, dt in zip(fields, dts, strict=True)]
    span = max(float(np.ptp(e)) for e in fields)
    out = []
    for e, dt, rate in zip(fields, dts, rates, strict=True):
        m = 1
        if 0.0 < rate <= SLOW_RATE * max(rates):
            m = min(int(BLOCK_SHARE * span / (rate * dt)), int(fastest_tau_s / dt), e.size // 2)
        out.append(m if m >= BLOCK_MIN else 1)
    return out


def _means(x: FloatArray, m: int) -> FloatArray:
    """Means of ``x``'s rows in blocks of ``m`` (a last partial block left out)."""
    n = (x.shape[0] // m) * m
    return x[:n].reshape(n // m, m, *x.shape[1:]).mean(axis=1)


def coarse(prob: Problem, per_sweep: Sequence[int]) -> Problem:
    """``prob`` with sweep ``i`` seen in means of blocks of ``per_sweep[i]`` samples (a block is
    judged if all its samples are), or, where that is 1, judged on every k-th sample down to
    about :data:`THIN_ROWS` rows; :attr:`~afmctl.fit.preisach_problem.Problem.weights` the
    samples a row stands for. Shares the full problem's grid, start states, creep elements, rod
    bounds and the noise's sum of squares (its convergence test)."""
    d = prob.data
    fields, masks, ys, dts, phi, trans, weights = [], [], [], [], [], [], []
    for i, m in enumerate(per_sweep):
        e, mask, y, dt = d.fields[i], d.masks[i], d.y[i], d.dts[i]
        if m == 1:
            mask, y, k = every_kth(mask, y, THIN_ROWS)
            fields.append(e), masks.append(mask), ys.append(y), dts.append(dt)
            phi.append(prob.phi[i]), trans.append(prob.trans[i]), weights.append(k)
            continue
        full = np.full(e.size, math.nan)
        full[mask] = y
        judged = _means(mask.astype(float), m) == 1.0
        fields.append(_means(e, m))
        masks.append(judged)
        ys.append(_means(full, m)[judged])
        dts.append(m * dt)
        phi.append(np.ascontiguousarray(_means(prob.phi[i], m)))
        trans.append(_means(prob.trans[i], m))
        weights.append(m)
    out = copy.copy(prob)
    out.data = Data(fields, masks, ys, dts, d.noise, gaps_s=list(d.gaps_s))
    out.phi, out.trans, out.blocks, out.weights = phi, trans, list(per_sweep), weights
    return out


__all__ = ["BLOCK_MIN", "BLOCK_SHARE", "SLOW_RATE", "THIN_ROWS", "blocks", "coarse"]
