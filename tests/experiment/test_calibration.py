"""The default model of track: recorded on the stage, identified, cached; afmctl sweep; and
calibration of stages whose amplifier is unipolar or semi-bipolar, never unasked on hardware."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.drivers import open_stage
from afmctl.experiment import calibration
from afmctl.files import sweepfile as sweeps
from afmctl.files.profile import Profile
from afmctl.planning import sweepdesign as sd
from tests.harness.paths import PROFILES, REPO
from tests.harness.sigint import interrupt_when

ROOT = REPO
EMULATED = (PROFILES / "emulated.toml").read_text()


def test_cached_model_is_identified_from_recorded_sweeps_then_reused(
        profile: Profile, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    cal = calibration.for_track(profile, None, open_stage=open_stage)  # dry-run path: a private emulator
    assert cal.new and cal.path.parent.parent == calibration.cache_dir(profile)
    recorded = sorted(Path(p).name for p in cal.sweeps)
    assert recorded == ["triangle_0.279hz.csv", "triangle_27.9hz.csv", "triangle_5.58hz.csv"]
    assert all(Path(p).exists() for p in cal.sweeps)
    assert profile.emulator is not None
    truth = profile.emulator.model
    model = cal.model
    assert model != truth  # identified, not copied
    assert model.rod.natural_hz == pytest.approx(truth.rod.natural_hz, rel=0.05)
    assert model.polarization.eta == pytest.approx(truth.polarization.eta, rel=0.1)
    stamp = cal.path.stat().st_mtime_ns
    again = calibration.for_track(profile, None, open_stage=open_stage)
    assert again.model == model and not again.new  # from the cache, not refitted
    assert again.path == cal.path and again.path.stat().st_mtime_ns == stamp
    assert again.identified == cal.identified and again.sweeps == cal.sweeps
    time.sleep(1.1)
    fresh = calibration.for_track(profile, None, recalibrate=True, open_stage=open_stage)
    assert fresh.new and fresh.path != cal.path and cal.path.exists()  # the old one is kept
    assert calibration.find(profile).path == fresh.path  # the latest is used


def test_sweep_command_records_sweep_files_and_resumes(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["sweep", "--out", str(tmp_path), "--only", "triangle_27.9hz"])
    assert res.exit_code == 0, res.output
    s = sweeps.read(tmp_path / "triangle_27.9hz.csv")
    assert s.meta["frequency_hz"] == "27.9" and s.thickness_um == 100.0
    assert s.meta["v_range_V"] == "-150 150"
    assert np.ptp(s.displacement_um) > 50 and np.max(np.abs(s.voltage_v)) == pytest.approx(150, abs=0.1)
    assert not list(tmp_path.glob("*.incomplete*"))  # removed once the sweep is complete
    stamp = (tmp_path / "triangle_27.9hz.csv").stat().st_mtime_ns
    again = CliRunner().invoke(main, ["sweep", "--out", str(tmp_path), "--only",
                                      "triangle_27.9hz"])
    assert again.exit_code == 2 and "never overwritten" in again.stderr
    assert "--resume" in again.stderr and len(again.stderr.splitlines()) == 1
    resumed = CliRunner().invoke(main, ["sweep", "--out", str(tmp_path), "--only",
                                        "triangle_27.9hz", "--only", "triangle_5.58hz",
                                        "--resume"])
    assert resumed.exit_code == 0, resumed.output
    assert resumed.stdout.split() == [str(tmp_path / "triangle_5.58hz.csv")]
    assert "already recorded, kept" in resumed.stderr
    assert (tmp_path / "triangle_27.9hz.csv").stat().st_mtime_ns == stamp


@pytest.mark.parametrize(("args", "message"), [
    (["--only", "square"], "not in the standard set"),
    (["--v-range", "-200", "150"], "exceeds the profile's limits"),
    (["--v-range", "20", "150"], "must contain 0 V"),
    (["--v-range", "100", "-100"], "VMIN must be below VMAX"),
    (["--v-range", "nan", "150"], "not a finite number"),
    (["--amplitude", "150"], "No such option '--amplitude'"),
])
def test_sweep_rejects_bad_options(tmp_path: Path, args: list[str], message: str) -> None:
    res = CliRunner().invoke(main, ["sweep", "--out", str(tmp_path / "o"), *args])
    assert res.exit_code == 2 and message in res.stderr, res.output
    assert len(res.stderr.splitlines()) == 1
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("v_range", [(0.0, 150.0), (-30.0, 150.0), (-100.0, 100.0)])
def test_sweep_covers_a_unipolar_semi_or_bipolar_profile(tmp_path: Path,
                                                         v_range: tuple[float, float]) -> None:
    """The emulated device refuses anything outside its profile's range: the sweep must fit."""
    lo, hi = v_range
    prof = tmp_path / "p.toml"
    prof.write_text(EMULATED.replace("v_min_V = -150.0", f"v_min_V = {lo}")
                    .replace("v_max_V = 150.0", f"v_max_V = {hi}"))
    out = tmp_path / "s"
    res = CliRunner().invoke(main, ["sweep", "--profile", str(prof), "--out", str(out),
                                    "--only", "triangle_27.9hz"])
    assert res.exit_code == 0, res.output
    recorded = sweeps.read(out / "triangle_27.9hz.csv").voltage_v
    # the minor loops (400,000 samples: 40 s on the emulated device) from the same design the
    # command recorded the triangle from
    loops = dict((n, v) for n, _, v in sd.standard_set(v_range=v_range))["minor_loops_0.1hz"]
    for v in (recorded, loops):
        assert v.min() >= lo and v.max() <= hi
        assert v.min() == pytest.approx(lo, abs=0.05 * (hi - lo))
        assert v.max() == pytest.approx(hi, abs=0.05 * (hi - lo))


