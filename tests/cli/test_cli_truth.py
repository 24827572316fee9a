"""What afmctl shows must be what is true (issue 27 items 1, 2, 13, 15): a flagged model is said
to be flagged where its figures are shown, corrected readings are named and drawn as scored, an
interrupted track keeps what was played, run files are scored again by `afmctl score`, and `play`
says what it plays and draws it.

The stage is the shipped emulated one with a hidden sensor delay of 5 samples (its own plant, so
the truth between samples is known); runs are real time on the in-process stage.
"""

from __future__ import annotations

import dataclasses as dc
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl import plots
from afmctl.cli import main
from afmctl.drivers.device import plant
from afmctl.experiment import runner as experiment
from afmctl.files import modelfile, runfile
from afmctl.files import sweepfile as sw
from afmctl.files.modelfile import FitRecord
from afmctl.model import effects as fx
from afmctl.model.transducer import Transducer
from afmctl.planning import sweepdesign as sd
from tests.harness.paths import PROFILES, REPO

DELAY = 5  # samples: the stage's hidden sensor delay
TRACK = ["track", "triangle", "--freq", "27.9", "--amplitude", "27.04", "--periods", "2"]


@pytest.fixture(scope="module")
def delayed_profile(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shipped emulated profile with a sensor that reads DELAY samples late."""
    text = (PROFILES / "emulated.toml").read_text()
    text = text.replace("# [emulator.effects.sensor_delay]\n# samples = 2",
                        f"[emulator.effects.sensor_delay]\nsamples = {DELAY}")
    assert f"samples = {DELAY}" in text
    path = tmp_path_factory.mktemp("profile") / "delayed.toml"
    path.write_text(text.replace('name = "emulated"', 'name = "delayed"'))
    return path


def model_file(folder: Path, model: Transducer, name: str, fit: FitRecord | None = None) -> Path:
    path = folder / name
    modelfile.write(model, path, fit=fit)
    return path


FLAG = FitRecord("identify", "tri.csv left at 23.1x its sensor noise: the model misses something "
                 "there", True, ("tri.csv",), (23.1,))


# ----------------------------------------------------------------------------------------------
# item 1: a flagged model is said to be flagged where its figures are shown
# ----------------------------------------------------------------------------------------------


def test_identify_records_its_verdict_in_the_model_file(tmp_path: Path) -> None:
    """A sweep of a stage with a hidden sensor delay is fitted above twice its noise: identify
    warned on stderr, and now the model file says so too ([fit] flagged), for track to repeat."""
    from afmctl.files.profile import default_profile
    cfg = dc.replace(default_profile().emulator, effects=fx.Effects(sensor_delay_samples=DELAY),
                     seed=3)
    v = sd.loop(27.9, -150.0, 150.0, 3, 10_000.0)
    u, _ = plant.expected_readback(cfg, 10_000.0, v)
    sw.write(sw.from_arrays(v, u, 10_000.0, {"frequency_hz": "27.9", "layer_thickness_um": "100"},
                            "tri"), tmp_path / "tri.csv")
    fast = (PROFILES / "emulated.toml").read_text() + (
        "\n[identify]\nrestarts = 0\ndensity = \"parametric\"\nmax_nfev = 40\n"
        "n_coercive_fit = 32\n")
    (tmp_path / "fast.toml").write_text(fast)
    res = CliRunner().invoke(main, ["identify", str(tmp_path / "tri.csv"), "--profile",
                                    str(tmp_path / "fast.toml"), "-o", str(tmp_path / "m.toml")])
    assert res.exit_code == 0, res.output
    fit = modelfile.read_fit(tmp_path / "m.toml")
    assert fit is not None and fit.by == "identify" and fit.flagged
    assert fit.sweeps == ("tri.csv",) and fit.rms_over_noise[0] > 2
    assert "tri.csv left at" in fit.verdict


def test_track_and_learning_warn_on_a_flagged_model(delayed_profile: Path, nominal: Transducer,
                                                    tmp_path: Path) -> None:
    """The model misses the sensor delay and identify flagged it: track and learning say so, and
    what the readings cannot tell (learning improved the readings while the stage got worse)."""
    flagged = model_file(tmp_path, nominal, "flagged.toml", FLAG)
    res = CliRunner().invoke(main, [*TRACK, "--profile", str(delayed_profile), "--model",
                                    str(flagged), "--filter", "inverse", "--learn", "1",
                                    "--out", str(tmp_path / "learn"), "--json"])
    assert res.exit_code == 0, res.output
    warning = [ln for ln in res.stderr.splitlines() if ln.startswith("warning: ")]
    assert len(warning) == 1, res.stderr
    assert f"identify flagged model {flagged}: tri.csv left at 23.1x" in warning[0]
    assert "learning optimises the readings" in warning[0]
    assert "readings that improve need not mean the stage does" in warning[0]
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    assert doc["model_fit"]["flagged"] is True
    res = CliRunner().invoke(main, [*TRACK, "--profile", str(delayed_profile), "--model",
                                    str(flagged), "--filter", "inverse", "--dry-run", "--out",
                                    str(tmp_path / "dry")])
    assert res.exit_code == 0 and "warning: identify flagged model" in res.stderr


def test_an_unflagged_model_tracks_without_a_warning(nominal: Transducer, tmp_path: Path) -> None:
    clean = model_file(tmp_path, nominal, "clean.toml",
                       FitRecord("identify", "every sweep within 2x its sensor noise", False))
    res = CliRunner().invoke(main, [*TRACK, "--model", str(clean), "--dry-run", "--out",
                                    str(tmp_path / "dry")])
    assert res.exit_code == 0 and "warning" not in res.stderr, res.stderr


# ----------------------------------------------------------------------------------------------
# item 2: corrected readings are named and drawn as scored
# ----------------------------------------------------------------------------------------------


def test_a_sensor_correcting_model_shows_what_it_scores(delayed_profile: Path,
                                                        nominal: Transducer,
                                                        tmp_path: Path) -> None:
    """With a model that knows the sensor delay, the readings are corrected before scoring:
    run.csv holds the corrected readings in a column named as such, the printed RMS is theirs,
    and track.png draws them (not the raw readings under the corrected RMS)."""
    knows = model_file(tmp_path, dc.replace(nominal, effects=fx.Effects(
        sensor_delay_samples=DELAY)), "knows.toml")
    out = tmp_path / "o"
    res = CliRunner().invoke(main, [*TRACK, "--profile", str(delayed_profile), "--model",
                                    str(knows), "--filter", "inverse", "--out", str(out),
                                    "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    assert doc["readings_corrected_for"] == {"sensor_delay": {"samples": DELAY, "seconds": 0.0}}
    lines = (out / "run.csv").read_text().splitlines()
    header = lines[0].split(",")
    assert header == ["time_s", "desired_um", "voltage_V_inverse", "displacement_um_inverse",
                      "corrected_displacement_um_inverse"]
    table = np.array([[float(c) if c else np.nan for c in ln.split(",")] for ln in lines[1:]])
    desired, raw, corrected = table[:, 1], table[:, 3], table[:, 4]
    k0 = round(1 / 27.9 * 1e4)  # the steady part: one period in
    rms = doc["filters"]["inverse"]["rms_um"]
    assert np.sqrt(np.nanmean((corrected[k0:] - desired[k0:]) ** 2)) == pytest.approx(rms,
                                                                                    rel=1e-4)
    assert np.sqrt(np.nanmean((raw[k0:] - desired[k0:]) ** 2)) > 5 * rms  # raw: delayed
    assert "readings corrected for sensor_delay" in res.stderr
    run = runfile.read(out / "run_inverse.csv")  # the run file keeps the raw readings
    np.testing.assert_allclose(run.displacement_um[np.isfinite(run.desired_um)], raw, atol=1e-5)
    # track.png draws what is scored
    from afmctl.planning import track
    wf = track.Waveform("inverse", 1e-4, run.voltage_v, run.desired_um,
                        slice(int(np.flatnonzero(np.isfinite(run.desired_um))[0]),
                              int(np.flatnonzero(np.isfinite(run.desired_um))[-1]) + 1))
    d = track.Desired(1e-4, desired, 1 / 27.9, 27.04, "triangle")
    o = experiment.scored(wf, d, (run.displacement_um, run.voltage_v, True), out,
                          fx.Effects(sensor_delay_samples=DELAY))
    fig = plots.track_figure({"inverse": o}, d, 100.0, "sensor delay")
    drawn = fig.axes[0].lines[0]
    np.testing.assert_allclose(drawn.get_ydata(), corrected, atol=1e-5, equal_nan=True)
    assert "readings corrected for sensor delay" in drawn.get_label()


# ----------------------------------------------------------------------------------------------
# item 13: an interrupted track keeps what was played; `afmctl score`
# ----------------------------------------------------------------------------------------------


def test_ctrl_c_during_the_linear_run_keeps_the_inverse_score(nominal: Transducer,
                                                             tmp_path: Path) -> None:
    """Ctrl-C while the linear run plays: the finished inverse run is scored, summary.json and
    track.png are written, the linear run is scored on what it got; its unplayed rows carry no
    voltage; exit 130 with the safe-state line."""
    model = model_file(tmp_path, nominal, "m.toml")
    out = tmp_path / "o"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "afmctl", *TRACK, "--periods", "20",
                             "--model", str(model), "--out", str(out)],
                            stderr=subprocess.PIPE, text=True, env=env)
    assert proc.stderr is not None
    seen = []
    for line in proc.stderr:
        seen.append(line)
        if line.strip().startswith("linear:"):  # the linear run is under way
            proc.send_signal(signal.SIGINT)
            break
    err = "".join(seen) + proc.stderr.read()
    proc.stderr.close()
    proc.wait(timeout=60)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == ("afmctl: error: interrupted; the stage was sent to "
                                            "its safe state")
    doc = json.loads((out / "summary.json").read_text())
    assert doc["interrupted"].startswith("KeyboardInterrupt")
    inv, lin = doc["filters"]["inverse"], doc["filters"]["linear"]
    assert inv["complete"] and inv["rms_um"] < 0.1
    assert not lin["complete"] and lin["missing_samples"] > 0
    assert (out / "track.png").stat().st_size > 10_000
    assert f"inverse  RMS {inv['rms_um']:.4f} um" in err
    run = runfile.read(out / "run_linear.csv")
    status = [ln.rsplit(",", 1)[1] for ln in (out / "run_linear.csv").read_text().splitlines()
              if ln[:1].isdigit()]
    unplayed = np.array([s == "not played" for s in status])
    assert unplayed.any() and unplayed[-1] and not unplayed[0]
    assert np.isnan(run.voltage_v[unplayed]).all() and np.isfinite(run.voltage_v[~unplayed]).all()


def test_score_rescoring_a_run_file_gives_tracks_figures(nominal: Transducer,
                                                        tmp_path: Path) -> None:
    model = model_file(tmp_path, nominal, "m.toml")
    out = tmp_path / "o"
    res = CliRunner().invoke(main, [*TRACK, "--model", str(model), "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    res = CliRunner().invoke(main, ["score", str(out / "run_inverse.csv"),
                                    str(out / "run_linear.csv"), "--out", str(tmp_path / "s"),
                                    "--json"])
    assert res.exit_code == 0, res.output
    again = json.loads(res.stdout.strip().splitlines()[-1])
    for name in ("inverse", "linear"):
        for key in ("rms_um", "max_um", "rms_transient_um", "steady"):
            assert again["filters"][name][key] == pytest.approx(doc["filters"][name][key],
                                                                rel=1e-6, abs=2e-6), (name, key)
    assert again["ratio_linear_over_inverse"] == pytest.approx(doc["ratio_linear_over_inverse"],
                                                               rel=1e-3)
    assert (tmp_path / "s" / "track.png").stat().st_size > 10_000


def test_score_refuses_a_file_that_is_not_a_run(tmp_path: Path) -> None:
    (tmp_path / "x.csv").write_text("a,b\n1,2\n")
    res = CliRunner().invoke(main, ["score", str(tmp_path / "x.csv"), "--out",
                                    str(tmp_path / "s")])
    assert res.exit_code == 2 and res.stderr.count("\n") == 1, res.output
    assert "not an afmctl run file" in res.stderr and not (tmp_path / "s").exists()


# ----------------------------------------------------------------------------------------------
# item 15: play
# ----------------------------------------------------------------------------------------------


def test_dry_run_waveforms_carry_their_metadata_and_play_warns_on_another_profile(
        nominal: Transducer, tmp_path: Path) -> None:
    """A dry-run waveform names its profile, model and trajectory in its header; played on
    another profile, or without the model it was made with, play warns; it draws play.png and
    prints its RMS once."""
    model = model_file(tmp_path, nominal, "m.toml")
    res = CliRunner().invoke(main, [*TRACK, "--profile", "emulated-foreign", "--model",
                                    str(model), "--filter", "inverse", "--offset", "30",
                                    "--dry-run", "--out", str(tmp_path / "dry")])
    assert res.exit_code == 0, res.output
    from afmctl.files import waveformfile
    w = waveformfile.read(tmp_path / "dry" / "waveform_inverse.csv")
    assert w.meta["profile"] == "emulated-foreign" and w.meta["model"] == str(model)
    assert w.meta["trajectory"] == "triangle 27.9 Hz, 27.04 um"
    assert float(w.meta["period_s"]) == pytest.approx(1 / 27.9)
    out = tmp_path / "play"
    res = CliRunner().invoke(main, ["play", str(tmp_path / "dry" / "waveform_inverse.csv"),
                                    "--out", str(out)])
    assert res.exit_code == 0, res.output
    lines = res.stderr.splitlines()
    assert any(ln.startswith("warning: waveform_inverse.csv was made for profile "
                             "'emulated-foreign'") for ln in lines), res.stderr
    assert any(ln.startswith("warning: waveform_inverse.csv was made with model") for ln in lines)
    result = next(ln for ln in lines if ln.startswith("play: "))
    assert result.count("RMS") == 1 and "steady part" in result
    # a planned (not learned) waveform says nothing of what it did: nothing to compare with
    summary = json.loads((out / "summary.json").read_text())
    assert "moved_on" not in summary and "learned_rms_steady_um" not in summary
    assert (out / "play.png").stat().st_size > 10_000
