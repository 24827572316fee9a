"""Joint least-squares identification of the stage model from sweeps (paper Sections 2.2 and 4).

The model is the transducer of :mod:`afmctl.model.transducer`: field ``E = V / thickness`` drives the
homogenized polarization (13), which forces the rod (16). The fit runs in the well-scaled
internal parametrization of :mod:`afmctl.fit.parametrization` (``m`` and ``P_R`` fixed by convention
and reported as fixed): the nonlinear parameters go to :func:`scipy.optimize.least_squares` (in
logs, with bounds), the gains ``(g1, g2, offset)`` are projected out by linear least squares at
every evaluation (variable projection). First a lognormal ``nu_1`` / normal ``nu_2`` fit (six
nonlinear parameters); optionally (``density="discrete"``) a general nonnegative coercive density
on fixed nodes, smoothed by a Tikhonov penalty, refined from it. The interaction density stays
normal (the closed-form kernel; a discrete ``nu_2`` would need the much slower grid kernel).

The state is carried through each sweep from its start: depoled, then the first voltage applied
quasi-statically (:func:`afmctl.model.transducer.initial`). For speed the hysteresis is evaluated during
the fit on a decimated copy of the field that keeps every turning point (the model (13) depends
only on them) and interpolated back; the rod runs at the full rate. Per-sweep errors, however,
are always those of the final model at the default node counts and the full rate.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy import optimize
from threadpoolctl import threadpool_limits

from afmctl.errors import FitInputError
from afmctl.files import modelfile as mf
from afmctl.files.sweepfile import Sweep
from afmctl.files.tomlfile import Table
from afmctl.fit import cores
from afmctl.fit import density as dn
from afmctl.fit import noise as ns
from afmctl.fit import parametrization as pz
from afmctl.fit import representation as rep
from afmctl.fit import stall
from afmctl.fit import uncertainty as unc
from afmctl.fit.prediction import (
    SweepError,
    finite_or_none,
    judge_set,
    predict,
    predict_set,
    start_state,
    sweep_error,
)
from afmctl.fit.uncertainty import Estimate
from afmctl.model import hysteresis as hy
from afmctl.model import transducer as td

FloatArray = NDArray[np.float64]
Window = tuple[float, float] | None
#: A sweep is at the noise floor when its fit RMS is at most this many times its sensor noise.
FLOOR = 1.5
#: Above this many times its noise a sweep is named on stderr (``afmctl identify``).
WARN = 2.0
#: A different start state must lower the sum of squares by this many noise variances.
START_MARGIN = 25.0
#: The grid is asked between the HEM's first solve and its refit from re-chosen starts only if
#: those starts left more than this share of the first solve's worst error (sweep RMS / noise).
STARTS_LEFT = 0.5
#: The first solve from the first start, where the grid may be fitted after it
#: (:func:`solve_round` with ``enough``), stops where it stalls (:mod:`afmctl.fit.stall`) while
#: some sweep is over :data:`afmctl.fit.representation.EARLY` times its noise. The starts are
#: then re-chosen and the grid asked as before; if the grid does not decide, the solve goes on
#: from where it stopped (:func:`global_fit`).
#: Two sweeps' sensor zeros disagree when they differ by more than this many times the larger of
#: their fit RMS (or noise): more than a misfit's mean could shift a fitted offset.
OFFSET_AGREE = 5.0
#: Above this many times its noise on some sweep, the fit tries a general coercive density
#: (kept if it lowers the sum of squares by more than 2 noise variances per added parameter and
#: leaves no sweep above its noise and more than :data:`REFINE_WORSE` times its lognormal
#: misfit: the density is quasi-static and shared by every sweep, so a density that trades the
#: slow sweep for a fast one absorbs dynamics, e.g. a mode below the rod ringing after the fast
#: triangle's corners).
REFINE = 1.25
REFINE_WORSE = 1.1
#: The fit is polished with more coercive nodes if they change a sweep by this share of its noise.
POLISH_SHARE = 0.3
#: At most this many coercive nodes during the fit (the model itself gets N_c).
POLISH_MAX_NODES = 512
#: Largest error (um) the coercive-field discretization of an identified model may add.
DISCRETIZATION_UM = 0.01

__all__ = ["Estimate", "FitResult", "Settings", "SweepError", "fit", "predict", "predict_set",
           "judge_set", "start_state", "sweep_error", "envelope", "n_coercive_for",
           "resolve_thickness", "FLOOR", "WARN"]


@dataclass(frozen=True)
class Settings:
    """Options of :func:`fit`.

    Parameters
    ----------
    mass_kg : float
        Fixed effective mass ``m`` of (16), kg (a scale convention, see
        :mod:`afmctl.fit.parametrization`).
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
    restarts : int
        Further starts tried (the next-best points of the starting grid) while a sweep's fit
        stays above :data:`FLOOR` times its sensor noise.
    density : {"auto", "parametric", "discrete"}
        ``discrete`` refines the lognormal fit with a general coercive density; ``auto`` tries
        that refinement (:mod:`afmctl.fit.density`) when a sweep stays above :data:`REFINE`
        times its noise and keeps it if it lowers the sum of squares by more than 2 noise
        variances per added parameter without leaving a sweep above its noise and more than
        :data:`REFINE_WORSE` times worse; ``parametric`` never does.
    n_density_nodes : int
        Nodes of the discrete coercive density.
    smoothing : float
        Tikhonov weight lambda of the discrete density's second differences (dimensionless).
    representation : {"auto", "hem", "preisach", "bouc-wen"}
        ``auto``: when the parametric HEM stays above the noise floor, also fit the Preisach grid
        with creep (:mod:`afmctl.fit.preisach`) and Bouc-Wen (:mod:`afmctl.fit.boucwen`) and keep
        whichever has the lower held-out error (:mod:`afmctl.fit.representation`); ``hem``
        never; ``preisach`` and ``bouc-wen`` always keep that one.
    """

    mass_kg: float = 0.05
    p_r: float = 0.3
    thickness_um: float | None = None
    fallback_thickness_um: float | None = None
    window_s: Window = None
    n_coercive_fit: int = 96
    field_step: float = 0.004
    max_nfev: int = 300
    restarts: int = 3
    density: Literal["auto", "parametric", "discrete"] = "auto"
    n_density_nodes: int = 24
    smoothing: float = 1e-6
    representation: Literal["auto", "hem", "preisach", "bouc-wen"] = "auto"

    @property
    def scales(self) -> pz.Scales:
        return pz.Scales(self.mass_kg, self.p_r)


def settings_from_table(t: Table | None, base: Settings = Settings()) -> Settings:
    """Settings from a profile's ``[identify]`` table (keys ``mass_kg``, ``p_r_C_per_m2``,
    ``thickness_um``, ``n_coercive_fit``, ``field_step``, ``max_nfev``, ``restarts``, ``density``,
    ``n_density_nodes``, ``smoothing``, ``representation``); missing keys keep ``base``."""
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
        restarts=t.integer("restarts", base.restarts, minimum=0),
        density=t.string("density", base.density,  # type: ignore[arg-type]
                         choices=("auto", "parametric", "discrete")),
        n_density_nodes=t.integer("n_density_nodes", base.n_density_nodes, minimum=3),
        smoothing=t.number("smoothing", base.smoothing, nonnegative=True),
        representation=t.string("representation", base.representation,  # type: ignore[arg-type]
                                choices=("auto", "hem", "preisach", "bouc-wen")))
    t.reject_unknown()
    return settings


@dataclass(frozen=True)
class FitResult:
    """Outcome of :func:`fit`: the model, parameters, per-sweep errors and the solver's status.

    ``success`` is True only if the solver reports convergence (status > 0) and the result is
    finite; a fit stopped by ``max_nfev`` or failing is reported as such. It says nothing about
    how good the fit is: that is ``at_noise_floor`` (every sweep within :data:`FLOOR` times its
    sensor noise). ``finite`` says the model is usable at all (its best point, converged or not).
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
    x: FloatArray = field(repr=False)  # the lognormal fit's log(theta), also after a refinement
    uncertainty: dict[str, Any] = field(default_factory=dict, repr=False)
    envelope: mf.Envelope | None = None
    restarts: int = 0
    finite: bool = True
    representation: str = "hem"
    representations: dict[str, Any] = field(default_factory=dict)
    held_out: tuple[int, ...] = ()  # sweeps judged, not fitted (afmctl.fit.openloops)

    @property
    def at_noise_floor(self) -> bool:
        return all(s.rms_over_noise <= FLOOR for s in self.sweeps)

    def above_floor(self, factor: float = WARN) -> list[SweepError]:
        """The sweeps whose fit RMS exceeds ``factor`` times their sensor noise."""
        return [s for s in self.sweeps if not s.rms_over_noise <= factor]

    @property
    def zero_index(self) -> int:
        """The sweep whose sensor zero is the model's (:func:`afmctl.fit.parametrization.zero_sweep`
        of the sweeps' starts; never a sweep held out of the fit)."""
        return pz.zero_sweep([s.start for s in self.sweeps], self.held_out)

    def offsets_disagreeing(self) -> list[SweepError]:
        """The sweeps whose sensor zero differs from the model's by more than :data:`OFFSET_AGREE`
        times the larger fit RMS (or noise) of the two: the sensor was re-zeroed between them, or
        the sweep's start state does not fit it and its offset absorbed the misfit."""
        z = self.sweeps[self.zero_index]
        return [s for s in self.sweeps if abs(s.offset_um - z.offset_um)
                > OFFSET_AGREE * max(s.rms_um, z.rms_um, s.noise_um, z.noise_um)]

    def record(self, by: str = "identify") -> mf.FitRecord:
        """The model file's ``[fit]`` record: flagged when a sweep is left above :data:`WARN`
        times its sensor noise (the model misses something there)."""
        above = self.above_floor()
        verdict = ("; ".join(f"{Path(s.file).name} left at {s.rms_over_noise:.1f}x its sensor "
                             f"noise" for s in above) + ": the model misses something there"
                   if above else f"every sweep within {WARN:g}x its sensor noise")
        return mf.FitRecord(by, verdict, bool(above), tuple(Path(s.file).name for s in self.sweeps),
                            tuple(min(s.rms_over_noise, 1e9) for s in self.sweeps))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the ``--json`` output of ``afmctl identify``)."""
        return {
            "success": self.success, "status": self.status, "message": self.message,
            "nfev": self.nfev, "seconds": round(self.seconds, 3), "restarts": self.restarts,
            "thickness_known": self.thickness_known, "at_noise_floor": self.at_noise_floor,
            "n_coercive": self.model.polarization.n_coercive,
            "parameters": {p.name: {"value": finite_or_none(p.value), "stderr": finite_or_none(p.stderr),
                                    "unit": p.unit, "fixed": p.fixed} for p in self.parameters},
            "sweeps": [s.to_dict() for s in self.sweeps],
            "uncertainty": self.uncertainty,
            "envelope": None if self.envelope is None else self.envelope.to_dict(),
            "finite": self.finite, "representation": self.representation,
            "representations": self.representations,
            "sensor_zero_file": self.sweeps[self.zero_index].file,
            "offsets_disagree": bool(self.offsets_disagreeing()),
        }


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


def n_coercive_for(model: td.Transducer, fields: Sequence[FloatArray],
                   tol_um: float = DISCRETIZATION_UM,
                   starts: Sequence[str] = ("depoled", "positive", "negative")) -> int:
    """Coercive nodes for ``model`` so the discretization of (13) adds at most ``tol_um`` to the
    displacement over the field histories ``fields`` (MV/m; the identified sweeps span the
    envelope) from each of the ``starts``, from :func:`afmctl.model.hysteresis.n_coercive_for` with the
    rod's static gain
    ``1e6 (|a1| + 2 |a2| P + 3 |a3| P^2) / k`` (um per C/m^2, a bound of the force's slope) at the
    largest polarization reached."""
    pol, rod = model.polarization, model.rod
    e_max = max(float(np.max(np.abs(e))) for e in fields)
    p_max = float(np.max(np.abs(hy.run(pol, np.array([e_max, -e_max, e_max]),
                                       hy.initial_state(pol))[0])))
    gain = 1e6 * (abs(rod.a1) + (2 * abs(rod.a2) + 3 * abs(rod.a3) * p_max) * p_max) / rod.k
    hows = tuple(sorted({"depoled" if s == "previous" else s for s in starts}))
    return hy.n_coercive_for(pol, list(fields), tol_um / max(gain, 1e-300),
                             starts=hows)  # type: ignore[arg-type]


def envelope(sweeps: Sequence[Sweep], thickness_um: float) -> mf.Envelope:
    """The validity envelope of a model identified on ``sweeps``: their voltage and field range,
    frequencies (metadata ``frequency_hz``, else turning points per second / 2) and sample rates."""
    v_lo = min(float(np.min(s.voltage_v)) for s in sweeps)
    v_hi = max(float(np.max(s.voltage_v)) for s in sweeps)

    def freq(s: Sweep) -> float:
        if s.frequency_hz is not None:
            return s.frequency_hz
        n_turns = pz.turning_points(s.voltage_v).size - 2
        return 0.5 * n_turns / max(float(s.time_s[-1] - s.time_s[0]), s.dt)

    return mf.Envelope(v_lo, v_hi, v_lo / thickness_um, v_hi / thickness_um,
                       tuple(round(freq(s), 6) for s in sweeps),
                       tuple(round(1.0 / s.dt, 6) for s in sweeps))


# ----------------------------------------------------------------------------------------------
# the fit
# ----------------------------------------------------------------------------------------------


Space = pz.LognormalSpace | dn.DiscreteSpace


@dataclass
class Problem:
    """The sweeps prepared for the residual, their stacked measurements and noise floors."""

    sweeps: Sequence[Sweep]
    preps: list[pz.Prepared]
    y: FloatArray
    noise: FloatArray
    settings: Settings
    say: Callable[[str], None]
    nfev: int = 0

    def per_sweep(self, r: FloatArray) -> FloatArray:
        """RMS of the stacked residual ``r`` per sweep over its sensor noise."""
        ends = np.cumsum([int(p.mask.sum()) for p in self.preps])
        parts = np.split(r[:ends[-1]], ends[:-1])
        return np.array([np.sqrt(np.mean(q ** 2)) for q in parts]) / self.noise


def _residual_fn(space: Space, y: FloatArray) -> Callable[[FloatArray], FloatArray]:
    def residual(x: FloatArray) -> FloatArray:
        return np.concatenate((pz.project(space.design(x), y)[1], space.penalty(x)))

    return residual


def _cost(space: Space, y: FloatArray, x: FloatArray) -> float:
    return float(np.sum(_residual_fn(space, y)(x) ** 2))


def _solve(space: Space, x0: FloatArray, prob: Problem,
           stop_stalled: bool = False) -> optimize.OptimizeResult:
    """Least squares from ``x0`` (``stop_stalled``: stopped where :func:`_stalled` says)."""
    lo, hi = space.bounds()
    x0 = np.clip(x0, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    sol = optimize.least_squares(_residual_fn(space, prob.y), x0, bounds=(lo, hi),
                                 x_scale=space.x_scale, diff_step=1e-6,
                                 max_nfev=prob.settings.max_nfev, workers=cores.mapped,
                                 callback=_stalled(prob) if stop_stalled else None)
    if sol.status == -2:
        sol.message = stall.message(f"some sweep over {rep.EARLY:g}x its noise")
    prob.nfev += int(sol.nfev)
    return sol


def _stalled(prob: Problem) -> Callable[[optimize.OptimizeResult], None]:
    """:func:`afmctl.fit.stall.callback`, far off while some sweep is over
    :data:`afmctl.fit.representation.EARLY` times its noise."""
    return stall.callback(lambda r: float(np.max(prob.per_sweep(r.fun))) > rep.EARLY)


def choose_starts(space: pz.LognormalSpace, x: FloatArray, y: FloatArray,
                  margin: float = 0.0) -> pz.LognormalSpace:
    """Each sweep's initial hysteresis state among :data:`afmctl.fit.parametrization.STARTS` at the
    parameters ``x``: the best joint assignment (all sweeps alike, or the first alike and the
    others each where the previous left it), then coordinate descent, one sweep at a time (two
    passes). A change must lower the sum of squares by more than ``margin`` (um^2).

    After a sweep has reached both of its voltage extremes only the hysterons it cannot switch
    still remember the start; they shift ``Q`` by a constant, which the quadratic force term
    turns into a gain: small, but at the noise floor it decides the fit. The gains are shared,
    so sweeps that started alike must be switched together (one at a time, a shared gain fitted
    to the others holds each back).
    """
    n = len(space.preps)
    best, cost = space, _cost(space, y, x) - margin

    def consider(starts: tuple[str, ...]) -> bool:
        nonlocal best, cost
        if starts == best.starts:
            return False
        trial = best.with_starts(starts)
        c = _cost(trial, y, x)
        if c < cost:
            best, cost = trial, c - margin
            return True
        return False

    for first in pz.STARTS[:3]:
        consider((first,) * n)
        consider((first,) + ("previous",) * (n - 1))
    for _ in range(2):
        changed = False
        for i in range(n):
            for cand in pz.STARTS[:3] if i == 0 else pz.STARTS:
                changed |= consider(best.starts[:i] + (cand,) + best.starts[i + 1:])
        if not changed:
            break
    return best


Enough = Callable[[pz.LognormalSpace, optimize.OptimizeResult, FloatArray], bool]


def solve_round(space: pz.LognormalSpace, x0: FloatArray, prob: Problem,
                enough: Enough | None = None) -> tuple[pz.LognormalSpace, optimize.OptimizeResult]:
    """Solve, re-choose the starts, and solve again if they changed, unless ``enough(space,
    solution, ratio)``, asked at the re-chosen starts with the first solution's parameters, says
    no refit will matter (the grid far ahead: on preisach-u the refit took 40 of the HEM's 72 s
    and stayed at 43x the noise). Then that solution is returned with its residual at those
    starts. ``enough`` is asked only where the re-chosen starts left more than
    :data:`STARTS_LEFT` of the first solution's worst error: where the starts explained most of
    it (a stage of the paper's family fitted from the wrong state), the refit may reach the
    noise floor, and is run first."""
    sol = _solve(space, x0, prob, stop_stalled=enough is not None)
    chosen = choose_starts(space, sol.x, prob.y, START_MARGIN * float(np.mean(prob.noise ** 2)))
    if chosen.starts == space.starts:
        return space, sol
    if enough is not None:
        at = optimize.OptimizeResult(sol)
        at.fun = _residual_fn(chosen, prob.y)(sol.x)
        at.cost = 0.5 * float(at.fun @ at.fun)
        ratio = prob.per_sweep(at.fun)
        left = float(np.max(ratio)) > STARTS_LEFT * float(np.max(prob.per_sweep(sol.fun)))
        if left and enough(chosen, at, ratio):
            prob.say(f"  starts {', '.join(chosen.starts)}: the paper's model not refitted")
            return chosen, at
    prob.say(f"  starts {', '.join(chosen.starts)}: refitting")
    return chosen, _solve(chosen, sol.x, prob)


def global_fit(prob: Problem, enough: Enough | None = None
               ) -> tuple[pz.LognormalSpace, optimize.OptimizeResult, int]:
    """The lognormal fit from data-driven starting values; more starts (the next-best distinct
    points of the starting grid) while a sweep stays above :data:`FLOOR` times its noise, unless
    ``enough(space, solution, ratio)`` says after the first that no start will do.
    Returns the best space, solution and the number of restarts."""
    st = prob.settings
    space = pz.LognormalSpace(prob.preps, st.scales, st.n_coercive_fit)
    coarse = pz.LognormalSpace(prob.preps, st.scales, 24)
    ranked = coarse.starts_ranked(lambda x: _cost(coarse, prob.y, x))
    best: tuple[pz.LognormalSpace, optimize.OptimizeResult] | None = None
    restarts = 0
    for k, x_grid in enumerate(ranked[:1 + st.restarts]):
        x0 = coarse.tune_rod(x_grid, lambda x: _cost(coarse, prob.y, x))
        if not k:
            prob.say("starting guess " + ", ".join(
                f"{n}={v:.4g}" for n, v in zip(pz.THETA_NAMES, np.exp(x0), strict=True)))
        else:
            restarts += 1
            prob.say(f"restart {k}: " + ", ".join(f"{v:.3g}" for v in np.exp(x0)))
        space, sol = solve_round(space, x0, prob, None if k else enough)
        ratio = _said(prob, sol)
        decided = bool(np.all(ratio <= FLOOR)) or (not k and enough is not None
                                                    and enough(space, sol, ratio))
        if sol.status == -2 and not decided:  # stalled, and kept after all: solved on
            sol = _solve(space, sol.x, prob)
            ratio = _said(prob, sol, "solved on: ")
            decided = bool(np.all(ratio <= FLOOR))
        if best is None or sol.cost < best[1].cost:
            best = (space, sol)
        if decided:
            break
    assert best is not None
    return best[0], best[1], restarts


def _said(prob: Problem, sol: optimize.OptimizeResult, lead: str = "") -> FloatArray:
    """Each sweep's RMS over its noise at ``sol``, said with the solver's message."""
    ratio = prob.per_sweep(sol.fun)
    prob.say(f"  {lead}{sol.message} (status {sol.status}); RMS / noise per sweep "
             + " / ".join(f"{r:.2f}" for r in ratio))
    return ratio


def _discretization_matters(space: pz.LognormalSpace, x: FloatArray, n_c: int,
                            prob: Problem) -> bool:
    """True if the fit's own coercive nodes and ``n_c`` nodes differ, on some sweep, by more than
    :data:`POLISH_SHARE` of its noise in RMS (then the fit is polished with more nodes)."""
    a_fit, a_fine = space.design(x), space.with_starts(space.starts, n_c).design(x)
    beta, _ = pz.project(a_fit, prob.y)
    return bool(np.max(prob.per_sweep((a_fine - a_fit) @ beta))
                > POLISH_SHARE)


def _with_nodes(model: td.Transducer, n_c: int, space: pz.LognormalSpace,
                sweeps: Sequence[Sweep], offsets: FloatArray,
                say: Callable[[str], None]) -> tuple[td.Transducer, list[FloatArray]]:
    """The model with ``n_c`` coercive nodes, unless it fits the sweeps worse than with the nodes
    it was fitted with (then the parameters absorbed the fit's discretization, and the fitted
    node count is kept and said)."""
    pol = replace(model.polarization, n_coercive=space.n_coercive)
    fitted = replace(model, polarization=pol)
    if n_c <= space.n_coercive:
        return fitted, predict_set(fitted, sweeps, space.starts, offsets)
    fine = replace(model, polarization=replace(pol, n_coercive=n_c))
    p_fine = predict_set(fine, sweeps, space.starts, offsets)
    p_fit = predict_set(fitted, sweeps, space.starts, offsets)

    def sse(pred: list[FloatArray]) -> float:
        return sum(float(np.sum((s.displacement_um - u)[s.mask(None)] ** 2))
                   for s, u in zip(sweeps, pred, strict=True))

    if sse(p_fine) <= 1.1 * sse(p_fit):
        return fine, p_fine
    say(f"N_c = {n_c} fits worse than the fit's {space.n_coercive} nodes: keeping "
        f"{space.n_coercive} (its discretization may exceed {DISCRETIZATION_UM} um)")
    return fitted, p_fit


def _model(space: Space, x: FloatArray, y: FloatArray, thickness_um: float) -> td.Transducer:
    """The physical model at ``x`` (gains projected; the sensor zero of the sweep
    :func:`afmctl.fit.parametrization.zero_sweep` names)."""
    beta, _ = pz.project(space.design(x), y)
    return space.model(x, np.array([beta[0], beta[1], beta[2 + pz.zero_sweep(space.starts)]]),
                       thickness_um)


def fit(sweeps: Sequence[Sweep], settings: Settings = Settings(),
        progress: Callable[[str], None] | None = None) -> FitResult:
    """Fit the transducer jointly to ``sweeps`` by least squares (variable projection).

    Parameters
    ----------
    sweeps : sequence of Sweep
        In the order they were recorded. Each starts from its own hysteresis state (chosen among
        :data:`afmctl.fit.parametrization.STARTS`) and has its own sensor zero; each is judged from
        its :attr:`~afmctl.files.sweepfile.Sweep.memory_index` on.
    settings : Settings
    progress : callable, optional
        Receives one-line progress messages (the CLI prints them on stderr).

    Returns
    -------
    FitResult
        The model (its ``N_c`` chosen by :func:`n_coercive_for`), parameters with 1-sigma,
        per-sweep errors of that model at the full rate against each sweep's sensor noise,
        the uncertainty, the validity envelope and the solver's status. A sweep of minor loops
        that do not close and that the fit misses far more than the others is left out and
        judged held out (:mod:`afmctl.fit.openloops`, ``representations["left_out"]``).

    Examples
    --------
    >>> from afmctl.files import sweepfile as sw
    >>> from afmctl.planning.sweepdesign import voltage_triangle
    >>> true = pz.to_model(np.array([1.0, 0.4, 0.3, 0.36, 250.0, 0.25]),
    ...                    np.array([10.0, 0.5, 0.0]), pz.Scales(), 100.0)
    >>> v = voltage_triangle(27.9, 150.0, 3, 5000.0)
    >>> s = sw.from_arrays(v, predict(true, v, 2e-4), 5000.0, {"layer_thickness_um": "100"})
    >>> fit([s]).sweeps[0].rms_um < 0.05
    True
    """
    from afmctl.fit import openloops  # it judges identify's results

    # small dense algebra: more BLAS threads only contend (as in diagnose)
    with threadpool_limits(limits=1, user_api="blas"):
        return openloops.without_spoilers(_fit(sweeps, settings, progress), sweeps, settings,
                                          _fit, progress)


def _fit(sweeps: Sequence[Sweep], settings: Settings,
         progress: Callable[[str], None] | None) -> FitResult:
    say = progress or (lambda _msg: None)
    t0 = time.perf_counter()
    thickness, known = resolve_thickness(sweeps, settings)
    try:
        preps = [pz.prepare(s, thickness, settings.field_step, settings.window_s) for s in sweeps]
    except ValueError as exc:
        raise FitInputError(str(exc)) from None
    noise = np.array([max(ns.sensor_noise_um(s.displacement_um), 1e-12) for s in sweeps])
    prob = Problem(sweeps, preps, np.concatenate([p.y for p in preps]), noise, settings, say)
    other = rep.Grid(sweeps, thickness, settings, noise, say, t0)
    space, sol, restarts = global_fit(prob, other.early if settings.representation != "hem" else None)
    if other.decided:  # the grid left the HEM far behind after its first start: no polishing
        return other.choose(rep.first_start(prob, space, sol, thickness, known, restarts, t0),
                            prob, space, sol)
    ok = sol.success and sol.status > 0
    fields = [p.field[p.keep] for p in preps]
    n_c = n_coercive_for(_model(space, sol.x, prob.y, thickness), fields, starts=space.starts)
    if n_c > space.n_coercive and _discretization_matters(space, sol.x, n_c, prob):
        n_fit = min(n_c, POLISH_MAX_NODES)
        say(f"polishing with {n_fit} coercive nodes (N_c = {n_c} for < {DISCRETIZATION_UM} um)")
        space, sol = solve_round(space.with_starts(space.starts, n_fit), sol.x, prob)
        ok = sol.success and sol.status > 0
    final: Space = space
    x_lognormal = sol.x
    worst = float(np.max(prob.per_sweep(sol.fun)))
    if settings.density == "discrete" or (settings.density == "auto" and worst > REFINE):
        beta, _ = pz.project(space.design(sol.x), prob.y)
        disc, x0 = dn.DiscreteSpace.around(np.exp(sol.x), preps, settings.scales,
                                           settings.n_density_nodes, settings.smoothing,
                                           float(beta[0]), space.starts)
        say(f"general coercive density ({settings.n_density_nodes} nodes) ...")
        x0 = disc.refined(x0, prob.y)
        dsol = _solve(disc, x0, prob)
        gain = 2 * (sol.cost - dsol.cost) / float(np.mean(prob.noise ** 2))
        before, after = prob.per_sweep(sol.fun), prob.per_sweep(dsol.fun)
        say(f"  {dsol.message} (status {dsol.status}); RMS / noise per sweep "
            + " / ".join(f"{r:.2f}" for r in after))
        traded = bool(np.any((after > REFINE_WORSE * before) & (after > 1.0)))
        if settings.density == "discrete" or (gain > 2 * (x0.size - sol.x.size)
                                              and not traded):
            final, sol = disc, dsol
            ok = ok and dsol.success and dsol.status > 0
    beta, _ = pz.project(final.design(sol.x), prob.y)
    offsets = beta[2:]
    model = _model(final, sol.x, prob.y, thickness)
    if isinstance(final, pz.LognormalSpace):
        model, predicted = _with_nodes(model, n_c, space, sweeps, offsets, say)
    else:
        predicted = predict_set(model, sweeps, space.starts, offsets)
    env = envelope(sweeps, thickness)
    errors = judge_set(sweeps, predicted, space.starts, offsets, settings.window_s)
    cov, names = unc.covariance(final, sol.x, beta, prob.y)
    finite = bool(np.all(np.isfinite(sol.x)) and np.all(np.isfinite(beta)))
    est = unc.estimates(final, sol.x, beta, cov, settings.scales, pz.zero_sweep(final.starts))
    hem = FitResult(model, est, errors,
                    bool(ok and finite), int(sol.status), str(sol.message), prob.nfev,
                    time.perf_counter() - t0, known, x_lognormal,
                    unc.summary(names, np.concatenate((sol.x, beta)), cov), env, restarts, finite)
    if settings.representation in ("preisach", "bouc-wen") or (settings.representation == "auto"
                                                               and not hem.at_noise_floor):
        return other.choose(hem, prob, space, sol)
    return hem
