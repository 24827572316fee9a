"""Out-of-family piezo stages: Preisach, modified Prandtl-Ishlinskii or Bouc-Wen hysteresis, with
log-time creep, frame drift and stage dynamics of their own.

Written without afmctl's model code, so that afmctl is judged on stages whose hysteresis is not its
model's (issue 23). A stage is a frozen :class:`FamilyStage`; the operators are those of
:mod:`~afmctl.drivers.device.foreign.families`, the time stepping is
:func:`~afmctl.drivers.device.foreign.family_kernel.run_kernel` (its docstring lists the chain:
amplifier, operator, output map, creep, rod modes, drift, gauge).

Units: voltage V, displacement um, time s. The normalized input ``w`` is 0 at the low end of the
drive range, 1 at the high end (``0 .. 150 V`` unipolar, ``-150 .. 150 V`` bipolar).

Loops are stage-like by construction (:func:`random_family_stage`): the reversible weight ``lam``
is solved for (bisection) so that the major loop's largest width is the drawn hysteresis (10-18 %
of the span), the output map is convex (``g2, g3 >= 0``), the span 60-110 um.

API
---
``initial_state(stage)`` (poled: once over the drive range and back to 0 V),
``run(stage, voltage_V, rate_hz, state) -> (true_um, reading_um, state)`` (noise-free; the
emulator adds the noise), ``idle(stage, state, seconds, voltage_V)`` (exact for any length of
hold: creep relaxes, the drift grows), ``describe(stage)``.

Example
-------
>>> import numpy as np
>>> stage = random_family_stage(np.random.default_rng(1), "preisach")
>>> true_um, reading_um, state = run(stage, np.linspace(0, 150, 2001), 1000.0,
...                                  initial_state(stage))
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy import linalg, special

from afmctl.drivers.device.foreign import family_kernel as kn
from afmctl.drivers.device.foreign.families import (
    creep_constants,
    everett_table,
    preisach_start,
)

FloatArray = NDArray[np.float64]
FAMILIES = ("preisach", "prandtl-ishlinskii", "bouc-wen")
#: Longest gauge averaging window, substeps (the ring's size).
RING = 64


@dataclass(frozen=True)
class Lobe:
    """One skewed, correlated Gaussian of a Preisach density in (coercive, interaction) input.

    ``E_c = (alpha - beta) / 2``, ``E_I = (alpha + beta) / 2`` (normalized input units); density
    ``weight * 2 phi_2(E_c, E_I) Phi(skew (E_c - ec_mean) / ec_sd)``, ``phi_2`` the bivariate
    normal with correlation ``rho``.
    """

    ec_mean: float
    ec_sd: float
    ei_mean: float
    ei_sd: float
    rho: float = 0.0
    skew: float = 0.0
    weight: float = 1.0


@dataclass(frozen=True)
class Preisach:
    """Classical Preisach operator with the density of ``lobes`` (relays with thresholds within
    ``low .. 1``; the input stays in 0 .. 1); ``grid`` points per threshold for the Everett table."""

    lobes: tuple[Lobe, ...]
    low: float = -0.3
    grid: int = 257

    def density(self, a: FloatArray, b: FloatArray) -> FloatArray:
        ec, ei = 0.5 * (a - b), 0.5 * (a + b)
        out = np.zeros_like(a)
        for lb in self.lobes:
            x, y = (ec - lb.ec_mean) / lb.ec_sd, (ei - lb.ei_mean) / lb.ei_sd
            q = (x * x - 2 * lb.rho * x * y + y * y) / (1 - lb.rho ** 2)
            g = np.exp(-0.5 * q) / (2 * math.pi * lb.ec_sd * lb.ei_sd * math.sqrt(1 - lb.rho ** 2))
            out += lb.weight * 2 * g * special.ndtr(lb.skew * x)
        return np.where(ec > 0, out, 0.0)


@dataclass(frozen=True)
class PrandtlIshlinskii:
    """Weighted play operators (thresholds in normalized input, increasing, the first 0)."""

    thresholds: tuple[float, ...]
    weights: tuple[float, ...]


@dataclass(frozen=True)
class BoucWen:
    """``dz = A dw - beta |dw| |z|^(n-1) z - gamma dw |z|^n`` (normalized input)."""

    A: float
    beta: float
    gamma: float
    n: float


Operator = Preisach | PrandtlIshlinskii | BoucWen


@dataclass(frozen=True)
class Loop:
    """From operator output ``y`` to displacement: ``q = (y + lam w - y_lo) / (y_hi - y_lo)``,
    ``u = span_um (g1 q + g2 q^2 + g3 q^3)`` (um; ``g1 + g2 + g3 = 1``)."""

    lam: float
    y_lo: float
    y_hi: float
    g2: float
    g3: float
    span_um: float

    @property
    def g1(self) -> float:
        return 1.0 - self.g2 - self.g3


@dataclass(frozen=True)
class Creep:
    """Krejci-Kuhnen creep: ``per_decade`` of a step per time decade between ``tau_min_s`` and
    ``tau_max_s`` (:func:`~afmctl.drivers.device.foreign.families.creep_constants`)."""

    per_decade: float
    tau_min_s: float = 0.01
    tau_max_s: float = 1000.0


@dataclass(frozen=True)
class Extras:
    """Second forms of ``afmctl diagnose``'s causes (all off by default); see
    :mod:`~afmctl.drivers.device.foreign.family_kernel` for each formula.

    amplifier_hz : three equal real poles at this frequency, Hz (amplifier-lag).
    viscous_tau_s : the hysteresis sees the input through this lag, s (thermal-relaxation).
    mode2 : (frequency Hz, damping ratio, residue) of a second mode in modal sum (second-mode).
    adc_window_s : the gauge integrates the position over this window, s (sensor-delay).
    gauge_gap_um, gauge_mid_um : capacitive gap law ``mid + G d / (G - d)``, G of either sign
    (the gap closes or opens as the stage extends) (sensor-nonlinearity).
    gain_delta, gain_tau_s : gain warm-up ``1 + delta (1 - exp(-t / tau))`` (voltage-gain-drift).
    """

    amplifier_hz: float = 0.0
    viscous_tau_s: float = 0.0
    mode2: tuple[float, float, float] | None = None
    adc_window_s: float = 0.0
    gauge_gap_um: float = 0.0
    gauge_mid_um: float = 0.0
    gain_delta: float = 0.0
    gain_tau_s: float = 0.0

    @property
    def cause(self) -> str:
        """The diagnose cause this carries (``none`` if none)."""
        named = [("amplifier-lag", self.amplifier_hz > 0),
                 ("thermal-relaxation", self.viscous_tau_s > 0),
                 ("second-mode", self.mode2 is not None),
                 ("sensor-delay", self.adc_window_s > 0),
                 ("sensor-nonlinearity", self.gauge_gap_um != 0),
                 ("voltage-gain-drift", self.gain_tau_s > 0)]
        on = [c for c, yes in named if yes]
        return on[0] if len(on) == 1 else "none" if not on else "+".join(on)


@dataclass(frozen=True)
class FamilyStage:
    """An out-of-family stage.

    Parameters
    ----------
    family : str
        One of :data:`FAMILIES`.
    operator : Preisach, PrandtlIshlinskii or BoucWen
    loop : Loop
    resonance_hz, damping : float
        The rod's first mode (Hz, damping ratio).
    creep : Creep or None
    drift_um_per_s : float
        Frame drift, um/s, linear in device time since power-on (0: none).
    noise_um : float
        Gauge noise, 1 sigma, um (added by the emulator).
    zero_um : float
        The gauge's zero: reading = gauge(position) - zero_um.
    drive_range_V : tuple of float
    extras : Extras
    """

    family: str
    operator: Operator
    loop: Loop
    resonance_hz: float
    damping: float
    creep: Creep | None
    drift_um_per_s: float
    noise_um: float
    zero_um: float
    drive_range_V: tuple[float, float] = (0.0, 150.0)
    extras: Extras = field(default_factory=Extras)

    @property
    def w0(self) -> float:
        """Normalized input at 0 V (the power-on output)."""
        lo, hi = self.drive_range_V
        return (0.0 - lo) / (hi - lo)


@dataclass(frozen=True)
class FamilyState:
    """Everything the stage remembers (arrays copied, never shared between states)."""

    scalars: FloatArray
    memory: FloatArray
    creep: FloatArray
    ring: FloatArray


@dataclass(frozen=True)
class _Compiled:
    P: FloatArray
    F: FloatArray
    r: FloatArray
    p: FloatArray
    creep_c: FloatArray
    creep_decay: FloatArray
    creep_mean: FloatArray
    creep_tau: FloatArray
    modes: FloatArray
    amp: FloatArray


def _zoh(A: FloatArray, B: FloatArray, h: float) -> tuple[FloatArray, FloatArray]:
    """Exact discretization of ``x' = A x + B u`` with ``u`` held over ``h``."""
    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n], M[:n, n] = A, B
    E = linalg.expm(M * h)
    return E[:n, :n], E[:n, n]


