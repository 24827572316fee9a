"""Which representation ``identify`` keeps: the paper's parametric HEM, the Preisach grid, or
Bouc-Wen.

The homogenized energy model with lognormal/normal densities (six nonlinear parameters) is fitted
first: on a stage of its family it reaches the sensor noise and nothing more is done. When it stays
above the noise floor, the Preisach grid with creep (:mod:`afmctl.fit.preisach`: a non-separable
density on a grid, fitted as a regularized non-negative least-squares problem) is fitted too,
and so is a Bouc-Wen model (:mod:`afmctl.fit.boucwen`: nine parameters and a start state per
sweep, rate independent but without return-point memory, so its minor loops need not close,
which no Preisach-type model can fit) if some measured minor loop stays open
(:mod:`afmctl.fit.closure`) and the grid is not already within identify's noise floor, or if
the sweeps hold no minor loop to tell and neither the HEM nor the grid reaches
:data:`afmctl.fit.identify.FLOOR` times the noise (whole-range triangles cannot tell a Bouc-Wen
stage from a Preisach-type one, but a Bouc-Wen stage's memory outlives the range's ends, which
no wiping-out model follows: on foreign-xy-2's y axis, a two-axis set of triangles, the grid
stayed at 29.9x and Bouc-Wen with its fitted start states reaches 1.0x). They are
compared by their **held-out** error against each sweep's sensor noise:

* the grid's is measured: it is fitted on three of four folds of residual blocks and judged on
  the fourth, each in turn;
* the HEM's and Bouc-Wen's are their errors on the same samples from the full fit: with about
  ten parameters against thousands of samples their optimism is of order ``p / N`` (well below
  1 %). The grid and Bouc-Wen must beat the HEM by :data:`MARGIN` (the paper's model extrapolates
  beyond the identified range by its physics; the grid knows nothing outside the cells the
  sweeps switched), and the lower of the two wins between them.

Speed: after the HEM's first solve (its starts re-chosen, before it is solved again from them),
if some sweep is more than :data:`EARLY` times its noise (the HEM's family does not describe the
stage), the grid is fitted at once; if its worst held-out error is then :data:`DECISIVE` times
below the HEM's, the HEM's second solve, restarts and refinements are skipped (on the
out-of-family stages of the benches they never closed such a gap: a Prandtl-Ishlinskii stage's
HEM went from 12.6x to 7.5x the noise in 110 s of restarts, polishing and a general density,
against the grid's 2.7x; preisach-u's second solve took 40 s to stay at 43x). Before that grid,
if a measured minor loop stays open (:mod:`afmctl.fit.closure`), Bouc-Wen is fitted first
(:meth:`Grid.bouc_wen_first`): within the noise floor it decides, and neither the grid nor the
HEM's restarts are fitted (bw-u of the benches: 153 -> 32 s, the same errors to 0.001x the
noise); otherwise it is set aside after a start that leaves some sweep over
:data:`FIRST_GIVE_UP` times its noise, which is what creep's open loops cost (4-10 s on the
creeping Preisach stages).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from afmctl.files.sweepfile import Sweep
from afmctl.fit import boucwen as bf
from afmctl.fit import closure
from afmctl.fit import preisach as pf
from afmctl.fit import uncertainty as unc
from afmctl.fit.parametrization import rod_of, turning_points
from afmctl.fit.prediction import finite_or_none
from afmctl.model import boucwen as bm
from afmctl.model import preisach as pr

if TYPE_CHECKING:
    from scipy import optimize

    from afmctl.fit import identify as idf
    from afmctl.fit import parametrization as pz

FloatArray = NDArray[np.float64]
#: The HEM's first start this many times above some sweep's noise: fit the grid at once.
EARLY = 5.0
#: The grid's worst held-out error this many times below the HEM's: the HEM's restarts are moot.
DECISIVE = 3.0
#: Reversals farther than this share of the range from its ends are inside it.
EDGE = 0.05
#: Below this many interior reversal voltages the grid's interior is the smoothing's guess (the
#: CLI says so and suggests ``afmctl sweep --design full``, whose curves reverse at 19).
REVERSALS_NEEDED = 4
#: A branch leaving a reversal teaches the grid its interior only if it is traced, not jumped:
#: moving no faster than this many times the sweep's range per second (twice the 5.58 Hz
#: triangle's slew, the rate of the reversals design's curves). The separating sweep's steps
#: (80-170 ranges/s) and multisine (30-50) are faster: on an independent tester's Preisach stage
#: (non-separable density) identified on the separating design, counted as reversal curves they
#: hid that the grid missed a 62-124 V loop by 7x the noise (0.18 um; with the reversals design
#: 1.4x).
TRACED_RANGES_PER_S = closure.SLOW_RANGES_PER_S  # the rate closure takes as quasi-static
#: ... over at least this share of the range (a multisine's wiggles trace little).
TRACED_SHARE = 0.1
#: Reversal voltages closer than this share of the range are one.
LEVEL = 0.02
#: The grid is kept only if its worst held-out error is below this share of the HEM's.
MARGIN = 0.9
#: Bouc-Wen fitted before the grid (:meth:`Grid.bouc_wen_first`, a minor loop open) stops after a
#: start that leaves some sweep over this many times its noise: on stages whose loops creep
#: open (a Preisach-type stage with creep) it is far off, and the grid is fitted next
#: (preisach-b-creep: stopped after its first start, 10 s, at 97x).
FIRST_GIVE_UP = 4.5
#: Where the grid's worst held-out error is within identify's noise floor
#: (:data:`afmctl.fit.identify.FLOOR`, 1.5x the noise), Bouc-Wen is not fitted (with
#: ``representation = "auto"``): the grid is already at the floor, and Bouc-Wen could only bring
#: the fit closer to the noise. A policy, not a bound: creep opens the minor loops of
#: Preisach-type stages, and there Bouc-Wen's first start alone took 48 s to stop at 28x
#: (preisach-u-creep, the grid at 1.03x) and 75-166 s to stop at 42x (pi-b-creep, the grid at
#: 1.40x), while on the Bouc-Wen stages the grid stays far above the floor (bw-u: 39x). (The HEM
#: may still be kept over a settled grid if it beats it by :data:`MARGIN`.)


#: How each representation's worst error (``representations.<name>``) is judged, said beside it
#: in ``why``: the grid's on blocks its fit did not see, the others' on the samples they were
#: fitted to (few parameters: the optimism is about their number over the samples').
HOW_JUDGED = {"hem": "held-out blocks, from the full fit", "preisach": "held out",
              "bouc-wen": "in sample"}


class Grid:
    """The Preisach grid and Bouc-Wen as identify's alternatives: each fitted at most once, then
    compared."""

    def __init__(self, sweeps: Sequence[Sweep], thickness_um: float, settings: idf.Settings,
                 noise: FloatArray, say: Callable[[str], None], t0: float) -> None:
        self.sweeps, self.thickness, self.settings = list(sweeps), thickness_um, settings
        self.noise, self.say, self.t0 = noise, say, t0
        self.fit: pf.PreisachFit | None = None
        self.bw: bf.BoucWenFit | None = None
        self.decided = False
        #: Bouc-Wen, fitted first (the minor loops stay open), is within the noise floor
        self.by_bouc_wen = False
        self.tried_first = False
        #: the worst error (over the noise) of Bouc-Wen fitted first and set aside (inf: no fit)
        self.first_worst: float | None = None

    def data(self) -> pf.Data:
        return pf.sweep_data(self.sweeps, self.thickness, self.noise, self.settings.window_s)

    def run(self, starts: Sequence[str], x_hem: FloatArray) -> pf.PreisachFit:
        """Fit the grid once: the start assignments tried are the HEM's and every sweep alike."""
        if self.fit is None:
            self.say("fitting the Preisach grid with creep (the paper's model is above its "
                     "noise floor) ...")
            self.fit = pf.fit(self.data(), pf.start_candidates(starts), rod_of(x_hem),
                              self.thickness, self.settings.mass_kg, say=self.say)
        return self.fit

    def bouc_wen(self, starts: Sequence[str], x_hem: FloatArray) -> bf.BoucWenFit | None:
        """Fit Bouc-Wen once (None if no shape has a loop), its start states begun at the HEM's
        starts or each sweep where the one before left the stage (a Bouc-Wen stage forgets
        nothing), its rod started at the grid's (searched on its own) if the grid was fitted,
        else the HEM's. With the grid fitted, Bouc-Wen stops after a start that leaves some sweep
        over :data:`DECISIVE` times the grid's worst held-out error (not expected to win from there)."""
        if self.bw is None:
            self.say("fitting a Bouc-Wen model (its minor loops need not close) ...")
            self.bw = self._bouc_wen(starts, x_hem, None if self.fit is None else
                                     DECISIVE * float(np.max(self.fit.heldout_rms_um / self.noise)))
        return self.bw

    def _bouc_wen(self, starts: Sequence[str], x_hem: FloatArray, give_up: float | None,
                  why: str = "where another representation is far below"
                  ) -> bf.BoucWenFit | None:
        rod0 = ((self.fit.model.rod.natural_hz, self.fit.model.rod.damping_ratio)
                if self.fit is not None else rod_of(x_hem))
        chained = [(first,) + ("previous",) * (len(starts) - 1)
                   for first in ("depoled", "negative", "positive")]
        try:
            return bf.fit(self.data(), [tuple(starts), *chained], rod0, self.thickness,
                          self.settings.mass_kg, self.settings.p_r, say=self.say,
                          give_up=give_up, field_step=self.settings.field_step,
                          give_up_why=why)
        except ValueError as exc:
            self.say(f"  no Bouc-Wen fit: {exc}")
            return None

    def bouc_wen_first(self, starts: Sequence[str], x_hem: FloatArray) -> bool:
        """With ``representation = "auto"`` and a measured minor loop that stays open: Bouc-Wen
        before the grid, stopped after a start that leaves some sweep above
        :data:`FIRST_GIVE_UP` times its noise. True (and kept) if its worst error is then within
        identify's noise floor: the grid, a Preisach-type model, cannot close that gap, and
        could only bring the fit closer to the noise. Otherwise it is set aside, and Bouc-Wen is
        fitted again later as before, if at all (started at the grid's rod, judged against the
        grid's error)."""
        from afmctl.fit import identify as idf

        if self.tried_first or self.settings.representation != "auto":
            return self.by_bouc_wen
        self.tried_first = True
        if closure.check(self.sweeps, self.noise)["close"] is not False:
            return False
        self.say("a measured minor loop stays open: a Bouc-Wen model first (kept if within the "
                 "noise floor) ...")
        bw = self._bouc_wen(starts, x_hem, FIRST_GIVE_UP,
                            "not expected to reach the noise floor from there")
        worst = np.inf if bw is None else float(np.max(bw.heldout_rms_um / self.noise))
        if worst > idf.FLOOR:
            self.first_worst = worst
            self.say(("  no Bouc-Wen fit" if bw is None else
                      f"  Bouc-Wen left {worst:.2f}x the noise (over {idf.FLOOR:g}x)")
                     + ": set aside; the Preisach grid next")
            return False
        self.bw, self.by_bouc_wen = bw, True
        return True

    def early(self, space: pz.LognormalSpace, sol: optimize.OptimizeResult,
              ratio: FloatArray) -> bool:
        """After the HEM's first start: True if the grid makes its restarts moot."""
        if self.settings.representation not in ("auto", "preisach") or float(np.max(ratio)) <= EARLY:
            return False
        if self.bouc_wen_first(space.starts, sol.x):
            self.decided = True
            return True
        fit, was = self.run(space.starts, sol.x), self.decided
        self.decided = bool(DECISIVE * np.max(fit.heldout_rms_um / self.noise)
                            < float(np.max(ratio)))
        if self.decided and not was:
            self.say(f"  the grid's held-out error is over {DECISIVE:g}x below the paper's "
                     "model's: no restarts")
        return self.decided

    def choose(self, hem: idf.FitResult, prob: idf.Problem, space: pz.LognormalSpace,
               sol: optimize.OptimizeResult) -> idf.FitResult:
        """``hem``, or the grid's or Bouc-Wen's result if its held-out error is lower (by
        :data:`MARGIN`), with every representation's figures under ``representations``."""
        from dataclasses import replace

        from afmctl.fit import identify as idf

        want = self.settings.representation
        grid = (self.run(space.starts, sol.x) if want in ("auto", "preisach")
                and not self.by_bouc_wen else None)
        loops = closure.check(self.sweeps, self.noise)["close"]
        worst = {"hem": max(s.rms_over_noise for s in hem.sweeps)}
        if grid is not None:
            worst["preisach"] = float(np.max(grid.heldout_rms_um / self.noise))
        untold = loops is None and min(worst.values()) > idf.FLOOR
        settled = worst.get("preisach", np.inf) <= idf.FLOOR
        bw = (self.bouc_wen(space.starts, sol.x) if want == "bouc-wen"
              or (want == "auto" and (loops is False or untold) and not settled) else None)
        if bw is not None:
            worst["bouc-wen"] = float(np.max(bw.heldout_rms_um / self.noise))
        chosen = want if want in worst else min(
            worst, key=lambda k: worst[k] / (1.0 if k == "hem" else MARGIN))
        why = ("asked for (--profile [identify] representation)" if chosen == want else
               ("no Bouc-Wen fit (asked for); " if want == "bouc-wen" else "")
               + "worst error over the noise " + ", ".join(
                   f"{k} {v:.2f}x ({HOW_JUDGED[k]})" for k, v in worst.items()))
        figures: dict[str, Any] = {
            "chosen": chosen, "why": why,
            "hem": {"worst_over_noise": worst["hem"], "heldout_note": "error on the held-out "
                    "blocks from the full fit (about ten parameters: optimism ~ p/N)",
                    "per_sweep_over_noise": [s.rms_over_noise for s in hem.sweeps]}}
        if grid is not None:
            figures["preisach"] = {**_grid_figures(grid, self.noise),
                                   "interior_reversals": interior_reversals(self.sweeps),
                                   "interior_loops": grid.interior_loops,
                                   "force_cubic_fitted": grid.cubic}
        elif self.by_bouc_wen:
            figures["preisach"] = {"skipped": (
                f"a measured minor loop stays open and Bouc-Wen, fitted first, is within "
                f"identify's noise floor ({worst['bouc-wen']:.2f}x): a Preisach-type grid "
                "could only bring the fit closer to the noise")}
        figures["bouc_wen"] = (bf.figures(bw, self.noise) if bw is not None else
                               {"skipped": _why_no_bouc_wen(want, loops, worst, settled)})
        if self.first_worst is not None:  # fitted before the grid and set aside (None: no fit)
            figures["bouc_wen"]["first_set_aside_over_noise"] = finite_or_none(self.first_worst)
        self.say(f"representation: {chosen} ({why})")
        if chosen == "preisach" and grid is not None:
            return self._result(hem, prob, grid, figures, estimates(grid.model, grid))
        if chosen == "bouc-wen" and bw is not None:
            return self._result(hem, prob, bw, figures, bw_estimates(bw))
        return replace(hem, representations=figures)

    def _result(self, hem: idf.FitResult, prob: idf.Problem,
                fit: pf.PreisachFit | bf.BoucWenFit, figures: dict[str, Any],
                est: tuple[unc.Estimate, ...]) -> idf.FitResult:
        from afmctl.fit import identify as idf

        model = fit.model  # judged with each sweep's own history: sensor zero, creep transient
        errors = idf.judge_set(self.sweeps, fit.predicted, fit.starts, fit.offsets,
                               self.settings.window_s)
        name = "Preisach grid: Gauss-Newton" if figures["chosen"] == "preisach" else "Bouc-Wen"
        msg = f"{name} {fit.how} after {fit.iterations} steps"
        return idf.FitResult(
            model, est, errors, fit.converged, 1 if fit.converged else 0, msg,
            prob.nfev + fit.iterations, time.perf_counter() - self.t0, hem.thickness_known, hem.x,
            fit.uncertainty, hem.envelope, hem.restarts, bool(np.isfinite(fit.offsets).all()),
            figures["chosen"], figures)


