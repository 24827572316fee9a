"""Joint least-squares identification of the stage model from sweeps (paper Sections 2.2 and 4).

The model is the transducer of :mod:`afmctl.transducer`: field ``E = V / thickness`` drives the
homogenized polarization (13) with lognormal ``nu_1`` and normal ``nu_2`` (criteria (12)), which
forces the rod (16). Its physical parameters are not all identifiable from displacement alone:

* ``(m, c, k, a1~, a2~)`` enter (16) only through ``c/m``, ``k/m``, ``a1~/m``, ``a2~/m``;
* ``P -> s P`` (``eta -> eta/s``, ``P_R -> s P_R``) with ``a1~ -> a1~/s``, ``a2~ -> a2~/s^2``
  leaves the force unchanged.

So the fit works in a well-scaled internal parametrization and ``m`` and ``P_R`` are fixed by
convention (reported as fixed). Writing ``Q = eta P = E + r H(E)`` with ``r = eta P_R`` (MV/m) and
``H = sum_i v_i erf(y_i / (sqrt(2) sigma_I))`` in [-1, 1] (the closed-form ``normal`` kernel of
:mod:`afmctl.hysteresis`), the rod (16) becomes

``u = g1 L[Q] + g2 L[Q^2] + offset``

where ``L`` is the unit-DC-gain second-order filter with natural frequency ``f_n`` and damping
ratio ``zeta``, ``g1 = 1e6 a1~ / (k eta)`` (um per MV/m) and ``g2 = 1e6 a2~ / (k eta^2)``. The
nonlinear parameters ``theta = (median E_c, sigma_ln, sigma_I, r, f_n, zeta)`` are fitted by
:func:`scipy.optimize.least_squares` (in logs, with bounds); the linear ones ``(g1, g2, offset)``
are projected out by linear least squares at every evaluation (variable projection).

The state is carried through each sweep from its start: depoled, then the first voltage applied
quasi-statically (:func:`afmctl.transducer.initial`). For speed the hysteresis is evaluated during
the fit on a decimated copy of the field that keeps every turning point (the model (13) depends
only on them) and interpolated back; the rod runs at the full rate. Per-sweep errors, however,
are always those of the final model at the default node counts and the full rate.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import optimize

from afmctl import hysteresis as hy
from afmctl import rod as rd
from afmctl import transducer as td
from afmctl.sweeps import Sweep
from afmctl.tomlfile import Table

FloatArray = NDArray[np.float64]
THETA_NAMES = ("median_MV_per_m", "sigma_ln", "std_MV_per_m", "r_MV_per_m", "natural_hz",
               "damping_ratio")
Window = tuple[float, float] | None


@dataclass(frozen=True)
class Settings:
    """Options of :func:`fit`.

    Parameters
    ----------
    mass_kg : float
        Fixed effective mass ``m`` of (16), kg (a scale convention, see the module docstring).
    p_r : float
        Fixed remanence ``P_R``, C/m^2 (a scale convention).
    thickness_um : float or None
        Layer thickness, um. None: take it from the sweeps' metadata, or fit in volts
        (thickness 1 um, so the field in MV/m equals the voltage in V) if they do not give it.
    window_s : (float, float) or None
        Only samples with ``t0 <= t < t1`` enter the residual; the model still runs from t = 0.
    n_coercive_fit : int
        Coercive nodes used during the fit (the result uses ``Polarization``'s default 256).
    field_step : float
        During the fit the hysteresis is evaluated only where the field has moved by more than
        ``field_step`` times its peak magnitude since the last evaluated sample, and at every
        turning point; linear interpolation in between (0 evaluates every sample).
    max_nfev : int
        Budget of residual evaluations of the solver.
    """

    mass_kg: float = 0.05
    p_r: float = 0.3
    thickness_um: float | None = None
    window_s: Window = None
    n_coercive_fit: int = 64
    field_step: float = 0.004
    max_nfev: int = 300


def settings_from_table(t: Table | None, base: Settings = Settings()) -> Settings:
    """Settings from a profile's ``[identify]`` table (keys ``mass_kg``, ``p_r_C_per_m2``,
    ``thickness_um``, ``n_coercive_fit``, ``field_step``, ``max_nfev``); missing keys keep
    ``base``."""
    if t is None:
        return base
    thick = t.number("thickness_um", positive=True) if t.has("thickness_um") else base.thickness_um
    return Settings(
        mass_kg=t.number("mass_kg", base.mass_kg, positive=True),
        p_r=t.number("p_r_C_per_m2", base.p_r, positive=True), thickness_um=thick,
        window_s=base.window_s, n_coercive_fit=t.integer("n_coercive_fit", base.n_coercive_fit,
                                                         minimum=4),
        field_step=t.number("field_step", base.field_step, nonnegative=True),
        max_nfev=t.integer("max_nfev", base.max_nfev, minimum=1))


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
    theta: FloatArray = field(repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the ``--json`` output of ``afmctl identify``)."""
        return {
            "success": self.success, "status": self.status, "message": self.message,
            "nfev": self.nfev, "seconds": round(self.seconds, 3),
            "thickness_known": self.thickness_known,
            "parameters": {p.name: {"value": p.value, "stderr": p.stderr, "unit": p.unit,
                                    "fixed": p.fixed} for p in self.parameters},
            "sweeps": [{"file": s.file, "rms_um": s.rms_um, "max_um": s.max_um,
                        "range_um": s.range_um, "rms_pct": s.rms_pct, "max_pct": s.max_pct,
                        "n_samples": s.n_samples} for s in self.sweeps],
        }


