"""One catalogue of causes (:data:`afmctl.fit.candidates.CAUSES`): every list of causes elsewhere
agrees with it, so a cause added to diagnose cannot be missing from the emulated device, the
foreign plant or the benchmarks that judge it."""

from __future__ import annotations

from afmctl.drivers.device import plant
from afmctl.drivers.device.foreign import effects as foreign_effects
from afmctl.files import profile
from afmctl.fit import candidates as cd
from afmctl.fit import diagnose as dg
from benchmarks import bench_diagnose, bench_learn, foreign_learn

VOCABULARY = set(cd.NAMES) - {"none"}


def test_the_catalogue_names_every_candidate_once_with_its_physics() -> None:
    assert cd.NAMES[0] == "none" and len(set(cd.NAMES)) == len(cd.NAMES)
    assert all(len(text) > 40 for text in cd.CAUSES.values())
    forms = set(cd.FORMS)
    assert set(cd.SLOWEST_FIRST) <= VOCABULARY | forms and set(cd.INPUT_SIDE) <= VOCABULARY | forms
    assert dg.Settings().candidates == cd.NAMES


def test_every_second_form_is_fitted_as_a_candidate_of_its_cause() -> None:
    """A form is a cause of the vocabulary written another way: in the catalogue, never a
    cause of its own, fitted whenever its cause is."""
    cat = cd.catalogue(3, 1.5, 5000.0, 300.0, 30.0)
    assert set(cd.FORMS.values()) <= VOCABULARY and not set(cd.FORMS) & set(cd.NAMES)
    assert set(cd.FORMS) <= set(cat)
    assert dg.with_forms(["none", "thermal-relaxation"]) == ["none", "thermal-relaxation",
                                                              "viscous-relaxation"]
    assert dg.with_forms(["none", "amplifier-lag"]) == ["none", "amplifier-lag"]


def test_the_emulated_device_hides_every_cause_of_the_catalogue() -> None:
    assert set(plant.HIDDEN_RANGES) == VOCABULARY


def test_the_foreign_plant_writes_every_cause_and_three_beyond_it() -> None:
    written = set(foreign_effects.CAUSES)
    assert written - set(foreign_effects.OUT_OF_VOCABULARY) == VOCABULARY
    assert set(profile.FOREIGN_CAUSES) == written


def test_the_benchmarks_judge_every_cause() -> None:
    assert set(bench_diagnose.IN_VOCABULARY) == VOCABULARY
    assert set(bench_learn.CAUSES) == VOCABULARY
    assert set(foreign_learn.CAUSES) == set(cd.NAMES)


def test_a_cause_keeps_the_form_that_fits_its_halves_best() -> None:
    """``in_forms``: the better fit on the fitted halves wins under the cause's name (a NaN fit
    RMS never wins), the held-out halves play no part, and a form asked for alone stands for its
    cause; each form's figures are recorded."""
    from dataclasses import replace as rep

    from afmctl.fit.diagnosis import Judged
    from afmctl.fit.extension import Extended

    def judged(name: str, fit_rms: float, heldout: float) -> Judged:
        ext = Extended(name, None, (), {}, True, 1, None, (), (), None)  # type: ignore[arg-type]
        return Judged(ext, 1, heldout, (heldout,), 1.0, fit_rms)

    kernel, viscous = judged("thermal-relaxation", 0.3, 0.1), judged("viscous-relaxation", 0.05, 0.2)
    out = dg.in_forms({"none": judged("none", 1.0, 1.0), "thermal-relaxation": kernel,
                       "viscous-relaxation": viscous})
    assert list(out) == ["none", "thermal-relaxation"]
    won = out["thermal-relaxation"]
    assert won.fitted.name == "viscous-relaxation" and won.cause == "thermal-relaxation"
    assert won.label == "thermal-relaxation (viscous-relaxation)"
    assert won.forms == (("thermal-relaxation", 0.3, 0.1), ("viscous-relaxation", 0.05, 0.2))
    nan = dg.in_forms({"thermal-relaxation": rep(kernel, fit_rms_um=float("nan")),
                       "viscous-relaxation": rep(viscous, fit_rms_um=9.0)})
    assert nan["thermal-relaxation"].fitted.name == "viscous-relaxation"
    alone = dg.in_forms({"viscous-relaxation": viscous})
    assert list(alone) == ["thermal-relaxation"] and alone["thermal-relaxation"] is not viscous
    assert dg.with_forms(["thermal-relaxation", "viscous-relaxation"]) == [
        "thermal-relaxation", "viscous-relaxation"]