def _why_no_bouc_wen(want: str, loops: bool | None, worst: dict[str, float],
                     settled: bool) -> str:
    from afmctl.fit import identify as idf

    if want == "auto" and settled and loops is False:
        return (f"the minor loops do not close, but the grid's held-out error "
                f"({worst['preisach']:.2f}x the noise) is within identify's noise floor "
                f"({idf.FLOOR:g}x): Bouc-Wen could only bring the fit closer to the noise")
    if want != "auto" or loops is False:
        return "not fitted"
    return ("the minor loops close: a Preisach-type stage" if loops else
            "no minor loop to tell, and a Preisach-type fit at the noise floor")


def first_start(prob: idf.Problem, space: pz.LognormalSpace, sol: optimize.OptimizeResult,
                thickness: float, known: bool, restarts: int, t0: float) -> idf.FitResult:
    """The HEM's result at its first start, unpolished (when the grid wins outright)."""
    from afmctl.fit import identify as idf
    from afmctl.fit import parametrization as pz

    beta, _ = pz.project(space.design(sol.x), prob.y)
    model = idf._model(space, sol.x, prob.y, thickness)
    predicted = idf.predict_set(model, prob.sweeps, space.starts, beta[2:])
    errors = idf.judge_set(prob.sweeps, predicted, space.starts, beta[2:],
                           prob.settings.window_s)
    return idf.FitResult(model, (), errors, bool(sol.success and sol.status > 0),
                         int(sol.status), str(sol.message), prob.nfev, time.perf_counter() - t0,
                         known, sol.x, {}, idf.envelope(prob.sweeps, model.thickness_um),
                         restarts, bool(np.all(np.isfinite(sol.x))))