# ----------------------------------------------------------------------------------------------
# internal parametrization <-> model
# ----------------------------------------------------------------------------------------------


def to_model(theta: FloatArray, gains: FloatArray, settings: Settings,
             thickness_um: float, n_coercive: int = 256) -> td.Transducer:
    """Physical model from ``theta`` (see :data:`THETA_NAMES`, linear values) and
    ``gains = (g1 um/(MV/m), g2 um/(MV/m)^2, offset um)``.

    ``eta = r / P_R``, ``k = m (2 pi f_n)^2``, ``c = 2 zeta sqrt(k m)``, ``a1~ = g1 k eta / 1e6``,
    ``a2~ = g2 k eta^2 / 1e6`` (eq. (16) with u in um).
    """
    median, sig, std, r, fn, zeta = (float(x) for x in theta)
    g1, g2, off = (float(x) for x in gains)
    eta = r / settings.p_r
    m = settings.mass_kg
    k = m * (2 * math.pi * fn) ** 2
    rod = rd.Rod(m=m, c=2 * zeta * math.sqrt(k * m), k=k, a1=g1 * k * eta / 1e6,
                 a2=g2 * k * eta ** 2 / 1e6, offset_um=off)
    pol = hy.Polarization(eta=eta, p_r=settings.p_r, coercive=hy.Lognormal(median, sig),
                          interaction=hy.Normal(std), n_coercive=n_coercive)
    return td.Transducer(pol, rod, thickness_um)


def _physical(p: FloatArray, settings: Settings) -> FloatArray:
    """Free physical parameters from the internal vector ``p = (log theta, g1, g2, offset)``."""
    model = to_model(np.exp(p[:6]), p[6:], settings, 1.0)
    pol, rod = model.polarization, model.rod
    return np.array([pol.eta, pol.coercive.median, pol.coercive.sigma,  # type: ignore[union-attr]
                     pol.interaction.std, rod.c, rod.k, rod.a1, rod.a2,  # type: ignore[union-attr]
                     rod.offset_um, rod.natural_hz, rod.damping_ratio])


PHYSICAL = (("eta", "(MV/m)/(C/m^2)"), ("coercive_median", "MV/m"), ("coercive_sigma_ln", "1"),
            ("interaction_std", "MV/m"), ("c", "N s/m"), ("k", "N/m"), ("a1", "N/(C/m^2)"),
            ("a2", "N/(C/m^2)^2"), ("offset", "um"), ("natural_frequency", "Hz"),
            ("damping_ratio", "1"))


