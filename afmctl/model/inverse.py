"""Inverse filters: Algorithm 2 (P -> E), Algorithm 3 (displacement -> field) and the linear filter.

Both algorithms solve, sample by sample, a scalar monotone equation in the field ``E_k`` from the
model's memory at ``k - 1``:

* Algorithm 2: ``P(E_k) = P*_k``. The E-P relation of (13) is monotone (Section 3).
* Algorithm 3: ``u_{k+d}(E_k) = u*_{k+d}``, the rod (16) advanced ``d`` samples with the force
  ``a1 P(E_k) + a2 P(E_k)^2`` (``+ a3 P(E_k)^3``, :attr:`afmctl.model.rod.Rod.a3`) held (the second
  line of (18) for ``d = 1``). The paper's inequalities (19) are what make this well posed: the
  (1,2) entry ``alpha_1`` of ``e^{A t}`` is positive, so the prediction is increasing in the held
  force, hence (for ``a1 + 2 a2 P + 3 a3 P^2 > 0``) in ``E_k``, even where the E-u loop itself is
  not monotone. The sign of ``u* - u~`` (``u~`` with ``E`` held at ``E_{k-1}``)
  gives the direction of the field step, exactly as in Algorithm 3.

The solve marches ``E`` from ``E_{k-1}`` in that direction with an adaptive step (the first step from
the last local slope, doubled until the target is passed), then narrows the bracket by safeguarded
regula falsi (Illinois) and ends, as in the paper, with linear interpolation between the bracketing
trials. Algorithm 2 is the same routine with the "plant" ``u = P``.

``horizon = 1`` is Algorithm 3 as printed. A longer horizon inverts the rod ``d`` samples ahead with the
field held, which moves the sampling zero of the discretized rod (near -1 at high sample rates) that
makes the literal one-step inverse chatter; see :func:`algorithm3`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from afmctl.model import creep as cr
from afmctl.model import hysteresis as hy
from afmctl.model import transducer as tr
from afmctl.model.creep import _update as _creep_update
from afmctl.model.hysteresis import _quiet_band, _step, banded

FloatArray = NDArray[np.float64]
_NONE = np.zeros(0)  # no creep elements


@nb.njit(cache=True, nogil=True)
def _poly(g1: float, g2: float, g3: float, p: float) -> float:
    """``g1 p + g2 p^2 + g3 p^3``: the force of (16) (with its cubic) or its prediction."""
    return (g1 + (g2 + g3 * p) * p) * p


@nb.njit(cache=True, nogil=True)
def _root(g1: float, g2: float, g3: float, rhs: float) -> float:
    """The root of ``_poly(g1, g2, g3, p) = rhs`` on the branch through ``p = 0`` where the slope
    is positive (NaN if there is none): the quadratic's closed form, then Newton on the cubic."""
    disc = g1 * g1 + 4.0 * g2 * rhs
    if disc < 0.0:
        return math.nan
    p = rhs / g1 if g2 == 0.0 else (-g1 + math.sqrt(disc)) / (2.0 * g2)
    if g3 == 0.0:
        return p
    for _ in range(30):
        slope = g1 + (2.0 * g2 + 3.0 * g3 * p) * p
        if slope <= 0.0:
            return math.nan
        step = (_poly(g1, g2, g3, p) - rhs) / slope
        p -= step
        if abs(step) <= 1e-14 * (1.0 + abs(p)):
            return p
    return math.nan


@nb.njit(cache=True, nogil=True)
def _predict(kind: int, e: float, dt: float, st: np.ndarray, out: np.ndarray, ec: np.ndarray,
             wc: np.ndarray, ei: np.ndarray, cw: np.ndarray, scal: np.ndarray, c0: float,
             g1: float, g2: float, g3: float, creep: float) -> tuple[float, float]:
    """Prediction for field ``e`` and the hysteretic output ``P_h(e)`` (the force sees
    ``P_h + creep``, the creep part of this sample)."""
    p = _step(kind, e, dt, st, out, ec, wc, ei, cw, scal)
    return c0 + _poly(g1, g2, g3, p + creep), p


