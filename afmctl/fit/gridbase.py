"""Diagnose's second base: the Preisach grid, with and without its creep elements.

When neither the paper's model nor any of its one-effect extensions explains the sweeps
(``unexplained``), the stage's hysteresis may simply not be of the paper's family: a Preisach
density that is not separable, a Prandtl-Ishlinskii or Bouc-Wen stage (issue 23). identify then
chooses the Preisach grid (:mod:`afmctl.fit.preisach`); :func:`judge` fits it twice, without and
with the log-time creep elements of :mod:`afmctl.model.creep` (:func:`afmctl.fit.preisach.runs`),
and judges both as identify judges the grid: on held-out blocks (:func:`afmctl.fit.preisach.heldout`:
the residual rows cut into blocks dealt to four folds, each fold judged by the fit on the other
three; the root mean of the per-sweep mean squares). Not on the sweeps' second halves, as
diagnose judges its candidates: on a bipolar stage's three standard triangles the first halves
miss the slow sweep's major branch above 0 V (its first half goes up the virgin curve), so a
first-half grid misses the second half by 40-70x the noise with or without creep, where the
blocks judge it at 1-3x (preisach-b-creep, docs/results/diagnose.md).

Creep and what is not creep (:class:`CreepRule`; measured on the out-of-family stages,
docs/results/diagnose.md):

- **creep**: the elements take at least ``per_decade`` of a step per decade of time (0.003:
  0.3 %; PI's tutorial gives 1-2 %), at least ``short_share`` of their weight sits on the
  sub-second elements (log-time creep starts within the first second after a step), and they
  lower the held-out RMS at least ``gain`` times;
- **drift**: the elements take ``per_decade`` or more, less than ``short_share`` of the weight on
  the sub-second elements and at least ``long_share`` on the slowest (100 s and up: an offset
  that keeps growing over the whole record, which no decade of creep describes), and they lower
  the held-out RMS at least ``drift_gain`` times: diagnose stays ``unexplained`` and says so;
- **thermal relaxation** (an exponential knee, kernel (10)) concentrates the weight on one or two
  neighbouring time constants; creep spreads it over decades: the weight must span at least
  ``decades`` decades (the shortest range of time constants holding 80 % of it).

Pure numerics: no I/O.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl.files.sweepfile import Sweep
from afmctl.fit import extension as ext
from afmctl.fit import preisach as pf
from afmctl.model import creep as cr

FloatArray = NDArray[np.float64]


#: What a verdict on the grid means (:attr:`afmctl.fit.diagnosis.Diagnosis.explanation`).
CAUSES = {
    "none": "the stage's hysteresis is not of the paper's family (its lognormal / normal "
            "densities), but the Preisach grid identify chooses for such stages explains the data "
            "to the noise, with nothing beyond it",
    "creep": "log-time creep of the piezo (Krejci-Kuhnen creep operators): after every change of "
             "voltage the stage keeps moving the way it last moved, by about the same amount per "
             "decade of time, over decades (not one exponential knee)",
}
#: The suggestion when the creep elements sit on the slowest time constants (:meth:`GridBase.drift`).
DRIFT_HINT = {
    "feature": "drift",
    "reading": "the Preisach grid's creep elements put their weight on the 100-1000 s time "
               "constants: an offset that keeps growing through the record, a drift that no "
               "decade of creep describes (not absorbed into the model)",
    "measure": "the same sweep repeated over some minutes and a hold at constant voltage: creep "
               "slows down on a straight line against log time, a drift keeps going"}


@dataclass(frozen=True)
class CreepRule:
    """When the grid's creep elements name ``creep`` (or a drift): see the module docstring.
    Times in s, shares of the elements' total weight."""

    per_decade: float = 0.003
    short_share: float = 0.1
    long_share: float = 0.5
    gain: float = 1.5
    drift_gain: float = 1.05
    decades: float = 1.5
    short_s: float = 0.32
    long_s: float = 100.0


