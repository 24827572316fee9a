"""afmctl diagnose on foreign stages (an independent simulator, hidden effects made by other physics
than the candidates): a clean stage gets ``none`` at the noise floor, an effect is named, an effect
outside the vocabulary comes out ``unexplained``; the CLI's JSON; the extended model tracks better
on a stage carrying an effect; each candidate's residual vanishes at its truth.

The CI subset runs three foreign stages made as ``benchmarks/bench_diagnose.py`` makes its 31 (two of
them with a few candidates only, to stay short); the bench runs all candidates on all stages."""

from __future__ import annotations

import dataclasses as dc
import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.experiment import runner as experiment
from afmctl.files import sweepfile as sw
from afmctl.files import twinfile
from afmctl.fit import candidate_space, candidates, verdict
from afmctl.fit import diagnose as dg
from afmctl.model import effects as fx
from afmctl.model import transducer as tr
from afmctl.planning import sweepdesign as sd
from afmctl.planning import track
from benchmarks import bench_diagnose as bench
from tests.harness.emulated import PROFILE


def stage_sweeps(cause: str, strength: float | None, index: int) -> list[sw.Sweep]:
    return bench.make_stage(cause, strength, index, refit=False)[1]


@pytest.mark.slow
@pytest.mark.parametrize(("cause", "strength", "index", "candidates", "verdict"), [
    ("sensor-delay", 0.9, 101, ("none", "sensor-delay", "sensor-nonlinearity"), "sensor-delay"),
    ("interference", 0.9, 102, ("none", "sensor-delay", "sensor-nonlinearity"), "unexplained"),
], ids=["delay", "interference"])
def test_foreign_stage_verdict(cause: str, strength: float, index: int,
                               candidates: tuple[str, ...], verdict: str) -> None:
    d = dg.diagnose(stage_sweeps(cause, strength, index), dg.Settings(candidates=candidates))
    assert d.cause == verdict, d.evidence()
    if verdict == "unexplained":
        assert d.base_over_noise > 2.0 and d.extended_rms_um == d.base_rms_um
        assert d.as_dict()["suggestions"], d.signature
    else:
        assert d.extended_over_noise < 2.0 and d.gain > 1.1, d.evidence()


