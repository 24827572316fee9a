"""Viscous relaxation of the switching: the dipoles see the field through a first-order lag.

A second form of thermal relaxation (the first is the thermally activated kernel (10)): the
switching part of the polarization (13) does not follow the field at once but relaxes towards it
with one time constant, while the reversible part ``E / eta`` does (the "viscous" dynamic
Preisach model of Bertotti and of Mayergoyz, the hysterons' field lagging the applied one)::

    P(t) = M[E_v](t) + lambda (E(t) - E_v(t)),      tau E_v' = E - E_v,

``M`` the paper's model (13), ``lambda`` its reversible slope (``W / eta``, C/m^2 per MV/m) and
``E_v`` the field the hysterons see. Slow sweeps see the paper's model; on fast ones the
hysterons see a smaller field, a phase later, so the loop changes with the rate; after a step the
polarization keeps switching with the exponential knee of ``tau`` (kernel (10)'s knee too, not
the straight line in log time of creep).

Discretization (zero-order hold, period ``dt``): ``E_v`` during sample ``k`` is its value at the
sample's start, ``E_v[k+1] = a E_v[k] + (1 - a) E[k]`` with ``a = exp(-dt / tau)``. So the
hysterons' field of sample ``k`` depends only on the samples before it, and ``P_k`` is affine in
``E_k`` with slope ``lambda`` once the past is known: the inverse (Algorithm 3,
:mod:`afmctl.model.inverse`) solves it in closed form. Pure functions; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import signal

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Viscous:
    """A first-order lag of the field the hysterons see.

    Parameters
    ----------
    time_s : float
        Relaxation time ``tau``, s (> 0).
    """

    time_s: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.time_s) and self.time_s > 0):
            raise ValueError(f"a viscous relaxation time must be > 0 s, got {self.time_s}")

    def factor(self, dt: float) -> float:
        """``a = exp(-dt / tau)``: what is left of the lag after one sample of ``dt`` s."""
        return math.exp(-dt / self.time_s)


def lagged(viscous: Viscous, field_mv_m: FloatArray, dt: float,
           start_mv_m: float) -> tuple[FloatArray, float]:
    """The hysterons' field during each sample (MV/m) and at the start of the next one.

    Parameters
    ----------
    viscous : Viscous
    field_mv_m : ndarray, shape (N,)
        Applied field held over each sample, MV/m.
    dt : float
        Sample period, s.
    start_mv_m : float
        The hysterons' field at the first sample's start, MV/m (at rest: the field held before).

    Returns
    -------
    lagged : ndarray, shape (N,)
        ``E_v[k]``, MV/m.
    end : float
        ``E_v[N]``, MV/m: where the next call starts.
    """
    e = np.asarray(field_mv_m, dtype=float)
    if e.size == 0:
        return e.copy(), start_mv_m
    a = viscous.factor(dt)
    out = signal.lfilter([0.0, 1.0 - a], [1.0, -a], e - start_mv_m) + start_mv_m
    return out, float(a * out[-1] + (1.0 - a) * e[-1])
