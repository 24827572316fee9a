"""Candidate model extensions: the paper's model plus one physical effect, fitted by least squares.

Each candidate cause of a model discrepancy (``afmctl diagnose``) is the identified model of
:mod:`afmctl.parametrization` (six nonlinear parameters ``x``, gains ``beta`` projected out) plus
a few parameters ``phi`` of one effect of :mod:`afmctl.effects` or of the thermal kernel (10):

=======================  ===============================================  =======================
name                     phi (internal)                                   acts on
=======================  ===============================================  =======================
``none``                 --                                               --
``thermal-relaxation``   log E_th (MV/m), log nu0 (1/s)                   kernel (10) for (4)
``amplifier-lag``        log f_a (Hz), log zeta_a, log S (MV/m/s)          field, before (13)
``sensor-delay``         d (samples of the fastest sweep; a time)         design columns
``sensor-nonlinearity``  c R, c3 R^2 (1/um, 1/um^2; R the range, um)     measured displacement
``second-mode``          log f_2 (Hz), log zeta_2, gain                   design columns
``voltage-gain-drift``   log g_s of every sweep but the last (mean 0)     field, per sweep
=======================  ===============================================  =======================

Every sweep weighs the same in the cost (rows scaled by ``sqrt(n_mean / n_s)``), so an effect seen
only on the fast sweeps is not drowned by the long slow ones. Pure numerics: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy import optimize

from afmctl import effects as fx
from afmctl import hysteresis as hy
from afmctl import parametrization as pz
from afmctl import transducer as td

FloatArray = NDArray[np.float64]
NAMES = ("none", "thermal-relaxation", "amplifier-lag", "sensor-delay", "sensor-nonlinearity",
         "second-mode", "voltage-gain-drift")
#: Candidates whose parameters change ``Q`` (they act on the field or in the kernel).
INPUT_SIDE = ("thermal-relaxation", "amplifier-lag", "voltage-gain-drift")
#: ``Q`` of this many recent parameter sets is remembered (:meth:`ExtendedSpace._q`).
MEMO = 12
#: An amplifier slew limit this many times the data's fastest field rate is out of reach (off).
SLEW_OFF = 3.0
#: Grid of the thermal kernel, in the fit and in the extended model (N_i x N_j hysterons).
THERMAL_GRID = (64, 48)


@dataclass(frozen=True)
class Candidate:
    """One candidate: its extra parameters' names, starting values and bounds (internal units).

    ``starts[0]`` is the effect switched off (the base model)."""

    name: str
    labels: tuple[str, ...]
    starts: tuple[tuple[float, ...], ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]

    @property
    def n_params(self) -> int:
        return len(self.labels)


def field_rate_max(preps: Sequence[pz.Prepared]) -> float:
    """Fastest rate of the field over the sweeps, MV/m/s."""
    return max(float(np.max(np.abs(np.diff(p.field)))) / p.dt for p in preps) or 1.0


def catalogue(n_sweeps: int, e_max: float, nyquist_hz: float, rod_hz: float,
              rate_max: float) -> dict[str, Candidate]:
    """The candidates for ``n_sweeps`` sweeps of peak field ``e_max`` (MV/m), Nyquist frequency
    (Hz), identified rod resonance ``rod_hz`` (Hz) and fastest field rate ``rate_max`` (MV/m/s).
    ``voltage-gain-drift`` needs two sweeps.

    The amplifier is of second order (a first order is its overdamped limit) with a slew limit
    that starts either out of reach (``SLEW_OFF`` times the fastest rate) or just below it."""
    lf, ln = math.log, math.log(nyquist_hz)
    slew_off = lf(SLEW_OFF * rate_max)
    cands = [
        Candidate("none", (), ((),), (), ()),
        Candidate("thermal-relaxation", ("log_field_scale_MV_per_m", "log_attempt_rate_per_s"),
                  ((lf(2e-4 * e_max), lf(1e6)),)  # close to the relay: the base model
                  + tuple((lf(f * e_max), lf(r)) for f in (0.003, 0.01, 0.03)
                          for r in (1e2, 1e4, 1e6)),
                  (lf(1e-4 * e_max), lf(0.1)), (lf(0.3 * e_max), lf(1e7))),
        Candidate("amplifier-lag", ("log_bandwidth_Hz", "log_damping_ratio", "log_slew_MV_per_m_s"),
                  ((ln + 2.9, lf(0.7), slew_off),)  # far beyond the data: the base model
                  + tuple((lf(f * rod_hz), lf(0.7), slew) for f in (0.3, 1.0, 3.0)
                          for slew in (slew_off, lf(0.7 * rate_max))) + ((ln, lf(0.7), slew_off),),
                  (lf(1.0), lf(0.05), lf(0.05 * rate_max)), (ln + 3, lf(10.0), slew_off + 1e-6)),
        Candidate("sensor-delay", ("delay_fastest_samples",),
                  ((0.0,), (0.5,), (2.0,), (5.0,), (10.0,), (25.0,)), (0.0,), (60.0,)),
        Candidate("sensor-nonlinearity", ("quadratic_times_range", "cubic_times_range2"),
                  ((0.0, 0.0), (-0.05, 0.0), (0.05, 0.0), (0.0, -0.05), (0.0, 0.05)),
                  (-0.3, -0.3), (0.3, 0.3)),
        Candidate("second-mode", ("log_frequency_Hz", "log_damping_ratio", "gain"),
                  ((lf(2.0 * rod_hz), lf(0.03), 1e-4),)  # no mode: the base model
                  + tuple((lf(f * rod_hz), lf(0.03), g) for f in (1.5, 2.2, 3.0, 4.0, 6.0)
                          for g in (0.1,)
                        if f * rod_hz < 0.8 * nyquist_hz) or ((ln - 1, lf(0.03), 0.1),),
                  (lf(min(1.05 * rod_hz, 0.3 * nyquist_hz)), lf(0.002), -0.9),
                  (ln, lf(0.5), 3.0)),
    ]
    if n_sweeps >= 2:
        k = n_sweeps - 1
        cands.append(Candidate("voltage-gain-drift", tuple(f"log_gain_{i + 1}" for i in range(k)),
                               (tuple([0.0] * k),), tuple([-0.3] * k), tuple([0.3] * k)))
    return {c.name: c for c in cands}


@dataclass(frozen=True)
class Extended:
    """A fitted candidate: the model (with its effect), per-sweep applied-voltage gains, initial
    hysteresis states and sensor zeros (um), and the solver's word."""

    name: str
    model: td.Transducer
    gains: tuple[float, ...]
    parameters: dict[str, float]
    success: bool
    nfev: int
    x: FloatArray
    starts: tuple[str, ...]
    offsets_um: tuple[float, ...]
    beta: FloatArray


