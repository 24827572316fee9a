"""The verdict of ``afmctl diagnose``: a cause, ``none`` or ``unexplained``, judged against the noise floor.

Every model is judged by its held-out RMS (um, the root mean of the per-sweep mean squares on the
halves no fit saw). A perfect model leaves exactly the sensor noise there, so the yardstick is the
*noise floor* ``sigma`` (the same root mean of the per-sweep noise variances) and every RMS is read
as a multiple of it: ``base_over_noise = base / sigma``, ``extended_over_noise = best / sigma``.

Rules (:class:`Rule`, defaults from issue 12):

1. ``none`` only if the base model is within ``none_within`` (1.5) of the floor and no candidate
   clears its bar. A base misfit above that is never ``none``.
2. A candidate *clears its bar* if its gain over the base reaches :func:`required_gain` (1.1 for one
   parameter, 0.05 more per further one) and it removes at least ``min_explained`` (50 %) of the
   base model's *excess* variance ``base^2 - sigma^2``.
3. The clearing candidate with the smallest held-out RMS is named if it comes within ``near``
   (2.0) of the floor, or if it removes at least ``clearly_explained`` (95 %) of the excess
   variance (a strong effect whose candidate formula is not exactly the stage's physics).
4. Otherwise ``unexplained``: neither the base nor any candidate explains the data down to the
   floor. The diagnosis then says how far each is, what the residual looks like and which
   measurement would tell more (:func:`suggestions`).
5. A sensor-side cause (:data:`afmctl.fit.candidates.TWINS`: it changes what afmctl believes the
   true position is) is named only when the sweeps *separate* it from its actuator-side twin:
   the twin's held-out RMS is at least ``separated`` (1.1, the gain one parameter must buy)
   times the sensor cause's, and so is its RMS on the halves both were fitted on (where those are
   known). Far from the floor, two models that fit their halves equally well can part on the
   held-out ones by how the base model's own misfit carries over (a Prandtl-Ishlinskii stage
   with its cubic map before the rod: both 1.83x the noise on the fitted halves, 1.89x and 2.16x
   held out); a nonlinearity the sweeps really place misses on both. A twin that much better
   than the sensor cause refutes it (it is not considered); between the two, the verdict is
   ``indistinguishable`` (the model keeps the readings uncorrected). A twin fitted only as such
   (``actuator-nonlinearity``) is never named.

Pure functions of numbers and dicts; no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl.fit.candidates import TWIN_ONLY, TWINS

#: The verdict when a sensor-side cause and its actuator-side twin are not separated (rule 5).
INDISTINGUISHABLE = "indistinguishable"


@dataclass(frozen=True)
class Rule:
    """Thresholds of the verdict, in multiples of the noise floor or fractions of excess variance."""

    none_within: float = 1.5
    near: float = 2.0
    min_explained: float = 0.5
    clearly_explained: float = 0.95
    separated: float = 1.1


@dataclass(frozen=True)
class Scored:
    """One model's held-out RMS (um), the number of parameters it adds to the base and its RMS on
    the data it was fitted on (um; NaN: not known)."""

    name: str
    heldout_rms_um: float
    n_params: int
    fit_rms_um: float = math.nan


def required_gain(n_params: int) -> float:
    """Held-out gain an extension with ``n_params`` parameters must reach to be named: 1.1 for one
    parameter and 0.05 more per further parameter (a parameter must buy at least 5 %)."""
    return 1.1 + 0.05 * max(n_params - 1, 0) if n_params else 1.0


def ratio(base_um: float, other_um: float) -> float:
    """Gain of a model over the base: base / its held-out RMS (inf for a perfect one)."""
    return base_um / other_um if other_um > 0 else math.inf


def floor(noise_um: Sequence[float]) -> float:
    """Noise floor (um) of the held-out RMS: root mean of the per-sweep noise variances (every sweep
    weighs the same, as in the held-out RMS)."""
    return math.sqrt(sum(s * s for s in noise_um) / len(noise_um))


def explained(base_um: float, other_um: float, floor_um: float) -> float:
    """Fraction of the base model's excess variance over the floor that ``other`` removes
    (1: down to the floor; 0: none; negative: worse). 0 if the base has no excess."""
    excess = base_um ** 2 - floor_um ** 2
    return (base_um ** 2 - other_um ** 2) / excess if excess > 0 else 0.0


def closest_phrase(name: str, explained_fraction: float) -> str:
    """How much of the base model's misfit the closest model explains, in words (issue 23:
    "closest: thermal-relaxation, explains 63 % of the misfit")."""
    if name == "none":
        return "closest: the paper's model itself"
    return (f"closest: {name}, explains {100 * explained_fraction:.0f} % of the misfit (the "
            f"held-out variance above the noise floor)")


def clears(base: Scored, s: Scored, floor_um: float, rule: Rule = Rule()) -> bool:
    """Whether candidate ``s`` gains enough over ``base`` to be considered (rule 2)."""
    return (s.n_params > 0 and ratio(base.heldout_rms_um, s.heldout_rms_um) >= required_gain(s.n_params)
            and explained(base.heldout_rms_um, s.heldout_rms_um, floor_um) >= rule.min_explained)


def judged_rms(squares: Sequence[NDArray[np.float64]], masks: Sequence[NDArray[np.bool_]]
               ) -> tuple[float, tuple[float, ...]]:
    """The RMS every model is judged by (um): the root mean of the per-sweep mean squares of
    ``squares`` (squared errors, um^2, one array per sweep) on the rows of ``masks``, and each
    sweep's RMS."""
    mse = [float(np.mean(e[m])) for e, m in zip(squares, masks, strict=True)]
    return math.sqrt(float(np.mean(mse))), tuple(math.sqrt(v) for v in mse)