def interior_reversals(sweeps: Sequence[Sweep]) -> int:
    """How many distinct voltages (more than 2 % of the range apart) the sweeps reverse at
    inside their range (more than :data:`EDGE` of it from either end), the branch after the
    reversal traced: at least :data:`TRACED_SHARE` of the range travelled by samples that move
    no faster than :data:`TRACED_RANGES_PER_S`. These are the reversal curves a Preisach grid
    learns its interior from. Triangles over the whole range have none; nor have steps and a
    fast multisine, which jump over their branches.

    Examples
    --------
    >>> from afmctl.files.sweepfile import from_arrays
    >>> tri = from_arrays(np.interp(np.arange(41), [0, 10, 30, 40], [0, 150, 0, 0]), np.zeros(41),
    ...                   100.0)
    >>> inner = from_arrays(np.interp(np.arange(41), [0, 10, 20, 30, 40], [0, 150, 60, 150, 0]),
    ...                     np.zeros(41), 100.0)
    >>> jumped = from_arrays(np.interp(np.arange(41), [0, 10, 20, 30, 40], [0, 150, 60, 150, 0]),
    ...                      np.zeros(41), 1e4)
    >>> interior_reversals([tri]), interior_reversals([tri, inner]), interior_reversals([jumped])
    (0, 1, 0)
    """
    lo = min(float(np.min(s.voltage_v)) for s in sweeps)
    hi = max(float(np.max(s.voltage_v)) for s in sweeps)
    span = max(hi - lo, 1e-12)
    levels = []
    for s in sweeps:
        v = np.asarray(s.voltage_v, float)
        turns = turning_points(v)
        for a, b in zip(turns[1:-1], turns[2:]):  # the ends are no reversals
            u = (v[a] - lo) / span
            steps = np.abs(np.diff(v[a:b + 1]))
            travel = float(np.sum(steps[steps <= TRACED_RANGES_PER_S * span * s.dt]))
            if EDGE < u < 1 - EDGE and travel >= TRACED_SHARE * span:
                levels.append(float(u))
    return int(np.count_nonzero(np.diff(np.sort(levels)) > LEVEL)) + 1 if levels else 0


