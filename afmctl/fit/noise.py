"""Sensor noise of a sweep, estimated from the data alone (no model).

The noise floor is what a perfect model of the stage would leave as fit RMS. ``afmctl identify``
compares every sweep's fit RMS with it: the ratio says whether the model is at the floor (about 1)
or not, which the RMS in um alone cannot say.

Estimator (:func:`sensor_noise_um`): the ``order``-th finite difference of the record,
``d_k = sum_j (-1)^j C(order, j) y_{k+j}``. For white noise of standard deviation ``s`` every
``d_k`` has variance ``C(2 order, order) s^2`` (the sum of the squared binomial coefficients),
whatever the signal; a signal sampled well above its own bandwidth contributes about
``(2 pi f dt)^order`` times its amplitude, which at ``order = 3`` is below 1e-3 of the range for
``f dt < 0.016`` (a 27.9 Hz triangle's 5th harmonic at 10 kHz, a 0.279 Hz one at 1 kHz, a
lightly damped resonance at 1/60 of the sample rate). What the signal does at corners of a
triangle or in a resonant transient is a few large differences: the scale is taken robustly,
``1.4826 median(|d - median(d)|)`` (the median absolute deviation, consistent for a normal
distribution), so such bursts do not count. The orders 3 to 8 are tried and the smallest
estimate kept: the signal can only inflate an estimate, and each order shrinks a component at
frequency ``f`` by ``2 sin(pi f dt)`` (0.56 for a resonance at 1/11 of the sample rate).
Assumes white noise: a sensor whose noise is low-pass filtered below the sample rate is
under-estimated (its high-frequency part is what this sees), and quantization steps coarser than
the noise are seen as noise.

References: the difference-based variance estimators of Rice (1984, Ann. Statist. 12, 1215) and
Hall, Kay & Titterington (1990, Biometrika 77, 521); robust (MAD) scale as in Donoho &
Johnstone's wavelet noise estimate (1994).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

#: Difference orders tried by the default estimator (see the module docstring).
ORDERS = (3, 4, 5, 6, 7, 8)
#: Consistency factor of the median absolute deviation for a normal distribution.
MAD_TO_SIGMA = 1.482602218505602


def sensor_noise_um(displacement_um: ArrayLike, order: int | None = None) -> float:
    """Standard deviation (um) of white sensor noise in a uniformly sampled record.

    Parameters
    ----------
    displacement_um : array_like, shape (N,)
        Measured displacement, um, uniformly sampled (N > order + 2).
    order : int, optional
        Order of the finite difference (>= 1). Default: the smallest estimate over
        :data:`ORDERS` (the signal only ever adds to an estimate, and its share shrinks by
        ``2 sin(pi f dt)`` per order, so a resonance sampled at a few times its frequency is
        suppressed too; for white noise the orders agree within a few %).

    Returns
    -------
    float
        Estimated noise standard deviation, um (0 for a noiseless record).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> t = np.arange(20000) / 10000.0
    >>> y = 40 * np.sin(2 * np.pi * 5.0 * t) + 0.02 * rng.standard_normal(t.size)
    >>> round(sensor_noise_um(y), 3)
    0.02
    """
    y = np.asarray(displacement_um, dtype=float)
    if order is None:
        return min(sensor_noise_um(y, k) for k in ORDERS if y.size >= k + 3)
    if order < 1 or y.ndim != 1 or y.size < order + 3:
        raise ValueError(f"need a 1-D record longer than {order + 2} samples and order >= 1")
    d = np.diff(y, order)
    scale = MAD_TO_SIGMA * float(np.median(np.abs(d - np.median(d))))
    return scale / math.sqrt(math.comb(2 * order, order))