def fitted_ratio(sensor: Scored, twin: Scored) -> float | None:
    """The twin's RMS on the data both were fitted on over the sensor cause's; None when either
    is not known."""
    if math.isnan(twin.fit_rms_um) or math.isnan(sensor.fit_rms_um):
        return None
    return ratio(twin.fit_rms_um, sensor.fit_rms_um)


def separated(sensor: Scored, twin: Scored | None, rule: Rule = Rule()) -> bool:
    """Whether the sweeps separate a sensor-side cause from its actuator-side twin (rule 5): the
    twin (None: not fitted) misses by ``rule.separated`` times the sensor cause's held-out RMS,
    and by as much on the data both were fitted on when both RMS are known."""
    if twin is None or ratio(twin.heldout_rms_um, sensor.heldout_rms_um) < rule.separated:
        return False
    fitted = fitted_ratio(sensor, twin)
    return fitted is None or fitted >= rule.separated


def refuted(s: Scored, by_name: dict[str, Scored], rule: Rule = Rule()) -> bool:
    """Whether ``s`` is a sensor-side cause whose actuator-side twin explains the data clearly
    better (by ``rule.separated``): the sweeps say the effect is before the rod, not in the
    sensor."""
    twin = by_name.get(TWINS.get(s.name, ""))
    return twin is not None and separated(twin, s, rule)


def decide(scored: Sequence[Scored], floor_um: float, rule: Rule = Rule()) -> str:
    """The verdict: the name of a candidate, ``none``, ``unexplained`` or ``indistinguishable``
    (rules 1-5).

    Parameters
    ----------
    scored : sequence of Scored
        The base model (``none``, no parameters added) and every candidate.
    floor_um : float
        Noise floor of the held-out RMS, um (:func:`floor`).
    rule : Rule
    """
    base = next(s for s in scored if s.name == "none")
    by_name = {s.name: s for s in scored}
    able = [s for s in scored if s.name not in TWIN_ONLY and clears(base, s, floor_um, rule)
            and not refuted(s, by_name, rule)]
    best = min(able, key=lambda s: s.heldout_rms_um, default=None)
    if best is not None and (best.heldout_rms_um <= rule.near * floor_um or explained(
            base.heldout_rms_um, best.heldout_rms_um, floor_um) >= rule.clearly_explained):
        if best.name in TWINS and not separated(best, by_name.get(TWINS[best.name]), rule):
            return INDISTINGUISHABLE
        return best.name
    if base.heldout_rms_um <= rule.none_within * floor_um:
        return "none"
    return "unexplained"


#: What the base model's residual looks like -> what it suggests and which measurement tells more.
_HINTS = (
    ("between_sweeps", "the residual's mean differs between sweeps",
     "repeat one sweep several times: a gain or offset that changes from run to run shows as "
     "different loops for the same command"),
    ("rate", "the residual follows the field rate (a lag or lead)",
     "a multi-frequency or chirp segment at one amplitude: a delay's phase grows with frequency, "
     "an amplifier's or a mode's magnitude and phase change near its corner"),
    ("turning_points", "the residual is concentrated just after the turning points",
     "a small-step staircase and a low-amplitude reversal: backlash shows as a dead band after "
     "each reversal, a mode as a ringing at its own frequency"),
    ("field_squared", "the residual depends on the position (field squared) alone",
     "the same loop at two frequencies and a calibration of the gauge against an independent "
     "reference: a sensor error is the same at every frequency"),
    ("tone", "the residual holds a tone that is no harmonic of the drive",
     "a record with the drive held constant: interference on the sensor line stays, the stage's "
     "response does not"),
    ("time", "the residual grows or decays in time",
     "a hold at constant voltage after a ramp: relaxation (creep) decays at fixed field, "
     "a thermal drift keeps going"),
)


def suggestions(signature: dict[str, Any]) -> list[dict[str, str]]:
    """The features of the residual signature (:func:`afmctl.fit.residuals.residual_signature`) that
    stand out, strongest first, each with what it suggests and the measurement that would tell
    more. Always at least one entry (a generic one if nothing stands out)."""
    score = {
        "between_sweeps": signature["between_sweeps_mean_spread_um"] / max(signature["rms_um"], 1e-12),
        "rate": abs(signature["corr_field_rate"]),
        "turning_points": signature["turning_point_ratio"] - 1.0,
        "field_squared": abs(signature["corr_field_squared"]) - abs(signature["corr_field"]),
        "tone": signature["tone_fraction"] * 2.0,
        "time": abs(signature["corr_time"]),
    }
    out = [{"feature": key, "reading": what, "measure": how}
           for key, what, how in sorted(_HINTS, key=lambda h: -score[h[0]]) if score[key] > 0.3]
    return out or [{"feature": "broadband", "reading": "the residual has no clear structure in "
                    "field, rate, time, turning points or between sweeps",
                    "measure": "a longer record of the same sweeps (more averaging) and a record "
                               "with the drive held constant (the sensor's own noise)"}]
