"""The actuators of the foreign x/y stage: each axis's free stroke as a hysteretic function of its
voltage history.

An actuator's *free stroke* ``d`` (um) is the displacement its stack would give against the
stage's flexures at rest: the blocked force over the axis's stiffness. It is rate independent (the
stage's dynamics act on it afterwards, :mod:`~afmctl.drivers.device.foreign.xy_stage`), so under
a zero-order-held voltage it is held too. Kinds:

``relay``
    The paper's family, written independently (:mod:`~afmctl.drivers.device.foreign.stage`): a
    stack of homogenized relay hysterons, ``d = (a1 P + a2 P^2) / k - zero`` with the polarization
    ``P`` of (11). The stack always sees 0 .. ``STACK_V``: a bipolar command ``-150 .. 150 V``
    reaches it through a level shift ``V_stack = STACK_V (V - lo) / (hi - lo)`` (a stack must not
    be driven far into negative field).
``preisach``, ``prandtl-ishlinskii``, ``bouc-wen``
    Out of the paper's family (:mod:`~afmctl.drivers.device.foreign.family_stage`): the operator on
    the normalized input ``w = (V - lo) / (hi - lo)``, its reversible part and its convex output
    map.
``linear``
    ``d = span w``: no hysteresis (for the plant's analytic limits).

Every kind's stroke is scaled by the actuator's ``gain``; over its drive range the major loop's
stroke spans ``0 .. gain * span_um`` (``span_um``: the unscaled kind's span).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from afmctl.drivers.device.foreign import family_kernel as kn
from afmctl.drivers.device.foreign import family_stage as fam
from afmctl.drivers.device.foreign import kernel as fk
from afmctl.drivers.device.foreign.stage import Stage, coercive_nodes
from afmctl.drivers.device.foreign.stages import random_stage

FloatArray = NDArray[np.float64]
KINDS = ("relay", "preisach", "prandtl-ishlinskii", "bouc-wen")
#: Voltage range the relay kind's stack sees, V.
STACK_V = 150.0
#: Largest width of the major loop over its span drawn for every kind.
HYSTERESIS = (0.10, 0.18)


@dataclass(frozen=True)
class Actuator:
    """One axis's hysteretic actuator.

    Parameters
    ----------
    kind : str
        One of :data:`KINDS` or ``linear``.
    drive_range_V : tuple of float
        The command's range (lo, hi), V; commands are clipped to it (the amplifier's rails).
    span_um : float
        Unscaled stroke span over the major loop, um.
    gain : float
        Scale on the stroke (dimensionless).
    relay : Stage or None
        The relay kind's stack (its drive range is 0 .. ``STACK_V``).
    family : FamilyStage or None
        The out-of-family kinds' operator and loop (its rod, creep and sensor are not used).
    """

    kind: str
    drive_range_V: tuple[float, float]
    span_um: float
    gain: float = 1.0
    relay: Stage | None = None
    family: fam.FamilyStage | None = None

    @property
    def stroke_span_um(self) -> float:
        """Span of the scaled stroke over the major loop, um."""
        return self.gain * self.span_um


@dataclass(frozen=True)
class ActuatorState:
    """The actuator's memory: ``scalars`` (the family kernel's scalar state, or empty) and
    ``memory`` (relay boundaries, MV/m; Preisach stack; play states; copied, never shared)."""

    scalars: FloatArray
    memory: FloatArray


def normalized(act: Actuator, voltage_V: FloatArray) -> FloatArray:
    """``(V - lo) / (hi - lo)`` of the command clipped to the drive range."""
    lo, hi = act.drive_range_V
    return (np.clip(np.asarray(voltage_V, dtype=float), lo, hi) - lo) / (hi - lo)


@numba.njit(cache=True)
def _relay_strokes(w: FloatArray, field_per_w: float, chi: float, f1: float, f2: float,
                   k1: float, zero: float, ec: FloatArray, vc: FloatArray, ifam: int,
                   scale: float, b: FloatArray, out: FloatArray) -> None:
    cdf = np.empty(b.size)
    for i in range(b.size):
        cdf[i] = fk.interaction_cdf(b[i], ifam, scale)
    for k in range(w.size):
        e = w[k] * field_per_w
        p = chi * e + fk.relay_step(b, cdf, ec, vc, e, ifam, scale)
        out[k] = (f1 * p + f2 * p * p) / k1 - zero


@numba.njit(cache=True)
def _family_strokes(w: FloatArray, P: FloatArray, F: FloatArray, r: FloatArray, p: FloatArray,
                    s: FloatArray, mem: FloatArray, out: FloatArray) -> None:
    for k in range(w.size):
        out[k] = kn.output_map(P, kn.core(P, F, r, p, s, mem, w[k]), w[k])


def _relay_raw(stage: Stage, w: FloatArray, b: FloatArray) -> FloatArray:
    mat, rod = stage.material, stage.rod
    ec, vc = coercive_nodes(mat.coercive, mat.n_coercive)
    out = np.empty(w.size)
    _relay_strokes(w, STACK_V / mat.layer_thickness_um, mat.chi_per_MVm,
                   1e6 * rod.a1_N_per_C_m2 * mat.remanence_C_m2,
                   1e6 * rod.a2_N_per_C2_m4 * mat.remanence_C_m2 ** 2, rod.stiffness_N_per_m,
                   stage.sensor.zero_um, ec, vc, mat.interaction.code, mat.interaction.std_MVm,
                   b, out)
    return out


def strokes_of(act: Actuator, w: FloatArray, state: ActuatorState
               ) -> tuple[FloatArray, ActuatorState]:
    """Free stroke (um) at each normalized input ``w`` (shape (N,)), and the state after."""
    w = np.ascontiguousarray(w, dtype=float)
    s, mem = state.scalars.copy(), state.memory.copy()
    if act.kind == "linear":
        raw = act.span_um * w
    elif act.kind == "relay":
        raw = _relay_raw(act.relay, w, mem)
    else:
        c = fam.compile_stage(act.family, 1000.0)
        raw = np.empty(w.size)
        _family_strokes(w, c.P, c.F, c.r, c.p, s, mem, raw)
    return act.gain * raw, ActuatorState(s, mem)


def strokes(act: Actuator, voltage_V: FloatArray, state: ActuatorState
            ) -> tuple[FloatArray, ActuatorState]:
    """Free stroke (um) for held command samples ``voltage_V`` (V, shape (N,)), and the state
    after; the stroke of sample k holds over its interval."""
    return strokes_of(act, normalized(act, voltage_V), state)


def power_on(act: Actuator) -> ActuatorState:
    """A poled actuator after one excursion to the top of its range and back to 0 V."""
    w0 = float(normalized(act, np.array([0.0]))[0])
    if act.family is not None:
        st = fam.initial_state(act.family)
        return ActuatorState(st.scalars.copy(), st.memory.copy())
    if act.kind == "linear":
        return ActuatorState(np.zeros(0), np.zeros(0))
    mat = act.relay.material
    ec, _ = coercive_nodes(mat.coercive, mat.n_coercive)
    b = np.full(ec.size, -fk.BIG)  # poled+: every relay up
    for w in (0.0, 1.0, w0):
        fk.relay_update(b, ec, w * STACK_V / mat.layer_thickness_um)
    return ActuatorState(np.zeros(0), b)


def major_loop(act: Actuator, n: int = 301) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(w, ascending, descending)`` stroke (um) on the second cycle over the whole range after
    power-on."""
    w = np.linspace(0.0, 1.0, n)
    path = np.concatenate([w[::-1], w, w[::-1], w])
    d, _ = strokes_of(act, path, power_on(act))
    return w, d[-n:], d[-2 * n:-n][::-1]


