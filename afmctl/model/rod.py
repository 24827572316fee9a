"""Lumped model of the stacked PZT rod, eqs. (16)-(18) of Hatch, Smith et al.

``m u'' + c u' + k u = a1 P(E) + a2 P(E)^2``  (16) (and, beyond the paper, ``+ a3 P(E)^3``: see
:attr:`Rod.a3`), written as ``x' = A x + B f`` (17) with
``x = [u, u']``. The displacement ``u`` is returned in um; internally SI (m, kg, N, s).

The forcing is held constant over each sample (the DAQ's zero-order hold), so the exact
discretization is ``x_{k+1} = Phi x_k + Gamma f_k`` with ``Phi = e^{A dt}`` and
``Gamma = int_0^dt e^{A s} ds B``, both from one matrix exponential of the augmented matrix
``[[A, B], [0, 0]] dt`` (the semigroup form (18) with ``E`` held at ``E_k``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm

FloatArray = NDArray[np.float64]
UM_PER_M = 1e6


@dataclass(frozen=True)
class Rod:
    """Parameters of the lumped rod (16).

    Parameters
    ----------
    m : float
        Effective mass, kg.
    c : float
        Effective damping, N s/m.
    k : float
        Effective stiffness, N/m.
    a1 : float
        Linear piezoelectric coupling ``A a_1``, N/(C/m^2).
    a2 : float
        Quadratic electrostrictive coupling ``A a_2``, N/(C/m^2)^2.
    a3 : float
        Cubic coupling, N/(C/m^2)^3: not in (16), which is 0 here. A Preisach-type operator
        followed by a static map that is not affine (a modified Prandtl-Ishlinskii stage's
        polynomial output map) has minor loops of a width that varies along the loop in a way
        the quadratic alone cannot follow; the Preisach grid's fit (:mod:`afmctl.fit.preisach`)
        identifies it.
    offset_um : float
        Sensor zero: displacement reported when u = 0, um.
    """

    m: float
    c: float
    k: float
    a1: float
    a2: float = 0.0
    a3: float = 0.0
    offset_um: float = 0.0

    @property
    def natural_hz(self) -> float:
        """Undamped resonance sqrt(k/m) / (2 pi), Hz."""
        return float(np.sqrt(self.k / self.m) / (2 * np.pi))

    @property
    def damping_ratio(self) -> float:
        return float(self.c / (2 * np.sqrt(self.k * self.m)))

    def force(self, p: FloatArray) -> FloatArray:
        """Right-hand side of (16) (with the cubic ``a3``), N, for polarization ``p`` in C/m^2."""
        return self.a1 * p + (self.a2 + self.a3 * p) * p * p

    def force_slope(self, p: float) -> float:
        """``d force / d P`` at ``p`` (C/m^2), N/(C/m^2)."""
        return self.a1 + (2.0 * self.a2 + 3.0 * self.a3 * p) * p


@dataclass(frozen=True)
class Discrete:
    """Exact zero-order-hold discretization of the rod at sample period ``dt`` (s).

    ``phi`` (2x2) and ``gamma`` (2,) map ``x_k = [u_k (m), v_k (m/s)]`` and the force ``f_k`` (N) to
    ``x_{k+1}``.
    """

    phi: FloatArray
    gamma: FloatArray
    dt: float

    def horizon(self, d: int) -> tuple[FloatArray, float]:
        """Row ``C Phi^d`` and gain ``C sum_{i<d} Phi^i Gamma`` (m/N): the displacement ``d``
        samples ahead with the force held, used by Algorithm 3."""
        row = np.array([1.0, 0.0])
        gain = 0.0
        for _ in range(d):
            gain += float(row @ self.gamma)
            row = row @ self.phi
        return row, gain


#: An eigenvalue of the horizon inverse's state map this close to zero is round-off, not a mode
#: (:func:`smooth_horizon`): it would die out by a factor of 1e9 every sample.
ROUND_OFF = 1e-9


def smooth_horizon(disc: Discrete, d_max: int = 64) -> int:
    """Smallest inversion horizon ``d`` whose inverse has no alternating (chattering) mode.

    Inverting the rod ``d`` samples ahead with the force held (Algorithm 3, :mod:`afmctl.model.inverse`)
    leaves the state to evolve with ``M_d = Phi - Gamma C Phi^d / g_d``. For ``d = 1`` one eigenvalue
    of ``M_d`` is the sampling zero of the discretized rod, near -1 at high sample rates: the field
    chatters between samples. Returns the first ``d`` whose eigenvalues all lie inside the unit
    circle, each with a positive real part or within :data:`ROUND_OFF` of zero.

    A heavily overdamped rod (a stage that behaves as a first-order lag) has a pole so fast that
    ``e^{lambda dt}`` is zero in double precision, and ``M_d`` a zero eigenvalue that round-off
    puts at about -1e-17: no mode at all, but taken for an alternating one it made the horizon 7
    (8 from :data:`afmctl.planning.track.HORIZONS`) on an independent tester's first-order
    700 Hz stage, and every corner of a 27.9 Hz triangle was turned 8 samples early (1.8 um
    spikes, 0.28 um RMS where horizon 2 gives 0.03 um through the same model).

    A rod that resonates above a quarter of the sample rate has poles with negative real parts
    itself, and no horizon meets the rule: then the horizon whose ``M_d`` has the smallest
    spectral radius (its modes die fastest), if that is below 1, else ``d_max``. A third
    tester's Bouc-Wen stage (3.5 kHz, damped 0.04, at 10 kHz) was given 64 before: every corner
    of a 27.9 Hz triangle turned 63 samples early, 12.4 um RMS against the linear filter's 1.8;
    the fastest-dying horizon there is 4 (radius 0.38).
    """
    radii = []
    for d in range(1, d_max + 1):
        ev = _horizon_eigvals(disc, d)
        if np.all((ev.real > 0) | (np.abs(ev) < ROUND_OFF)) and np.all(np.abs(ev) < 1):
            return d
        radii.append(float(np.max(np.abs(ev))))
    best = int(np.argmin(radii))
    return best + 1 if radii[best] < 1.0 else d_max


def horizon_radius(disc: Discrete, d: int) -> float:
    """The spectral radius of the horizon-``d`` inverse's state map ``M_d``
    (:func:`smooth_horizon`): 1 or more, the inverse at that horizon is unstable."""
    return float(np.max(np.abs(_horizon_eigvals(disc, d))))


def _horizon_eigvals(disc: Discrete, d: int) -> NDArray[np.complex128]:
    """The eigenvalues of ``M_d = Phi - Gamma C Phi^d / g_d`` (:func:`smooth_horizon`)."""
    row, gain = disc.horizon(d)
    return np.linalg.eigvals(disc.phi - np.outer(disc.gamma, row) / gain)


def discretize(rod: Rod, dt: float) -> Discrete:
    """Exact discretization (18) of the rod at sample period ``dt`` (s)."""
    a = np.array([[0.0, 1.0], [-rod.k / rod.m, -rod.c / rod.m]])
    aug = np.zeros((3, 3))
    aug[:2, :2] = a
    aug[1, 2] = 1.0 / rod.m
    e = expm(aug * dt)
    return Discrete(e[:2, :2].copy(), e[:2, 2].copy(), float(dt))


@nb.njit(cache=True, nogil=True)
def _simulate(phi: np.ndarray, gamma: np.ndarray, f: np.ndarray, x: np.ndarray) -> np.ndarray:
    u = np.empty(f.size)
    x0, x1 = x[0], x[1]
    for k in range(f.size):
        u[k] = x0
        n0 = phi[0, 0] * x0 + phi[0, 1] * x1 + gamma[0] * f[k]
        x1 = phi[1, 0] * x0 + phi[1, 1] * x1 + gamma[1] * f[k]
        x0 = n0
    x[0], x[1] = x0, x1
    return u


def simulate(rod: Rod, disc: Discrete, force_n: FloatArray,
             state: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
    """Displacement samples for a held force sequence.

    Parameters
    ----------
    rod : Rod
    disc : Discrete
        From :func:`discretize` at the sample period.
    force_n : ndarray, shape (N,)
        Force ``f_k`` held over ``[t_k, t_{k+1})``, N.
    state : ndarray, shape (2,), optional
        ``[u (m), u' (m/s)]`` at ``t_0``; default at rest at 0.

    Returns
    -------
    u_um : ndarray, shape (N,)
        Displacement at ``t_0 ... t_{N-1}`` (before each force sample acts), um, including the offset.
    state : ndarray, shape (2,)
        State at ``t_N``.
    """
    x = np.zeros(2) if state is None else np.array(state, dtype=float)
    u = _simulate(disc.phi, disc.gamma, np.ascontiguousarray(force_n, dtype=float), x)
    return u * UM_PER_M + rod.offset_um, x


def rest_state(rod: Rod, force_n: float) -> FloatArray:
    """Static equilibrium ``[f/k, 0]`` for a constant force (the static gain 1/k)."""
    return np.array([force_n / rod.k, 0.0])