def _mode(freq_hz: float, zeta: float, h: float) -> FloatArray:
    w = 2 * math.pi * freq_hz
    phi, gam = _zoh(np.array([[0.0, 1.0], [-w * w, -2 * zeta * w]]), np.array([0.0, w * w]), h)
    return np.concatenate([phi.ravel(), gam])


def substeps(stage: FamilyStage) -> int:
    """Substeps per sample: 4 when the amplifier or the gauge's window acts within a sample."""
    e = stage.extras
    return 4 if (e.amplifier_hz > 0 or e.adc_window_s > 0) else 1


@lru_cache(maxsize=32)
def _everett(op: Preisach) -> tuple[FloatArray, FloatArray]:
    grid = np.linspace(op.low, 1.0, op.grid)
    return grid, everett_table(op.density, grid)


def _operator_arrays(op: Operator) -> tuple[float, FloatArray, FloatArray, FloatArray, list]:
    """(kind, Everett table, play thresholds, play weights, extra P entries)."""
    empty = np.zeros(1)
    if isinstance(op, Preisach):
        grid, F = _everett(op)
        return kn.PREISACH, F, empty, empty, [(kn.I_ELOW, op.low), (kn.I_EH, grid[1] - grid[0])]
    if isinstance(op, PrandtlIshlinskii):
        return (kn.PI, np.zeros((2, 2)), np.array(op.thresholds), np.array(op.weights), [])
    return (kn.BOUC_WEN, np.zeros((2, 2)), empty, empty,
            [(kn.I_BWA, op.A), (kn.I_BWB, op.beta), (kn.I_BWG, op.gamma), (kn.I_BWN, op.n)])


