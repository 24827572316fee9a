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
