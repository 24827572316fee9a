"""Joint least-squares identification of the stage model from sweeps (paper Sections 2.2 and 4).

The model is the transducer of :mod:`afmctl.transducer`: field ``E = V / thickness`` drives the
homogenized polarization (13), which forces the rod (16). The fit runs in the well-scaled
internal parametrization of :mod:`afmctl.parametrization` (``m`` and ``P_R`` fixed by convention
and reported as fixed): the nonlinear parameters go to :func:`scipy.optimize.least_squares` (in
logs, with bounds), the gains ``(g1, g2, offset)`` are projected out by linear least squares at
every evaluation (variable projection). First a lognormal ``nu_1`` / normal ``nu_2`` fit (six
nonlinear parameters); optionally (``density="discrete"``) a general nonnegative coercive density
on fixed nodes, smoothed by a Tikhonov penalty, refined from it. The interaction density stays
normal (the closed-form kernel; a discrete ``nu_2`` would need the much slower grid kernel).

The state is carried through each sweep from its start: depoled, then the first voltage applied
quasi-statically (:func:`afmctl.transducer.initial`). For speed the hysteresis is evaluated during
the fit on a decimated copy of the field that keeps every turning point (the model (13) depends
only on them) and interpolated back; the rod runs at the full rate. Per-sweep errors, however,
are always those of the final model at the default node counts and the full rate.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy import optimize

from afmctl import effects as fx
from afmctl import parametrization as pz
from afmctl import transducer as td
from afmctl.sweeps import Sweep
from afmctl.tomlfile import InputError, Table

FloatArray = NDArray[np.float64]
Window = tuple[float, float] | None


class FitInputError(InputError):
    """The sweeps cannot be fitted as given (conflicting metadata, empty fit window)."""


@dataclass(frozen=True)
class Settings:
    """Options of :func:`fit`.

    Parameters
    ----------
    mass_kg : float
        Fixed effective mass ``m`` of (16), kg (a scale convention, see
        :mod:`afmctl.parametrization`).
    p_r : float
        Fixed remanence ``P_R``, C/m^2 (a scale convention).
    thickness_um : float or None
        Layer thickness, um. None: take it from the sweeps' metadata, else from
        ``fallback_thickness_um`` (a profile's ``[stack]``), else fit in volts (thickness 1 um,
        so the field in MV/m equals the voltage in V).
    fallback_thickness_um : float or None
        Layer thickness for sweeps whose metadata does not give one, um.
    window_s : (float, float) or None
        Only samples with ``t0 <= t < t1`` enter the residual; the model still runs from t = 0.
    n_coercive_fit : int
        Coercive nodes used during the fit (the identified model has 256).
    field_step : float
        During the fit the hysteresis is evaluated only where the field has moved by more than
        ``field_step`` times its peak magnitude since the last evaluated sample, and at every
        turning point; linear interpolation in between (0 evaluates every sample).
    max_nfev : int
        Budget of residual evaluations of the solver (per stage).
    density : {"parametric", "discrete"}
        ``discrete`` refines the lognormal fit with a general coercive density.
    n_density_nodes : int
        Nodes of the discrete coercive density.
    smoothing : float
        Tikhonov weight lambda of the discrete density's second differences (dimensionless).
    """

    mass_kg: float = 0.05
    p_r: float = 0.3
    thickness_um: float | None = None
    fallback_thickness_um: float | None = None
    window_s: Window = None
    n_coercive_fit: int = 96
    field_step: float = 0.004
    max_nfev: int = 300
    density: Literal["parametric", "discrete"] = "parametric"
    n_density_nodes: int = 24
    smoothing: float = 1e-6

    @property
    def scales(self) -> pz.Scales:
        return pz.Scales(self.mass_kg, self.p_r)


def settings_from_table(t: Table | None, base: Settings = Settings()) -> Settings:
    """Settings from a profile's ``[identify]`` table (keys ``mass_kg``, ``p_r_C_per_m2``,
    ``thickness_um``, ``n_coercive_fit``, ``field_step``, ``max_nfev``, ``density``,
    ``n_density_nodes``, ``smoothing``); missing keys keep ``base``."""
    if t is None:
        return base
    thick = t.number("thickness_um", positive=True) if t.has("thickness_um") else base.thickness_um
    settings = Settings(
        fallback_thickness_um=base.fallback_thickness_um,
        mass_kg=t.number("mass_kg", base.mass_kg, positive=True),
        p_r=t.number("p_r_C_per_m2", base.p_r, positive=True), thickness_um=thick,
        window_s=base.window_s, n_coercive_fit=t.integer("n_coercive_fit", base.n_coercive_fit,
                                                         minimum=4),
        field_step=t.number("field_step", base.field_step, nonnegative=True),
        max_nfev=t.integer("max_nfev", base.max_nfev, minimum=1),
        density=t.string("density", base.density, choices=("parametric", "discrete")),  # type: ignore[arg-type]
        n_density_nodes=t.integer("n_density_nodes", base.n_density_nodes, minimum=3),
        smoothing=t.number("smoothing", base.smoothing, nonnegative=True))
    t.reject_unknown()
    return settings


@dataclass(frozen=True)
class Estimate:
    """One fitted parameter with its approximate 1-sigma interval (0 for fixed ones)."""

    name: str
    value: float
    stderr: float
    unit: str
    fixed: bool = False


@dataclass(frozen=True)
class SweepError:
    """Error of a model on one sweep (over its judged window), um."""

    file: str
    rms_um: float
    max_um: float
    range_um: float
    n_samples: int

    @property
    def rms_pct(self) -> float:
        return 100.0 * self.rms_um / self.range_um

    @property
    def max_pct(self) -> float:
        return 100.0 * self.max_um / self.range_um


@dataclass(frozen=True)
class FitResult:
    """Outcome of :func:`fit`: the model, parameters, per-sweep errors and the solver's status.

    ``success`` is True only if the solver reports convergence (status > 0) and the result is
    finite; a fit stopped by ``max_nfev`` or failing is reported as such.
    """

    model: td.Transducer
    parameters: tuple[Estimate, ...]
    sweeps: tuple[SweepError, ...]
    success: bool
    status: int
    message: str
    nfev: int
    seconds: float
    thickness_known: bool
    x: FloatArray = field(repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the ``--json`` output of ``afmctl identify``)."""
        return {
            "success": self.success, "status": self.status, "message": self.message,
            "nfev": self.nfev, "seconds": round(self.seconds, 3),
            "thickness_known": self.thickness_known,
            "parameters": {p.name: {"value": _finite(p.value), "stderr": _finite(p.stderr),
                                    "unit": p.unit, "fixed": p.fixed} for p in self.parameters},
            "sweeps": [{"file": s.file, "rms_um": s.rms_um, "max_um": s.max_um,
                        "range_um": s.range_um, "rms_pct": s.rms_pct, "max_pct": s.max_pct,
                        "n_samples": s.n_samples} for s in self.sweeps],
        }