@lru_cache(maxsize=64)
def compile_stage(stage: FamilyStage, sample_rate_hz: float) -> _Compiled:
    """The kernel's arrays for ``stage`` at ``sample_rate_hz``."""
    nsub = substeps(stage)
    h = 1.0 / sample_rate_hz / nsub
    kind, F, r, p, extra = _operator_arrays(stage.operator)
    P = np.zeros(kn.N_PAR)
    lp, e = stage.loop, stage.extras
    lo, hi = stage.drive_range_V
    for i, x in [(kn.I_KIND, kind), (kn.I_H, h), (kn.I_NSUB, nsub), (kn.I_LO, lo), (kn.I_HI, hi),
                 (kn.I_LAM, lp.lam), (kn.I_YLO, lp.y_lo), (kn.I_YSCALE, 1 / (lp.y_hi - lp.y_lo)),
                 (kn.I_G1, lp.g1), (kn.I_G2, lp.g2), (kn.I_G3, lp.g3), (kn.I_SPAN, lp.span_um),
                 (kn.I_DRIFT, stage.drift_um_per_s), (kn.I_ZERO, stage.zero_um),
                 (kn.I_GAIN_D, e.gain_delta), (kn.I_GAIN_T, e.gain_tau_s),
                 (kn.I_AMP, float(e.amplifier_hz > 0)), (kn.I_VISC, e.viscous_tau_s),
                 (kn.I_AVG, min(RING, max(1, round(e.adc_window_s / h))) if e.adc_window_s else 0),
                 (kn.I_GAP, e.gauge_gap_um), (kn.I_MID, e.gauge_mid_um), *extra]:
        P[i] = x
    b2 = e.mode2[2] if e.mode2 is not None else 0.0
    P[kn.I_B1], P[kn.I_B2] = 1.0 - b2, b2
    modes = np.zeros((2, 6))
    modes[0] = _mode(stage.resonance_hz, stage.damping, h)
    if e.mode2 is not None:
        modes[1] = _mode(e.mode2[0], e.mode2[1], h)
    amp = np.zeros(12)
    if e.amplifier_hz > 0:
        a = 2 * math.pi * e.amplifier_hz
        A = np.array([[-a, 0, 0], [a, -a, 0], [0, a, -a]])
        phi, gam = _zoh(A, np.array([a, 0.0, 0.0]), h)
        amp = np.concatenate([phi.ravel(), gam])
    if stage.creep is not None:
        tau, c = creep_constants(stage.creep.per_decade, stage.creep.tau_min_s,
                                 stage.creep.tau_max_s)
    else:
        tau, c = np.ones(1), np.zeros(1)
    decay = np.exp(-h / tau)
    return _Compiled(P, F, r, p, c, decay, tau / h * (1 - decay), tau, modes, amp)


