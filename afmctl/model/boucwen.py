"""A Bouc-Wen polarization: rate-independent hysteresis without return-point memory.

Every Preisach-type model (the paper's (11)-(13), the grid of :mod:`afmctl.model.preisach`)
closes its minor loops: an excursion and a return to a reversal wipe the excursion out. A stage
whose loops stay open (:mod:`afmctl.fit.closure`) is out of their reach. The Bouc-Wen operator
(Bouc 1971, Wen 1976; for piezo stages Low & Guo 2009, Goldfarb & Celanovic 1997) is the
standard description of such a stage: one internal variable ``h`` whose rate follows the field's,

    dh/dE = A [1 - q |h / h_s|^n],   q = 1 while |h| grows (sign(A dE) = sign(h)), q = kappa else,

    P = E r + h,

with ``A`` of either sign (``A < 0`` is the form ``x = d V - h`` of Low & Guo and Goldfarb &
Celanovic: the Bouc-Wen loop subtracted from a linear part); the classic
``dh = A dE - beta |dE| |h|^(n-1) h - gamma dE |h|^n`` with ``h_s^n = A / (beta + gamma)``
(the saturation ``|h| -> h_s`` on a long monotone ramp) and
``kappa = (gamma - beta) / (beta + gamma)`` (``kappa < 0``: steeper toward zero than away, the
usual convex loop). It is rate independent (integrated in ``E``, not in time: RK4 substeps of at most
:data:`afmctl.model.hysteresis.BW_SUBSTEP` of ``h_s``), and ``dP/dE = r + dh/dE >= 0`` whenever
``|h| <= h_s``, ``kappa <= 1`` and, for ``A < 0``, ``r >= |A| max(1, 1 - kappa)``
(:attr:`BoucWen.least_slope`, checked): the E-P relation is monotone, so Algorithm 3 inverts it
as it inverts (13).

The state is ``(h, E_last)``: the compiled kernel is
:data:`afmctl.model.hysteresis.KIND_BOUC_WEN`; :func:`afmctl.model.hysteresis.run`, the transducer,
Algorithm 3 and everything on them take it as they take (13). Fitted by
:mod:`afmctl.fit.boucwen`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from afmctl.model import hysteresis as hy

FloatArray = NDArray[np.float64]
#: Bounds of ``kappa`` and the exponent ``n``.
KAPPA_BOUNDS = (-20.0, 1.0)
EXPONENT_BOUNDS = (0.5, 6.0)


@dataclass(frozen=True)
class BoucWen:
    """Bouc-Wen polarization ``P = r E + h`` (see the module).

    Parameters
    ----------
    reversible : float
        ``r``, slope of the reversible part, (C/m^2)/(MV/m), >= 0.
    rate : float
        ``A``, slope of ``h`` at ``h = 0``, (C/m^2)/(MV/m), non-zero (< 0: the loop subtracted).
    saturation : float
        ``h_s``, C/m^2, > 0: ``|h|`` on a long monotone ramp.
    kappa : float
        Shape of the branch toward zero (dimensionless, in :data:`KAPPA_BOUNDS`).
    exponent : float
        ``n`` (dimensionless, in :data:`EXPONENT_BOUNDS`).
    poling_mv_m : (float, float)
        The fields the initial states are poled at, MV/m (the range the stage is driven over):
        ``positive`` is ``h`` saturated at the upper one (a long ramp up to it), then brought to
        the first field; ``negative`` saturated at the lower one. NaN: saturated at the first
        field itself.

    Examples
    --------
    >>> bw = BoucWen(0.1, 1.0, 0.3, -0.5, 1.0)
    >>> p, _ = hy.run(bw, [0.0, 2.0, 0.0], hy.initial_state(bw))
    >>> bool(p[2] > 0.0)  # remanence after a ramp up and back
    True
    """

    reversible: float
    rate: float
    saturation: float
    kappa: float
    exponent: float
    poling_mv_m: tuple[float, float] = (math.nan, math.nan)

    #: No thermal activation (rate independent).
    thermal = None
    kernel: Literal["bouc-wen"] = "bouc-wen"
    #: No hysteron grid (the JSON's ``n_coercive``).
    n_coercive = 0

    def __post_init__(self) -> None:
        values = (self.reversible, self.rate, self.saturation, self.kappa, self.exponent)
        if not all(math.isfinite(v) for v in values):
            raise ValueError("Bouc-Wen parameters must be finite")
        if self.reversible < 0 or self.rate == 0 or self.saturation <= 0:
            raise ValueError("Bouc-Wen needs reversible >= 0, rate != 0 and saturation > 0")
        if not KAPPA_BOUNDS[0] <= self.kappa <= KAPPA_BOUNDS[1]:
            raise ValueError(f"Bouc-Wen kappa must be in {KAPPA_BOUNDS}, got {self.kappa}")
        if not EXPONENT_BOUNDS[0] <= self.exponent <= EXPONENT_BOUNDS[1]:
            raise ValueError(f"Bouc-Wen exponent must be in {EXPONENT_BOUNDS}, got {self.exponent}")
        lo, hi = self.poling_mv_m
        if math.isinf(lo) or math.isinf(hi) or (lo > hi):
            raise ValueError("Bouc-Wen poling fields must be finite (or NaN) and lo <= hi")
        if self.least_slope < -1e-9 * abs(self.rate):  # round-off of a fit at its margin 0
            raise ValueError(f"Bouc-Wen E-P relation not monotone: the reversible slope "
                             f"{self.reversible:g} must be at least |A| max(1, 1 - kappa) = "
                             f"{self.reversible - self.least_slope:g} for A < 0")

    @property
    def least_slope(self) -> float:
        """The least ``dP/dE`` over every state with ``|h| <= h_s``, (C/m^2)/(MV/m): ``r`` for
        ``A > 0`` (``kappa <= 1``), ``r - |A| max(1, 1 - kappa)`` for ``A < 0`` (just after a
        reversal at saturation)."""
        return self.reversible - max(-self.rate, 0.0) * max(1.0, 1.0 - self.kappa)

    @property
    def kind(self) -> int:
        return hy.KIND_BOUC_WEN

    @property
    def eta(self) -> float:
        """Reciprocal of a lower bound of the slope dP/dE, (MV/m)/(C/m^2): :attr:`least_slope`,
        or a thousandth of ``|A|`` if less (Algorithm 3 uses it to start its march)."""
        return 1.0 / max(self.least_slope, 1e-3 * abs(self.rate))

    def build_kernel(self) -> hy.Kernel:
        """Packed arrays of the ``KIND_BOUC_WEN`` kernel: ``ec = [A, h_s, kappa, n, E_lo, E_hi]``
        (the poling fields)."""
        ec = np.array([self.rate, self.saturation, self.kappa, self.exponent, *self.poling_mv_m])
        scal = np.array([1.0, 1.0, 0.0, 0.0, 0.0, self.reversible, 0.0])
        return hy.Kernel(hy.KIND_BOUC_WEN, ec, np.ones(ec.size), np.zeros(0), np.zeros(0),
                         np.zeros(1), scal)

    def hysteretic_range(self) -> float:
        """``h`` between its two saturations, ``2 h_s``, C/m^2."""
        return 2.0 * self.saturation


__all__ = ["BoucWen", "KAPPA_BOUNDS", "EXPONENT_BOUNDS"]