def loop_width(act: Actuator) -> float:
    """Largest width of the major loop over its span (dimensionless)."""
    _, up, down = major_loop(act)
    return float(np.max(np.abs(down - up)) / np.ptp(np.concatenate([up, down])))


def _relay_actuator(rng: np.random.Generator, drive: tuple[float, float], span_um: float
                    ) -> Actuator:
    """A relay stack whose loop width lies in :data:`HYSTERESIS` (drawn again until it does)."""
    for _ in range(60):
        stack = random_stage(rng, drive_range_V=(0.0, STACK_V), span_um=span_um, offset_um=0.0,
                             n_coercive=200)
        act = Actuator("relay", drive, span_um, relay=stack)
        if HYSTERESIS[0] <= loop_width(act) <= HYSTERESIS[1]:
            return act
    raise ValueError("no relay stack with a stage-like loop in 60 draws")


def random_actuator(rng: np.random.Generator, kind: str, drive: tuple[float, float],
                    span_um: float) -> Actuator:
    """An actuator of ``kind`` over ``drive`` (V) whose major loop spans ``span_um`` (um) with a
    width of 10-18 % of it."""
    if kind == "relay":
        return _relay_actuator(rng, drive, span_um)
    if kind not in fam.FAMILIES:
        raise ValueError(f"unknown actuator kind {kind!r} (one of {', '.join(KINDS)})")
    stage = fam.random_family_stage(rng, kind, drive_range_V=drive, span_um=span_um,
                                    hysteresis=float(rng.uniform(*HYSTERESIS)))
    return Actuator(kind, drive, span_um, family=stage)


def linear_actuator(drive: tuple[float, float], span_um: float, gain: float = 1.0) -> Actuator:
    """No hysteresis: ``d = gain span w``."""
    return Actuator("linear", drive, span_um, gain)


def summary(act: Actuator) -> dict:
    """The actuator's kind, range, spans and loop width as JSON-able data."""
    return {"kind": act.kind, "drive_range_V": list(act.drive_range_V), "span_um": act.span_um,
            "gain": act.gain, "stroke_span_um": act.stroke_span_um,
            "loop_width": 0.0 if act.kind == "linear" else loop_width(act),
            "stack_thickness_um": (act.relay.material.layer_thickness_um
                                   if act.relay is not None else None)}