def _state(stage: FamilyStage, w: float, x_in: float) -> FamilyState:
    """Rest at normalized input ``w`` reached from below, position ``x_in`` (um), time 0."""
    s = np.zeros(kn.N_STATE)
    s[kn.S_WH] = s[kn.S_WPREV] = w
    if isinstance(stage.operator, Preisach):
        mem, n = preisach_start(stage.operator.low, w)
        s[kn.S_N] = n
    elif isinstance(stage.operator, PrandtlIshlinskii):
        mem = np.full(len(stage.operator.thresholds), w)
    else:
        mem = np.zeros(1)
    n_creep = compile_stage(stage, 1000.0).creep_c.size
    return FamilyState(s, mem, np.full(n_creep, 0.0), np.zeros(RING))


def _settle(stage: FamilyStage, state: FamilyState, voltage_V: float) -> FamilyState:
    """The rod at rest and the creep settled at the held ``voltage_V`` (the operator moved there)."""
    c = compile_stage(stage, 1000.0)
    s, mem = state.scalars.copy(), state.memory.copy()
    lo, hi = stage.drive_range_V
    w = (min(max(voltage_V, lo), hi) - lo) / (hi - lo)
    s[kn.S_WH] = w
    d = kn.output_map(c.P, kn.core(c.P, c.F, c.r, c.p, s, mem, w), w)
    creep = np.full(state.creep.size, d)
    x = d + float(np.sum(c.creep_c * creep))
    b2 = stage.extras.mode2[2] if stage.extras.mode2 is not None else 0.0
    s[kn.S_X1], s[kn.S_X2], s[kn.S_V1], s[kn.S_V2] = (1 - b2) * x, b2 * x, 0.0, 0.0
    s[kn.S_A1] = s[kn.S_A2] = s[kn.S_A3] = voltage_V
    pos = x + stage.drift_um_per_s * s[kn.S_T]
    return FamilyState(s, mem, creep, np.full(RING, pos))


def initial_state(stage: FamilyStage) -> FamilyState:
    """Power-on of a poled stage: the operator from its lower end up to 0 V, then once over the
    top of the drive range and back to 0 V (as after its last use), settled there."""
    st = _state(stage, stage.w0, 0.0)
    c = compile_stage(stage, 1000.0)
    s, mem = st.scalars.copy(), st.memory.copy()
    for w in (1.0, stage.w0):
        kn.core(c.P, c.F, c.r, c.p, s, mem, w)
    return _settle(stage, FamilyState(s, mem, st.creep, st.ring), 0.0)


def run(stage: FamilyStage, voltage_V: FloatArray, sample_rate_hz: float, state: FamilyState
        ) -> tuple[FloatArray, FloatArray, FamilyState]:
    """Play held samples ``voltage_V`` (V) at ``sample_rate_hz`` from ``state``.

    Returns
    -------
    true_um : ndarray, shape (N,)
        Platform position (drift included) at each sample's start, um.
    reading_um : ndarray, shape (N,)
        The gauge's noise-free reading there, um.
    state : FamilyState
    """
    c = compile_stage(stage, float(sample_rate_hz))
    v = np.ascontiguousarray(voltage_V, dtype=float)
    s, mem = state.scalars.copy(), state.memory.copy()
    creep, ring = state.creep.copy(), state.ring.copy()
    true_um, reading = np.empty(v.size), np.empty(v.size)
    kn.run_kernel(c.P, c.F, c.r, c.p, c.creep_c, c.creep_decay, c.creep_mean, c.modes, c.amp,
                  s, mem, creep, ring, v, true_um, reading)
    return true_um, reading, FamilyState(s, mem, creep, ring)


