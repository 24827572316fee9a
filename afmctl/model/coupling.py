"""Cross-coupling between the axes of an x/y stage: the motion of one axis caused by another's.

A real x/y stage couples: driving x moves y a little, by geometry (a flexure's parasitic motion, a
tube's bending: -45 to -25 dB) and, near the shared resonances, through the structure's modes. The
paper models one axis; this module adds what two axes need, in the same terms: a linear operator
from the *source* axis's displacement to the *target* axis's, in um of target per um of source.

The low-order form is a static gain plus one mode that vanishes at DC::

    H(s) = static + (gain_hp (s/w)^2 + gain_bp 2 zeta (s/w)) / ((s/w)^2 + 2 zeta (s/w) + 1)

with ``w = 2 pi mode_hz``. ``gain_hp`` is the mode's high-frequency part (the target follows the
source's acceleration through the shared mass), ``gain_bp`` its velocity part (its value at the
resonance). ``mode_hz = 0`` means a static coupling only.

A guide flexure's parasitic motion is an arc: a parallelogram flexure of length ``L`` shortens by
``3 s^2 / (5 L)`` at a deflection ``s`` (Smith, *Foundations of ultraprecision mechanism design*),
so the target also moves by a term quadratic in the source, which a static gain cannot carry. It
is added beside ``H`` as ``quadratic ((x - centre)^2 - (reference - centre)^2)``: zero at the
reference, and ``static`` stays the slope at ``centre`` (the middle of the sweeps it was regressed
on: the stage's mid-range).

The operator acts on the source's displacement *relative to where it was while the target's own
model was identified* (``reference_um``): identify sweeps each axis with the other held, so the
target's model already carries the static part at that position.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import signal

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]


@dataclass(frozen=True)
class Coupling:
    """Motion of a target axis caused by a source axis's motion (one direction).

    Parameters
    ----------
    static : float
        DC gain, um of target per um of source (signed).
    mode_hz : float
        Natural frequency of the shared mode, Hz (0: static coupling only).
    damping : float
        Damping ratio of the shared mode (0 < damping).
    gain_hp : float
        The mode's high-frequency gain (acceleration path), um/um.
    gain_bp : float
        The mode's gain at its resonance (velocity path), um/um.
    reference_um : float
        Source displacement at which the target's own model was identified, um.
    quadratic : float
        The arc: target motion per squared source displacement from ``centre_um``, um/um^2
        (signed).
    centre_um : float
        Source displacement at which ``static`` is the slope, um (matters with a ``quadratic``).
    """

    static: float
    mode_hz: float = 0.0
    damping: float = 0.05
    gain_hp: float = 0.0
    gain_bp: float = 0.0
    reference_um: float = 0.0
    quadratic: float = 0.0
    centre_um: float = 0.0

    def __post_init__(self) -> None:
        for name in ("static", "mode_hz", "damping", "gain_hp", "gain_bp", "reference_um",
                     "quadratic", "centre_um"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"coupling {name} must be finite")
        if self.mode_hz < 0 or (self.mode_hz > 0 and self.damping <= 0):
            raise ValueError("coupling mode_hz must be >= 0 and its damping > 0")

    @property
    def static_db(self) -> float:
        """The static gain in dB (20 log10 |static|; -inf for none)."""
        return 20 * math.log10(abs(self.static)) if self.static else -math.inf

    def transfer(self) -> tuple[FloatArray, FloatArray]:
        """Numerator and denominator of ``H(s)`` in descending powers of ``s`` (s in rad/s)."""
        if self.mode_hz == 0:
            return np.array([self.static]), np.array([1.0])
        w, z = 2 * math.pi * self.mode_hz, self.damping
        den = np.array([1.0, 2 * z * w, w * w])
        num = self.static * den + np.array([self.gain_hp, self.gain_bp * 2 * z * w, 0.0])
        return num, den


def frf(c: Coupling, freq_hz: ArrayLike) -> ComplexArray:
    """The coupling's frequency response ``H(j 2 pi f)``, um of target per um of source.

    Parameters
    ----------
    c : Coupling
    freq_hz : array_like
        Frequencies, Hz (>= 0).
    """
    num, den = c.transfer()
    s = 2j * math.pi * np.asarray(freq_hz, dtype=float)
    return np.polyval(num, s) / np.polyval(den, s)


def caused(c: Coupling, source_um: ArrayLike, dt_s: float) -> FloatArray:
    """Target motion caused by a sampled source displacement, um (starting at rest).

    The source is taken piecewise linear between samples (first-order hold): the exact response
    of ``H(s)`` to the interpolated source, sampled at the same instants. Before the first sample
    the source is taken to have rested at its first value. The arc's term is added sample by
    sample (a flexure's geometry: static).

    Parameters
    ----------
    c : Coupling
    source_um : array_like, shape (N,)
        Source axis displacement at each sample, um.
    dt_s : float
        Sample interval, s.

    Returns
    -------
    ndarray, shape (N,)
        Target displacement caused, um (relative to its own model's prediction).
    """
    x = np.asarray(source_um, dtype=float) - c.reference_um
    arc = c.quadratic * x * (x + 2 * (c.reference_um - c.centre_um))
    if c.mode_hz == 0 or x.size == 0:
        return c.static * x + arc
    num, den = c.transfer()
    bd, ad, _ = signal.cont2discrete((num, den), dt_s, method="foh")
    bd = np.ravel(bd)
    zi = signal.lfilter_zi(bd, ad) * x[0]
    y, _ = signal.lfilter(bd, ad, x, zi=zi)
    return np.asarray(y, dtype=float) + arc


#: Rounds of :func:`own_motion`'s alternation.
ROUNDS = 3


def own_motion(here: Coupling, back: Coupling, mine_um: ArrayLike, other_um: ArrayLike,
               dt_s: float, rounds: int = ROUNDS) -> FloatArray:
    """An axis's own motion from both axes' readings, um.

    Each axis reads its own motion plus what the other's own motion causes (``x = X +
    c_xy[Y]``, ``y = Y + c_yx[X]``, ``here`` the coupling into this axis, ``back`` into the
    other): the couplings are identified so, from files where the target's own motion is
    constant. The own motions are found by alternating the two, ``rounds`` rounds from ``X =
    x``. One round leaves an error of ``c_xy c_yx c_xy`` per um of the other axis's motion,
    which is no constant where both axes move: foreign-xy-1 (couplings of -25 dB both ways),
    2.4e-4 um of x per um of y, 1.23x x's sensor noise in its file where both axes move; after a
    second round 0.58x, against the plant's x run with y held. Each further round multiplies the
    error by about ``c_xy c_yx``.

    Parameters
    ----------
    here, back : Coupling
        Into this axis from the other, and into the other from this one.
    mine_um, other_um : array_like, shape (N,)
        This axis's and the other axis's readings, um.
    dt_s : float
        Sample interval, s.
    rounds : int
        At least 1.
    """
    mine, other = np.asarray(mine_um, dtype=float), np.asarray(other_um, dtype=float)
    own = mine
    for _ in range(rounds):
        own = mine - caused(here, other - caused(back, own, dt_s), dt_s)
    return own
