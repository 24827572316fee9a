"""``afmctl scan raster`` on the emulated two-axis stage: a frame scanned with both filters (run
files, scan.gwy, scan.png, summary.json), and the refusals before anything moves (a one-axis
profile, a frame beyond the reach naming the largest that fits, a line rate the clock cannot
sample), each one line with exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import gwyfile
import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.files import runfile, waveformfile, xymodelfile
from afmctl.files.profile import load_profile
from afmctl.model.xy import XYModel
from tests.harness.xy_plant import detuned

FRAME = ["--size", "12", "8", "--pixels", "32", "--lines", "4", "--line-rate", "40"]


def model_file(tmp_path: Path) -> Path:
    """A two-axis model *off* the emulated stage's truth (each axis 1-3 % detuned, the coupling
    20 % off): what the scan plans with is not the plant that scores it."""
    prof = load_profile("emulated-xy")
    truth = {n: prof.axis(n).emulator.model for n in ("x", "y")}
    c = dict(prof.emulator.coupling)
    import dataclasses as dc
    model = XYModel({"x": detuned(truth["x"], 1.02, 0.99, 1.01),
                     "y": detuned(truth["y"], 0.98, 1.01, 1.02)},
                    {d: dc.replace(v, static=0.8 * v.static) for d, v in c.items()})
    path = tmp_path / "xy-model.toml"
    xymodelfile.write(model, path)
    return path


def test_scan_both_filters_writes_every_file(tmp_path: Path) -> None:
    out = tmp_path / "scan"
    res = CliRunner().invoke(main, ["scan", "raster", "--profile", "emulated-xy", "--model",
                                    str(model_file(tmp_path)), *FRAME, "--slow", "staircase",
                                    "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout.strip().splitlines()[-1])
    assert set(data["filters"]) == {"inverse", "linear"} and data["feedforward"] is True
    inv, lin = data["filters"]["inverse"], data["filters"]["linear"]
    assert inv["registration_px"] < lin["registration_px"]
    names = ("run_frame001_inverse.csv", "run_frame001_linear.csv")
    for name in names:
        run = runfile.read(out / name)
        assert run.complete and run.axes == ("x", "y") and run.voltage_v.shape[1] == 2
    obj = gwyfile.load(str(out / "scan.gwy"))
    titles = [obj[k] for k in obj if k.endswith("/data/title")]
    assert "frame 1 inverse: error fast trace" in titles and len(titles) == 24  # from 1
    assert obj["/0/data"].data.shape == (4, 32)
    assert (out / "scan.png").stat().st_size > 10_000
    assert "fast RMS" in res.stderr and "line 4/4" in res.stderr
    assert res.stderr.count("frame 1/1 inverse: line 1/4,") == 1  # the first progress line once
    assert inv["frames"][0]["frame"] == 1 and inv["frames"][0]["run_file"] == names[0]


def test_scan_learns_then_says_in_summary_json_what_learning_did(tmp_path: Path) -> None:
    """``--learn-frames 2 --frames 1``: the learning frames' run files, the learned waveform and
    its replay; ``summary.json`` (and ``--json``) carry ``learning``: the frames, the best one
    and its figure, why it stopped, every frame's figure (each equal to that frame's own in
    ``filters``), each axis's noise and learning cut-off."""
    out = tmp_path / "scan"
    res = CliRunner().invoke(main, ["scan", "raster", "--profile", "emulated-xy", "--model",
                                    str(model_file(tmp_path)), *FRAME, "--filter", "inverse",
                                    "--learn-frames", "2", "--frames", "1", "--out", str(out),
                                    "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout.strip().splitlines()[-1])
    assert json.loads((out / "summary.json").read_text())["learning"] == data["learning"]
    got = data["learning"]
    by_frame = got["over_noise_by_frame"]
    assert len(by_frame) == got["frames_learned"] + 1 and 1 <= got["frames_learned"] <= 2
    assert got["best_over_noise"] == min(by_frame) == by_frame[got["best_frame"]]
    assert by_frame == [data["filters"][f"learn{j:02d}"]["over_noise"]
                        for j in range(len(by_frame))]
    assert got["stop"] and set(got["cutoff_hz"]) == set(got["noise_um"]) == {"x", "y"}
    assert all(600.0 <= f <= 1200.0 for f in got["cutoff_hz"].values())
    assert (out / "waveform_learned.csv").exists() and runfile.read(
        out / "run_frame001_learned.csv").complete
    assert "learned up to" in res.stderr


def test_a_one_axis_profile_is_refused(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["scan", "raster", "--profile", "emulated", *FRAME, "--out",
                                    str(tmp_path / "o")])
    assert res.exit_code == 2 and "needs a two-axis stage" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and not (tmp_path / "o").exists()


def test_a_frame_beyond_reach_names_the_largest_that_fits(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["scan", "raster", "--profile", "emulated-xy", "--model",
                                    str(model_file(tmp_path)), "--size", "200", "100",
                                    "--pixels", "32", "--lines", "4", "--line-rate", "10",
                                    "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    assert "the largest that fits at this centre is" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and not (tmp_path / "o").exists()


def test_a_line_rate_beyond_the_clock_is_refused(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["scan", "raster", "--profile", "emulated-xy", "--size", "10",
                                    "10", "--pixels", "32", "--lines", "4", "--line-rate",
                                    "1000", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "at most 500 lines/s" in res.stderr


def test_play_replays_a_two_axis_waveform_file(tmp_path: Path) -> None:
    n = 2000
    t = np.arange(n) * 1e-4
    v = np.column_stack([20 * np.sin(np.pi * t / t[-1]), -15 * np.sin(np.pi * t / t[-1])])
    d = np.full((n, 2), np.nan)
    d[500:1500] = 1.0
    wave = tmp_path / "w.csv"
    wave.write_text(waveformfile.format_text(t, v, d, {"profile": "emulated-xy"}))
    res = CliRunner().invoke(main, ["play", str(wave), "--profile", "emulated-xy", "--out",
                                    str(tmp_path / "p"), "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout.strip().splitlines()[-1])
    run = runfile.read(tmp_path / "p" / "run_play.csv")
    assert run.complete and run.voltage_v == pytest.approx(v, abs=1e-5)
    err = run.displacement_um[500:1500] - 1.0
    assert data["axes"]["y"]["rms_um"] == pytest.approx(
        float(np.sqrt(np.mean(err[:, 1] ** 2))), rel=1e-6)
    one = CliRunner().invoke(main, ["play", str(wave), "--profile", "emulated", "--out",
                                    str(tmp_path / "q")])
    assert one.exit_code == 2 and "two-axis waveform" in one.stderr


def test_play_refuses_a_two_axis_waveform_outside_an_axis_limits_before_its_folder(
        tmp_path: Path) -> None:
    """y beyond its own range (+-120 V; x's is +-150 V): one line naming the axis, exit 2, no
    output folder (the stage's own guard, StageBase.check_waveform, called before it is made)."""
    t = np.arange(4000) * 1e-4
    v = np.column_stack([100 * np.sin(np.pi * t / t[-1]), 130 * np.sin(np.pi * t / t[-1])])
    wave = tmp_path / "w.csv"
    wave.write_text(waveformfile.format_text(t, v, np.full((t.size, 2), np.nan),
                                             {"profile": "emulated-xy"}))
    res = CliRunner().invoke(main, ["play", str(wave), "--profile", "emulated-xy", "--out",
                                    str(tmp_path / "p")])
    assert res.exit_code == 2 and res.stderr.count("\n") == 1, res.output
    assert "axis y (channel 1)" in res.stderr and "above the limit 120" in res.stderr
    assert not (tmp_path / "p").exists()
