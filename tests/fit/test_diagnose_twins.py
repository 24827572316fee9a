"""diagnose never hurts tracking (issue 23 item 4): a sensor-side cause is named only when the
sweeps separate it from its actuator-side twin.

On stages written independently of the fit: the modified Prandtl-Ishlinskii stage with a cubic
output map of :mod:`afmctl.drivers.device.foreign.family_stage` (the map acts before the rod's
dynamics; there is no gauge error), recorded through the driver in-process, and a stage of the
independent foreign plant (:mod:`afmctl.drivers.device.foreign.stage`) whose gauge has a
quadratic and cubic error (:mod:`afmctl.drivers.device.foreign.effects`), after a slow rod
(300 Hz) that a 27.9 Hz triangle shakes. Small sweep sets: every test costs one identification
at most; the in-family bench's two strong gauges are ``heavy`` (``pytest --heavy``: 100 s
together, the bench's full-size sets).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from afmctl.drivers.device.foreign import stage as plant
from afmctl.drivers.device.foreign.effects import random_effect
from afmctl.drivers.device.foreign.stages import random_stage
from afmctl.experiment import runner
from afmctl.files import sweepfile as sw
from afmctl.fit import diagnose as dg
from afmctl.fit import diagnosis_report
from afmctl.fit import identify as idf
from afmctl.fit import twins
from afmctl.planning import sweepdesign as sd
from afmctl.planning import track
from benchmarks import family_sets

#: (frequency Hz, cycles) of the small sweep sets, at the profile's 10 kHz.
SMALL = ((1.0, 2), (5.58, 3), (27.9, 5))
GAUGE_ONLY = ("none", "sensor-nonlinearity")  # its twin is added by diagnose


def _true_rms(s: family_sets.Session, model: object, desired: track.Desired) -> float:
    """RMS (um) of the stage's TRUE position against ``desired`` after its first period, the
    inverse filter planned with ``model`` and played through the driver."""
    wf = track.plan(model, desired, s.profile.limits, s.probe.voltage(), ("inverse",))["inverse"]
    s.probe.play(wf.voltage_v)
    err = s.probe.positions[-1][wf.tracking] - desired.u_um
    return family_sets.rms(err[int(round(desired.period_s / desired.dt_s)):])


def test_pi_stage_with_a_cubic_output_map_gets_no_sensor_correction() -> None:
    """The bench's pi-b stage (no gauge error): before, diagnose named sensor-nonlinearity
    (3.3x -> 1.89x the noise) and tracking with that model put the TRUE position 2.7x further
    off (0.559 um) than identify's model (0.210 um). Now the gauge and the same nonlinearity
    before the rod are not separated: ``indistinguishable``, the paper's model written,
    tracking as good as identify's, and a faster sweep suggested within the profile's slew.
    (The two fit their halves equally well, 1.83x the noise; held out the twin measured
    1.91x when this test was written and 2.16x on a later machine, which alone separated them.)"""
    case = family_sets.cases_named("pi-b")[0]
    with family_sets.session(case) as s:
        lo, hi, rate = s.profile.limits.v_min, s.profile.limits.v_max, s.profile.sample_rate_hz
        meta = {"layer_thickness_um": f"{s.profile.thickness_um:g}"}
        sweeps = [runner.record_sweep(s.probe, f"triangle_{hz:g}hz", hz,
                                      sd.loop(hz, lo, hi, n, rate), rate, meta)
                  for hz, n in SMALL]
        ident = idf.fit(sweeps, replace(idf.Settings(), representation="hem", restarts=0,
                                        density="parametric"))  # the model diagnose extends
        slew = s.profile.limits.slew_v_per_ms * 1e3  # V/s: the suggested sweep keeps to half
        d = dg.diagnose(sweeps, dg.Settings(candidates=GAUGE_ONLY, jobs=1, max_slew_v_per_s=slew),
                        start=ident.model)
        assert d.cause == "indistinguishable", d.evidence()
        assert d.extended_model.effects == ident.model.effects  # no sensor correction written
        a, b = family_sets.span_of(sweeps)
        desired = track.triangle(27.9, 0.6 * (b - a), 0.5 * (a + b), 3, 1 / rate)
        by_identify = _true_rms(s, ident.model, desired)
        by_diagnose = _true_rms(s, d.extended_model, desired)
    assert by_diagnose <= 1.2 * by_identify, (by_diagnose, by_identify)
    doc = d.as_dict()
    (pair,) = doc["twins"]
    assert pair["sensor"] == "sensor-nonlinearity" and not pair["separated"]
    assert pair["actuator_over_sensor_fitted"] < 1.1
    sweep = doc["separating_sweep"]
    assert sweep["sensor"] == "sensor-nonlinearity" and sweep["kind"] in ("triangle", "step")
    assert all(r["slew_V_per_s"] <= twins.SLEW_SHARE * slew * (1 + 1e-9) for r in sweep["tried"])
    assert sweep["difference_over_noise"] == pytest.approx(
        sweep["difference_um"] / d.noise_um)
    assert "do not tell an effect in the sensor from one before the rod's dynamics" in (
        doc["evidence"])
    assert doc["suggestions"][0]["measure"] == sweep["text"]
    assert "readings are kept uncorrected" in doc["explanation"]
    closest = doc["closest"]  # issue 23 item 7: how much of the misfit the closest explains
    frac = (d.base_rms_um ** 2 - closest["heldout_rms_um"] ** 2) / (d.base_rms_um ** 2
                                                                     - d.noise_um ** 2)
    assert closest["explained_fraction"] == pytest.approx(frac) and 0.5 < frac < 1.0
    assert closest["text"].startswith(f"closest: {closest['model']}, explains "
                                      f"{100 * frac:.0f} % of the misfit")


def _gauge_stage_sweeps(sets: tuple[tuple[float, int], ...]) -> list[sw.Sweep]:
    """Triangles over 0-150 V at 10 kHz, in sequence, on a foreign stage (300 Hz rod, damping
    0.05) with a quadratic and cubic gauge error (strength 0.5: 3.7x the noise on the paper's
    model)."""
    rng = np.random.default_rng(3)
    clean = random_stage(rng, drive_range_V=(0.0, 150.0), resonance_hz=300.0,
                         damping_ratio=0.05)
    stage = replace(clean, effects=(random_effect("sensor-nonlinearity", rng, clean, 0.5),))
    state, out = plant.initial_state(stage, "poled+"), []
    for hz, cycles in sets:
        v = sd.loop(hz, 0.0, 150.0, cycles, 10_000.0)
        _, reading, state = plant.run(stage, v, 10_000.0, state, rng)
        out.append(sw.from_arrays(v, reading, 10_000.0, {
            "frequency_hz": f"{hz:g}",
            "layer_thickness_um": f"{stage.material.layer_thickness_um:.6g}"}, f"tri_{hz:g}"))
    return out


def test_a_real_gauge_is_named_when_a_fast_triangle_separates_it() -> None:
    """The gauge after a 300 Hz rod: the 27.9 Hz triangle shows it acting on the shaken
    displacement (gauge 1.04x the noise, the same nonlinearity before the rod 2.7x): named,
    and written into the model."""
    d = dg.diagnose(_gauge_stage_sweeps(((1.0, 2), (27.9, 5))),
                    dg.Settings(candidates=GAUGE_ONLY, jobs=1))
    assert d.cause == "sensor-nonlinearity", d.evidence()
    assert d.extended_over_noise < 1.5
    assert d.extended_model.effects.sensor_cubic_per_um2 != 0.0
    (pair,) = d.twins
    assert pair["separated"] and pair["actuator_over_sensor"] > 1.5


def test_without_the_fast_triangle_the_verdict_says_which_sweep_would_separate() -> None:
    """The same stage and gauge on slow triangles alone: the two explain them equally well
    (both 1.04x): ``indistinguishable``, no correction, and the sweep suggested is a triangle
    between the recorded 5.58 Hz and the 27.9 Hz one that does separate them (above)."""
    d = dg.diagnose(_gauge_stage_sweeps(((1.0, 2), (5.58, 3))),
                    dg.Settings(candidates=GAUGE_ONLY, jobs=1))
    assert d.cause == "indistinguishable", d.evidence()
    assert d.extended_model.effects.sensor_cubic_per_um2 == 0.0
    s = d.separating
    assert s is not None and s["separates"] and s["kind"] == "triangle"
    assert 5.58 < s["frequency_hz"] <= 27.9 and s["difference_over_noise"] >= twins.SEPARATES
    assert s["text"].startswith(f"record a triangle at {s['frequency_hz']:.4g} Hz over 0 .. 150 V")
    assert "# afmctl diagnose: indistinguishable" in diagnosis_report.report(d, "residuals.png")
    from afmctl.cli.diagnose import _record  # the [fit] record both model files carry
    for extended in (False, True):
        assert "not separated by these sweeps" in _record(d, ("a.csv",), extended).verdict


@pytest.mark.heavy
@pytest.mark.parametrize(("strength", "index"), [(0.5, 104), (0.9, 114)])
def test_a_strong_gauge_is_named_with_its_cubic(strength: float, index: int) -> None:
    """The in-family bench's strong gauges (the independent plant). Index 104, a gauge polynomial
    about a centre 164 um with a half range of 28 um (52x the noise at the range end): from the
    five small starts the gauge stopped on its cubic's bound at 3.3x the noise and its twin (1.6x)
    refuted it; from the grid of starts it is named. Index 114 (19.6x on the paper's model): the
    local refit through the gauge left 5.2x; with identify's global fit beside it, named. Each
    near the floor, its cubic (frame-free up to the calibration's gain) the plant's ``q3 / R^2``
    within 20 %."""
    from benchmarks import bench_diagnose

    stage, sweeps, _, truth = bench_diagnose.make_stage("sensor-nonlinearity", strength, index)
    (gauge,) = stage.effects
    d = dg.diagnose(sweeps, dg.Settings(candidates=GAUGE_ONLY, jobs=1, held=False, grid=False))
    assert d.cause == "sensor-nonlinearity", d.evidence()
    assert d.extended_rms_um < 1.5 * d.noise_um
    cubic = d.table["sensor-nonlinearity"].fitted.parameters["cubic_per_um2"]
    assert cubic == pytest.approx(gauge.cubic / gauge.half_range_um ** 2, rel=0.2)
    assert truth["strength_used"] > 0.5  # the strong draw, as the bench makes it
