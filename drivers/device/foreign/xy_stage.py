"""A foreign x/y stage: two hysteretic axes coupled by a flexure's geometry and a shared structural
mode driven by the actuators' forces, written independently of afmctl's coupling model.

Units: voltage V, displacement um, time s, frequency Hz. Axis x is channel 0, y channel 1.

Actuators
    Each axis's free stroke ``d_i`` (um, blocked force over the axis's stiffness) is a hysteretic,
    rate-independent function of its own voltage history (:mod:`~afmctl.drivers.device.foreign.xy_actuator`:
    the paper's relay stack or a Preisach / Prandtl-Ishlinskii / Bouc-Wen operator; the two axes
    of a stage differ in kind and parameters). Under the zero-order-held command it is held too.
Structure (mass-normalized, three degrees of freedom ``q = (x_p, y_p, theta)``)
    ``q'' + D q' + K q = B d`` with the platform's translations ``x_p, y_p`` (um) and the shared
    mode's coordinate ``theta`` (a yaw / frame-rocking rotation, um at a reference radius)::

        K = [[wx^2, 0, kx wx wt], [0, wy^2, ky wy wt], [kx wx wt, ky wy wt, wt^2]]
        D = diag(2 zx wx, 2 zy wy, 2 zt wt)
        B = [[wx^2, 0], [0, wy^2], [ex wt^2, ey wt^2]]

    ``kx, ky``: the flexures' stiffness coupling of translation and rotation; ``ex, ey``: the
    actuators' lines of action off the centre of stiffness (their forces drive the mode). The
    shared mode's frequency (:func:`mode_hz`) is the undamped eigenfrequency of ``K`` whose mode
    shape is mostly ``theta``. Integrated exactly (zero-order hold, matrix exponential).
Position of the point of interest (what the sensors see, um)
    ``x = x_p + rx theta + g_xy(y_p)``, ``y = y_p + ry theta + g_yx(x_p)``: sensor arms ``rx, ry``
    off the rotation centre, and each axis's guide flexure moving the other axis by its
    misalignment plus a parallelogram flexure's arc, ``g(s) = alpha s + sign 3/5 (s - s_n)^2 / L``
    (:class:`Flexure`): slightly nonlinear in the source displacement.
Sensors
    Reading = position + offset (noise free here: :func:`noise_um` gives each axis's 1 sigma,
    the emulator or :func:`~afmctl.drivers.device.foreign.xy_sweeps.write_sweep_set` adds it).

The coupling in um of y per um of x is then a ratio of two transfer functions of the structure
(:func:`true_coupling`), both holding the source axis's own dynamics: it is not a static gain plus
one mode of displacement. The reading at sample k is taken at its start, before sample k acts.

Example
-------
>>> import numpy as np
>>> stage = random_xy_stage(np.random.default_rng(1), unipolar=True)
>>> v = np.column_stack([np.linspace(0, 150, 2001), np.full(2001, 40.0)])
>>> true_um, reading_um, state = run(stage, v, 10000.0, initial_state(stage))
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from functools import lru_cache

import numba
import numpy as np
from numpy.typing import NDArray
from scipy import linalg, optimize

from afmctl.drivers.device.foreign.xy_actuator import (
    KINDS,
    Actuator,
    ActuatorState,
    linear_actuator,
    power_on,
    random_actuator,
    strokes,
    summary,
)

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]
UNIPOLAR_V = (0.0, 150.0)
BIPOLAR_V = (-150.0, 150.0)


@dataclass(frozen=True)
class Structure:
    """The mass-normalized three-degree-of-freedom structure (see the module docstring).

    Parameters
    ----------
    axis_hz, axis_damping : tuple of float
        ``wx / 2 pi, wy / 2 pi`` (Hz) and ``zx, zy``.
    shared_hz, shared_damping : float
        ``wt / 2 pi`` (Hz, before the stiffness coupling moves it) and ``zt``.
    stiffness_coupling : tuple of float
        ``kx, ky`` (dimensionless, ``kx^2 + ky^2 < 1``).
    force_arm : tuple of float
        ``ex, ey``: rotation per um of free stroke at equal stiffness (dimensionless).
    sensor_arm : tuple of float
        ``rx, ry``: um of sensed translation per um of ``theta``.
    """

    axis_hz: tuple[float, float]
    axis_damping: tuple[float, float]
    shared_hz: float
    shared_damping: float
    stiffness_coupling: tuple[float, float]
    force_arm: tuple[float, float]
    sensor_arm: tuple[float, float]


@dataclass(frozen=True)
class Flexure:
    """Parasitic motion of one axis's guide on the other: ``g(s) = alpha s + sign 3/5 (s -
    neutral)^2 / L`` (um) for the source platform's translation ``s`` (um).

    Parameters
    ----------
    misalignment : float
        ``alpha``, um per um (the guide's angle to its axis).
    length_um : float
        ``L``, the parallelogram flexure's beam length, um.
    neutral_um : float
        ``s_n``, where the beams are straight, um.
    arc_sign : float
        +1 or -1 (which side the beams' arc shortens to).
    """

    misalignment: float
    length_um: float
    neutral_um: float
    arc_sign: float

    def offset_um(self, s: FloatArray) -> FloatArray:
        return self.misalignment * s + self.arc_sign * 0.6 * (s - self.neutral_um) ** 2 \
            / self.length_um

    def slope(self, s: float) -> float:
        """``dg/ds`` at ``s`` (um per um)."""
        return self.misalignment + self.arc_sign * 1.2 * (s - self.neutral_um) / self.length_um


@dataclass(frozen=True)
class XYStage:
    """A foreign x/y stage.

    Parameters
    ----------
    actuators : tuple of Actuator
        (x, y).
    structure : Structure
    flexures : tuple of Flexure
        (``g_yx``: x's guide moving y, ``g_xy``: y's guide moving x).
    sensor_noise_um, sensor_offset_um : tuple of float
        Per axis: 1 sigma of the gauge noise and its zero offset, um.
    name : str
    """

    actuators: tuple[Actuator, Actuator]
    structure: Structure
    flexures: tuple[Flexure, Flexure]
    sensor_noise_um: tuple[float, float]
    sensor_offset_um: tuple[float, float]
    name: str = ""

    @property
    def drive_range_V(self) -> tuple[tuple[float, float], tuple[float, float]]:
        return self.actuators[0].drive_range_V, self.actuators[1].drive_range_V


@dataclass(frozen=True)
class XYState:
    """The mechanics ``(q, q')`` (shape (6,)) and both actuators' memories."""

    mechanics: FloatArray
    actuators: tuple[ActuatorState, ActuatorState]


# ---------------------------------------------------------------- structure


def matrices(s: Structure) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``K`` (3, 3; 1/s^2), ``D`` (3, 3; 1/s) and ``B`` (3, 2; 1/s^2)."""
    wx, wy = (2 * math.pi * f for f in s.axis_hz)
    wt = 2 * math.pi * s.shared_hz
    kx, ky = s.stiffness_coupling
    K = np.array([[wx * wx, 0.0, kx * wx * wt], [0.0, wy * wy, ky * wy * wt],
                  [kx * wx * wt, ky * wy * wt, wt * wt]])
    D = np.diag([2 * s.axis_damping[0] * wx, 2 * s.axis_damping[1] * wy,
                 2 * s.shared_damping * wt])
    B = np.array([[wx * wx, 0.0], [0.0, wy * wy],
                  [s.force_arm[0] * wt * wt, s.force_arm[1] * wt * wt]])
    return K, D, B


def eigen_hz(s: Structure) -> tuple[FloatArray, FloatArray]:
    """Undamped natural frequencies (Hz, increasing) and mode shapes (columns)."""
    K, _, _ = matrices(s)
    lam, vec = np.linalg.eigh(K)
    return np.sqrt(lam) / (2 * math.pi), vec


def mode_hz(s: Structure) -> float:
    """The shared mode: the undamped eigenfrequency whose shape is mostly ``theta``, Hz."""
    f, vec = eigen_hz(s)
    return float(f[int(np.argmax(np.abs(vec[2])))])


@lru_cache(maxsize=64)
def discrete(s: Structure, rate_hz: float) -> tuple[FloatArray, FloatArray]:
    """Exact zero-order-hold map over one sample: ``z' = Phi z + Gamma d`` for ``z = (q, q')``."""
    K, D, B = matrices(s)
    aug = np.zeros((8, 8))
    aug[:3, 3:6] = np.eye(3)
    aug[3:6, :3], aug[3:6, 3:6], aug[3:6, 6:] = -K, -D, B
    E = linalg.expm(aug / rate_hz)
    return np.ascontiguousarray(E[:6, :6]), np.ascontiguousarray(E[:6, 6:])


@numba.njit(cache=True)
def _propagate(phi: FloatArray, gam: FloatArray, z: FloatArray, d: FloatArray,
               out: FloatArray) -> None:
    """``out[k] = z_k`` (before sample k acts); ``z`` advanced to ``z_N`` in place."""
    nz = z.size
    nxt = np.empty(nz)
    for k in range(d.shape[0]):
        for i in range(nz):
            out[k, i] = z[i]
        for i in range(nz):
            acc = gam[i, 0] * d[k, 0] + gam[i, 1] * d[k, 1]
            for j in range(nz):
                acc += phi[i, j] * z[j]
            nxt[i] = acc
        for i in range(nz):
            z[i] = nxt[i]


def position_um(stage: XYStage, q: FloatArray) -> FloatArray:
    """Sensed positions (N, 2) of structure coordinates ``q`` (N, 3), um."""
    rx, ry = stage.structure.sensor_arm
    g_yx, g_xy = stage.flexures
    x = q[:, 0] + rx * q[:, 2] + g_xy.offset_um(q[:, 1])
    y = q[:, 1] + ry * q[:, 2] + g_yx.offset_um(q[:, 0])
    return np.column_stack([x, y])


def _rest(stage: XYStage, d: FloatArray) -> FloatArray:
    K, _, B = matrices(stage.structure)
    return np.concatenate([np.linalg.solve(K, B @ d), np.zeros(3)])


# ---------------------------------------------------------------- API


def initial_state(stage: XYStage) -> XYState:
    """Both actuators poled and back at 0 V (:func:`~afmctl.drivers.device.foreign.xy_actuator.power_on`),
    the structure at rest there."""
    acts = tuple(power_on(a) for a in stage.actuators)
    return idle(stage, XYState(np.zeros(6), acts), np.zeros(2))  # type: ignore[arg-type]


def run(stage: XYStage, voltage_v: FloatArray, rate_hz: float, state: XYState
        ) -> tuple[FloatArray, FloatArray, XYState]:
    """Drive both axes with held samples and read both sensors at every sample instant.

    Parameters
    ----------
    stage : XYStage
    voltage_v : ndarray, shape (N, 2)
        Commands of x and y, V (clipped to each axis's range); sample k holds over
        ``[t_k, t_k + 1 / rate_hz)``.
    rate_hz : float
        Sample rate, Hz.
    state : XYState
        From :func:`initial_state` or a previous :func:`run` (never modified).

    Returns
    -------
    true_um : ndarray, shape (N, 2)
        Position of the point of interest at ``t_k``, um (before sample k acts).
    reading_um : ndarray, shape (N, 2)
        Noise-free sensor readings there, um.
    state : XYState
        At ``t_N``. Running a waveform in blocks gives what one call gives.
    """
    v = np.asarray(voltage_v, dtype=float).reshape(-1, 2)
    d = np.empty_like(v)
    acts = []
    for i, (act, st) in enumerate(zip(stage.actuators, state.actuators, strict=True)):
        d[:, i], new = strokes(act, v[:, i], st)
        acts.append(new)
    phi, gam = discrete(stage.structure, float(rate_hz))
    z = state.mechanics.copy()
    zs = np.empty((v.shape[0], 6))
    _propagate(phi, gam, z, np.ascontiguousarray(d), zs)
    true_um = position_um(stage, zs[:, :3])
    return true_um, true_um + np.asarray(stage.sensor_offset_um), XYState(z, tuple(acts))


def idle(stage: XYStage, state: XYState, voltage_v: FloatArray) -> XYState:
    """Go to the command ``voltage_v`` (V, shape (2,)) and hold it until every transient has died:
    the actuators step there, the structure rests at their strokes."""
    v = np.asarray(voltage_v, dtype=float).reshape(2)
    d, acts = np.empty(2), []
    for i, (act, st) in enumerate(zip(stage.actuators, state.actuators, strict=True)):
        stroke, new = strokes(act, v[i:i + 1], st)
        d[i] = stroke[0]
        acts.append(new)
    return XYState(_rest(stage, d), tuple(acts))  # type: ignore[arg-type]


def noise_um(stage: XYStage) -> FloatArray:
    """Sensor noise of x and y, 1 sigma, um (shape (2,))."""
    return np.asarray(stage.sensor_noise_um, dtype=float)


def operating_point(stage: XYStage) -> FloatArray:
    """Structure coordinates ``q0`` (3,) at rest with each stroke at the middle of its major loop
    (the stage's mid-range, where :func:`true_coupling` linearizes)."""
    d = np.array([0.5 * a.stroke_span_um for a in stage.actuators])
    return _rest(stage, d)[:3]


def _output_rows(stage: XYStage) -> FloatArray:
    """Linearized positions per structure coordinate at :func:`operating_point`: (2, 3)."""
    q0 = operating_point(stage)
    rx, ry = stage.structure.sensor_arm
    g_yx, g_xy = stage.flexures
    return np.array([[1.0, g_xy.slope(q0[1]), rx], [g_yx.slope(q0[0]), 1.0, ry]])


def stroke_response(stage: XYStage, freq_hz: FloatArray) -> ComplexArray:
    """Small-signal positions per free stroke at :func:`operating_point`: shape (F, 2, 2),
    ``[f, i, j]`` um of axis i per um of stroke j."""
    K, D, B = matrices(stage.structure)
    C = _output_rows(stage)
    w = 2 * math.pi * np.atleast_1d(np.asarray(freq_hz, dtype=float))
    dyn = K[None] - (w * w)[:, None, None] * np.eye(3) + 1j * w[:, None, None] * D[None]
    return C[None] @ np.linalg.solve(dyn, np.broadcast_to(B, (w.size, 3, 2)).astype(complex))


def true_coupling(stage: XYStage, freq_hz: FloatArray) -> dict:
    """The stage's cross-coupling, from its own formulas.

    Definition: both axes rest at :func:`operating_point` (each actuator's free stroke at the
    middle of its major loop, the structure static: the stage's mid-range). One axis's command
    moves by a small amount while the other's is held; the held axis's free stroke is then
    exactly constant (its actuator is rate independent and its voltage does not change). The
    coupling "yx" is the ratio of the y position's small-signal response to the x position's
    (both as the sensors see them, offsets aside), linearized about that point (the flexures' arc
    enters through its slope there). Both responses are linear in the same source stroke, so the
    source actuator's hysteresis (and any other law from voltage to stroke) cancels from the
    ratio: it is a property of the structure and the geometry alone. Over a sweep of the whole
    range the arc's secant slope is its slope at the sweep's middle (a quadratic's), which is the
    operating point's up to the held axis's own coupling (a few 1e-5 um/um), so a static gain
    fitted to full-range sweeps estimates ``yx_static`` too.

    Parameters
    ----------
    stage : XYStage
    freq_hz : ndarray, shape (F,)
        Frequencies, Hz (0 allowed).

    Returns
    -------
    dict
        ``yx_static``, ``xy_static`` (float, um of target per um of source, signed, at DC);
        ``yx_frf``, ``xy_frf`` (complex ndarray (F,), um per um, continuous-time steady state at
        each frequency).
    """
    f = np.atleast_1d(np.asarray(freq_hz, dtype=float))
    T = stroke_response(stage, np.concatenate([[0.0], f]))
    yx = T[:, 1, 0] / T[:, 0, 0]
    xy = T[:, 0, 1] / T[:, 1, 1]
    return {"yx_static": float(yx[0].real), "xy_static": float(xy[0].real),
            "yx_frf": yx[1:], "xy_frf": xy[1:]}


def db(gain: float) -> float:
    return 20.0 * math.log10(abs(gain))


def static_span_um(stage: XYStage) -> tuple[float, float]:
    """Quasi-static span of each axis's position over its actuator's major loop, um
    (linearized at the operating point)."""
    T0 = stroke_response(stage, np.zeros(1))[0].real
    return (float(T0[0, 0] * stage.actuators[0].stroke_span_um),
            float(T0[1, 1] * stage.actuators[1].stroke_span_um))


def describe(stage: XYStage) -> dict:
    """All parameters with derived figures (coupling in dB, modes, spans), JSON-able."""
    truth = true_coupling(stage, np.zeros(0))
    f, _ = eigen_hz(stage.structure)
    return {
        "name": stage.name,
        "actuators": {ax: summary(a) for ax, a in zip("xy", stage.actuators, strict=True)},
        "structure": asdict(stage.structure),
        "flexures": {"yx": asdict(stage.flexures[0]), "xy": asdict(stage.flexures[1])},
        "sensor_noise_um": list(stage.sensor_noise_um),
        "sensor_offset_um": list(stage.sensor_offset_um),
        "derived": {
            "mode_hz": mode_hz(stage.structure),
            "natural_hz": [float(x) for x in f],
            "yx_static": truth["yx_static"], "xy_static": truth["xy_static"],
            "yx_static_db": db(truth["yx_static"]), "xy_static_db": db(truth["xy_static"]),
            "static_span_um": list(static_span_um(stage)),
            "operating_point_um": [float(x) for x in operating_point(stage)],
        },
    }


def without_hysteresis(stage: XYStage) -> XYStage:
    """The stage with linear actuators of the same stroke spans (the structure unchanged)."""
    acts = tuple(linear_actuator(a.drive_range_V, a.span_um, a.gain) for a in stage.actuators)
    return replace(stage, actuators=acts)  # type: ignore[arg-type]


# ---------------------------------------------------------------- random stages


def _logu(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _sign(rng: np.random.Generator, p_minus: float = 0.5) -> float:
    return -1.0 if rng.random() < p_minus else 1.0


def _structure(rng: np.random.Generator, mode: float) -> Structure:
    """Axes 1.4-3 x the shared mode; force arms 0.1-0.35 and stiffness couplings 0.02-0.15 that
    add; the uncoupled shared frequency solved so that :func:`mode_hz` is ``mode``."""
    eps = tuple(_sign(rng) * rng.uniform(0.1, 0.35) for _ in range(2))
    kap = tuple(-math.copysign(rng.uniform(0.02, 0.15), e) for e in eps)
    s = Structure((mode * _logu(rng, 1.4, 3.0), mode * _logu(rng, 1.4, 3.0)),
                  (_logu(rng, 0.03, 0.2), _logu(rng, 0.03, 0.2)), mode,
                  _logu(rng, 0.03, 0.12), kap, eps, (0.0, 0.0))  # type: ignore[arg-type]
    ft = optimize.brentq(lambda ft: mode_hz(replace(s, shared_hz=ft)) - mode, 0.5 * mode,
                         1.2 * mode, xtol=1e-9)
    return replace(s, shared_hz=float(ft))


def _calibrate(stage: XYStage, target: tuple[float, float], share: tuple[float, float],
               spans: tuple[float, float]) -> XYStage:
    """Sensor arms, misalignments and actuator gains such that the static couplings are
    ``target`` (yx, xy), the structural path (``theta`` and ``kx, ky``) carries ``share`` of each,
    and each axis spans ``spans`` (um). Fixed-point iteration (the couplings are small)."""
    K, _, B = matrices(stage.structure)
    S = np.linalg.solve(K, B)  # static q per unit stroke: columns x, y
    for _ in range(100):
        q0 = operating_point(stage)
        g_yx, g_xy = stage.flexures
        rx, ry = stage.structure.sensor_arm
        den_x = S[0, 0] + g_xy.slope(q0[1]) * S[1, 0] + rx * S[2, 0]
        den_y = S[1, 1] + g_yx.slope(q0[0]) * S[0, 1] + ry * S[2, 1]
        ry = (share[0] * target[0] * den_x - S[1, 0]) / S[2, 0]
        rx = (share[1] * target[1] * den_y - S[0, 1]) / S[2, 1]
        a_yx = (1 - share[0]) * target[0] * den_x / S[0, 0] - (g_yx.slope(q0[0])
                                                               - g_yx.misalignment)
        a_xy = (1 - share[1]) * target[1] * den_y / S[1, 1] - (g_xy.slope(q0[1])
                                                               - g_xy.misalignment)
        acts = tuple(replace(a, gain=sp / (a.span_um * den))
                     for a, sp, den in zip(stage.actuators, spans, (den_x, den_y), strict=True))
        stage = replace(stage, actuators=acts,
                        structure=replace(stage.structure, sensor_arm=(float(rx), float(ry))),
                        flexures=(replace(g_yx, misalignment=float(a_yx)),
                                  replace(g_xy, misalignment=float(a_xy))))
    return stage


def random_xy_stage(rng: np.random.Generator, *, unipolar: bool, coupling_db: float | None = None,
                    mode_hz: float | None = None, name: str = "") -> XYStage:
    """Draw a foreign x/y stage.

    Parameters
    ----------
    rng : numpy.random.Generator
    unipolar : bool
        Both axes over 0 .. 150 V (True) or -150 .. 150 V (False).
    coupling_db : float, optional
        Static coupling y from x, dB (-45 .. -25 drawn if None); x from y lies within 5 dB of it
        (clipped to -45 .. -25). Signs drawn.
    mode_hz : float, optional
        The shared mode, Hz (150 .. 800 log-uniform if None).
    name : str

    Returns
    -------
    XYStage
        Axes of two different kinds (:data:`~afmctl.drivers.device.foreign.xy_actuator.KINDS`),
        spans 60-110 um, loop widths 10-18 %; axis modes 1.4-3 x the shared mode; the structural
        path carries 20-70 % of each static coupling (of either sign against the geometric
        part); flexure beams 20-50 mm; sensor noise 5-30 nm, offsets within +-2 um.
    """
    drive = UNIPOLAR_V if unipolar else BIPOLAR_V
    c_yx = rng.uniform(-45.0, -25.0) if coupling_db is None else float(coupling_db)
    c_xy = float(np.clip(c_yx + rng.uniform(-5.0, 5.0), -45.0, -25.0))
    target = tuple(_sign(rng) * 10 ** (c / 20) for c in (c_yx, c_xy))
    share = tuple(_sign(rng, 0.3) * rng.uniform(0.2, 0.7) for _ in range(2))
    mode = _logu(rng, 150.0, 800.0) if mode_hz is None else float(mode_hz)
    kinds = rng.choice(len(KINDS), size=2, replace=False)
    spans = tuple(float(rng.uniform(60.0, 110.0)) for _ in range(2))
    acts = tuple(random_actuator(rng, KINDS[int(k)], drive, sp)
                 for k, sp in zip(kinds, spans, strict=True))
    flex = tuple(Flexure(0.0, _logu(rng, 2e4, 5e4), rng.uniform(0.0, 0.4) * sp, _sign(rng))
                 for sp in spans)
    stage = XYStage(acts, _structure(rng, mode), flex,  # type: ignore[arg-type]
                    (_logu(rng, 0.005, 0.03), _logu(rng, 0.005, 0.03)),
                    (rng.uniform(-2.0, 2.0), rng.uniform(-2.0, 2.0)), name)
    return _calibrate(stage, target, share, spans)  # type: ignore[arg-type]


#: (unipolar, static coupling y from x in dB, shared mode Hz) of :func:`xy_stages`.
BENCH_SPECS = ((True, -25.0, 150.0), (False, -45.0, 800.0), (True, -35.0, 400.0),
               (False, -30.0, 250.0), (True, -42.0, 600.0), (False, -38.0, 180.0),
               (True, -28.0, 750.0), (False, -33.0, 500.0))


@lru_cache(maxsize=1)
def _bench() -> tuple[XYStage, ...]:
    return tuple(random_xy_stage(np.random.default_rng(2500 + i), unipolar=u, coupling_db=c,
                                 mode_hz=m, name=f"foreign-xy-{i + 1}")
                 for i, (u, c, m) in enumerate(BENCH_SPECS))


def xy_stages() -> list[XYStage]:
    """The fixed foreign x/y stages for benchmarks (:data:`BENCH_SPECS`, seeds 2500 + i)."""
    return list(_bench())