def _grid_figures(fit: pf.PreisachFit, noise: FloatArray) -> dict[str, Any]:
    grid = fit.model.polarization
    assert isinstance(grid, pr.PreisachGrid)
    return {"worst_heldout_over_noise": float(np.max(fit.heldout_rms_um / noise)),
            "heldout_over_noise": [float(v) for v in fit.heldout_rms_um / noise],
            "insample_over_noise": [float(v) for v in fit.insample_over_noise],
            "grid": [grid.n_coercive, grid.n_interaction], "coefficients": fit.n_coefficients,
            "smoothing": fit.smoothing, "creep": fit.creep,
            "creep_per_decade": None if fit.model.creep is None else
            fit.model.creep.per_decade(),
            "creep_acts_on": None if fit.model.creep is None else fit.model.creep.acts_on,
            "seconds": round(fit.seconds, 3),
            "candidates_heldout_sse_over_noise": fit.candidates}


def _stderr(fit: pf.PreisachFit | bf.BoucWenFit, name: str) -> float:
    """1-sigma of the fit's internal parameter ``name`` (NaN if it has none)."""
    v = fit.uncertainty.get("parameters", {}).get(name, {}).get("stderr")
    return float("nan") if v is None else float(v)


def _rod_estimates(fit: pf.PreisachFit | bf.BoucWenFit) -> list[unc.Estimate]:
    """The rod (16) of a grid's or Bouc-Wen's model (intervals of the natural frequency and
    damping from their logs'), its sensor zero and the polarization's reversible slope."""
    rod = fit.model.rod
    return [unc.Estimate("natural_frequency", rod.natural_hz,
                         rod.natural_hz * _stderr(fit, "log_fn"), "Hz"),
            unc.Estimate("damping_ratio", rod.damping_ratio,
                         rod.damping_ratio * _stderr(fit, "log_zeta"), "1"),
            unc.Estimate("k", rod.k, float("nan"), "N/m"),
            unc.Estimate("c", rod.c, float("nan"), "N s/m"),
            unc.Estimate("a1", rod.a1, float("nan"), "N/(C/m^2)"),
            unc.Estimate("a2", rod.a2, float("nan"), "N/(C/m^2)^2"),
            unc.Estimate("a3", rod.a3, 0.0 if rod.a3 == 0.0 else float("nan"), "N/(C/m^2)^3",
                         fixed=rod.a3 == 0.0),  # held at 0: Bouc-Wen, or no interior loops
            unc.Estimate("offset", rod.offset_um, float("nan"), "um"),
            unc.Estimate("reversible_slope", fit.model.polarization.reversible, float("nan"),
                         "(C/m^2)/(MV/m)")]


