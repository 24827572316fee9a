"""The residual of one candidate cause on prepared sweeps (:class:`ExtendedSpace`): the paper's
model of :mod:`afmctl.fit.parametrization` (six nonlinear parameters ``x``, gains ``beta``
projected out) plus a few parameters ``phi`` of one effect of :mod:`afmctl.model.effects`, of the
thermal kernel (10) or of the viscous lag (:mod:`afmctl.model.viscous`); what :mod:`afmctl.fit.extension`
fits, with the progress lines of a fit and the fitted effect's parameters with units.

Every sweep weighs the same in the cost (rows scaled by ``sqrt(n_mean / n_s)``), so an effect seen
only on the fast sweeps is not drowned by the long slow ones. Pure numerics: no I/O.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from afmctl.fit import parametrization as pz
from afmctl.fit.candidates import INPUT_SIDE, Candidate, calibration_readings, reading_frame
from afmctl.fit.relaxation import THERMAL_COLUMNS, THERMAL_FINE, thermal_polarization
from afmctl.model import effects as fx
from afmctl.model import hysteresis as hy
from afmctl.model import transducer as td
from afmctl.model import viscous as vs

FloatArray = NDArray[np.float64]
#: ``Q`` of this many recent parameter sets is remembered (:meth:`ExtendedSpace._q`).
MEMO = 12
#: Seconds between a fit's progress lines (:class:`Progress`).
PROGRESS_S = 15.0
#: Samples after each kept one at which a lagged field is also kept while the command rests
#: (:func:`settling`): offsets growing by this factor, so a chord between two of them misses an
#: exponential approach by under 0.5 % of the step.
SETTLING_GROWTH = 1.25


@dataclass
class Progress:
    """Progress lines of one candidate's fit (``say``: one line each, e.g. to stderr): each
    stage as it starts (:meth:`stage`) and, every :data:`PROGRESS_S` seconds, how many
    residuals it has evaluated (:meth:`tick`, from :meth:`ExtendedSpace.residual`)."""

    say: Callable[[str], None]
    name: str
    t0: float = field(default_factory=time.perf_counter)
    last: float = field(default_factory=time.perf_counter)
    evaluations: int = 0

    def stage(self, text: str) -> None:
        self.say(f"  {self.name}: {text} ({time.perf_counter() - self.t0:.0f} s)")
        self.last = time.perf_counter()

    def tick(self) -> None:
        self.evaluations += 1
        now = time.perf_counter()
        if now - self.last >= PROGRESS_S:
            self.last = now
            self.say(f"  {self.name}: {self.evaluations} residual evaluations, "
                     f"{now - self.t0:.0f} s")


def settling(keep: NDArray[np.intp], n: int) -> NDArray[np.intp]:
    """``keep`` (sorted sample indices of a sweep of ``n`` samples) and, in each gap between two
    of them, the samples at offsets ``1, 2, 3, ...`` growing by :data:`SETTLING_GROWTH` from the
    gap's start: where a field that lags the command (:mod:`afmctl.model.viscous`) still moves
    while the command rests (a hold, a step's plateau), which the command's own samples miss. The
    same whatever the lag, so the cost stays smooth in it."""
    gaps = np.diff(np.append(keep, n))
    top = max(int(gaps.max(initial=1)), 2)
    count = math.ceil(math.log(top) / math.log(SETTLING_GROWTH)) + 1
    offsets = np.unique(np.round(SETTLING_GROWTH ** np.arange(count)).astype(np.intp))
    inside = offsets[None, :] < gaps[:, None]
    return np.union1d(keep, (keep[:, None] + offsets[None, :])[inside])


def log_gains(phi: FloatArray) -> FloatArray:
    """Per-sweep log gains from the free ones: the last makes their mean 0, so the model keeps
    the sweeps' average gain (a model for ``track``, which cannot know a future run's gain)."""
    return np.concatenate((phi, [-float(np.sum(phi))]))


class ExtendedSpace:
    """The residual of one candidate on prepared sweeps: ``z = (x, phi)``. Each sweep starts
    from the hysteresis state of ``base.starts`` and has its own sensor zero (as in
    :func:`afmctl.fit.identify.fit`). ``calibration_um``: the readings a gauge is calibrated on, um
    (default :func:`afmctl.fit.candidates.calibration_readings` of ``preps``; diagnose gives the
    slowest recorded sweep's, whole); ``gauge_frame``: centre and half width (um) of the readings
    a gauge error is fitted about, and their third and fourth central moments (um^3, um^4;
    absent: a uniform spread); default :func:`afmctl.fit.candidates.reading_frame` of
    ``calibration_um`` (:func:`afmctl.model.effects.gauge`); ``progress``: where the fit says
    how far it is (:class:`Progress`; shared by the spaces derived from this one)."""

    def __init__(self, candidate: Candidate, preps: Sequence[pz.Prepared], base: pz.LognormalSpace,
                 field_step: float, range_um: float, dt_min: float | None = None,
                 gauge_frame: tuple[float, ...] | None = None,
                 thermal_grid: tuple[int, float, int] = THERMAL_FINE,
                 calibration_um: FloatArray | None = None,
                 progress: Progress | None = None) -> None:
        self.candidate, self.preps, self.base = candidate, list(preps), base
        self.progress = progress
        self.step_rel = field_step
        self.range_um = range_um
        self.calibration_um = (calibration_readings(self.preps) if calibration_um is None
                               else calibration_um)
        self.gauge_frame = gauge_frame or reading_frame(self.calibration_um)
        self.dt_min = dt_min or min(p.dt for p in self.preps)
        n = np.array([p.mask.sum() for p in self.preps], dtype=float)
        self.weights = np.sqrt(n.mean() / n)
        self.thermal_grid = thermal_grid
        self._memo: dict[bytes, list[FloatArray]] = {}

    @functools.cached_property
    def thermal_keep(self) -> list[NDArray[np.intp]]:
        """Per sweep: the samples kernel (10) is run on (field steps of the thermal grid's)."""
        step = self.thermal_grid[1]
        return [pz.decimation(p.field, step * float(np.max(np.abs(p.field)))) for p in self.preps]

    @functools.cached_property
    def _settling(self) -> list[NDArray[np.intp]]:
        """Per sweep: the command's kept samples and those a lagged field settles on
        (:func:`settling`)."""
        return [settling(p.keep, p.field.size) for p in self.preps]

    def bounds(self) -> tuple[FloatArray, FloatArray]:
        lo, hi = self.base.bounds()
        return (np.concatenate((lo, self.candidate.lower)),
                np.concatenate((hi, self.candidate.upper)))

    def _fields(self, phi: FloatArray) -> list[tuple[FloatArray, NDArray[np.intp]]]:
        """Per sweep: the field the hysteresis sees (MV/m, full rate) and the samples kept: the
        command's (its turning points and field steps) and the amplifier output's own turning
        points. Not re-decimated per ``phi``: samples that jump as ``phi`` moves would make the
        cost a staircase in ``phi`` that finite differences cannot follow."""
        name, out = self.candidate.name, []
        for s, p in enumerate(self.preps):
            e, keep = p.field, p.keep
            if name == "voltage-gain-drift":
                e = e * math.exp(log_gains(phi)[s])
            elif name == "amplifier-lag":
                chain = fx.compile_chain(self._amplifier(phi, 1.0), p.dt)
                e = fx.lag(chain, e, float(e[0]))[0]
                keep = np.union1d(keep, pz.turning_points(e))
            elif name == "viscous-relaxation":  # the hysterons' field; from rest at the first
                e = vs.lagged(vs.Viscous(math.exp(phi[0])), e, p.dt, float(e[0]))[0]
                keep = np.union1d(self._settling[s], pz.turning_points(e))
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
            fine = [(p.field, k) for p, k in zip(self.preps, self.thermal_keep, strict=True)]
            return [pz.at_full_rate(e.size, keep, q) + pz.at_full_rate(e.size, k, d)
                    for (e, keep), q, (_, k), d
                    in zip(fields, q_keep, fine, self._thermal(theta, phi, fine), strict=True)]
        if self.candidate.name == "viscous-relaxation":  # the reversible part sees the field
            return [pz.at_full_rate(e.size, keep, q) + (p.field - e)
                    for (e, keep), q, p in zip(fields, q_keep, self.preps, strict=True)]
        return [pz.at_full_rate(e.size, keep, q) for (e, keep), q in zip(fields, q_keep,
                                                                           strict=True)]

    def _thermal(self, theta: FloatArray, phi: FloatArray,
                 fields: list[tuple[FloatArray, NDArray[np.intp]]]) -> list[FloatArray]:
        """Departure of kernel (10) from the relay kernel at the kept samples, each held for its
        time: ``Q`` of (10) on the thermal grid (:func:`thermal_polarization`) minus the relay's
        on the same rows with the interaction integrated in closed form, so the rows' quadrature
        error cancels and the departure vanishes with the field scale."""
        holds = [np.diff(keep, append=p.field.size) * p.dt
                 for (_, keep), p in zip(fields, self.preps, strict=True)]
        kept = [e[keep] for e, keep in fields]
        rows, _, n_max = self.thermal_grid
        pol = thermal_polarization(theta, hy.Thermal(math.exp(phi[0]), math.exp(phi[1])), n_max,
                                   rows)
        hot = pz.run_from(pol, kept, self.base.starts, holds)
        relay = pz.hysteresis(theta, kept, rows, starts=self.base.starts)
        return [a - b for a, b in zip(hot, relay, strict=True)]

    def _output(self, phi: FloatArray) -> fx.Effects:
        if self.candidate.name == "sensor-delay":
            return fx.Effects(sensor_delay_s=float(phi[0]) * self.dt_min)
        if self.candidate.name == "second-mode":
            return fx.Effects(second_mode=fx.SecondMode(math.exp(phi[0]), math.exp(phi[1]),
                                                        float(phi[2]), float(phi[3])))
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
        m, r, *moments = self.gauge_frame
        mu3, mu4 = moments or (0.0, 0.0)
        return fx.Effects(sensor_quadratic_per_um=float(phi[0]) / self.range_um,
                          sensor_cubic_per_um2=float(phi[1]) / self.range_um ** 2,
                          sensor_center_um=m, sensor_half_range_um=r,
                          sensor_third_moment_um3=mu3, sensor_fourth_moment_um4=mu4)

    def gauge_seeds(self, x: FloatArray) -> list[tuple[float, float]]:
        """Where else a refit through a gauge error starts (:func:`afmctl.fit.extension._started`,
        from the model ``x`` a first refit gave): the cubic error solved by least squares, the
        curvature at 0.
        A strong gauge is out of reach of local runs from the base model, which bent its loops
        and its rod term ``a2 L[Q^2]`` to take up the gauge's error. The readings are
        ``y = w + c P2(w) + c3 P3(w)`` with ``w`` linear in the gains and zeros, so to first
        order ``(c, c3)`` solve with them on ``[L[Q], L[Q^2], 1_s, P2(y), P3(y)]``. Only ``c3`` is
        kept: quasi-statically the gauge's ``c w^2`` is the rod's ``a2 Q^2`` to first order
        (``w`` is ``a1 Q``), so the ``c`` of that solve is ill-determined, while ``c3 w^3`` is the
        one cubic in ``Q`` of the two; the refit and the joint fit find ``c``. Empty for other
        candidates."""
        if self.candidate.name != "sensor-nonlinearity":
            return []
        a, _ = self.system(np.concatenate((x, np.zeros(2))))
        terms = np.concatenate([wt * fx.gauge_terms(self._gauge(np.ones(2)), p.y)
                                for p, wt in zip(self.preps, self.weights, strict=True)])
        y = np.concatenate([wt * p.y for p, wt in zip(self.preps, self.weights, strict=True)])
        c3 = np.linalg.lstsq(np.column_stack((a, terms)), y, rcond=None)[0][-1]
        return [(0.0, float(np.clip(c3 * self.range_um ** 2, self.candidate.lower[1],
                                    self.candidate.upper[1])))]

    @property
    def n_rod(self) -> int:
        """Design columns of the rod: ``L[Q]``, ``L[Q^2]``, ... (:attr:`Candidate.powers`)."""
        return self.candidate.powers

    def _filtered(self, z: FloatArray) -> list[tuple[FloatArray, ...]]:
        """Per sweep at the full rate: ``L[Q]``, ``L[Q^2]`` (and higher powers,
        :attr:`n_rod`) and ``1`` after the output effects (the sensor zero is the rod's, so it
        sees them too)."""
        theta, phi = np.exp(z[:6]), z[6:]
        out, blocks = self._output(phi), []
        for q, p in zip(self._q(theta, phi), self.preps, strict=True):
            cols = tuple(pz.unit_filter(q ** k, theta[4], theta[5], p.dt)
                         for k in range(1, self.n_rod + 1)) + (np.ones(q.size),)
            if out != fx.Effects():
                chain = fx.compile_chain(out, p.dt)
                cols = tuple(fx.measure(chain, c, *fx.rest(chain, float(c[0])))[0]
                             for c in cols)
            blocks.append(cols)
        return blocks

    def columns(self, z: FloatArray) -> list[FloatArray]:
        """Per sweep at the full rate: ``[L[Q], L[Q^2], 1]`` (higher powers before the ``1``,
        :attr:`n_rod`) after the output effects (the sensor zero is the rod's, so it sees them
        too), shape (N, :attr:`n_rod` + 1)."""
        return [np.column_stack(c) for c in self._filtered(z)]

    @functools.cached_property
    def _rows(self) -> list[NDArray[np.intp]]:
        """Per sweep: the samples of its residual (its mask's)."""
        return [np.flatnonzero(p.mask) for p in self.preps]

    def system(self, z: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Weighted design matrix ``[L[Q], L[Q^2], 1_s]`` (``1_s`` one sensor zero per sweep)
        and target (the readings through the inverse gauge). Only the residual's rows are
        gathered from the full-rate columns."""
        gauge = self._gauge(z[6:])
        rows = self._rows
        k = self.n_rod
        a = np.zeros((sum(r.size for r in rows), k + len(rows)))
        start = 0
        for s, (cols, r, w) in enumerate(zip(self._filtered(z), rows, self.weights, strict=True)):
            stop = start + r.size
            for j in range(k):
                a[start:stop, j] = w * cols[j][r]
            a[start:stop, k + s] = w * cols[k][r]
            start = stop
        ys = [w * fx.ungauge(gauge, p.y) for p, w in zip(self.preps, self.weights, strict=True)]
        return a, np.concatenate(ys)

    def readings(self, z: FloatArray, beta: FloatArray) -> list[FloatArray]:
        """What the sensor reads (um) at every sample of every sweep for ``z`` and the linear
        parameters ``beta = (g1, g2, zero_1, ..., zero_S)`` (more gains before the zeros,
        :attr:`n_rod`)."""
        gauge, k = self._gauge(z[6:]), self.n_rod
        return [fx.gauge(gauge, c[:, :k] @ beta[:k] + c[:, k] * beta[k + s])
                for s, c in enumerate(self.columns(z))]

    def _derived(self, preps: Sequence[pz.Prepared] | None = None,
                 base: pz.LognormalSpace | None = None,
                 thermal_grid: tuple[int, float, int] | None = None) -> ExtendedSpace:
        """This space with the given parts replaced (the scales and the gauge frame kept)."""
        return ExtendedSpace(self.candidate, self.preps if preps is None else preps,
                             base or self.base, self.step_rel, self.range_um, self.dt_min,
                             self.gauge_frame, thermal_grid or self.thermal_grid,
                             self.calibration_um, self.progress)

    def with_starts(self, starts: Sequence[str]) -> ExtendedSpace:
        """The same candidate with other initial states of the sweeps (:data:`pz.STARTS`)."""
        return self._derived(base=self.base.with_starts(starts))

    def with_grid(self, thermal_grid: tuple[int, float, int]) -> ExtendedSpace:
        """The same candidate with another thermal grid (rows, field step, most columns)."""
        return self._derived(thermal_grid=thermal_grid)

    def on(self, preps: Sequence[pz.Prepared], starts: Sequence[str] | None = None
           ) -> ExtendedSpace:
        """The same candidate, starts (or ``starts``, one per sweep) and node count on other
        prepared sweeps (the whole sweeps a fit on their first halves is judged on)."""
        return self._derived(preps, pz.LognormalSpace(preps, self.base.scales,
                                                      self.base.n_coercive,
                                                      starts or self.base.starts))

    def through(self, phi: FloatArray) -> pz.LognormalSpace:
        """The base model's space on the fields the hysteresis sees with the input-side effect
        ``phi`` (the amplifier's output), or on the readings a sensor delay ``phi`` had made late
        advanced back, or a gauge error ``phi`` undone: the paper's model fitted through the
        effect."""
        if self.candidate.name == "sensor-delay":
            preps = [replace(p, y=fx.advance(p.y, float(phi[0]) * self.dt_min / p.dt))
                     for p in self.preps]
        elif self.candidate.name == "sensor-nonlinearity":
            preps = [replace(p, y=fx.ungauge(self._gauge(phi), p.y)) for p in self.preps]
        else:
            preps = [replace(p, field=e, keep=keep)
                     for p, (e, keep) in zip(self.preps, self._fields(phi), strict=True)]
        return pz.LognormalSpace(preps, self.base.scales, self.base.n_coercive, self.base.starts)

    def residual(self, z: FloatArray) -> FloatArray:
        if self.progress is not None:
            self.progress.tick()
        a, y = self.system(z)
        return pz.project(a, y)[1]

    def to_model(self, z: FloatArray, thickness_um: float
                 ) -> tuple[td.Transducer, tuple[float, ...], tuple[float, ...]]:
        """The physical model (effect included; the last sweep's sensor zero), the per-sweep
        applied-voltage gains and sensor zeros (um). A gauge error is fitted in the frame of the
        slowest sweep's readings and stated in that of its positions (:func:`effects.position_frame`:
        the rod's gains and zeros scaled and shifted with it), the frame of a lab's linear
        calibration of the gauge on that sweep: the readings the model predicts are the same.
        The model of a candidate with higher powers of ``Q`` lacks them (a model file holds none:
        that twin is judged, never written)."""
        a, y = self.system(z)
        beta, _ = pz.project(a, y)
        phi, name = z[6:], self.candidate.name
        gauge = self._gauge(phi)
        if name == "sensor-nonlinearity":  # positions in the frame of the gauge's calibration
            shift, scale, gauge = fx.position_frame(gauge, self.calibration_um)
            beta = np.concatenate((scale * beta[:2], shift + scale * beta[2:]))
        zero = beta[self.n_rod + pz.zero_sweep(self.base.starts)]
        model = self.base.model(z[:6], np.array([beta[0], beta[1], zero]), thickness_um)
        offsets = tuple(float(b) for b in beta[self.n_rod:])
        gains = tuple([1.0] * len(self.preps))
        if name == "thermal-relaxation":
            grid = thermal_polarization(np.exp(z[:4]), hy.Thermal(math.exp(phi[0]),
                                                                math.exp(phi[1])),
                                        THERMAL_COLUMNS[2])
            model = replace(model, polarization=replace(
                model.polarization, thermal=grid.thermal, n_coercive=grid.n_coercive,
                interaction=grid.interaction))
        elif name == "amplifier-lag":
            model = replace(model, effects=self._amplifier(phi, thickness_um))
        elif name == "viscous-relaxation":
            model = replace(model, viscous=vs.Viscous(math.exp(phi[0])))
        elif name == "sensor-nonlinearity":
            model = replace(model, effects=gauge)
        elif name == "voltage-gain-drift":
            gains = tuple(math.exp(v) for v in log_gains(phi))
            model = replace(model, effects=fx.Effects(voltage_gain_sigma=float(np.std(gains,
                                                                                     ddof=1))))
        else:
            model = replace(model, effects=self._output(phi))
        return model, gains, offsets


def physical(name: str, model: td.Transducer,
             gains: Sequence[float | FloatArray]) -> dict[str, float]:
    """The fitted effect's parameters with units in their names (a gain that drifts in time:
    its sweep's mean; the amplifier's rails, if the drift's fit has them)."""
    e, th = model.effects, model.polarization.thermal
    if name == "thermal-relaxation" and th is not None:
        return {"field_scale_MV_per_m": th.field_scale, "attempt_rate_per_s": th.attempt_rate}
    if name == "amplifier-lag" and e.amplifier_bandwidth_hz is not None:
        return {"bandwidth_Hz": e.amplifier_bandwidth_hz,
                "damping_ratio": e.amplifier_damping_ratio or math.nan,
                "slew_V_per_s": e.amplifier_slew_v_per_s or math.inf}
    if name == "viscous-relaxation" and model.viscous is not None:
        return {"relaxation_time_s": model.viscous.time_s}
    if name == "sensor-delay":
        return {"delay_s": e.sensor_delay_s, "window_s": e.sensor_window_s}
    if name == "sensor-nonlinearity":
        return {"quadratic_per_um": e.sensor_quadratic_per_um,
                "cubic_per_um2": e.sensor_cubic_per_um2}
    if name == "second-mode" and e.second_mode is not None:
        m = e.second_mode
        return {"frequency_Hz": m.frequency_hz, "damping_ratio": m.damping_ratio, "gain": m.gain,
                "rate_gain": m.rate_gain}
    if name == "voltage-gain-drift":
        rails = {} if e.amplifier_rails_v is None else dict(zip(("rail_low_V", "rail_high_V"),
                                                                e.amplifier_rails_v, strict=True))
        return {f"gain_sweep_{i + 1}": float(np.mean(g)) for i, g in enumerate(gains)} | rails
    return {}