def idle(stage: FamilyStage, state: FamilyState, seconds: float, voltage_V: float
         ) -> FamilyState:
    """Hold ``voltage_V`` for ``seconds`` (long against the rod and the amplifier): exact for the
    creep operators (each relaxes by ``exp(-seconds / tau)``), the drift and the gain warm-up."""
    if seconds <= 0:
        return state
    c = compile_stage(stage, 1000.0)
    s = state.scalars.copy()
    s[kn.S_T] += seconds
    e = stage.extras
    g = 1 + e.gain_delta * (1 - math.exp(-s[kn.S_T] / e.gain_tau_s)) if e.gain_tau_s else 1.0
    settled = _settle(stage, FamilyState(s, state.memory, state.creep, state.ring),
                      g * voltage_V)
    d = settled.creep[0]  # the operator's output at the hold
    creep = d + (state.creep - d) * np.exp(-seconds / c.creep_tau)
    x = d + float(np.sum(c.creep_c * creep))
    b2 = e.mode2[2] if e.mode2 is not None else 0.0
    ss = settled.scalars
    ss[kn.S_X1], ss[kn.S_X2] = (1 - b2) * x, b2 * x
    pos = x + stage.drift_um_per_s * ss[kn.S_T]
    return FamilyState(ss, settled.memory, creep, np.full(RING, pos))


def describe(stage: FamilyStage) -> dict:
    """All parameters, JSON-able, with the cause the stage carries."""
    out = asdict(stage)
    out["cause"] = stage.extras.cause
    out["creep_per_decade"] = stage.creep.per_decade if stage.creep else 0.0
    return out


# -- random stages ----------------------------------------------------------------------------
def _core_path(op: Operator, w0: float, ws: FloatArray) -> FloatArray:
    """The operator's output along the input path ``ws`` from power-on at ``w0``."""
    stage = FamilyStage("x", op, Loop(0.0, 0.0, 1.0, 0.0, 0.0, 1.0), 1000.0, 0.5, None, 0.0,
                        0.0, 0.0, (0.0, 1.0))
    c = compile_stage(stage, 1000.0)
    st = _state(stage, w0, 0.0)
    s, mem = st.scalars.copy(), st.memory.copy()
    return np.array([kn.core(c.P, c.F, c.r, c.p, s, mem, float(w)) for w in ws])