# ----------------------------------------------------------------------------------------------
# data preparation and the residual
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Prepared:
    field: FloatArray       # MV/m, full rate
    keep: NDArray[np.intp]  # samples on which the hysteresis is evaluated during the fit
    mask: NDArray[np.bool_]  # samples entering the residual
    y: FloatArray           # measured displacement on the mask, um
    dt: float


def turning_points(x: FloatArray) -> NDArray[np.intp]:
    """Indices of the local extrema of ``x`` (ends of every monotone run), plus both ends."""
    d = np.sign(np.diff(x))
    nz = np.flatnonzero(d)
    if nz.size < 2:
        return np.array([0, x.size - 1])
    flips = nz[1:][d[nz[1:]] != d[nz[:-1]]]
    return np.unique(np.concatenate(([0, x.size - 1], flips)))


def decimation(field: FloatArray, step: float) -> NDArray[np.intp]:
    """Samples on which to evaluate the hysteresis: every turning point, and one whenever the
    accumulated field variation has grown by ``step`` (same units as ``field``).

    Model (13) depends only on the turning points; in between the output is a smooth function of
    the field, so linear interpolation over steps ``step`` errs by O(step^2).
    """
    if step <= 0:
        return np.arange(field.size)
    travel = np.concatenate(([0.0], np.cumsum(np.abs(np.diff(field)))))
    bins = np.floor(travel / step)
    new = np.flatnonzero(np.diff(bins) > 0) + 1
    return np.unique(np.concatenate((new, turning_points(field))))


def _prepare(sweep: Sweep, thickness_um: float, settings: Settings) -> _Prepared:
    e = sweep.voltage_v / thickness_um
    keep = decimation(e, settings.field_step * float(np.max(np.abs(e))))
    mask = sweep.mask(settings.window_s)
    if not mask.any():
        raise ValueError(f"{sweep.name}: no samples in the fit window {settings.window_s}")
    return _Prepared(e, keep, mask, sweep.displacement_um[mask], sweep.dt)


def _hysteresis(theta: FloatArray, prep: _Prepared, n_coercive: int) -> FloatArray:
    """``Q = E + r H(E)`` (MV/m) at the full rate, evaluated on the kept samples (13)."""
    median, sig, std, r = theta[:4]
    pol = hy.Polarization(eta=1.0, p_r=float(r), coercive=hy.Lognormal(float(median), float(sig)),
                          interaction=hy.Normal(float(std)), n_coercive=n_coercive)
    q, _ = hy.run(pol, prep.field[prep.keep], hy.initial_state(pol))
    if prep.keep.size == prep.field.size:
        return q
    return np.interp(np.arange(prep.field.size), prep.keep, q)


@functools.lru_cache(maxsize=64)
def _unit_rod(fn: float, zeta: float, dt: float) -> tuple[rd.Rod, rd.Discrete]:
    """Rod (16) with m = 1 and unit DC gain per unit force/k, and its exact discretization (18)."""
    w = 2 * np.pi * fn
    rod = rd.Rod(m=1.0, c=2 * zeta * w, k=w * w, a1=1.0)
    return rod, rd.discretize(rod, dt)


def _unit_filter(x: FloatArray, fn: float, zeta: float, dt: float) -> FloatArray:
    """``L[x]``: the rod normalized to unit DC gain, at rest in equilibrium with ``x[0]``."""
    rod, disc = _unit_rod(float(fn), float(zeta), float(dt))
    u, _ = rd.simulate(rod, disc, x * (rod.k * 1e-6), np.array([x[0] * 1e-6, 0.0]))
    return u


def _design(theta: FloatArray, preps: Sequence[_Prepared], n_coercive: int) -> FloatArray:
    """Columns ``[L[Q], L[Q^2], 1]`` on the residual samples of all sweeps, stacked."""
    blocks = []
    for prep in preps:
        q = _hysteresis(theta, prep, n_coercive)
        lq = _unit_filter(q, theta[4], theta[5], prep.dt)
        lq2 = _unit_filter(q * q, theta[4], theta[5], prep.dt)
        blocks.append(np.column_stack((lq, lq2, np.ones_like(q)))[prep.mask])
    return np.vstack(blocks)