def _creep_estimates(model: Any) -> list[unc.Estimate]:
    """The model's log-time creep, per decade and per element (none without creep)."""
    if model.creep is None:
        return []
    return [unc.Estimate("creep_per_decade", model.creep.per_decade(), float("nan"), "1")] + [
        unc.Estimate(f"creep@{t:g}s", c, float("nan"), "1")
        for t, c in zip(model.creep.tau_s, model.creep.weights, strict=True)]


def estimates(model: Any, fit: pf.PreisachFit) -> tuple[unc.Estimate, ...]:
    """The grid model's scalar parameters: the rod (16), the grid, creep (no intervals for the
    density's weights: they are non-negative, judged by held-out error instead)."""
    out = _rod_estimates(fit) + [unc.Estimate("hysteretic_range",
                                              model.polarization.hysteretic_range(),
                                              float("nan"), "C/m^2")]
    return tuple(out + _creep_estimates(model) + [
        unc.Estimate("m", model.rod.m, 0.0, "kg", fixed=True),
        unc.Estimate("p_scale", fit.p_scale, 0.0, "C/m^2", fixed=True)])


def bw_estimates(fit: bf.BoucWenFit) -> tuple[unc.Estimate, ...]:
    """The Bouc-Wen model's parameters: the rod (16), the operator and its creep (1-sigma of the
    rod's and the shape's from the fit's uncertainty; the physical scales are conventions)."""
    bw = fit.model.polarization
    assert isinstance(bw, bm.BoucWen)
    return tuple(_rod_estimates(fit) + [
        unc.Estimate("bouc_wen_rate", bw.rate, float("nan"), "(C/m^2)/(MV/m)"),
        unc.Estimate("bouc_wen_saturation", bw.saturation, float("nan"), "C/m^2"),
        unc.Estimate("bouc_wen_kappa", bw.kappa, _stderr(fit, "kappa"), "1"),
        unc.Estimate("bouc_wen_exponent", bw.exponent, _stderr(fit, "n"), "1")]
        + _creep_estimates(fit.model) + [unc.Estimate("m", fit.model.rod.m, 0.0, "kg", fixed=True)])


__all__ = ["Grid", "EARLY", "DECISIVE", "MARGIN", "estimates", "bw_estimates",
           "first_start"]