@dataclass(frozen=True)
class GridBase:
    """The grid fitted without (``plain``) and with (``crept``) creep, as diagnose's
    :class:`~afmctl.fit.extension.Extended` (the model, its starts and sensor zeros), each with
    its held-out RMS (um, overall and per sweep) and readings on the sweeps (um); the creep
    elements' figures and the wall time (s)."""

    plain: ext.Extended
    crept: ext.Extended
    plain_rms_um: float
    crept_rms_um: float
    plain_per_sweep_um: tuple[float, ...]
    crept_per_sweep_um: tuple[float, ...]
    plain_readings: tuple[FloatArray, ...]
    crept_readings: tuple[FloatArray, ...]
    per_decade: float
    short_share: float
    long_share: float
    span_decades: float
    seconds: float

    @property
    def gain(self) -> float:
        """Held-out RMS without creep over with it."""
        return self.plain_rms_um / self.crept_rms_um if self.crept_rms_um > 0 else math.inf

    def creep(self, rule: CreepRule = CreepRule()) -> bool:
        """Whether the elements describe log-time creep (the module docstring's rule)."""
        return (self.per_decade >= rule.per_decade and self.short_share >= rule.short_share
                and self.gain >= rule.gain and self.span_decades >= rule.decades)

    def drift(self, rule: CreepRule = CreepRule()) -> bool:
        """Whether the elements sit on the slowest time constants: a drift, not creep."""
        return (self.per_decade >= rule.per_decade and self.short_share < rule.short_share
                and self.long_share >= rule.long_share and self.gain >= rule.drift_gain)

    def text(self, noise_um: float) -> str:
        """The grid's figures in one clause."""
        return (f"held-out {self.plain_rms_um / noise_um:.2f}x the noise without creep, "
                f"{self.crept_rms_um / noise_um:.2f}x with it (gain {self.gain:.2f}); the creep "
                f"elements take {100 * self.per_decade:.2f} % of a step per decade, "
                f"{100 * self.short_share:.0f} % of their weight on the sub-second ones and "
                f"{100 * self.long_share:.0f} % on 100 s and up, 80 % of it within "
                f"{self.span_decades:.1f} decades")

    def as_dict(self, noise_um: float) -> dict[str, Any]:
        return {"heldout_rms_um": {"without_creep": self.plain_rms_um,
                                   "with_creep": self.crept_rms_um},
                "over_noise": {"without_creep": self.plain_rms_um / noise_um,
                               "with_creep": self.crept_rms_um / noise_um},
                "heldout_rms_per_sweep_um": {"without_creep": list(self.plain_per_sweep_um),
                                             "with_creep": list(self.crept_per_sweep_um)},
                "creep_gain": self.gain, "creep_per_decade": self.per_decade,
                "creep_share_subsecond": self.short_share,
                "creep_share_100s_up": self.long_share,
                "creep_span_decades": self.span_decades, "seconds": round(self.seconds, 2),
                "method": "the Preisach grid fitted without and with its creep elements "
                          "(10 ms - 1000 s), each judged on held-out blocks as identify judges "
                          "it (four folds)"}


def shares(tau_s: FloatArray, weights: FloatArray, rule: CreepRule = CreepRule()
           ) -> tuple[float, float, float]:
    """The share of the creep weight on time constants up to ``rule.short_s`` and from
    ``rule.long_s``, and the span (decades) of the shortest range of time constants holding
    80 % of it (0 without weight)."""
    total = float(np.sum(weights))
    if total <= 0:
        return 0.0, 0.0, 0.0
    taus = np.unique(tau_s)
    per = np.array([float(np.sum(weights[tau_s == t])) for t in taus]) / total
    span = min((math.log10(taus[j] / taus[i]) for i in range(taus.size)
                for j in range(i, taus.size) if per[i:j + 1].sum() >= 0.8), default=0.0)
    return (float(per[taus <= rule.short_s].sum()), float(per[taus >= rule.long_s].sum()),
            float(span))