def _with_zeros(blocks: Sequence[FloatArray]) -> FloatArray:
    """Stack per-sweep blocks ``[g1 col, g2 col, zero col]`` into ``[L[Q], L[Q^2], 1_s]``: the
    zero column of each sweep in a column of its own."""
    n = len(blocks)
    out = np.zeros((sum(b.shape[0] for b in blocks), 2 + n))
    row = 0
    for s, b in enumerate(blocks):
        out[row:row + b.shape[0], :2] = b[:, :2]
        out[row:row + b.shape[0], 2 + s] = b[:, 2]
        row += b.shape[0]
    return out


def _log_gains(phi: FloatArray) -> FloatArray:
    """Per-sweep log gains from the free ones: the last makes their mean 0, so the model keeps
    the sweeps' average gain (a model for ``track``, which cannot know a future run's gain)."""
    return np.concatenate((phi, [-float(np.sum(phi))]))


class ExtendedSpace:
    """The residual of one candidate on prepared sweeps: ``z = (x, phi)``. Each sweep starts
    from the hysteresis state of ``base.starts`` and has its own sensor zero (as in
    :func:`afmctl.identify.fit`). ``gauge_frame``: centre and half width (um) of the readings a
    gauge error is fitted about (default: those of ``preps``; :func:`afmctl.effects.gauge`)."""

    def __init__(self, candidate: Candidate, preps: Sequence[pz.Prepared], base: pz.LognormalSpace,
                 field_step: float, range_um: float, dt_min: float | None = None,
                 gauge_frame: tuple[float, float] | None = None) -> None:
        self.candidate, self.preps, self.base = candidate, list(preps), base
        self.step_rel = field_step
        self.step = [field_step * float(np.max(np.abs(p.field))) for p in self.preps]
        self.range_um = range_um
        y = np.concatenate([p.y for p in self.preps])
        self.gauge_frame = gauge_frame or (float(y.max() + y.min()) / 2, float(np.ptp(y)) / 2)
        self.dt_min = dt_min or min(p.dt for p in self.preps)
        n = np.array([p.mask.sum() for p in self.preps], dtype=float)
        self.weights = np.sqrt(n.mean() / n)
        self._memo: dict[bytes, list[FloatArray]] = {}

    def bounds(self) -> tuple[FloatArray, FloatArray]:
        lo, hi = self.base.bounds()
        return (np.concatenate((lo, self.candidate.lower)),
                np.concatenate((hi, self.candidate.upper)))

    def _fields(self, phi: FloatArray) -> list[tuple[FloatArray, NDArray[np.intp]]]:
        """Per sweep: the field the hysteresis sees (MV/m, full rate) and the samples kept."""
        name, out = self.candidate.name, []
        for s, (p, step) in enumerate(zip(self.preps, self.step, strict=True)):
            e, keep = p.field, p.keep
            if name == "voltage-gain-drift":
                e = e * math.exp(_log_gains(phi)[s])
            elif name == "amplifier-lag":
                chain = fx.compile_chain(self._amplifier(phi, 1.0), p.dt)
                e = fx.lag(chain, e, float(e[0]))[0]
                keep = pz.decimation(e, step)
            out.append((e, keep))
        return out

    def _q(self, theta: FloatArray, phi: FloatArray) -> list[FloatArray]:
        """``Q`` at the full rate per sweep (eq. (13), or (10) for thermal relaxation).

        Remembered for the last few arguments it depends on (``theta[:4]``, and ``phi`` for the
        effects that act before or in the hysteresis): a finite-difference Jacobian moves one
        parameter at a time, and the rod's and the output effects' parameters leave ``Q`` alone.
        """
        key = theta[:4].tobytes() + (phi.tobytes() if self.candidate.name in INPUT_SIDE else b"")
        if key not in self._memo:
            if len(self._memo) >= MEMO:
                self._memo.pop(next(iter(self._memo)))
            self._memo[key] = self._q_new(theta, phi)
        return self._memo[key]

    def _q_new(self, theta: FloatArray, phi: FloatArray) -> list[FloatArray]:
        fields = self._fields(phi)
        q_keep = pz.hysteresis(theta, [e[keep] for e, keep in fields], self.base.n_coercive,
                               starts=self.base.starts)
        if self.candidate.name == "thermal-relaxation":
            off = np.asarray(self.candidate.starts[0])
            q_keep = [q + a - b for q, a, b in zip(q_keep, self._thermal(theta, phi, fields),
                                                    self._thermal(theta, off, fields), strict=True)]
        return [np.interp(np.arange(e.size), keep, q) if keep.size < e.size else q
                for (e, keep), q in zip(fields, q_keep, strict=True)]

    def _thermal(self, theta: FloatArray, phi: FloatArray,
                 fields: list[tuple[FloatArray, NDArray[np.intp]]]) -> list[FloatArray]:
        """``Q`` of kernel (10) on the :data:`THERMAL_GRID` at the kept samples, each held for
        its time. Used as a difference to the relay limit (``starts[0]``): the grid's own error
        (0.2 % of ``Q`` against the relay kernel's closed form) cancels."""
        holds = [np.diff(keep, append=p.field.size) * p.dt
                 for (_, keep), p in zip(fields, self.preps, strict=True)]
        return pz.hysteresis(theta, [e[keep] for e, keep in fields], THERMAL_GRID[0],
                             hy.Thermal(math.exp(phi[0]), math.exp(phi[1])), THERMAL_GRID[1],
                             holds, self.base.starts)

    def _output(self, phi: FloatArray) -> fx.Effects:
        if self.candidate.name == "sensor-delay":
            return fx.Effects(sensor_delay_s=float(phi[0]) * self.dt_min)
        if self.candidate.name == "second-mode":
            return fx.Effects(second_mode=fx.SecondMode(math.exp(phi[0]), math.exp(phi[1]),
                                                        float(phi[2])))
        return fx.Effects()

    def _amplifier(self, phi: FloatArray, thickness_um: float) -> fx.Effects:
        """The amplifier of ``phi`` (its slew in V/s for a stack ``thickness_um`` thick; none if
        the slew stayed out of reach)."""
        slew = math.exp(phi[2])
        on = slew < math.exp(self.candidate.upper[2]) / 1.5
        return fx.Effects(amplifier_bandwidth_hz=math.exp(phi[0]),
                          amplifier_damping_ratio=math.exp(phi[1]),
                          amplifier_slew_v_per_s=slew * thickness_um if on else None)

    def _gauge(self, phi: FloatArray) -> fx.Effects:
        if self.candidate.name != "sensor-nonlinearity":
            return fx.Effects()
        return fx.Effects(sensor_quadratic_per_um=float(phi[0]) / self.range_um,
                          sensor_cubic_per_um2=float(phi[1]) / self.range_um ** 2,
                          sensor_center_um=self.gauge_frame[0],
                          sensor_half_range_um=self.gauge_frame[1])

    def columns(self, z: FloatArray) -> list[FloatArray]:
        """Per sweep at the full rate: ``[L[Q], L[Q^2], 1]`` after the output effects (the
        sensor zero is the rod's, so it sees them too), shape (N, 3)."""
        theta, phi = np.exp(z[:6]), z[6:]
        out, blocks = self._output(phi), []
        for q, p in zip(self._q(theta, phi), self.preps, strict=True):
            cols = np.column_stack((pz.sweep_columns(q, theta[4], theta[5], p.dt)[:, :2],
                                    np.ones(q.size)))
            if out != fx.Effects():
                chain = fx.compile_chain(out, p.dt)
                cols = np.column_stack([fx.measure(chain, c, *fx.rest(chain, float(c[0])))[0]
                                        for c in cols.T])
            blocks.append(cols)
        return blocks

    def system(self, z: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Weighted design matrix ``[L[Q], L[Q^2], 1_s]`` (``1_s`` one sensor zero per sweep)
        and target (the readings through the inverse gauge)."""
        gauge = self._gauge(z[6:])
        blocks = [w * c[p.mask] for c, p, w in zip(self.columns(z), self.preps, self.weights,
                                                      strict=True)]
        ys = [w * fx.ungauge(gauge, p.y) for p, w in zip(self.preps, self.weights, strict=True)]
        return _with_zeros(blocks), np.concatenate(ys)

    def readings(self, z: FloatArray, beta: FloatArray) -> list[FloatArray]:
        """What the sensor reads (um) at every sample of every sweep for ``z`` and the linear
        parameters ``beta = (g1, g2, zero_1, ..., zero_S)``."""
        gauge = self._gauge(z[6:])
        return [fx.gauge(gauge, c[:, :2] @ beta[:2] + c[:, 2] * beta[2 + s])
                for s, c in enumerate(self.columns(z))]

    def on(self, preps: Sequence[pz.Prepared]) -> ExtendedSpace:
        """The same candidate, starts and node count on other prepared sweeps (the whole sweeps
        a fit on their first halves is judged on)."""
        base = pz.LognormalSpace(preps, self.base.scales, self.base.n_coercive, self.base.starts)
        return ExtendedSpace(self.candidate, preps, base, self.step_rel, self.range_um,
                             self.dt_min, self.gauge_frame)

    def residual(self, z: FloatArray) -> FloatArray:
        a, y = self.system(z)
        return pz.project(a, y)[1]

    def to_model(self, z: FloatArray, thickness_um: float
                 ) -> tuple[td.Transducer, tuple[float, ...], tuple[float, ...]]:
        """The physical model (effect included; the last sweep's sensor zero), the per-sweep
        applied-voltage gains and sensor zeros (um)."""
        a, y = self.system(z)
        beta, _ = pz.project(a, y)
        model = self.base.model(z[:6], np.array([beta[0], beta[1], beta[-1]]), thickness_um)
        offsets = tuple(float(b) for b in beta[2:])
        phi, name = z[6:], self.candidate.name
        gains = tuple([1.0] * len(self.preps))
        if name == "thermal-relaxation":
            pol = replace(model.polarization, thermal=hy.Thermal(math.exp(phi[0]), math.exp(phi[1])),
                          n_coercive=THERMAL_GRID[0], n_interaction=THERMAL_GRID[1])
            model = replace(model, polarization=pol)
        elif name == "amplifier-lag":
            model = replace(model, effects=self._amplifier(phi, thickness_um))
        elif name == "sensor-nonlinearity":
            model = replace(model, effects=self._gauge(phi))
        elif name == "voltage-gain-drift":
            gains = tuple(math.exp(v) for v in _log_gains(phi))
            model = replace(model, effects=fx.Effects(voltage_gain_sigma=float(np.std(gains,
                                                                                     ddof=1))))
        else:
            model = replace(model, effects=self._output(phi))
        return model, gains, offsets


def physical(name: str, model: td.Transducer, gains: Sequence[float]) -> dict[str, float]:
    """The fitted effect's parameters with units in their names."""
    e, th = model.effects, model.polarization.thermal
    if name == "thermal-relaxation" and th is not None:
        return {"field_scale_MV_per_m": th.field_scale, "attempt_rate_per_s": th.attempt_rate}
    if name == "amplifier-lag" and e.amplifier_bandwidth_hz is not None:
        return {"bandwidth_Hz": e.amplifier_bandwidth_hz,
                "damping_ratio": e.amplifier_damping_ratio or math.nan,
                "slew_V_per_s": e.amplifier_slew_v_per_s or math.inf}
    if name == "sensor-delay":
        return {"delay_s": e.sensor_delay_s}
    if name == "sensor-nonlinearity":
        return {"quadratic_per_um": e.sensor_quadratic_per_um,
                "cubic_per_um2": e.sensor_cubic_per_um2}
    if name == "second-mode" and e.second_mode is not None:
        m = e.second_mode
        return {"frequency_Hz": m.frequency_hz, "damping_ratio": m.damping_ratio, "gain": m.gain}
    if name == "voltage-gain-drift":
        return {f"gain_sweep_{i + 1}": g for i, g in enumerate(gains)}
    return {}


def fit(space: ExtendedSpace, x_base: FloatArray, thickness_um: float,
        max_nfev: int, n_starts: int = 1) -> Extended:
    """Fit ``(x, phi)`` from the base parameters ``x_base``.

    Multi-start on the effect alone: from each of the ``n_starts`` best of the candidate's starting
    ``phi`` (by cost) a short least-squares run moves ``phi`` with the base model held (a
    Jacobian of a few columns); the best of those then starts the joint fit of ``(x, phi)``. The
    base model is in every candidate's family, so its own cost bounds the result's."""
    lo, hi = space.bounds()
    n_x = x_base.size

    def clip(z: FloatArray) -> FloatArray:
        return np.clip(z, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))

    def cost(z: FloatArray) -> float:
        return float(np.sum(space.residual(z) ** 2))

    def with_phi(phi: FloatArray) -> FloatArray:
        return space.residual(np.concatenate((x_base, phi)))

    starts = [clip(np.concatenate((x_base, s))) for s in space.candidate.starts]
    ranked = sorted(starts, key=cost)[:max(n_starts, 1)]
    nfev = len(starts)
    if n_x < ranked[0].size:
        runs = [optimize.least_squares(with_phi, z0[n_x:], bounds=(lo[n_x:], hi[n_x:]),
                                       diff_step=1e-6, max_nfev=max_nfev // 2) for z0 in ranked]
        nfev += sum(r.nfev for r in runs)
        best = min(runs, key=lambda r: float(r.cost))
        ranked = [clip(np.concatenate((x_base, best.x)))]
    sol = optimize.least_squares(space.residual, ranked[0], bounds=(lo, hi), diff_step=1e-6,
                                 max_nfev=max_nfev)
    model, gains, offsets = space.to_model(sol.x, thickness_um)
    return Extended(space.candidate.name, model, gains, physical(space.candidate.name, model, gains),
                    bool(sol.success and sol.status > 0), nfev + int(sol.nfev), sol.x,
                    space.base.starts, offsets, pz.project(*space.system(sol.x))[0])
