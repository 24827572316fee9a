"""Thermal relaxation's second form (:mod:`afmctl.model.viscous`: the hysterons see the field
through a first-order lag) named on an out-of-family plant that afmctl was not built from.

The stage is one of the bench's other-form stages (:mod:`afmctl.drivers.device.foreign.family_stage`:
a Preisach operator stepped in substeps, the operator's input lagged by ``tau_visc``) with a seed
the bench does not use, recorded through the driver. Diagnose fits the form alone (the
catalogue's kernel (10) takes ten minutes there; the bench fits both).
"""

from __future__ import annotations

import dataclasses as dc
from pathlib import Path

import numpy as np
import pytest

from afmctl.drivers.device.foreign.family_physics import family_stage_of
from afmctl.fit import candidates as cd
from afmctl.fit import diagnose as dg
from afmctl.fit import identify as idf
from afmctl.files import modelfile
from benchmarks import family_sets

CASE = family_sets.Case("viscous-held-out", "preisach", seed=417, density="separable",
                        effect="thermal-relaxation", reversals=False)


@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory: pytest.TempPathFactory) -> tuple[dg.Diagnosis, list, float]:
    folder = tmp_path_factory.mktemp("viscous")
    with family_sets.session(CASE) as s:
        sweeps = family_sets.record(s, folder / "sweeps")
    d = dg.diagnose(sweeps, dg.Settings(jobs=1, candidates=("none", "viscous-relaxation"),
                                        held=False, grid=False))
    tau = family_stage_of(CASE.spec, CASE.drive_V).extras.viscous_tau_s
    return d, sweeps, tau


@pytest.mark.slow
def test_the_viscous_form_is_named_thermal_relaxation(diagnosed) -> None:
    """Named ``thermal-relaxation`` in its viscous form, the plant's relaxation time found within
    15 %, the paper's model's held-out misfit cut more than five-fold; the table keeps the cause's
    name alone."""
    d, _, tau = diagnosed
    assert d.cause == "thermal-relaxation", d.evidence()
    row = d.as_dict()["candidates"]["thermal-relaxation"]
    assert row["form"] == "viscous-relaxation"
    assert set(row["forms"]) == {"viscous-relaxation"}
    found = row["fitted"]["relaxation_time_s"]
    assert abs(found / tau - 1) < 0.15, (found, tau)
    assert d.base_over_noise > 5 * d.extended_over_noise, d.evidence()
    assert set(d.as_dict()["candidates"]) == {"none", "thermal-relaxation"}
    assert "viscous-relaxation" not in cd.NAMES  # a form, never a cause of its own


@pytest.mark.slow
def test_the_written_model_predicts_what_the_fit_was_judged_by(diagnosed, tmp_path: Path) -> None:
    """``extended.toml`` holds the lag (``[polarization.viscous]``), and the model read back,
    simulated sample by sample through the transducer, misses the fitted halves by the fit's own
    RMS (within 5 %); without the lag its readings move by more than ten times that."""
    d, sweeps, _ = diagnosed
    path = tmp_path / "extended.toml"
    modelfile.write(d.extended.model, path)
    back = modelfile.read(path)
    assert back.viscous is not None and back == d.extended.model
    halves = [dg.first_half(s) for s in sweeps]
    fitted = d.table["thermal-relaxation"]
    got = idf.predict_set(back, halves, d.extended.starts, d.extended.offsets_um)
    err = [float(np.sqrt(np.mean((s.displacement_um - u)[s.mask(None)] ** 2)))
           for s, u in zip(halves, got, strict=True)]
    rms = float(np.sqrt(np.mean(np.square(err))))
    assert abs(rms / fitted.fit_rms_um - 1) < 0.05, (rms, fitted.fit_rms_um)
    without = dc.replace(back, viscous=None)
    off = idf.predict_set(without, halves, d.extended.starts, d.extended.offsets_um)
    assert max(float(np.max(np.abs(a - b))) for a, b in zip(got, off, strict=True)) > 10 * rms


def test_the_fits_samples_follow_a_lagged_field_through_holds_and_steps(profile) -> None:
    """The candidate's residual runs the hysterons on a subset of the samples and draws a line
    between them; on the separating design's holds and fast steps a lagged field keeps moving
    while the command rests. Its ``Q`` equals the hysteresis run on every sample of the lagged
    field to 0.5 % of the range (:func:`afmctl.fit.candidate_space.settling`); on the command's
    samples and the lagged field's turning points alone it missed by more than 5 %."""
    from afmctl.files import sweepfile
    from afmctl.fit import candidate_space as cs
    from afmctl.fit import parametrization as pz
    from afmctl.model import viscous as vs
    from afmctl.planning import sweepdesign as sd

    fs, lim = profile.sample_rate_hz, profile.limits
    v, _ = sd.separating_sweep((lim.v_min, lim.v_max), fs, lim.max_rate_v_per_ms * 1e3)
    prep = pz.prepare(sweepfile.from_arrays(v, np.zeros_like(v), fs), profile.thickness_um,
                      0.001, None)
    cand = cd.catalogue(1, float(np.max(np.abs(prep.field))), fs / 2, 300.0,
                        cd.field_rate_max([prep]))["viscous-relaxation"]
    space = cs.ExtendedSpace(cand, [prep], pz.LognormalSpace([prep], pz.Scales(), 64,
                                                              ("depoled",)), 0.001, 50.0)
    theta = np.array([0.6, 0.4, 0.1, 0.5, 300.0, 0.3])
    for tau in (1e-3, 2.5e-3, 1e-2):
        e_v = vs.lagged(vs.Viscous(tau), prep.field, prep.dt, float(prep.field[0]))[0]
        full = pz.hysteresis(theta, [e_v], 64, starts=("depoled",))[0] + (prep.field - e_v)
        got = space._q(theta, np.array([np.log(tau)]))[0]
        assert np.max(np.abs(got - full)) < 0.005 * np.ptp(full), tau
        sparse = np.union1d(prep.keep, pz.turning_points(e_v))
        line = pz.at_full_rate(e_v.size, sparse, pz.hysteresis(
            theta, [e_v[sparse]], 64, starts=("depoled",))[0]) + (prep.field - e_v)
        assert np.max(np.abs(line - full)) > 0.05 * np.ptp(full), tau