@nb.njit(cache=True, nogil=True)
def _solve(kind: int, target: float, e0: float, y0: float, slope: float, floor: float,
           e_min: float, e_max: float, dt: float, st: np.ndarray, sc: np.ndarray, ec: np.ndarray,
           wc: np.ndarray, ei: np.ndarray, cw: np.ndarray, scal: np.ndarray, c0: float, g1: float, g2: float,
           g3: float, creep: float, tol: float) -> tuple[float, float, float, float]:
    """Field ``E`` with prediction ``c0 + g1 P + g2 P^2 + g3 P^3`` within ``tol`` of ``target``,
    ``P = P_h(E) + creep``.

    Trials start from memory ``st`` (left unchanged); the accepted trial's new memory is left in
    ``sc``. Returns (E, P(E), |prediction - target|, local slope dy/dE). ``floor`` is a lower
    bound of the slope (the reversible part alone), which keeps round-off out of the first step.
    The march never leaves ``[e_min, e_max]`` (MV/m): an unreachable target ends at the limit, and
    the returned error says by how much it was missed.
    """
    fa = y0 - target
    direction = -1.0 if fa > 0.0 else 1.0
    ea = e0
    eb = min(max(ea + direction * max(abs(fa) / slope, 1e-12), e_min), e_max)
    if abs(fa) <= tol:
        eb = e0
    yb, pb = _predict(kind, eb, dt, st, sc, ec, wc, ei, cw, scal, c0, g1, g2, g3, creep)
    fb = yb - target
    bracketed = False
    side = 0
    for _ in range(300):
        if abs(fb) <= tol or eb == ea:
            break
        if not bracketed and fb * fa > 0.0:  # not passed yet: march on (secant, at most x8)
            step = eb - ea
            sec = -fb * step / (fb - fa) if (fb - fa) * direction * step > 0.0 else 8.0 * step
            ec_ = min(max(eb + (sec if 0.0 < sec / step <= 8.0 else 2.0 * step), e_min), e_max)
            ea, fa = eb, fb
        else:  # bracketed: Illinois regula falsi, the paper's linear interpolation
            bracketed = True
            ec_ = eb - fb * (eb - ea) / (fb - fa)
            if not (min(ea, eb) < ec_ < max(ea, eb)):
                ec_ = 0.5 * (ea + eb)
        yc, pc = _predict(kind, ec_, dt, st, sc, ec, wc, ei, cw, scal, c0, g1, g2, g3, creep)
        fc = yc - target
        if bracketed:
            if fc * fb < 0.0:
                ea, fa, side = eb, fb, 0
            else:
                if side == 1:
                    fa *= 0.5
                side = 1
        if abs(ec_ - eb) > 1e-9:
            slope = max((fc - fb) / (ec_ - eb), floor)
        eb, fb, pb = ec_, fc, pc
    return eb, pb, abs(fb), slope


