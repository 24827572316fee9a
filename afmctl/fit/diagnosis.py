"""The outcome of ``afmctl diagnose`` (:func:`afmctl.fit.diagnose.diagnose`): the verdict, every
judged model and what they say, as the report and ``diagnosis.json`` state it. No I/O."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from afmctl.files.sweepfile import Sweep
from afmctl.fit import candidates as cd
from afmctl.fit import extension as ext
from afmctl.fit import gridbase as gb
from afmctl.fit import verdict as vd
from afmctl.fit.residuals import predicted
from afmctl.fit.verdict import ratio, required_gain
from afmctl.model import transducer as td

if TYPE_CHECKING:  # heldbase builds on Judged, below
    from afmctl.fit.heldbase import HeldBase

FloatArray = NDArray[np.float64]


#: The base of the causes of :mod:`afmctl.fit.heldbase` (the report's words).
HELD_BASE = "identify's general coercive density with its hysteresis held"
#: What ``none`` on that base means (:attr:`Diagnosis.explanation`).
HELD_NONE = ("the stage's coercive density is not the paper's lognormal / normal, but identify's "
             "general coercive density explains the data to within what the causes can add")


def fitted_text(parameters: dict[str, float]) -> str:
    return ", ".join(f"{k} = {v:.4g}" for k, v in parameters.items())


@dataclass(frozen=True)
class Judged:
    """One candidate: its fit on the first halves, its RMS error (um) on the second halves
    (overall and per sweep), the fit's wall time (s) and its RMS error on the first halves (um,
    the same root mean of per-sweep mean squares; NaN: not computed) and, for a cause fitted in
    more than one form (:data:`afmctl.fit.candidates.FORMS`), each form's RMS on the fitted and
    the held-out halves (um): the fit is the form that fitted its halves best."""

    fitted: ext.Extended
    n_params: int
    heldout_rms_um: float
    heldout_per_sweep_um: tuple[float, ...]
    fit_seconds: float
    fit_rms_um: float = math.nan
    forms: tuple[tuple[str, float, float], ...] = ()

    @property
    def cause(self) -> str:
        """The cause this fit stands for (a second form's, :data:`afmctl.fit.candidates.FORMS`)."""
        return cd.FORMS.get(self.fitted.name, self.fitted.name)

    @property
    def label(self) -> str:
        """The cause, and the form fitted when it is a second form (for the reader)."""
        name = self.fitted.name
        return f"{self.cause} ({name})" if name in cd.FORMS else name

    def as_dict(self, base_rms: float, noise_um: float) -> dict[str, Any]:
        return {"heldout_rms_um": self.heldout_rms_um, "gain": ratio(base_rms, self.heldout_rms_um),
                "over_noise": ratio(self.heldout_rms_um, noise_um),
                "required_gain": required_gain(self.n_params), "parameters_added": self.n_params,
                "heldout_rms_per_sweep_um": list(self.heldout_per_sweep_um),
                "fit_rms_um": None if math.isnan(self.fit_rms_um) else self.fit_rms_um,
                "fitted": self.fitted.parameters, "fit_success": self.fitted.success,
                "fit_evaluations": self.fitted.nfev, "fit_seconds": round(self.fit_seconds, 2),
                "form": self.fitted.name,
                **({"forms": {n: {"fit_rms_um": f, "heldout_rms_um": h}
                              for n, f, h in self.forms}} if self.forms else {})}


@dataclass(frozen=True)
class Diagnosis:
    """Outcome of :func:`diagnose`: the verdict, held-out RMS (um) of the base and the extended
    model, the noise floor (um, overall and per sweep), the candidate table, both models fitted on
    the first halves (the extended one with its per-sweep applied-voltage gains; the base again if no
    cause is named), the residual signature, the wall time (s), every fitted sensor-side cause
    with its actuator-side twin (:func:`afmctl.fit.twins.pairs`) and, when the verdict is
    ``indistinguishable``, the sweep that would separate them
    (:func:`afmctl.fit.twins.separating_sweep`, with the pair's names), the causes on identify's
    general density with its hysteresis held (:mod:`afmctl.fit.heldbase`) when they were tried:
    then a verdict other than ``unexplained`` that is not the grid's is theirs, with their
    ``none`` as the base, and the Preisach grid without and with creep
    (:mod:`afmctl.fit.gridbase`) when it was fitted: then a verdict of ``creep`` or ``none`` is
    the grid's, and the base is the grid without creep."""

    cause: str
    base_rms_um: float
    extended_rms_um: float
    noise_um: float
    noise_per_sweep_um: tuple[float, ...]
    table: dict[str, Judged]
    base: ext.Extended
    extended: ext.Extended
    signature: dict[str, Any]
    seconds: float
    files: tuple[str, ...]
    twins: tuple[dict[str, Any], ...] = ()
    separating: dict[str, Any] | None = None
    grid: gb.GridBase | None = None
    held: HeldBase | None = None

    @property
    def on_grid(self) -> bool:
        """Whether the verdict is the Preisach grid's (its base the grid without creep)."""
        return self.grid is not None and self.cause in ("creep", "none")

    @property
    def on_held(self) -> bool:
        """Whether the verdict is that of the causes on identify's general density with its
        hysteresis held (:mod:`afmctl.fit.heldbase`)."""
        return self.held is not None and not self.on_grid and self.cause != "unexplained"

    @property
    def verdict_table(self) -> dict[str, Judged]:
        """The table the verdict was read from (the held base's or the paper's)."""
        return self.held.table if self.on_held and self.held is not None else self.table

    @property
    def base_name(self) -> str:
        if self.on_held:
            return HELD_BASE
        return "the Preisach grid without creep" if self.on_grid else "the paper's model"

    @property
    def paper_rms_um(self) -> float:
        """Held-out RMS of the paper's model (um): the candidates' base."""
        return self.table["none"].heldout_rms_um

    @property
    def gain(self) -> float:
        return ratio(self.base_rms_um, self.extended_rms_um)

    @property
    def base_model(self) -> td.Transducer:
        return self.base.model

    @property
    def extended_model(self) -> td.Transducer:
        """The extended model for ``track`` (``extended.toml``): the stage as the record left
        it (:attr:`afmctl.fit.extension.Extended.present`)."""
        return self.extended.present

    @property
    def kept_grid(self) -> bool:
        """Whether the model files are the Preisach grid without creep although no cause was
        named: the verdict ``unexplained``, the grid fitted and held out below the paper's
        model. An independent tester's lightly damped Preisach stage: the grid at 1.95x the
        noise, the paper's model at 55x; tracked with the paper's model (then
        ``extended.toml``), 0.90 um, 14x the identified grid's 0.064 um. Without creep: a
        drift the creep elements would absorb stays out (its hint says so)."""
        return (self.cause == "unexplained" and self.grid is not None
                and self.grid.plain_rms_um < self.paper_rms_um)

    @property
    def file_models(self) -> tuple[td.Transducer, td.Transducer]:
        """The models of ``base.toml`` and ``extended.toml``: the base and the extended model,
        or both the grid without creep (:attr:`kept_grid`; ``extended.toml`` as the record
        left the stage, as the grid's verdicts write it)."""
        if self.kept_grid and self.grid is not None:
            return self.grid.plain.model, self.grid.plain.present
        return self.base_model, self.extended_model

    @property
    def files_name(self) -> str:
        """What :attr:`file_models` are (``model_files`` of the JSON)."""
        return ("the Preisach grid without creep (no cause named)" if self.kept_grid
                else self.base_name)

    @property
    def file_over_noise(self) -> tuple[float, float]:
        """Held-out RMS over the noise of :attr:`file_models`."""
        if self.kept_grid and self.grid is not None:
            over = ratio(self.grid.plain_rms_um, self.noise_um)
            return over, over
        return self.base_over_noise, self.extended_over_noise

    @property
    def extended_gains(self) -> tuple[float | FloatArray, ...]:
        """Each sweep's applied-voltage gain (an array: one per sample, for a gain that drifts
        in time)."""
        return self.extended.gains

    def predictions(self, sweeps: Sequence[Sweep]) -> tuple[list[FloatArray], list[FloatArray]]:
        """Readings (um) the base and the extended model (fitted on the first halves; the
        grid's on the whole sweeps) predict for ``sweeps``, each sweep from its start, with its
        sensor zero and gain."""
        return predicted(self.base, sweeps), predicted(self.extended, sweeps)

    @property
    def base_over_noise(self) -> float:
        return ratio(self.base_rms_um, self.noise_um)

    @property
    def extended_over_noise(self) -> float:
        return ratio(self.extended_rms_um, self.noise_um)

    @property
    def closest(self) -> Judged:
        """The model (the paper's, a candidate, or one on the held base that was not refused)
        with the smallest held-out RMS."""
        return self._closest()[0]

    def _closest(self) -> tuple[Judged, float, str]:
        """:attr:`closest`, the held-out RMS of its table's base (um) and that base's name."""
        pool = [(j, self.paper_rms_um, "the paper's model") for j in self.table.values()]
        if self.held is not None:
            base = self.held.table["none"].heldout_rms_um
            pool += [(j, base, HELD_BASE) for j in self.held.judged.values()]
        return min(pool, key=lambda p: p[0].heldout_rms_um)

    @property
    def explanation(self) -> str:
        """The verdict's physical reading."""
        if self.cause == vd.INDISTINGUISHABLE:
            return cd.INDISTINGUISHABLE
        if self.on_grid:
            return gb.CAUSES[self.cause]
        if self.on_held and self.cause == "none":
            return HELD_NONE
        return cd.CAUSES.get(self.cause, cd.UNEXPLAINED)

    def closest_dict(self) -> dict[str, Any]:
        """The model nearest the floor: held-out RMS (um), over the noise, the fraction of its
        base model's misfit it explains (:func:`afmctl.fit.verdict.explained`), that base and a
        phrase."""
        c, base, base_name = self._closest()
        frac = vd.explained(base, c.heldout_rms_um, self.noise_um)
        return {"model": c.cause, "form": c.fitted.name, "heldout_rms_um": c.heldout_rms_um,
                "over_noise": ratio(c.heldout_rms_um, self.noise_um), "explained_fraction": frac,
                "base": base_name, "text": vd.closest_phrase(
                    c.label if base_name != HELD_BASE else f"{c.label} (on {base_name})", frac)}

    def suggestions(self) -> list[dict[str, str]]:
        """What would tell more: the residual's hints when unexplained, the separating sweep
        when indistinguishable, the reversal curves when creep was named on sweeps that reverse
        at few voltages inside their range (none otherwise)."""
        if self.cause == "unexplained":
            drift = [gb.DRIFT_HINT] if self.grid is not None and self.grid.drift() else []
            return drift + vd.suggestions(self.signature)
        if self.cause == "creep" and self.grid is not None:
            return self.grid.hints()
        if self.separating is not None:
            s = self.separating
            return [{"feature": "twins", "reading": f"{s['sensor']} and its actuator-side twin "
                     f"{s['actuator']} explain these sweeps equally well",
                     "measure": s["text"]}]
        return []

    def as_dict(self) -> dict[str, Any]:
        """The ``diagnosis.json`` object (and ``--json`` output); non-finite numbers are null."""
        return json_safe({
            "cause": self.cause, "explanation": self.explanation,
            "base_rms_um": self.base_rms_um, "extended_rms_um": self.extended_rms_um,
            "gain": self.gain, "noise_um": self.noise_um,
            "noise_per_sweep_um": list(self.noise_per_sweep_um),
            "base_over_noise": self.base_over_noise,
            "extended_over_noise": self.extended_over_noise,
            "closest": self.closest_dict(),
            "evidence": self.evidence(),
            "suggestions": self.suggestions(),
            "twins": list(self.twins), "separating_sweep": self.separating,
            "candidates": {k: j.as_dict(self.paper_rms_um, self.noise_um)
                           for k, j in self.table.items()},
            "base_model": self.base_name,
            "model_files": self.files_name,
            "grid": None if self.grid is None else self.grid.as_dict(),
            "held": None if self.held is None else self.held.as_dict(self.noise_um),
            "extended_gains": [float(np.mean(g)) for g in self.extended_gains],
            "residuals": self.signature, "sweeps": list(self.files),
            "seconds": round(self.seconds, 2),
            "method": "fit on the first half of every sweep, judged on the second half (state "
                      "carried through); each sweep weighs the same; every held-out RMS read "
                      "against the noise floor; " + (
                          "the verdict is the Preisach grid's (grid.method): the model files "
                          "are its fits on the whole sweeps" if self.on_grid else
                          "nothing explains the sweeps: the model files are the Preisach grid's "
                          "fit without creep on the whole sweeps (grid.method), the best model "
                          "fitted" if self.kept_grid else
                          "the verdict is that of the causes on identify's general density, its "
                          "hysteresis held (held): the model files are those fits on the first "
                          "halves" if self.on_held else
                          "the model files are the fits on the first halves")})

    def evidence(self) -> str:
        """One paragraph: why this cause (or none, or unexplained)."""
        ranked = sorted(self.table.values(), key=lambda j: j.heldout_rms_um)
        lines = [f"{j.label}: held-out {j.heldout_rms_um:.4f} um "
                 f"({ratio(j.heldout_rms_um, self.noise_um):.2f}x noise), gain "
                 f"{ratio(self.paper_rms_um, j.heldout_rms_um):.2f} (needs "
                 f"{required_gain(j.n_params):.2f})" for j in ranked[:3]]
        floor = (f"noise floor {self.noise_um:.4f} um; base model at "
                 f"{self.base_over_noise:.2f}x noise")
        if self.cause == "unexplained":
            c = self.closest
            head = (f"unexplained: {floor}, the closest model ({c.label}) at "
                    f"{ratio(c.heldout_rms_um, self.noise_um):.2f}x: nothing reaches the floor"
                    f" ({self.closest_dict()['text']})")
        elif self.separating is not None:
            s = self.separating
            sensor, twin = self.verdict_table[s["sensor"]], self.verdict_table[s["actuator"]]
            pair = next(p for p in self.twins if p["sensor"] == s["sensor"])
            head = (f"indistinguishable: {floor}; {s['sensor']} at "
                    f"{ratio(sensor.heldout_rms_um, self.noise_um):.2f}x and its actuator-side "
                    f"twin {s['actuator']} at {ratio(twin.heldout_rms_um, self.noise_um):.2f}x "
                    f"(the twin must miss by {s['needed']:.2f}x the sensor cause's RMS, held "
                    f"out and on the fitted halves, to separate them; it misses by "
                    f"{_misses(pair)}): these sweeps do "
                    f"not tell an effect in the sensor from one before the rod's dynamics, so the "
                    f"readings are kept uncorrected (the model is {self.base_name}'s)")
        else:
            fitted = fitted_text(self.extended.parameters)
            head = (f"{self.cause}: {floor}, held-out RMS {self.base_rms_um:.4f} -> "
                    f"{self.extended_rms_um:.4f} um (gain {self.gain:.2f}, "
                    f"{self.extended_over_noise:.2f}x noise)" + (f" with {fitted}" if fitted else ""))
        held = "" if self.held is None else self._held_text()
        grid = "" if self.grid is None else (
            f"; the paper's model and its extensions leave it unexplained (the paper's model at "
            f"{ratio(self.paper_rms_um, self.noise_um):.2f}x noise), so the Preisach grid was "
            f"fitted and judged on held-out blocks: {self.grid.text()}"
            + ("" if self.cause != "creep" or self.extended_over_noise <= vd.Rule().near else
               f"; with creep it is still {self.extended_over_noise:.2f}x the noise: the "
               f"grid's shape or a further effect is left"))
        return head + held + grid + "; best of the paper's family: " + "; ".join(lines)

    def _held_text(self) -> str:
        """What the causes on the held general density said (:meth:`evidence`)."""
        assert self.held is not None
        t, floor = self.held.judged, self.noise_um
        text = (f"; the paper's model and its extensions leave it unexplained (the paper's model "
                f"at {ratio(self.paper_rms_um, floor):.2f}x noise), so the causes were tried on "
                f"{HELD_BASE}: that model at {ratio(t['none'].heldout_rms_um, floor):.2f}x")
        causes = [j for n, j in t.items() if n != "none"]
        if causes:
            j = min(causes, key=lambda j: j.heldout_rms_um)
            text += (f", the best cause there ({j.fitted.name}) at "
                     f"{ratio(j.heldout_rms_um, floor):.2f}x")
        return text


def json_safe(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by None (JSON has no NaN or inf)."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _misses(pair: dict[str, Any]) -> str:
    """How far the twin of a :func:`afmctl.fit.twins.pairs` row misses against the sensor
    cause, held out and (if known) on the fitted halves."""
    held = f"{pair['actuator_over_sensor']:.2f}x held out"
    fitted = pair["actuator_over_sensor_fitted"]
    return held if fitted is None else f"{held} and {fitted:.2f}x fitted"
