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
#: An amplifier slew limit this many times the data's fastest field rate is out of reach (off).
SLEW_OFF = 3.0
#: Grid of the thermal kernel, in the fit and in the extended model (N_i x N_j hysterons).
THERMAL_GRID = (32, 24)


@dataclass(frozen=True)
class Candidate:
    """One candidate: its extra parameters' names, starting values and bounds (internal units)."""

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
                  + tuple((lf(f * e_max), lf(r)) for f in (0.01, 0.04) for r in (30.0, 300.0)),
                  (lf(1e-4 * e_max), lf(0.1)), (lf(0.3 * e_max), lf(1e7))),
        Candidate("amplifier-lag", ("log_bandwidth_Hz", "log_damping_ratio", "log_slew_MV_per_m_s"),
                  tuple((lf(f * rod_hz), lf(0.7), slew) for f in (0.3, 1.0, 3.0)
                        for slew in (slew_off, lf(0.7 * rate_max))) + ((ln, lf(0.7), slew_off),),
                  (lf(1.0), lf(0.05), lf(0.05 * rate_max)), (ln + 3, lf(10.0), slew_off + 1e-6)),
        Candidate("sensor-delay", ("delay_fastest_samples",),
                  ((0.5,), (2.0,), (5.0,), (10.0,), (25.0,)), (0.0,), (60.0,)),
        Candidate("sensor-nonlinearity", ("quadratic_times_range", "cubic_times_range2"),
                  ((-0.05, 0.0), (0.05, 0.0), (0.0, -0.05), (0.0, 0.05)), (-0.3, -0.3), (0.3, 0.3)),
        Candidate("second-mode", ("log_frequency_Hz", "log_damping_ratio", "gain"),
                  tuple((lf(f * rod_hz), lf(0.03), g) for f in (1.5, 2.2, 3.0, 4.0, 6.0)
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
    """A fitted candidate: the model (with its effect), per-sweep gains, and the solver's word."""

    name: str
    model: td.Transducer
    gains: tuple[float, ...]
    parameters: dict[str, float]
    success: bool
    nfev: int
    x: FloatArray


def _log_gains(phi: FloatArray) -> FloatArray:
    """Per-sweep log gains from the free ones: the last makes their mean 0, so the model keeps
    the sweeps' average gain (a model for ``track``, which cannot know a future run's gain)."""
    return np.concatenate((phi, [-float(np.sum(phi))]))


class ExtendedSpace:
    """The residual of one candidate on prepared sweeps: ``z = (x, phi)``."""

    def __init__(self, candidate: Candidate, preps: Sequence[pz.Prepared], base: pz.LognormalSpace,
                 field_step: float, range_um: float) -> None:
        self.candidate, self.preps, self.base = candidate, list(preps), base
        self.step = [field_step * float(np.max(np.abs(p.field))) for p in self.preps]
        self.range_um = range_um
        self.dt_min = min(p.dt for p in self.preps)
        n = np.array([p.mask.sum() for p in self.preps], dtype=float)
        self.weights = np.sqrt(n.mean() / n)

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
        """``Q`` at the full rate per sweep (eq. (13), or (10) for thermal relaxation)."""
        fields = self._fields(phi)
        thermal, holds = None, None
        if self.candidate.name == "thermal-relaxation":
            thermal = hy.Thermal(math.exp(phi[0]), math.exp(phi[1]))
            holds = [np.diff(keep, append=p.field.size) * p.dt
                     for (_, keep), p in zip(fields, self.preps, strict=True)]
        n_c = THERMAL_GRID[0] if thermal else self.base.n_coercive
        q_keep = pz.hysteresis(theta, [e[keep] for e, keep in fields], n_c, thermal,
                               THERMAL_GRID[1], holds)
        return [np.interp(np.arange(e.size), keep, q) if keep.size < e.size else q
                for (e, keep), q in zip(fields, q_keep, strict=True)]

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
                          sensor_cubic_per_um2=float(phi[1]) / self.range_um ** 2)

    def system(self, z: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Weighted design matrix ``[L[Q], L[Q^2], 1]`` (after the output effects) and target."""
        theta, phi = np.exp(z[:6]), z[6:]
        out = self._output(phi)
        gauge = self._gauge(phi)
        blocks, ys = [], []
        for q, p, w in zip(self._q(theta, phi), self.preps, self.weights, strict=True):
            cols = pz.sweep_columns(q, theta[4], theta[5], p.dt)
            if out != fx.Effects():
                chain = fx.compile_chain(out, p.dt)
                cols = np.column_stack([fx.measure(chain, col, *fx.rest(chain, float(col[0])))[0]
                                        for col in cols.T])
            blocks.append(w * cols[p.mask])
            ys.append(w * fx.ungauge(gauge, p.y))
        return np.vstack(blocks), np.concatenate(ys)

    def residual(self, z: FloatArray) -> FloatArray:
        a, y = self.system(z)
        return pz.project(a, y)[1]

    def to_model(self, z: FloatArray, thickness_um: float) -> tuple[td.Transducer, tuple[float, ...]]:
        """The physical model (effect included) and the per-sweep applied-voltage gains."""
        a, y = self.system(z)
        beta, _ = pz.project(a, y)
        model = self.base.model(z[:6], beta, thickness_um)
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
        return model, gains


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
    model, gains = space.to_model(sol.x, thickness_um)
    return Extended(space.candidate.name, model, gains, physical(space.candidate.name, model, gains),
                    bool(sol.success and sol.status > 0), nfev + int(sol.nfev), sol.x)