@pytest.mark.slow
def test_cli_on_a_clean_foreign_stage_claims_nothing(tmp_path: Path) -> None:
    (tmp_path / "sweeps").mkdir()
    t0 = 1000.0  # one after another, 0.5 s apart, but at three rates: no twin can follow them
    for s in stage_sweeps("none", None, 0):
        sw.write(sw.from_arrays(s.voltage_v, s.displacement_um, 1 / s.dt,
                                {**s.meta, "started_s": f"{t0:.6f}"}),
                 tmp_path / "sweeps" / f"{s.path}.csv")
        t0 += s.voltage_v.size * s.dt + 0.5
    files = sorted(str(p) for p in (tmp_path / "sweeps").glob("*.csv"))
    out = tmp_path / "diag"
    res = CliRunner().invoke(main, ["diagnose", *files, "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    assert doc["cause"] == "none", doc["evidence"]
    assert doc["gain"] == pytest.approx(1.0)
    assert doc["base_rms_um"] == doc["extended_rms_um"]
    assert doc["base_over_noise"] == pytest.approx(doc["base_rms_um"] / doc["noise_um"])
    assert doc["base_over_noise"] < 1.5 and doc["extended_over_noise"] < 1.5
    assert set(doc["candidates"]) == set(candidates.NAMES) | set(candidates.TWIN_ONLY)
    for row in doc["candidates"].values():
        assert {"heldout_rms_um", "gain", "required_gain", "parameters_added", "over_noise"} <= set(row)
    assert json.loads((out / "diagnosis.json").read_text()) == doc
    for name in ("base.toml", "extended.toml", "report.md", "residuals.png"):
        assert (out / name).stat().st_size > 0
    assert "twin.json" not in res.stderr and not list(out.glob("*.twin.json"))
    assert "no twin written: the sweeps do not say every hold" in res.stderr  # nor identify:
    res = CliRunner().invoke(main, ["identify", *files, "-o", str(tmp_path / "m.toml")])
    assert res.exit_code == 0 and "no twin written" in res.stderr, res.output
    assert not (tmp_path / "m.twin.json").exists()
    again = CliRunner().invoke(main, ["diagnose", *files, "--out", str(out)])
    assert again.exit_code == 2 and "already holds a diagnosis" in again.stderr


@pytest.mark.slow
def test_cli_leaves_each_models_twin_beside_it(nominal, tmp_path: Path) -> None:  # noqa: ANN001
    """A sweep that says when it started: base.toml and extended.toml each get their twin of the
    stage as the sweep left it (of that model file, as track checks), and a second diagnosis
    with --force on a sweep that does not say removes them rather than leave them stale."""
    v = sd.voltage_triangle(27.9, 150.0, 3, 10_000.0)
    u, _, _ = tr.simulate(tr.compile_model(nominal, 1e-4), v, tr.initial(nominal))
    u = u + np.random.default_rng(0).normal(0.0, 0.02, u.size)
    timed = {"layer_thickness_um": f"{nominal.thickness_um:g}", "started_s": "1000.0"}
    sw.write(sw.from_arrays(v, u, 10_000.0, timed), tmp_path / "timed.csv")
    out = tmp_path / "diag"
    res = CliRunner().invoke(main, ["diagnose", str(tmp_path / "timed.csv"), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "wrote base.twin.json, extended.twin.json" in res.stderr
    for name in ("base", "extended"):
        kept = twinfile.read(out / f"{name}.twin.json")
        assert kept.model_sha256 == twinfile.digest(out / f"{name}.toml")
        assert kept.held_v == pytest.approx(float(v[-1]))
    del timed["started_s"]
    sw.write(sw.from_arrays(v, u, 10_000.0, timed), tmp_path / "untimed.csv")
    res = CliRunner().invoke(main, ["diagnose", str(tmp_path / "untimed.csv"), "--out", str(out),
                                    "--force"])
    assert res.exit_code == 0, res.output
    assert not list(out.glob("*.twin.json"))


def test_bad_input_exits_2_and_writes_nothing(tmp_path: Path, nominal) -> None:  # noqa: ANN001
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,voltage_V\n0,0\n0.001,1\n")
    out = tmp_path / "diag"
    res = CliRunner().invoke(main, ["diagnose", str(bad), "--out", str(out)])
    assert res.exit_code == 2 and len(res.stderr.strip().splitlines()) == 1, res.output
    good = tmp_path / "good.csv"
    v = sd.voltage_triangle(27.9, 150.0, 2, 10_000.0)
    sw.write(sw.from_arrays(v, v / 5, 10_000.0), good)
    from afmctl.files import modelfile
    modelfile.write(nominal, tmp_path / "m.toml")  # a model with a misspelt key
    (tmp_path / "m.toml").write_text((tmp_path / "m.toml").read_text().replace("k_N_per_m",
                                                                                "k_N_per_mm"))
    res = CliRunner().invoke(main, ["diagnose", str(good), "--model", str(tmp_path / "m.toml"),
                                    "--out", str(out)])
    assert res.exit_code == 2 and "k_N_per_m" in res.stderr, res.output
    assert len(res.stderr.strip().splitlines()) == 1 and not out.exists()
    # a general coercive density (identify's) is taken since issue 27 item 5:
    # tests/fit/test_parametrization.py::test_a_general_density_model_starts_the_lognormal_fits


def test_required_gain_grows_with_parameters() -> None:
    assert verdict.required_gain(0) == 1.0
    assert verdict.required_gain(1) == pytest.approx(1.1)
    assert verdict.required_gain(3) == pytest.approx(1.2)


@pytest.mark.parametrize("effects", [fx.Effects(sensor_delay_samples=5.0),
                                     fx.Effects(amplifier_bandwidth_hz=300.0),
                                     fx.Effects(second_mode=fx.SecondMode(650.0, 0.03, 0.45))],
                         ids=["sensor-delay", "amplifier-lag", "second-mode"])
def test_track_with_extended_model_beats_base_on_stage_with_effect(
        effects: fx.Effects, tmp_path: Path) -> None:
    """Judged by the readings as each model corrects them and by the stage's true position (the
    emulator's plant between samples); the models are the truth without and with the effect
    (diagnose's own output is used end to end in benchmarks/bench_diagnose.py). A sensor delay
    does not move the stage: with the true plant both runs move it alike, and only the extended
    model reads it right."""
    from afmctl.drivers.inprocess import InProcessStage, accelerated
    assert PROFILE.emulator is not None
    prof = dc.replace(PROFILE, emulator=dc.replace(PROFILE.emulator, effects=effects))
    assert prof.emulator is not None
    base = PROFILE.emulator.model
    desired = track.triangle(27.9, 27.04, 0.0, 3, 1 / prof.sample_rate_hz)
    scores = {}
    with InProcessStage(prof, clock=accelerated(4.0)) as stage:
        for name, model in (("base", base), ("extended", dc.replace(base, effects=effects))):
            plans = track.plan(model, desired, prof.limits, stage.voltage(), ("inverse",))
            runs = experiment.run_all(stage, plans, desired, tmp_path / name, {},
                                      prof.emulator.true_model, sensor=model.effects)
            scores[name] = runs["inverse"].score
    ext, base_score = scores["extended"], scores["base"]
    assert ext.rms_um < 0.5 * base_score.rms_um, scores  # the readings, each model's correction
    assert ext.rms_between_um is not None and base_score.rms_between_um is not None
    if fx.sensor_part(effects) == effects:  # the sensor only misreports: the same true motion
        assert ext.rms_between_um == pytest.approx(base_score.rms_between_um, rel=1e-9)
    else:  # the effect moves the stage: its inverse moves it better
        assert ext.rms_between_um < 0.5 * base_score.rms_between_um, scores


@pytest.mark.parametrize(("name", "effects", "phi", "gains", "tol_um"), [
    ("none", fx.Effects(), [], (1.0, 1.0), 1e-4),
    ("amplifier-lag", fx.Effects(amplifier_bandwidth_hz=300.0, amplifier_damping_ratio=0.5,
                                 amplifier_slew_v_per_s=6e3),  # below the 27.9 Hz rate
     [math.log(300.0), math.log(0.5), math.log(6e3 / 100.0)], (1.0, 1.0), 5e-3),
    ("sensor-delay", fx.Effects(sensor_delay_s=3e-4), [3.0], (1.0, 1.0), 1e-4),
    ("second-mode", fx.Effects(second_mode=fx.SecondMode(600.0, 0.03, 0.4)),
     [math.log(600.0), math.log(0.03), 0.4, 0.0], (1.0, 1.0), 1e-4),
    ("voltage-gain-drift", fx.Effects(), [-math.log(1.015)], (1 / 1.015, 1.015), 1e-4),
    ("sensor-nonlinearity", fx.Effects(sensor_quadratic_per_um=2e-3, sensor_cubic_per_um2=-2e-5,
                                       sensor_center_um=40.0, sensor_half_range_um=35.0),
     None, (1.0, 1.0), 1e-4),
])
def test_candidate_residual_vanishes_at_the_truth(name: str, effects: fx.Effects, phi: list | None,
                                                  gains: tuple[float, float], tol_um: float,
                                                  nominal) -> None:  # noqa: ANN001
    """What a candidate fits (its design columns and target) is what ``identify.predict`` says
    the extended model does: noise-free data of the true model with the effect leave a residual
    at the true parameters below the fit's approximations (decimation: 2.4 nm for the lag)."""
    from afmctl.fit import identify as idf
    from afmctl.fit import parametrization as pz
    fs = 10_000.0
    truth = dc.replace(nominal, effects=effects)
    volts = [sd.voltage_triangle(27.9, 150.0, 2, fs), sd.voltage_triangle(5.58, 150.0, 1, fs)]
    sweeps = [sw.from_arrays(v, idf.predict(truth, v, 1 / fs, g), fs)
              for v, g in zip(volts, gains, strict=True)]
    preps = [pz.prepare(s, nominal.thickness_um, 0.004, None) for s in sweeps]
    base = pz.LognormalSpace(preps, pz.Scales(), 256)
    range_um = max(float(np.ptp(p.y)) for p in preps)
    x = pz.internal(nominal)
    cand = candidates.catalogue(2, *pz.extent(preps), float(np.exp(x[4])),
                               candidates.field_rate_max(preps))[name]
    frame = (effects.sensor_center_um, effects.sensor_half_range_um)
    space = candidate_space.ExtendedSpace(cand, preps, base, 0.004, range_um,
                                    gauge_frame=frame if name == "sensor-nonlinearity" else None)
    z = np.concatenate((x, phi if phi is not None else [2e-3 * range_um, -2e-5 * range_um ** 2]))
    r = space.residual(z)
    assert np.sqrt(np.mean(r ** 2)) < tol_um


def test_the_summary_counts_a_worse_track_only_the_model_foresaw() -> None:
    """``track_extended_worse_foreseen``: of the cases the extended model tracked worse, those
    whose own predicted RMS had been at least half its true one (the bench's amplifier lag of
    strength 0.9: true 11.5 / 13.8 um, the extended model predicting 15.4 um); not a model that
    promised 0.09 um and missed by 9.5 (its strong sensor delay), nor one that tracked better."""
    def row(cause: str, base: float, ext: float, pred: float | None) -> dict[str, object]:
        return {"cause": cause, "named": cause, "seconds": 1.0, "track_base_rms_um": base,
                "track_extended_rms_um": ext, "track_extended_predicted_rms_um": pred}

    rows = [row("amplifier-lag", 11.5, 13.8, 15.4), row("sensor-delay", 4.4, 9.5, 0.085),
            row("sensor-delay", 0.26, 0.014, 0.01), row("second-mode", 0.5, 0.9, None)]
    s = bench.summary(rows)
    assert s["track_extended_beats_base"] == 1 and s["track_cases"] == 4
    assert s["track_extended_worse_foreseen"] == 1
