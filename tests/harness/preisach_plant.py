"""A classical Preisach stage written for the tests, independently of afmctl's model code.

The textbook Preisach operator over switching thresholds ``alpha >= beta`` (a relay is up after
``E >= alpha``, down after ``E <= beta``; not afmctl's coercive/interaction play form), evaluated
the classical way: Mayergoyz's Everett function ``F(a, b)`` (the density's mass over the triangle
``b <= beta <= alpha <= a``, tabulated on a fine grid and interpolated bilinearly: a continuum, no
relay staircase) over the stack of dominant input extrema with the wiping-out rule. The density is
a mixture of two correlated Gaussians in ``(alpha, beta)``: neither separable in coercive and
interaction field nor centred. Its output (plus a reversible part) drives a
second-order rod integrated with scipy's own zero-order-hold discretization, optionally through
log-time creep (first-order elements, updated exactly), and a gauge adds white noise. Used to show
the Preisach identification and inverse on data that did not come from the code being tested.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from afmctl.files import sweepfile as sw
from afmctl.planning import sweepdesign as sd

FloatArray = NDArray[np.float64]
THICKNESS_UM = 100.0


@dataclass
class PreisachStage:
    """The plant. ``creep_per_element`` (share of a step per element, elements at 2 per decade
    from 10 ms to 1000 s) 0 for none. State: relay states, creep elements, rod; kept between
    calls (``play`` continues where the last call ended)."""

    seed: int = 1
    noise_um: float = 0.015
    natural_hz: float = 700.0
    damping: float = 0.12
    gain_um: float = 100.0
    creep_per_element: float = 0.0
    n: int = 600
    zero_um: float = 0.0
    mu: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        e = np.linspace(-0.1, 1.6, self.n)  # MV/m, beyond the 0 ... 1.5 driven
        a, b = np.meshgrid(e, e, indexing="ij")
        dens = np.zeros(a.shape)
        for (ma, mb, sa, sb, rho, w) in ((0.95, 0.55, 0.30, 0.30, 0.6, 1.0),
                                         (0.55, 0.35, 0.18, 0.22, -0.3, 0.45)):
            za, zb = (a - ma) / sa, (b - mb) / sb
            dens += w * np.exp(-(za * za - 2 * rho * za * zb + zb * zb) / (2 * (1 - rho * rho)))
        dens[b > a] = 0.0
        self.mu = dens / dens.sum()
        # Everett table: F[i, j] = mass over beta >= e_j, alpha <= e_i (the triangle if j <= i)
        self.everett = np.cumsum(np.cumsum(self.mu[:, ::-1], axis=1)[:, ::-1], axis=0)
        self.grid = e
        self.stack = [float(e[-1])]  # poled positive: every relay up (M_0 above them all)
        self.creep_tau = np.logspace(-2, 3, 11)
        self.creep_z = np.zeros(self.creep_tau.size)
        self.rod = None
        self.rng = np.random.default_rng(self.seed)

    def rest(self) -> None:
        """Leave the stage idle (at its last voltage) long enough for every creep element and
        the rod to settle."""
        if self.rod is not None:
            self.creep_z[:] = self.h_last
            total = self.h_last * (1.0 + self.creep_per_element * self.creep_z.size)
            self.rod = np.array([total, 0.0])

    def _f(self, hi: float, lo: float) -> float:
        """Everett function: the mass of relays with ``lo <= beta <= alpha <= hi``."""
        g = self.grid
        x = np.interp(hi, g, np.arange(g.size))
        y = np.interp(lo, g, np.arange(g.size))
        i, j = min(int(x), g.size - 2), min(int(y), g.size - 2)
        u, v = x - i, y - j
        t = self.everett
        return float((1 - u) * (1 - v) * t[i, j] + u * (1 - v) * t[i + 1, j]
                     + (1 - u) * v * t[i, j + 1] + u * v * t[i + 1, j + 1])

    def preisach(self, e: float) -> float:
        """Apply field ``e`` (MV/m): update the alternating stack of dominant extrema (wiping out
        every pair the new value exceeds) and return the output in [-1, 1]."""
        st = self.stack  # M_0 > m_1 < M_1 > m_2 ...: maxima at even, minima at odd positions
        last_is_max = len(st) % 2 == 1
        if e == st[-1]:
            pass
        elif (e > st[-1]) == last_is_max:
            st[-1] = e  # the running extreme moves on
        else:
            st.append(e)  # a reversal
        while len(st) >= 3 and ((len(st) % 2 == 1 and st[-1] >= st[-3])
                                or (len(st) % 2 == 0 and st[-1] <= st[-3])):
            del st[-3:-1]  # wiping out: the older extreme of this kind and the one after it
        down = 0.0  # mass switched down: sum over minima m_k of F(M_{k-1}, m_k) - F(M_k, m_k)
        for k in range(1, len(st), 2):
            m = st[k]
            down += self._f(st[k - 1], m) - (self._f(st[k + 1], m) if k + 1 < len(st) else 0.0)
        return 1.0 - 2.0 * down

    def hysteresis(self, field_mv_m: FloatArray) -> FloatArray:
        """The Preisach output (plus 20 % reversible), um, per sample; the memory carried on."""
        return np.array([self.gain_um * (0.4 * self.preisach(float(e)) + 0.2 * e / 1.5)
                         for e in field_mv_m])

    def play(self, voltage_v: FloatArray, dt: float, noisy: bool = True) -> FloatArray:
        """Readings (um) for a voltage history held ``dt`` s per sample (reading k before
        sample k's voltage acts)."""
        h = self.hysteresis(np.asarray(voltage_v, float) / THICKNESS_UM)
        self.h_last = float(h[-1])
        if self.creep_per_element:
            a = np.exp(-dt / self.creep_tau)
            if self.rod is None:
                self.creep_z[:] = h[0]
            tot = np.empty(h.size)
            for k, hk in enumerate(h):
                tot[k] = hk + self.creep_per_element * float(self.creep_z.sum())
                self.creep_z = a * self.creep_z + (1 - a) * hk
            h = tot
        w = 2 * np.pi * self.natural_hz
        sys = signal.cont2discrete((np.array([[0.0, 1.0], [-w * w, -2 * self.damping * w]]),
                                    np.array([[0.0], [w * w]]), np.array([[1.0, 0.0]]),
                                    np.zeros((1, 1))), dt, method="zoh")
        ad, bd = sys[0], sys[1][:, 0]
        x = np.array([h[0], 0.0]) if self.rod is None else self.rod
        u = np.empty(h.size)
        for k, hk in enumerate(h):
            u[k] = x[0]
            x = ad @ x + bd * hk
        self.rod = x
        return u + (self.rng.normal(0.0, self.noise_um, u.size) if noisy else 0.0)


def standard_sweeps(stage: PreisachStage) -> list[sw.Sweep]:
    """The other-family sets' design: 0.279 Hz nested loops at 1 kHz, 5.58 Hz at 5 kHz, 27.9 Hz
    at 10 kHz, all 0 ... 150 V, in sequence on the same stage, which rests (its creep settles)
    before each."""
    out = []
    for name, v, rate in (("nested_0.279Hz", sd.nested_loops(0.279, None, 3, 1000.0, (0, 150)),
                           1000.0),
                          ("tri_5.58Hz", sd.loop(5.58, 0.0, 150.0, 4, 5000.0), 5000.0),
                          ("tri_27.9Hz", sd.loop(27.9, 0.0, 150.0, 6, 10000.0), 10000.0)):
        stage.rest()
        u = stage.play(v, 1.0 / rate)
        stage.zero_um = float(u[0])  # the gauge zeroed at each sweep's first sample
        out.append(sw.from_arrays(v, u - u[0], rate, {"layer_thickness_um": "100"}, name))
    return out
