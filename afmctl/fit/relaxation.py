"""The thermal-relaxation candidate's grid: kernel (10) of the paper on a hysteron grid of its own.

``afmctl diagnose``'s thermal candidate (:mod:`afmctl.fit.extension`) runs the thermally activated
kernel (6)-(10) of :mod:`afmctl.model.hysteresis` on a grid chosen for it: coercive rows at quantile
midpoints of nu_1 and interaction columns close enough that the thermally smeared switching of
neighbours overlaps. Its fit also starts the coercive density afresh (:func:`density_starts`):
thermally activated switching ahead of E_c is what a relay fit absorbs in a distorted density.
Pure numerics: no I/O.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy import special

from afmctl.model import hysteresis as hy

FloatArray = NDArray[np.float64]

#: Coercive rows of the thermal kernel's grid (quantile midpoints of nu_1), in the fit and the model.
THERMAL_ROWS = 64
#: Rows, samples' field step and most columns of the coarse grid the multi-start searches on.
THERMAL_COARSE = (16, 0.004, 256)
#: Interaction columns of the thermal grid: uniform over +-THERMAL_SPAN sigma_I and at most
#: ``field_scale / 1.5`` apart (the thermally smeared switching of neighbours overlaps, so the
#: grid resolves kernel (10) at any field scale), between these counts (fit, and model for track).
THERMAL_COLUMNS = (64, 8192, 512)
THERMAL_SPAN = 4.5
#: Field step (relative to the peak) of the samples kernel (10) is run on, each held for its time:
#: the rates (7)-(8) change by e^(z dE / E_th) over a step, so it is finer than the relay's.
THERMAL_STEP = 0.001
#: The grid of the joint fit after the multi-start (rows, field step, most columns): the coarse
#: grid's few columns blur switching at small field scales (spaced wider than ``field_scale / 1.5``
#: below 0.016 MV/m at sigma_I = 0.3 MV/m), where a fit on it settles at too small a scale.
THERMAL_JOINT = (THERMAL_COARSE[0], THERMAL_COARSE[1], 1024)
#: The fine thermal grid (rows, field step, most columns): the fit's polish and the judgement.
THERMAL_FINE = (THERMAL_ROWS, THERMAL_STEP, THERMAL_COLUMNS[1])
#: Medians (fractions of the peak field) and log-widths of :func:`density_starts`.
DENSITY_MEDIANS = (0.25, 0.45, 0.7)
DENSITY_WIDTHS = (0.4, 0.8)


def thermal_polarization(theta: FloatArray, thermal: hy.Thermal, n_max: int,
                         rows: int = THERMAL_ROWS) -> hy.Polarization:
    """The thermally activated model (10) of ``theta[:4]`` (median E_c, sigma_ln, sigma_I, r;
    MV/m) on its grid: ``rows`` coercive rows, interaction columns uniform over
    ``+-THERMAL_SPAN sigma_I`` spaced at most ``field_scale / 1.5`` (at most ``n_max``), weighted
    by the normal density nu_2 (``eta = 1``, ``p_r = r``: ``Q`` of (13))."""
    median, sig, std, r = (float(v) for v in theta[:4])
    n = int(np.clip(math.ceil(2 * THERMAL_SPAN * std * 1.5 / thermal.field_scale),
                    THERMAL_COLUMNS[0], n_max))
    u = THERMAL_SPAN * ((2 * np.arange(n) + 1) / n - 1)
    dens = np.exp(-0.5 * u * u)
    dens /= np.sum(dens) * (u[1] - u[0]) * std  # weights (value x cell width) sum to 1
    return hy.Polarization(eta=1.0, p_r=r, coercive=hy.Lognormal(median, sig),
                           interaction=hy.Discrete(tuple(std * u), tuple(dens)),
                           n_coercive=rows, thermal=thermal)


def density_starts(x_base: FloatArray, e_max: float) -> list[FloatArray]:
    """Coercive densities to start a relaxation fit from (``x`` with ``theta[:4]`` replaced):
    medians 0.25-0.7 of the peak field ``e_max`` (MV/m) and two widths, each with the base fit's
    interaction width and rod, and ``r`` scaled so that the weight of the hysterons that switch
    below ``e_max`` (the loops' height) stays the base fit's."""
    median, sig, std, r = np.exp(x_base[:4])

    def below(m: float, s: float) -> float:
        return float(special.ndtr(math.log(e_max / m) / s))

    height = r * below(median, sig)
    return [np.concatenate((np.log([f * e_max, s, std, height / below(f * e_max, s)]), x_base[4:]))
            for f in DENSITY_MEDIANS for s in DENSITY_WIDTHS]