def _finite(v: float) -> float | None:
    """JSON has no NaN/inf: non-finite values become null."""
    return v if np.isfinite(v) else None


# ----------------------------------------------------------------------------------------------
# solver and uncertainty
# ----------------------------------------------------------------------------------------------


Space = pz.LognormalSpace | pz.DiscreteSpace


def _residual_fn(space: Space, y: FloatArray) -> Callable[[FloatArray], FloatArray]:
    def residual(x: FloatArray) -> FloatArray:
        return np.concatenate((pz.project(space.design(x), y)[1], space.penalty(x)))

    return residual


def _solve(space: Space, x0: FloatArray, y: FloatArray, max_nfev: int) -> optimize.OptimizeResult:
    lo, hi = space.bounds()
    x0 = np.clip(x0, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    return optimize.least_squares(_residual_fn(space, y), x0, bounds=(lo, hi),
                                  x_scale=space.x_scale, diff_step=1e-6, max_nfev=max_nfev)


def _covariance(space: Space, x: FloatArray, beta: FloatArray, y: FloatArray) -> FloatArray:
    """``s^2 (J^T J)^+`` for the full internal vector ``(x, g1, g2, offset)`` (data rows only)."""
    a0 = space.design(x)
    r0 = y - a0 @ beta
    cols = []
    for i in range(x.size):
        step = 1e-5 * max(1.0, abs(float(x[i])))
        xs = x.copy()
        xs[i] += step
        cols.append(-((space.design(xs) - a0) @ beta) / step)
    jac = np.column_stack(cols + [-a0])
    s2 = float(r0 @ r0) / max(1, y.size - jac.shape[1])
    return s2 * np.linalg.pinv(jac.T @ jac)


def _estimates(space: Space, x: FloatArray, beta: FloatArray, cov: FloatArray,
               settings: Settings) -> tuple[Estimate, ...]:
    """Delta-method 1-sigma for the physical parameters; m and P_R reported as fixed."""
    p = np.concatenate((x, beta))
    n = x.size

    def values(q: FloatArray) -> FloatArray:
        return np.array([v for _, v, _ in pz.describe(space.model(q[:n], q[n:], 1.0))])

    f0 = values(p)
    jac = np.empty((f0.size, p.size))
    for i in range(p.size):
        h = 1e-6 * max(1.0, abs(p[i]))
        pp = p.copy()
        pp[i] += h
        jac[:, i] = (values(pp) - f0) / h
    var = np.einsum("ij,jk,ik->i", jac, cov, jac)
    described = pz.describe(space.model(x, beta, 1.0))
    out = [Estimate(name, float(v), float(np.sqrt(max(s, 0.0))), unit)
           for (name, v, unit), s in zip(described, var, strict=True)]
    out += [Estimate("m", settings.mass_kg, 0.0, "kg", fixed=True),
            Estimate("p_r", settings.p_r, 0.0, "C/m^2", fixed=True)]
    return tuple(out)


def resolve_thickness(sweeps: Sequence[Sweep], settings: Settings) -> tuple[float, bool]:
    """Layer thickness (um) for the fit and whether it is known (else 1.0: fit in volts)."""
    if settings.thickness_um is not None:
        return settings.thickness_um, True
    known = {s.thickness_um for s in sweeps if s.thickness_um is not None}
    if len(known) > 1:
        raise FitInputError(f"sweeps disagree on layer_thickness_um: {sorted(known)}")
    if known:
        return known.pop(), True
    fallback = settings.fallback_thickness_um
    return (fallback, True) if fallback is not None else (1.0, False)


# ----------------------------------------------------------------------------------------------
# public entry points
# ----------------------------------------------------------------------------------------------


def predict(model: td.Transducer, voltage_v: FloatArray, dt: float,
            gain: float = 1.0) -> FloatArray:
    """Displacement (um) the model predicts for a voltage history, as the sensor reads it.

    From the depoled state with the first voltage applied quasi-statically (as every sweep is
    assumed to start), through the model's effects (:mod:`afmctl.effects`, none for a model of
    the paper's form) with applied-voltage gain ``gain``.
    """
    chain = fx.compile_chain(model.effects, dt)
    v = gain * np.asarray(voltage_v, dtype=float)
    v, _ = fx.lag(chain, v, float(v[0]))
    u, _, _ = td.simulate(td.compile_model(model, dt), v, td.initial(model, "depoled", v[0]))
    return fx.measure(chain, u, *fx.rest(chain, float(u[0])))[0]


def sweep_error(model: td.Transducer, sweep: Sweep, window_s: Window = None) -> SweepError:
    """RMS, max and range (um) of ``measured - predicted`` on ``sweep`` (within ``window_s``)."""
    m = sweep.mask(window_s)
    err = (sweep.displacement_um - predict(model, sweep.voltage_v, sweep.dt))[m]
    y = sweep.displacement_um[m]
    return SweepError(sweep.path or sweep.name, float(np.sqrt(np.mean(err ** 2))),
                      float(np.max(np.abs(err))), float(np.ptp(y)), int(m.sum()))


def _stage(space: Space, x0: FloatArray, y: FloatArray, settings: Settings,
           say: Callable[[str], None], label: str) -> tuple[optimize.OptimizeResult, FloatArray]:
    sol = _solve(space, x0, y, settings.max_nfev)
    say(f"{label}: {sol.message} (status {sol.status}, {sol.nfev} evaluations)")
    beta, _ = pz.project(space.design(sol.x), y)
    return sol, beta


def fit(sweeps: Sequence[Sweep], settings: Settings = Settings(),
        progress: Callable[[str], None] | None = None) -> FitResult:
    """Fit the transducer jointly to ``sweeps`` by least squares (variable projection).

    Parameters
    ----------
    sweeps : sequence of Sweep
        Each simulated from its own start (depoled, first voltage applied quasi-statically).
    settings : Settings
    progress : callable, optional
        Receives one-line progress messages (the CLI prints them on stderr).

    Returns
    -------
    FitResult
        The model (default node counts for the lognormal density), parameters with 1-sigma,
        per-sweep errors of that model at the full rate, and the solver's status.

    Examples
    --------
    >>> from afmctl import sweeps as sw
    >>> true = pz.to_model(np.array([1.0, 0.4, 0.3, 0.36, 250.0, 0.25]),
    ...                    np.array([10.0, 0.5, 0.0]), pz.Scales(), 100.0)
    >>> v = sw.triangle(27.9, 150.0, 3, 5000.0)
    >>> s = sw.from_arrays(v, predict(true, v, 2e-4), 5000.0, {"layer_thickness_um": "100"})
    >>> fit([s]).sweeps[0].rms_um < 0.05
    True
    """
    say = progress or (lambda _msg: None)
    t0 = time.perf_counter()
    thickness, known = resolve_thickness(sweeps, settings)
    try:
        preps = [pz.prepare(s, thickness, settings.field_step, settings.window_s) for s in sweeps]
    except ValueError as exc:
        raise FitInputError(str(exc)) from None
    y = np.concatenate([p.y for p in preps])
    space: Space = pz.LognormalSpace(preps, settings.scales, settings.n_coercive_fit)
    coarse = pz.LognormalSpace(preps, settings.scales, 24)
    x0 = coarse.start(lambda x: float(np.sum(_residual_fn(coarse, y)(x) ** 2)))
    say("starting guess " + ", ".join(f"{n}={v:.4g}" for n, v in
                                        zip(pz.THETA_NAMES, np.exp(x0), strict=True)))
    sol, beta = _stage(space, x0, y, settings, say, "lognormal density")
    nfev, ok = sol.nfev, sol.success and sol.status > 0
    if settings.density == "discrete":
        space, x0 = pz.DiscreteSpace.around(np.exp(sol.x), preps, settings.scales,
                                            settings.n_density_nodes, settings.smoothing,
                                            float(beta[0]))
        sol, beta = _stage(space, x0, y, settings, say, "discrete density")
        nfev, ok = nfev + sol.nfev, ok and sol.success and sol.status > 0
    cov = _covariance(space, sol.x, beta, y)
    model = space.model(sol.x, beta, thickness)
    errors = tuple(sweep_error(model, s, settings.window_s) for s in sweeps)
    ok = bool(ok and np.all(np.isfinite(sol.x)) and np.all(np.isfinite(beta)))
    return FitResult(model, _estimates(space, sol.x, beta, cov, settings), errors, ok,
                     int(sol.status), str(sol.message), int(nfev), time.perf_counter() - t0,
                     known, sol.x)
