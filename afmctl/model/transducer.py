"""The stage model: voltage -> field -> polarization (13) -> rod (16) -> displacement.

A :class:`Transducer` bundles the polarization model, the rod and the layer thickness that turns
volts into field (``E [MV/m] = V [V] / thickness [um]``). Its memory is a :class:`StageState`
that every call takes and returns, so hysteresis cannot be silently dropped between calls.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from afmctl.model import creep as cr
from afmctl.model import hysteresis as hy
from afmctl.model import rod as rd
from afmctl.model import viscous as vs
from afmctl.model.effects import Effects

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Transducer:
    """Polarization model + rod + electrode spacing.

    Parameters
    ----------
    polarization : hysteresis.Polarization
    rod : rod.Rod
    thickness_um : float
        Layer thickness, um; field (MV/m) = voltage (V) / thickness_um.
    effects : Effects
        What the stage adds around this model (amplifier, sensor, second mode; see
        :mod:`afmctl.model.effects`); none by default. :func:`simulate` is the paper's model alone;
        ``afmctl diagnose`` fits effects and ``afmctl track`` inverts them.
    creep : creep.Creep or None
        Log-time creep of the polarization (:mod:`afmctl.model.creep`) between the hysteresis and
        the rod; none by default.
    initial : {"depoled", "positive", "negative"} or str
        The hysteresis state the stage was in before the voltages the model was identified on
        (identify finds it from the data; a stage poled once keeps that state outside the
        voltage range it is driven over, e.g. below 0 V on a unipolar stage): the default
        state of :func:`initial`. A Bouc-Wen model's may be a state named by its value
        (:func:`afmctl.model.hysteresis.bouc_wen_state`), fitted.
    viscous : viscous.Viscous or None
        Viscous relaxation of the switching (:mod:`afmctl.model.viscous`): the hysterons of (13)
        see the field through a first-order lag, the reversible part does not. Only with the
        paper's densities (:class:`~afmctl.model.hysteresis.Polarization`); none by default.
    """

    polarization: hy.Polarization
    rod: rd.Rod
    thickness_um: float
    effects: Effects = field(default_factory=Effects)
    initial: hy.Initial | str = "depoled"
    creep: cr.Creep | None = None
    viscous: vs.Viscous | None = None

    def __post_init__(self) -> None:
        if self.viscous is not None and not isinstance(self.polarization, hy.Polarization):
            raise ValueError("viscous relaxation needs the paper's polarization model (13), "
                             f"not {type(self.polarization).__name__}")

    def field(self, voltage_v: FloatArray) -> FloatArray:
        return np.asarray(voltage_v, dtype=float) / self.thickness_um


@dataclass(frozen=True)
class StageState:
    """Hysteresis memory, rod state ``[u (m), u' (m/s)]``, creep state (C/m^2 per element;
    empty without creep) and the field the hysterons see at the next sample's start (MV/m,
    :mod:`afmctl.model.viscous`; empty without viscous relaxation, or at rest at the next
    sample's field)."""

    polarization: hy.PolarizationState
    rod: FloatArray
    creep: FloatArray = field(default_factory=lambda: np.zeros(0))
    lag: FloatArray = field(default_factory=lambda: np.zeros(0))


def initial(model: Transducer, how: hy.Initial | str | None = None,
            voltage_v: float = 0.0) -> StageState:
    """State at rest: the initial polarization ``how`` (default the model's own
    :attr:`Transducer.initial`), then ``voltage_v`` applied quasi-statically (and held long
    enough for any creep to settle)."""
    ps = hy.initial_state(model.polarization, model.initial if how is None else how)
    e = voltage_v / model.thickness_um
    p, ps = hy.run(model.polarization, np.array([e]), ps)
    return at_rest(model, ps, float(p[0]), e)


def rest_lag(model: Transducer, field_mv_m: float) -> FloatArray:
    """The hysterons' lagged field after a rest under ``field_mv_m`` (MV/m): that field for a
    model with viscous relaxation (:attr:`Transducer.viscous`), empty otherwise."""
    return np.zeros(0) if model.viscous is None else np.array([float(field_mv_m)])


def at_rest(model: Transducer, ps: hy.PolarizationState, p_h: float,
            field_mv_m: float) -> StageState:
    """The stage settled at hysteretic output ``p_h`` (C/m^2) with memory ``ps`` under the field
    ``field_mv_m`` (MV/m): creep elements settled, rod in static equilibrium, the hysterons'
    lagged field (a model with viscous relaxation) at that field."""
    creep, f_h = model.creep, float(model.rod.force(np.array([p_h]))[0])
    lag = rest_lag(model, field_mv_m)
    if creep is not None and creep.acts_on == "force":
        z = cr.rest_state(creep, f_h)
        return StageState(ps, rd.rest_state(model.rod, f_h + cr.offset(creep, z)), z, lag)
    z = cr.rest_state(creep, p_h)
    p = p_h + cr.offset(creep, z)
    return StageState(ps, rd.rest_state(model.rod, float(model.rod.force(np.array([p]))[0])), z,
                      lag)


@dataclass(frozen=True)
class Compiled:
    """A model prepared for one sample period: kernel arrays and the rod's discretization."""

    model: Transducer
    kernel: hy.Kernel
    disc: rd.Discrete

    @property
    def dt(self) -> float:
        return self.disc.dt


def compile_model(model: Transducer, dt: float) -> Compiled:
    """Precompute quadrature nodes and the exact rod discretization at sample period ``dt`` (s)."""
    return Compiled(model, hy.build_kernel(model.polarization), rd.discretize(model.rod, dt))