@nb.njit(cache=True, nogil=True)
def _algorithm3(kind: int, target: np.ndarray, e_init: float, p_init: float, x: np.ndarray,
                st: np.ndarray, dt: float, ec: np.ndarray, wc: np.ndarray, ei: np.ndarray,
                cw: np.ndarray, scal: np.ndarray, phi: np.ndarray, gam: np.ndarray,
                row: np.ndarray, gain: float, a1: float, a2: float, a3: float, offset: float,
                floor: float, e_min: float, e_max: float, tol: float, ca: np.ndarray,
                cc: np.ndarray, cr_: np.ndarray, z: np.ndarray, on_force: bool, keep: int,
                st_kept: np.ndarray, x_kept: np.ndarray, z_kept: np.ndarray, lag_a: float,
                lag: np.ndarray, lag_kept: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fields for targets ``target[k]`` = desired u at sample ``k + d`` (um), rod state ``x`` (m).

    ``ca``, ``cc``, ``cr_``, ``z``: creep factors ``a_j``, weights ``c_j``, thresholds and state
    (updated in place; empty without creep, :mod:`afmctl.model.creep`), driven by ``P_h`` or, if
    ``on_force``, by the force ``F(P_h)`` and added to it (N). ``p_init`` is the
    hysteretic output ``P_h``. ``lag``: the hysterons' field at the first sample's start (MV/m,
    updated in place; empty: no viscous lag), ``lag_a`` its factor (:mod:`afmctl.model.viscous`):
    the hysteresis of sample ``k`` then steps at that field, known from the past, and ``P`` is
    ``P_h + lin (E - E_v)``, solved for ``E`` in closed form. ``st_kept``, ``x_kept``, ``z_kept``,
    ``lag_kept`` get the state after the first ``keep`` samples (left as they are if ``keep`` is
    not in ``1 ... N``).
    """
    n = target.size
    e_out = np.empty(n)
    u_out = np.empty(n)
    err = np.empty(n)
    sc = np.empty_like(st)
    e_prev, p_prev, slope = e_init, p_init, floor
    g1, g2, g3 = gain * a1 * 1e6, gain * a2 * 1e6, gain * a3 * 1e6
    lin, off = scal[5] / scal[0], scal[6] / scal[0]
    lo, hi = _quiet_band(kind, st, ec, ei) if banded(kind) else (0.0, -1.0)
    p_switch = p_init - (e_init * lin + off)
    for k in range(n):
        u_out[k] = x[0] * 1e6 + offset
        c0 = (row[0] * x[0] + row[1] * x[1]) * 1e6 + offset
        creep = 0.0
        for j in range(cc.size):
            creep += cc[j] * z[j]
        f_creep = 0.0
        if on_force:  # a known force this sample: it moves the rod like its past does
            f_creep, creep = creep, 0.0
            c0 += gain * f_creep * 1e6
        # inside the quiet band P(E) = lin E + off + p_switch: solve the force law exactly
        p = _root(g1, g2, g3, target[k] - c0) - creep
        e = (p - off - p_switch) / lin
        if lag.size:  # the hysterons step at their lagged field; P is affine in E
            p_h = _step(kind, lag[0], dt, st, sc, ec, wc, ei, cw, scal)
            st[:] = sc
            if math.isnan(p):
                e = e_max if target[k] > c0 else e_min
            else:
                e = min(max(lag[0] + (p - p_h) / lin, e_min), e_max)
            p = p_h + lin * (e - lag[0])
            err[k] = abs(c0 + _poly(g1, g2, g3, p + creep) - target[k])
            lag[0] = lag_a * lag[0] + (1.0 - lag_a) * e
        elif lo < e < hi and e_min <= e <= e_max:
            err[k] = 0.0
        else:
            if kind == 2:  # u~ with the field held at E_{k-1}: thermally active dipoles go
                y0 = _predict(kind, e_prev, dt, st, sc, ec, wc, ei, cw, scal, c0, g1, g2, g3,
                              creep)[0]
            else:  # on switching (creep) while it is held; a relay's P stays put
                y0 = c0 + _poly(g1, g2, g3, p_prev + creep)
            e, p, err[k], slope = _solve(kind, target[k], e_prev, y0, slope, floor, e_min, e_max,
                                         dt, st, sc, ec, wc, ei, cw, scal, c0, g1, g2, g3, creep,
                                         tol)
            st[:] = sc  # commit the accepted trial's memory
            if banded(kind):
                lo, hi = _quiet_band(kind, st, ec, ei)
                p_switch = p - (e * lin + off)
        f = _poly(a1, a2, a3, p + creep)
        x0 = phi[0, 0] * x[0] + phi[0, 1] * x[1] + gam[0] * (f + f_creep)
        x[1] = phi[1, 0] * x[0] + phi[1, 1] * x[1] + gam[1] * (f + f_creep)
        x[0] = x0
        if cc.size:
            _creep_update(f if on_force else p, ca, cr_, z)
        e_out[k] = e
        e_prev, p_prev = e, p
        if k == keep - 1:
            st_kept[:] = st
            x_kept[:] = x
            z_kept[:] = z
            lag_kept[:] = lag
    return e_out, u_out, err


@dataclass(frozen=True)
class Inversion:
    """Result of an inverse filter.

    Attributes
    ----------
    field_mv_m : ndarray, shape (N,)
        Field to apply at each sample, MV/m.
    predicted : ndarray, shape (N,)
        The model's own response at each sample (Algorithm 2: P in C/m^2 after the sample; Algorithm 3:
        displacement in um at the sample instant, before that sample's field acts).
    error : ndarray, shape (N,)
        ``|prediction - target|`` of the accepted field per sample (at most the tolerance unless
        the target was out of reach).
    state : transducer.StageState or hysteresis.PolarizationState
        Model memory after the last sample.
    kept : transducer.StageState or None
        Algorithm 3's model memory after the samples it was asked to keep (``keep``).
    """

    field_mv_m: FloatArray
    predicted: FloatArray
    error: FloatArray
    state: object
    kept: object = None

    def voltage(self, thickness_um: float) -> FloatArray:
        return self.field_mv_m * thickness_um


def algorithm2(params: hy.Polarization, p_target: FloatArray, state: hy.PolarizationState,
               e_init: float = 0.0, tol: float = 1e-10, dt: float = 1e-4,
               e_max: float = 1e3, e_min: float | None = None) -> Inversion:
    """Algorithm 2: fields whose forward polarization (13) follows ``p_target`` (C/m^2).

    ``state`` must be the memory at field ``e_init`` (MV/m) before the first sample. The error
    ``|P_in - P_out|`` per sample is returned as ``error``: at most ``tol`` (C/m^2). The fields stay
    in ``[e_min, e_max]`` (MV/m; ``e_min`` defaults to ``-e_max``).
    """
    k = hy.build_kernel(params)
    st = state.copy_values()
    p0, _ = hy.run(k, np.array([e_init]), state, dt)
    x = np.zeros(2)
    e, _, w = _algorithm3(k.kind, np.ascontiguousarray(p_target, dtype=float), e_init, p0[0], x, st,
                          dt, k.ec, k.wc, k.ei, k.cw, k.scal, np.eye(2), np.zeros(2),
                          np.zeros(2), 1e-6, 1.0, 0.0, 0.0, 0.0, 0.5 / params.eta,
                          -e_max if e_min is None else e_min, e_max, tol, _NONE, _NONE, _NONE,
                          _NONE, False, -1, _NONE, _NONE, _NONE, 0.0, _NONE, _NONE)
    p_out, _ = hy.run(k, e, state, dt)
    return Inversion(e, p_out, w, hy.PolarizationState(k.kind, st))


def algorithm3(cm: tr.Compiled, u_target_um: FloatArray, state: tr.StageState,
               e_init: float = 0.0, horizon: int = 1, tol_um: float = 1e-7,
               e_max: float = 1e3, e_min: float | None = None, keep: int | None = None
               ) -> Inversion:
    """Algorithm 3: fields whose forward displacement (16)+(13) follows ``u_target_um``.

    With creep (:attr:`afmctl.model.transducer.Transducer.creep`) the creep part of each sample
    is known from the samples before it (:mod:`afmctl.model.creep`): the inverse solves for the
    hysteretic output that, with it, gives the force the target needs, and carries the creep state,
    so a held or slow trajectory does not drift. With viscous relaxation
    (:attr:`afmctl.model.transducer.Transducer.viscous`) the hysterons' field of each sample is
    known from the samples before it, so the hysteresis steps there and the field solves the
    force law in closed form through the reversible part (the lag's state starts from
    ``state.lag``, or at ``e_init`` if that is empty).

    Parameters
    ----------
    cm : transducer.Compiled
        Model at the sample period.
    u_target_um : ndarray, shape (N,)
        Desired displacement at samples ``1 ... N`` (the field of sample ``k`` acts over
        ``[t_k, t_{k+1})``, so the first field can only influence ``u_1``), um.
    state : transducer.StageState
        Model state at sample 0, reached with field ``e_init`` (MV/m) held.
    horizon : int
        ``d``: the field of sample ``k`` is chosen so that the rod held ``d`` samples ahead reaches
        ``u*_{k+d}``. 1 is the paper's Algorithm 3; the desired trajectory is extended by its last
        value for the final ``d - 1`` targets.
    tol_um : float
        Accept a field once its predicted displacement is this close to the target, um.
    e_max : float
        Largest field the march may try, MV/m (e.g. the upper voltage limit / thickness).
    e_min : float, optional
        Lowest field the march may try, MV/m (default ``-e_max``; e.g. the lower voltage limit /
        thickness: a unipolar stage is never asked for a negative field).
    keep : int, optional
        Also return the model state after the first ``keep`` fields (``Inversion.kept``): where a
        caller that keeps only those goes on from (the state :func:`transducer.simulate` of
        their voltages reaches, up to round-off).

    Returns
    -------
    Inversion
        ``predicted`` is the model's displacement at samples ``0 ... N-1``.
    """
    if horizon < 1:
        raise ValueError("horizon must be >= 1")
    u = np.ascontiguousarray(u_target_um, dtype=float)
    target = np.concatenate([u[horizon - 1:], np.full(horizon - 1, u[-1])])
    row, gain = cm.disc.horizon(horizon)
    rod = cm.model.rod
    ps = state.polarization
    p0, _ = hy.run(cm.kernel, np.array([e_init]), ps, cm.dt)
    x = np.array(state.rod, dtype=float)
    st = ps.copy_values()
    creep = cm.model.creep
    on_force = creep is not None and creep.acts_on == "force"
    drive = float(rod.force(p0)[0]) if on_force else float(p0[0])
    z = np.array(state.creep, dtype=float) if state.creep.size else cr.rest_state(creep, drive)
    ca = _NONE if creep is None else creep.factors(cm.dt)
    cc = _NONE if creep is None else np.asarray(creep.weights, dtype=float)
    cth = _NONE if creep is None else np.asarray(creep.thresholds, dtype=float)
    dfdp = abs(rod.force_slope(float(p0[0]) + (0.0 if on_force else cr.offset(creep, z)))
               ) or abs(rod.a1)
    floor = 0.5 * gain * dfdp * 1e6 / cm.model.polarization.eta
    lag = (np.zeros(0) if cm.model.viscous is None else
           np.array([float(state.lag[0]) if state.lag.size else e_init]))
    lag_a = 0.0 if cm.model.viscous is None else cm.model.viscous.factor(cm.dt)
    kept = (np.empty_like(st), np.empty_like(x), np.empty_like(z), np.empty_like(lag))
    e, pred, w = _algorithm3(cm.kernel.kind, target, e_init, p0[0], x, st, cm.dt, cm.kernel.ec,
                             cm.kernel.wc, cm.kernel.ei, cm.kernel.cw, cm.kernel.scal,
                             cm.disc.phi, cm.disc.gamma, row, gain, rod.a1, rod.a2, rod.a3, rod.offset_um,
                             floor, -e_max if e_min is None else e_min, e_max, tol_um, ca, cc,
                             cth, z, on_force, -1 if keep is None else keep, *kept[:3], lag_a,
                             lag, kept[3])
    at = None
    if keep is not None and 1 <= keep <= u.size:
        at = tr.StageState(hy.PolarizationState(ps.kind, kept[0]), kept[1], kept[2], kept[3])
    return Inversion(e, pred, w, tr.StageState(hy.PolarizationState(ps.kind, st), x, z, lag), at)


# ----------------------------------------------------------------------------------------------
# literal algorithms (slow reference oracles)
# ----------------------------------------------------------------------------------------------


def _march(trial, e_prev: float, y_prev: float, target: float, e_step: float) -> float:
    """Fixed-step march from ``e_prev`` until ``trial(E)`` passes ``target``, then interpolate."""
    if y_prev == target:
        return e_prev
    d_e = math.copysign(e_step, target - y_prev)
    e_a, y_a = e_prev, y_prev
    while True:
        e_b = e_a + d_e
        y_b = trial(e_b)
        if (target - y_b) * d_e <= 0:
            return e_a + (target - y_a) * (e_b - e_a) / (y_b - y_a)
        e_a, y_a = e_b, y_b


def algorithm2_literal(params: hy.Polarization, p_target: FloatArray,
                       state: hy.PolarizationState, e_step: float = 1e-3) -> FloatArray:
    """Algorithm 2 as printed: fixed ``E_step`` march, then linear interpolation (slow)."""
    e_prev, out = 0.0, []
    p_prev = hy.run(params, [e_prev], state)[0][0]
    for p_star in p_target:
        e = _march(lambda x, s=state: hy.run(params, [x], s)[0][0], e_prev, p_prev, p_star, e_step)
        (p_prev,), state = hy.run(params, [e], state)
        e_prev = e
        out.append(e)
    return np.array(out)


def algorithm3_literal(cm: tr.Compiled, u_target_um: FloatArray, state: tr.StageState,
                       e_step: float = 1e-3) -> FloatArray:
    """Algorithm 3 as printed (horizon 1, fixed ``E_step``, linear interpolation); slow oracle.

    ``u~_{k+1}`` holds the field at ``E_{k-1}``; the march direction is ``sgn(u*_{k+1} - u~_{k+1})``
    (inequalities (19)); each trial advances the rod one sample from ``x_k`` with the trial force.
    """
    rod, disc = cm.model.rod, cm.disc
    ps, x = state.polarization, np.array(state.rod, dtype=float)
    e_prev, out = 0.0, []

    def u_next(e: float) -> float:
        p = hy.run(cm.kernel, [e], ps, cm.dt)[0][0]
        return float((disc.phi[0] @ x + disc.gamma[0] * rod.force(np.array(p))) * 1e6
                     + rod.offset_um)

    for u_star in u_target_um:
        e = _march(u_next, e_prev, u_next(e_prev), u_star, e_step)
        (p,), ps = hy.run(cm.kernel, [e], ps, cm.dt)
        x = disc.phi @ x + disc.gamma * rod.force(np.array(p))
        e_prev = e
        out.append(e)
    return np.array(out)


# ----------------------------------------------------------------------------------------------
# linear filter (the paper's baseline)
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LinearFilter:
    """The paper's linear filter: ``V = (u* - offset_um) / gain_um_per_v``.

    A linear scaling of the field-displacement relation that accommodates the scale between input
    and output but neglects hysteresis, nonlinearity and dynamics.
    """

    gain_um_per_v: float
    offset_um: float

    def voltage(self, u_target_um: FloatArray) -> FloatArray:
        return (np.asarray(u_target_um, dtype=float) - self.offset_um) / self.gain_um_per_v


def fit_linear(voltage_v: FloatArray, displacement_um: FloatArray) -> LinearFilter:
    """Least-squares line through measured (or simulated) voltage-displacement pairs."""
    a = np.column_stack([voltage_v, np.ones(len(voltage_v))])
    (g, o), *_ = np.linalg.lstsq(a, displacement_um, rcond=None)
    return LinearFilter(float(g), float(o))