def _data(sweeps: Sequence[Sweep], thickness_um: float, noise_um: Sequence[float]) -> pf.Data:
    return pf.Data([s.voltage_v / thickness_um for s in sweeps], [s.mask(None) for s in sweeps],
                   [s.displacement_um[s.mask(None)] for s in sweeps], [s.dt for s in sweeps],
                   np.asarray(noise_um, float))


def judge(sweeps: Sequence[Sweep], thickness_um: float, mass_kg: float,
          noise_um: Sequence[float], starts: Sequence[str], rod0: tuple[float, float],
          say: Callable[[str], None], settings: pf.Settings = pf.Settings()) -> GridBase:
    """Fit the grid on ``sweeps`` without and with creep and judge both on held-out blocks.

    Parameters
    ----------
    sweeps : sequence of Sweep
    thickness_um, mass_kg : float
        Layer thickness (um) and the fixed effective mass (kg, a scale convention).
    noise_um : sequence of float
        Each sweep's sensor noise (um).
    starts : sequence of str
        The paper's model's start states; each sweep alike from ``positive``, ``depoled`` and
        ``negative`` is tried too.
    rod0 : (float, float)
        Starting natural frequency (Hz) and damping ratio of the rod.
    settings : afmctl.fit.preisach.Settings
        The grid's fit (identify's by default).
    """
    t0 = time.perf_counter()
    n = len(sweeps)
    cands = [tuple(starts)] + [(s,) * n for s in ("positive", "depoled", "negative")]
    fitted = pf.runs(_data(sweeps, thickness_um, noise_um), cands, rod0, settings, say)
    prob = fitted.problem
    out: dict[bool, tuple[ext.Extended, list[FloatArray], FloatArray]] = {}
    for creep, run in ((False, fitted.plain), (True, fitted.crept)):
        per = pf.heldout(prob, run.theta, fitted.penalty, (fitted.smoothing,),
                         creep)[fitted.smoothing]
        model = pf.build(run.theta, prob, mass_kg, thickness_um, settings.p_scale, creep)
        name = "preisach-grid" + (" with creep" if creep else "")
        out[creep] = (ext.Extended(name, model, (1.0,) * n, {}, run.converged, run.iterations,
                                   np.zeros(0), prob.starts,
                                   tuple(float(o) for o in run.theta.offsets), np.zeros(0)),
                      prob.predict(run.theta, full=True), per)
    c = fitted.crept.theta.c
    creep = cr.Creep(tuple(float(t) for t in prob.el_tau), tuple(float(w) for w in c),
                     tuple(float(r) for r in prob.el_thr))
    short, long, span = shares(prob.el_tau, c)
    (plain, plain_u, plain_per), (crept, crept_u, crept_per) = out[False], out[True]
    return GridBase(plain, crept, _root_mean(plain_per), _root_mean(crept_per),
                    tuple(map(float, plain_per)), tuple(map(float, crept_per)), tuple(plain_u),
                    tuple(crept_u), creep.per_decade() if c.any() else 0.0, short, long, span,
                    time.perf_counter() - t0)


def _root_mean(per_sweep_um: FloatArray) -> float:
    """The root mean of the per-sweep mean squares (um): every sweep weighs the same."""
    return math.sqrt(float(np.mean(np.square(per_sweep_um))))


def verdict(grid: GridBase, floor_um: float, rule: CreepRule = CreepRule(),
            none_within: float = 1.5) -> str:
    """``creep`` if the elements describe creep (:meth:`GridBase.creep`); ``none`` if the grid
    without creep is within ``none_within`` of the noise floor ``floor_um`` (um) and its creep
    elements neither gain ``rule.gain`` nor sit on a drift; else ``unexplained``."""
    if grid.creep(rule):
        return "creep"
    if (not grid.drift(rule) and grid.gain < rule.gain
            and grid.plain_rms_um <= none_within * floor_um):
        return "none"
    return "unexplained"