def _project(a: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Linear least-squares gains and the residual ``y - A beta``."""
    beta, *_ = np.linalg.lstsq(a.T @ a, a.T @ y, rcond=None)  # normal equations: 3 columns
    return beta, y - a @ beta


def _residual_fn(preps: Sequence[_Prepared], n_coercive: int) -> Callable[[FloatArray], FloatArray]:
    y = np.concatenate([p.y for p in preps])

    def residual(log_theta: FloatArray) -> FloatArray:
        return _project(_design(np.exp(log_theta), preps, n_coercive), y)[1]

    return residual


# ----------------------------------------------------------------------------------------------
# starting guess, solver, uncertainty
# ----------------------------------------------------------------------------------------------


def initial_guess(preps: Sequence[_Prepared], n_coercive: int = 24) -> FloatArray:
    """Starting ``theta`` from the data alone: field range scales a small grid over coercive
    median and hysteretic weight (rod static), then a grid over the natural frequency."""
    e_max = max(float(np.max(np.abs(p.field))) for p in preps) or 1.0
    nyquist = 0.5 / min(p.dt for p in preps)
    res = _residual_fn(preps, n_coercive)

    def cost(theta: tuple[float, ...]) -> float:
        return float(np.sum(res(np.log(np.array(theta))) ** 2))

    static = 0.45 * nyquist
    grid = [(mf * e_max, 0.5, 0.3 * mf * e_max, rf * e_max, static, 0.5)
            for mf in (0.2, 0.5, 0.9) for rf in (0.05, 0.2, 0.6)]
    best = min(grid, key=cost)
    freqs = [f for f in (30.0, 100.0, 300.0, 1000.0, 3000.0) if f < 0.45 * nyquist]
    best = min([best] + [best[:4] + (f, 0.3) for f in freqs], key=cost)
    return np.array(best)


def _bounds(theta0: FloatArray, preps: Sequence[_Prepared]) -> tuple[FloatArray, FloatArray]:
    e_max = max(float(np.max(np.abs(p.field))) for p in preps) or 1.0
    nyquist = 0.5 / min(p.dt for p in preps)
    lo = np.log([1e-3 * e_max, 0.02, 1e-3 * e_max, 1e-4 * e_max, 0.5, 0.003])
    hi = np.log([10 * e_max, 3.0, 10 * e_max, 100 * e_max, 20 * nyquist, 5.0])
    return lo, hi


def _covariance(log_theta: FloatArray, beta: FloatArray, preps: Sequence[_Prepared],
                n_coercive: int, y: FloatArray) -> tuple[FloatArray, float]:
    """``s^2 (J^T J)^-1`` for the full internal vector ``(log theta, g1, g2, offset)``."""
    a0 = _design(np.exp(log_theta), preps, n_coercive)
    r0 = y - a0 @ beta
    cols = []
    for i in range(log_theta.size):
        step = 1e-5
        th = log_theta.copy()
        th[i] += step
        cols.append(-(_design(np.exp(th), preps, n_coercive) @ beta - a0 @ beta) / step)
    jac = np.column_stack(cols + [-a0])
    dof = max(1, y.size - jac.shape[1])
    s2 = float(r0 @ r0) / dof
    return s2 * np.linalg.pinv(jac.T @ jac), s2


def _estimates(p: FloatArray, cov: FloatArray, settings: Settings) -> tuple[Estimate, ...]:
    """Delta-method 1-sigma for the physical parameters; m and P_R reported as fixed."""
    f0 = _physical(p, settings)
    jac = np.empty((f0.size, p.size))
    for i in range(p.size):
        h = 1e-6 * max(1.0, abs(p[i]))
        pp = p.copy()
        pp[i] += h
        jac[:, i] = (_physical(pp, settings) - f0) / h
    var = np.einsum("ij,jk,ik->i", jac, cov, jac)
    out = [Estimate(name, float(v), float(np.sqrt(max(s, 0.0))), unit)
           for (name, unit), v, s in zip(PHYSICAL, f0, var, strict=True)]
    out += [Estimate("m", settings.mass_kg, 0.0, "kg", fixed=True),
            Estimate("p_r", settings.p_r, 0.0, "C/m^2", fixed=True)]
    return tuple(out)


def resolve_thickness(sweeps: Sequence[Sweep], settings: Settings) -> tuple[float, bool]:
    """Layer thickness (um) for the fit and whether it is known (else 1.0: fit in volts)."""
    if settings.thickness_um is not None:
        return settings.thickness_um, True
    known = {s.thickness_um for s in sweeps if s.thickness_um is not None}
    if len(known) > 1:
        raise ValueError(f"sweeps disagree on layer_thickness_um: {sorted(known)}")
    return (known.pop(), True) if known else (1.0, False)


# ----------------------------------------------------------------------------------------------
# public entry points
# ----------------------------------------------------------------------------------------------


def predict(model: td.Transducer, voltage_v: FloatArray, dt: float) -> FloatArray:
    """Displacement (um) the model predicts for a voltage history, from the depoled state with the
    first voltage applied quasi-statically (as every sweep is assumed to start)."""
    v = np.asarray(voltage_v, dtype=float)
    u, _, _ = td.simulate(td.compile_model(model, dt), v, td.initial(model, "depoled", v[0]))
    return u


def sweep_error(model: td.Transducer, sweep: Sweep, window_s: Window = None) -> SweepError:
    """RMS, max and range (um) of ``measured - predicted`` on ``sweep`` (within ``window_s``)."""
    m = sweep.mask(window_s)
    err = (sweep.displacement_um - predict(model, sweep.voltage_v, sweep.dt))[m]
    y = sweep.displacement_um[m]
    return SweepError(sweep.path or sweep.name, float(np.sqrt(np.mean(err ** 2))),
                      float(np.max(np.abs(err))), float(np.ptp(y)), int(m.sum()))


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
        The model at the default node counts, parameters with 1-sigma, per-sweep errors of that
        model, and the solver's status.

    Examples
    --------
    >>> from afmctl import sweeps as sw
    >>> true = to_model(np.array([1.0, 0.4, 0.3, 0.36, 250.0, 0.25]),
    ...                 np.array([10.0, 0.5, 0.0]), Settings(), 100.0)
    >>> v = sw.triangle(27.9, 150.0, 3, 5000.0)
    >>> s = sw.from_arrays(v, predict(true, v, 2e-4), 5000.0, {"layer_thickness_um": "100"})
    >>> fit([s]).sweeps[0].rms_um < 0.05
    True
    """
    say = progress or (lambda _msg: None)
    t0 = time.perf_counter()
    thickness, known = resolve_thickness(sweeps, settings)
    preps = [_prepare(s, thickness, settings) for s in sweeps]
    n_c = settings.n_coercive_fit
    theta0 = initial_guess(preps)
    say("starting guess " + ", ".join(f"{n}={v:.4g}" for n, v in zip(THETA_NAMES, theta0,
                                                                        strict=True)))
    lo, hi = _bounds(theta0, preps)
    x0 = np.clip(np.log(theta0), lo + 1e-9, hi - 1e-9)
    sol = optimize.least_squares(_residual_fn(preps, n_c), x0, bounds=(lo, hi), x_scale=1.0,
                                 diff_step=1e-6, max_nfev=settings.max_nfev)
    say(f"solver: {sol.message} (status {sol.status}, {sol.nfev} evaluations)")
    y = np.concatenate([p.y for p in preps])
    beta, _ = _project(_design(np.exp(sol.x), preps, n_c), y)
    cov, _ = _covariance(sol.x, beta, preps, n_c, y)
    p = np.concatenate((sol.x, beta))
    model = to_model(np.exp(sol.x), beta, settings, thickness)
    errors = tuple(sweep_error(model, s, settings.window_s) for s in sweeps)
    ok = bool(sol.success and sol.status > 0 and np.all(np.isfinite(p)))
    return FitResult(model, _estimates(p, cov, settings), errors, ok, int(sol.status),
                     str(sol.message), int(sol.nfev), time.perf_counter() - t0, known,
                     np.exp(sol.x))