def major_loop(op: Operator, w0: float, n: int = 201, cycles: int = 3
               ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(w, ascending, descending)``: the operator's last of ``cycles`` cycles over 0 .. 1."""
    w = np.linspace(0.0, 1.0, n)
    up0 = np.linspace(w0, 1.0, n)
    path = np.concatenate([up0] + [np.concatenate([w[::-1], w]) for _ in range(cycles)])
    y = _core_path(op, w0, path)
    return w, y[-n:], y[-2 * n:-n][::-1]


def hysteresis_of(w: FloatArray, up: FloatArray, down: FloatArray, lam: float, g2: float,
                  g3: float) -> tuple[float, float, float]:
    """(largest width / span, y_lo, y_hi) of the loop with reversible weight ``lam`` and output
    map ``g``."""
    a, d = up + lam * w, down + lam * w
    lo, hi = min(a.min(), d.min()), max(a.max(), d.max())
    qa, qd = (a - lo) / (hi - lo), (d - lo) / (hi - lo)

    def g(q: FloatArray) -> FloatArray:
        return (1 - g2 - g3) * q + g2 * q * q + g3 * q ** 3

    return float(np.max(g(qd) - g(qa))), float(lo), float(hi)


def solve_loop(op: Operator, w0: float, hysteresis: float, g2: float, g3: float,
               span_um: float) -> Loop:
    """The :class:`Loop` whose major loop has the given largest width / span (bisection on the
    reversible weight ``lam``; ValueError if the operator alone is narrower)."""
    w, up, down = major_loop(op, w0)
    scale = float(np.ptp(np.concatenate([up, down])))
    if hysteresis_of(w, up, down, 0.0, g2, g3)[0] < hysteresis:
        raise ValueError("the operator's own loop is narrower than the hysteresis asked for")
    lo_l, hi_l = 0.0, 1000.0 * scale
    for _ in range(80):
        mid = 0.5 * (lo_l + hi_l)
        if hysteresis_of(w, up, down, mid, g2, g3)[0] > hysteresis:
            lo_l = mid
        else:
            hi_l = mid
    lam = 0.5 * (lo_l + hi_l)
    _, y_lo, y_hi = hysteresis_of(w, up, down, lam, g2, g3)
    return Loop(lam, y_lo, y_hi, g2, g3, span_um)


def _log(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def random_operator(rng: np.random.Generator, family: str, density: str = "random",
                    w0: float = 0.0) -> Operator:
    """An operator of ``family``; a Preisach ``density`` is ``random`` (two or three skewed,
    correlated, off-centre lobes: neither separable nor centred) or ``separable`` (one lobe,
    no correlation or skew, interaction centred at 0 V, normalized ``w0``: in the paper's
    family)."""
    if family == "preisach":
        if density == "separable":
            return Preisach((Lobe(rng.uniform(0.15, 0.35), rng.uniform(0.06, 0.15), w0,
                                  rng.uniform(0.1, 0.25)),), low=-1.0)
        lobes = tuple(Lobe(rng.uniform(0.05, 0.25), rng.uniform(0.03, 0.1),
                           rng.uniform(0.1, 0.9), rng.uniform(0.1, 0.35),
                           float(rng.choice([-1, 1]) * rng.uniform(0.3, 0.8)),
                           float(rng.choice([-1, 1]) * rng.uniform(2.0, 6.0)),
                           rng.uniform(0.3, 1.0))
                      for _ in range(int(rng.integers(2, 4))))
        return Preisach(lobes)
    if family == "prandtl-ishlinskii":
        m = 12
        r = np.linspace(0.0, rng.uniform(0.3, 0.6), m)
        p = np.exp(-r / rng.uniform(0.1, 0.4))
        return PrandtlIshlinskii(tuple(float(x) for x in r), tuple(float(x) for x in p / p.sum()))
    if family == "bouc-wen":
        beta = rng.uniform(1.5, 6.0)
        return BoucWen(1.0, beta, float(rng.uniform(-0.5, 0.5) * beta), rng.uniform(1.0, 2.0))
    raise ValueError(f"unknown family {family!r} (one of {', '.join(FAMILIES)})")


def random_family_stage(rng: np.random.Generator, family: str,
                        drive_range_V: tuple[float, float] = (0.0, 150.0), creep: bool = False,
                        drift: bool = False, density: str = "random",
                        extras: Extras | None = None, **fixed: float) -> FamilyStage:
    """Draw an out-of-family stage (see the module docstring for the loop's shape).

    Ranges: span 60-110 um, hysteresis 10-18 %, output map convex (``g2`` 0.1-0.35; the
    modified PI's cubic ``g3`` 0.05-0.2), rod 300-3000 Hz with damping 0.03-0.3 (log-uniform),
    creep 1-2 % per decade, drift 5-30 nm/s of either sign, noise 10-30 nm. ``fixed`` may fix
    ``span_um``, ``hysteresis``, ``resonance_hz``, ``damping``, ``noise_um``,
    ``creep_per_decade``, ``drift_um_per_s``.
    """
    known = {"span_um", "hysteresis", "resonance_hz", "damping", "noise_um", "creep_per_decade",
             "drift_um_per_s"}
    if set(fixed) - known:
        raise ValueError(f"unknown parameter(s) {sorted(set(fixed) - known)}")
    d = {"span_um": rng.uniform(60.0, 110.0), "hysteresis": rng.uniform(0.10, 0.18),
         "resonance_hz": _log(rng, 300.0, 3000.0), "damping": _log(rng, 0.03, 0.3),
         "noise_um": _log(rng, 0.01, 0.03), "creep_per_decade": rng.uniform(0.01, 0.02),
         "drift_um_per_s": float(rng.choice([-1, 1]) * rng.uniform(0.005, 0.03))}
    d.update(fixed)
    lo, hi = drive_range_V
    w0 = (0.0 - lo) / (hi - lo)
    g3 = rng.uniform(0.05, 0.2) if family == "prandtl-ishlinskii" else 0.0
    g2 = rng.uniform(0.1, 0.3) if family == "prandtl-ishlinskii" else rng.uniform(0.1, 0.35)
    for _ in range(20):
        op = random_operator(rng, family, density, w0)
        try:
            loop = solve_loop(op, w0, d["hysteresis"], g2, g3, d["span_um"])
            break
        except ValueError:
            continue
    else:
        raise ValueError(f"no {family} operator wide enough in 20 draws")
    stage = FamilyStage(family, op, loop, d["resonance_hz"], d["damping"],
                        Creep(d["creep_per_decade"]) if creep else None,
                        d["drift_um_per_s"] if drift else 0.0, d["noise_um"], 0.0,
                        (float(lo), float(hi)), extras or Extras())
    st = initial_state(stage)
    zero = float(st.ring[0]) + rng.uniform(-1.0, 1.0)  # the gauge zeroed near power-on
    return replace(stage, zero_um=zero)