def serial_profile(tmp_path: Path, url: str, v_min: float = 0.0) -> Path:
    """A lab-like profile: the serial protocol on ``url`` (not the in-process emulator)."""
    text = (EMULATED.replace('kind = "emulated"', f'kind = "serial"\nurl = "{url}"')
            .replace('name = "emulated"', 'name = "unipolar-lab"')
            .replace("v_min_V = -150.0", f"v_min_V = {v_min}"))
    path = tmp_path / "lab.toml"
    path.write_text(text)
    return path


@pytest.mark.slow
def test_real_stage_is_never_calibrated_unasked_then_calibrates_within_its_range(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A 0-150 V stage behind the serial protocol: without a model, track stops and says how to
    calibrate (the device applied nothing); with --calibrate it records the sweeps within
    0-150 V, identifies, tracks, and names the model it used. (This plant reaches 6.5-53.6 um on
    0-150 V, so the triangle is centred at 30 um.)"""
    from afmctl.drivers.device.emulated import EmulatedDevice
    from afmctl.drivers.device.serial_server import SerialServer
    from afmctl.files.profile import load_profile

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    with EmulatedDevice(load_profile(serial_profile(tmp_path, "socket://x:1"))) as dev, \
            SerialServer(dev, "socket://127.0.0.1:0") as ser:
        prof = serial_profile(tmp_path, ser.url)
        argv = ["track", "triangle", "--profile", str(prof), "--freq", "27.9", "--amplitude",
                "27.04", "--offset", "30", "--out", str(tmp_path / "run"), "--json"]
        res = CliRunner().invoke(main, argv)
        assert res.exit_code == 2, res.output
        assert "no calibration" in res.stderr and "afmctl sweep" in res.stderr
        assert "--calibrate" in res.stderr and len(res.stderr.splitlines()) == 1
        with dev.lock:
            assert dev.emulator.applied_log(time.monotonic()).size == 0
        res = CliRunner().invoke(main, [*argv, "--calibrate"])
        assert res.exit_code == 0, res.output
        with dev.lock:
            applied = dev.emulator.applied_log(time.monotonic())
    assert applied.min() >= 0.0 and applied.max() <= 150.0
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    model = doc["model"]
    assert model["calibrated_now"] and len(model["sweeps"]) == 3
    assert Path(model["file"]).exists() and model["identified"]
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["model"] == model
    assert f"model {model['file']}" in res.stderr
    print("unipolar ratio", doc["ratio_linear_over_inverse"],
          {k: f["rms_um"] for k, f in doc["filters"].items()})
    assert doc["ratio_linear_over_inverse"] >= 10  # issue 14 target (26 measured)


@pytest.mark.slow
def test_ctrl_c_in_sweep_keeps_the_sweep_in_progress_and_resume_records_it(
        tmp_path: Path) -> None:
    """A real SIGINT to a real `afmctl sweep`: exit 130, one line saying what was kept; the
    incomplete sweep is a valid sweep file marked interrupted; --resume records what is missing
    and removes the incomplete one, so that identify takes the folder (issue 27 item 7)."""
    import os
    import subprocess
    import sys

    out = tmp_path / "s"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    argv = [sys.executable, "-m", "afmctl", "sweep", "--out", str(out), "--only",
            "triangle_0.279hz"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    partial = out / "triangle_0.279hz.incomplete.csv"
    err = interrupt_when(
        proc, lambda: partial.exists() and partial.read_text().count("\n") >= 2000)
    assert proc.returncode == 130, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("afmctl: error: interrupted; the stage was sent to its safe state")
    assert str(partial) in last and "--resume" in last
    assert "100 %" not in err  # the progress does not jump to the end
    assert partial.read_text().rstrip().splitlines()[-1].startswith("# end: interrupted")
    kept = sweeps.read(partial)
    assert 1000 < kept.time_s.size < 71_686 and kept.meta["frequency_hz"] == "0.279"
    assert not (out / "triangle_0.279hz.csv").exists()
    res = CliRunner().invoke(main, ["sweep", "--out", str(out), "--only", "triangle_0.279hz",
                                    "--resume"])
    assert res.exit_code == 0, res.output
    full = sweeps.read(out / "triangle_0.279hz.csv")
    assert full.time_s.size == 71_686 and not partial.exists()  # superseded, removed
    assert f"{partial}: the interrupted attempt, superseded" in res.stderr
    np.testing.assert_allclose(full.voltage_v[:kept.time_s.size], kept.voltage_v, atol=1e-6)
    assert [p.name for p in out.glob("*.csv")] == ["triangle_0.279hz.csv"]


def test_ctrl_c_in_identify_says_no_stage_was_touched(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    from afmctl.fit import identify

    def interrupted(*args: object, **kw: object) -> None:
        raise KeyboardInterrupt

    sweep = tmp_path / "a.csv"
    v = sd.voltage_triangle(27.9, 150.0, 2, 10_000.0)
    sweeps.write(sweeps.from_arrays(v, 0.1 * v, 10_000.0), sweep)
    monkeypatch.setattr(identify, "fit", interrupted)
    res = CliRunner().invoke(main, ["identify", str(sweep), "-o", str(tmp_path / "m.toml")])
    assert res.exit_code == 130
    assert res.stderr.strip().splitlines()[-1] == "afmctl: error: interrupted; no stage was touched"
    assert not (tmp_path / "m.toml").exists()