def simulate(cm: Compiled, voltage_v: FloatArray,
             state: StageState) -> tuple[FloatArray, FloatArray, StageState]:
    """Forward model: displacement for a sampled (zero-order-held) voltage.

    Parameters
    ----------
    cm : Compiled
    voltage_v : ndarray, shape (N,)
        Voltage held over each sample, V.
    state : StageState
        State at the first sample.

    Returns
    -------
    u_um : ndarray, shape (N,)
        Displacement at each sample instant (before that sample's voltage acts), um.
    p : ndarray, shape (N,)
        Polarization during each sample (with creep, if the model has it), C/m^2.
    state : StageState
        State after the last sample.
    """
    f, p, inner = driving_force(cm, voltage_v, state)
    u, x = rd.simulate(cm.model.rod, cm.disc, f, state.rod)
    return u, p, replace(inner, rod=x)


def reversible_slope(kernel: hy.Kernel) -> float:
    """The reversible part's slope ``W / eta`` of the paper's model (13), C/m^2 per MV/m."""
    return float(kernel.scal[5] / kernel.scal[0])


def polarization(cm: Compiled, voltage_v: FloatArray, state: StageState
                 ) -> tuple[FloatArray, hy.PolarizationState, FloatArray]:
    """The polarization (13) during each sample (C/m^2, before creep), through the viscous lag
    where the model has one (:mod:`afmctl.model.viscous`), the hysteresis memory and the lag's
    state after the last sample."""
    e = cm.model.field(voltage_v)
    if cm.model.viscous is None or e.size == 0:
        p, ps = hy.run(cm.kernel, e, state.polarization, cm.dt)
        return p, ps, state.lag
    start = float(state.lag[0]) if state.lag.size else float(e[0])
    e_v, end = vs.lagged(cm.model.viscous, e, cm.dt, start)
    p, ps = hy.run(cm.kernel, e_v, state.polarization, cm.dt)
    return p + reversible_slope(cm.kernel) * (e - e_v), ps, np.array([end])


def driving_force(cm: Compiled, voltage_v: FloatArray, state: StageState
                  ) -> tuple[FloatArray, FloatArray, StageState]:
    """The force (16) on the rod during each sample (N), with creep where the model has it
    (:attr:`afmctl.model.creep.Creep.acts_on`), the polarization (C/m^2; with creep if that acts
    on it), and the state after the last sample but the rod's (``state``'s own)."""
    p, ps, lag = polarization(cm, voltage_v, state)
    creep, z = cm.model.creep, state.creep
    if creep is None:
        f = cm.model.rod.force(p)
    elif creep.acts_on == "force":
        f = cm.model.rod.force(p)
        f, z = cr.run(creep, f, cm.dt, z if z.size else cr.rest_state(creep, _first(f)))
    else:
        p, z = cr.run(creep, p, cm.dt, z if z.size else cr.rest_state(creep, _first(p)))
        f = cm.model.rod.force(p)
    return f, p, StageState(ps, state.rod, z, lag)


#: :func:`held`: a hold of up to this many samples is simulated sample by sample; a longer one
#: in steps of up to this long, s, then so many samples.
HOLD_EXACT_SAMPLES = 20000
HOLD_STEP_MAX_S = 1.0
HOLD_FINE_SAMPLES = 2000


def held(cm: Compiled, voltage_v: float, seconds: float, state: StageState) -> StageState:
    """The state after ``voltage_v`` (V) is held for ``seconds`` more from ``state``: what a
    stage does between two runs (its creep goes on, its rod settles).

    Up to :data:`HOLD_EXACT_SAMPLES` samples it is :func:`simulate` of the held voltage. A
    longer hold is a zero-order hold of any length, so the hysteresis and the creep elements
    (:mod:`afmctl.model.creep`) are stepped exactly in steps that double from the sample period
    up to :data:`HOLD_STEP_MAX_S` (a 1000 s hold is about a thousand steps, not ten million
    samples); the last :data:`HOLD_FINE_SAMPLES` samples are the model's own, so the rod ends
    settled at the force the creep has reached (within a long step it sees the force it started
    with). Against the sample-by-sample simulation, on a creeping Prandtl-Ishlinskii stage's
    identified model: the same displacement to 2e-11 um after 30 s held (64 samples at the end
    left the rod ringing: 0.66 um off after 4 s on a 318 Hz, 30 %-damped rod).
    """
    n = int(round(seconds / cm.dt))
    fine = n if n <= HOLD_EXACT_SAMPLES else HOLD_FINE_SAMPLES
    rest, h, st = (n - fine) * cm.dt, cm.dt, state
    while rest > 0.5 * cm.dt:
        h = min(2.0 * h, HOLD_STEP_MAX_S, rest)
        step = Compiled(cm.model, cm.kernel, rd.discretize(cm.model.rod, h))
        st = simulate(step, np.array([voltage_v]), st)[2]
        rest -= h
    return simulate(cm, np.full(fine, float(voltage_v)), st)[2]


def _first(x: FloatArray) -> float:
    return float(x[0]) if x.size else 0.0


def displacement(model: Transducer, voltage_v: ArrayLike, dt_s: float,
                 state: StageState | None = None) -> FloatArray:
    """The model's displacement for a sampled voltage, um: (13) and (16) with the voltage held over
    each sample of ``dt_s`` seconds, from ``state`` (default :func:`initial`: the model's initial
    polarization at rest at the first sample's voltage). The same as :func:`simulate` on
    :func:`compile_model`, for a caller that wants the displacement alone.
    """
    v = np.asarray(voltage_v, dtype=float)
    st = state if state is not None else initial(model, voltage_v=float(v[0]) if v.size else 0.0)
    return simulate(compile_model(model, dt_s), v, st)[0]


def with_rod(model: Transducer, **changes: float) -> Transducer:
    return replace(model, rod=replace(model.rod, **changes))
