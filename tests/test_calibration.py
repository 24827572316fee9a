"""The default model of track: recorded on the stage, identified, cached; and afmctl sweep."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl import calibration, sweeps
from afmctl.cli import main
from afmctl.profile import Profile


def test_cached_model_is_identified_from_recorded_sweeps_then_reused(
        profile: Profile, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    model = calibration.cached_model(profile, None)  # dry-run path: a private emulator
    folder = calibration.cache_dir(profile)
    recorded = sorted(p.name for p in (folder / "sweeps").glob("*.csv"))
    assert recorded == ["triangle_0.279hz.csv", "triangle_27.9hz.csv", "triangle_5.58hz.csv"]
    assert profile.emulator is not None
    truth = profile.emulator.model
    assert model != truth  # identified, not copied
    assert model.rod.natural_hz == pytest.approx(truth.rod.natural_hz, rel=0.05)
    assert model.polarization.eta == pytest.approx(truth.polarization.eta, rel=0.1)
    stamp = (folder / "model.toml").stat().st_mtime_ns
    assert calibration.cached_model(profile, None) == model  # from the cache, not refitted
    assert (folder / "model.toml").stat().st_mtime_ns == stamp


def test_sweep_command_records_sweep_files(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["sweep", "--out", str(tmp_path), "--only", "triangle_27.9hz"])
    assert res.exit_code == 0, res.output
    s = sweeps.read(tmp_path / "triangle_27.9hz.csv")
    assert s.meta["frequency_hz"] == "27.9" and s.thickness_um == 100.0
    assert np.ptp(s.displacement_um) > 50 and np.max(np.abs(s.voltage_v)) == pytest.approx(150, abs=0.1)
    again = CliRunner().invoke(main, ["sweep", "--out", str(tmp_path), "--only",
                                      "triangle_27.9hz"])
    assert again.exit_code == 2 and "never overwritten" in again.stderr


def test_sweep_rejects_unknown_names_and_excess_amplitude(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["sweep", "--out", str(tmp_path), "--only", "square"])
    assert res.exit_code == 2 and "not in the standard set" in res.stderr
    res = CliRunner().invoke(main, ["sweep", "--out", str(tmp_path), "--amplitude", "200"])
    assert res.exit_code == 2 and "exceeds the profile's limits" in res.stderr
    assert not list(tmp_path.iterdir())
