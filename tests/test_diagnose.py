"""afmctl diagnose: a hidden effect on the emulated stage is found, named and gains on held-out data;
clean data claims nothing; the extended model tracks better on a stage carrying the effect.

The CI subset runs four cases of the seeded batch of ``benchmarks/bench_diagnose.py``
(:func:`afmctl.emulator.hidden_cases`; the bench runs all 14: two per cause, ``none`` included)."""

from __future__ import annotations

import dataclasses as dc
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import PROFILE

from afmctl import calibration, experiment, extension, track
from afmctl import diagnose as dg
from afmctl import emulator as em
from afmctl import effects as fx
from afmctl import sweeps as sw
from afmctl.cli import main
from afmctl.profile import Profile

def record(profile: Profile, out: Path) -> list[sw.Sweep]:
    """The standard triangles recorded on the stage through the driver interface (device clock
    4x real time)."""
    from drivers.inprocess import InProcessStage, accelerated
    with InProcessStage(profile, clock=accelerated(4.0)) as stage:
        return calibration.record_standard(stage, profile, out)


CI_CASES = [c for c in em.hidden_cases(extension.NAMES) if c in {("thermal-relaxation", 2), ("second-mode", 11),
                                         ("voltage-gain-drift", 12), ("sensor-delay", 6)}]


@pytest.mark.slow
@pytest.mark.parametrize(("cause", "index"), CI_CASES)
def test_hidden_effect_is_named_with_gain(cause: str, index: int, tmp_path: Path) -> None:
    d = dg.diagnose(record(em.with_hidden_effect(PROFILE, cause, index), tmp_path))
    assert d.cause == cause, d.evidence()
    assert d.gain >= 2.0, d.evidence()
    assert d.extended_model != d.base_model


@pytest.mark.slow
def test_cli_on_clean_sweeps_claims_nothing(tmp_path: Path) -> None:
    record(PROFILE, tmp_path / "sweeps")
    files = sorted(str(p) for p in (tmp_path / "sweeps").glob("*.csv"))
    out = tmp_path / "diag"
    res = CliRunner().invoke(main, ["diagnose", *files, "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    assert doc["cause"] == "none", doc["evidence"]
    assert doc["gain"] == pytest.approx(1.0)
    assert doc["base_rms_um"] == doc["extended_rms_um"] < 1.2 * PROFILE.emulator.noise_um  # type: ignore[union-attr]
    assert set(doc["candidates"]) == set(extension.NAMES)
    for row in doc["candidates"].values():
        assert {"heldout_rms_um", "gain", "required_gain", "parameters_added"} <= set(row)
        assert row["gain"] < row["required_gain"] or row is doc["candidates"]["none"]
    assert json.loads((out / "diagnosis.json").read_text()) == doc
    for name in ("base.toml", "extended.toml", "report.md", "residuals.png"):
        assert (out / name).stat().st_size > 0
    again = CliRunner().invoke(main, ["diagnose", *files, "--out", str(out)])
    assert again.exit_code == 2 and "already holds a diagnosis" in again.stderr


def test_bad_input_exits_2_and_writes_nothing(tmp_path: Path, nominal) -> None:  # noqa: ANN001
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,voltage_V\n0,0\n0.001,1\n")
    out = tmp_path / "diag"
    res = CliRunner().invoke(main, ["diagnose", str(bad), "--out", str(out)])
    assert res.exit_code == 2 and len(res.stderr.strip().splitlines()) == 1, res.output
    good = tmp_path / "good.csv"
    v = sw.triangle(27.9, 150.0, 2, 10_000.0)
    sw.write(sw.from_arrays(v, v / 5, 10_000.0), good)
    from afmctl import hysteresis as hy
    from afmctl import modelfile
    discrete = dc.replace(nominal, polarization=dc.replace(
        nominal.polarization, coercive=hy.Discrete((0.5, 1.0), (0.5, 0.5))))
    modelfile.write(discrete, tmp_path / "m.toml")
    res = CliRunner().invoke(main, ["diagnose", str(good), "--model", str(tmp_path / "m.toml"),
                                    "--out", str(out)])
    assert res.exit_code == 2 and "lognormal" in res.stderr, res.output
    assert not out.exists()


def test_required_gain_grows_with_parameters() -> None:
    assert dg.required_gain(0) == 1.0
    assert dg.required_gain(1) == pytest.approx(1.1)
    assert dg.required_gain(3) == pytest.approx(1.2)


@pytest.mark.parametrize("effects", [fx.Effects(sensor_delay_samples=5.0),
                                     fx.Effects(amplifier_bandwidth_hz=300.0)],
                         ids=["sensor-delay", "amplifier-lag"])
def test_track_with_extended_model_beats_base_on_stage_with_effect(
        effects: fx.Effects, tmp_path: Path) -> None:
    """The model track inverts: the truth without and with the effect (diagnose's own output is
    used end to end in benchmarks/bench_diagnose.py)."""
    from drivers.inprocess import InProcessStage, accelerated
    assert PROFILE.emulator is not None
    prof = dc.replace(PROFILE, emulator=dc.replace(PROFILE.emulator, effects=effects))
    base = PROFILE.emulator.model
    desired = track.triangle(27.9, 27.04, 0.0, 3, 1 / prof.sample_rate_hz)
    rms = {}
    with InProcessStage(prof, clock=accelerated(4.0)) as stage:
        for name, model in (("base", base), ("extended", dc.replace(base, effects=effects))):
            plans = track.plan(model, desired, prof.limits, stage.voltage(), ("inverse",))
            runs = experiment.run_all(stage, plans, desired, tmp_path / name, {}, None)
            rms[name] = runs["inverse"].score.rms_um
    assert rms["extended"] < 0.5 * rms["base"], rms
