"""The model's twin of the stage at the command line: identify leaves it beside the model, track
plans from it while it follows the stage and keeps it, and says why when it no longer does."""

from __future__ import annotations

import dataclasses as dc
import json
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.experiment import twin
from afmctl.files import modelfile, sweepfile, twinfile
from afmctl.files.profile import default_profile
from afmctl.model import creep as cr
from afmctl.model import transducer as tr
from afmctl.model.transducer import Transducer
from afmctl.planning import track

RATE = 10_000.0


def timed_sweeps(model: Transducer, counts: tuple[int, int], ago_s: float = 2.0,
                 top_v: float = 120.0) -> list[sweepfile.Sweep]:
    """Two triangles to ``top_v`` as a stage recorded them ``ago_s`` seconds ago (within
    :data:`afmctl.experiment.runner.IDLE_S` by default: no reading before the run), 0.5 s apart,
    as runs ``counts``, read as ``model`` moves from rest (the readings the twin compares itself
    with). The commands' stage is a new emulated one, at rest: only ``top_v=0`` (sweeps that
    hold 0 V) leaves its twin where that stage is, so that a reading of it is of the model's
    zero."""
    v = np.interp(np.arange(4000), [0, 2000, 3999], [0.0, top_v, 0.0])
    u = tr.simulate(tr.compile_model(model, 1 / RATE), v, tr.initial(model))[0]
    t0 = time.monotonic() - ago_s - 2 * (0.5 + v.size / RATE)
    return [sweepfile.from_arrays(v, u, RATE,
                                  {"started_s": f"{t0 + k * (0.5 + v.size / RATE):.6f}",
                                   "run_count": str(c)})
            for k, c in enumerate(counts)]


def test_track_plans_from_the_twin_while_it_follows_the_stage(nominal: Transducer,
                                                              tmp_path: Path) -> None:
    """A creeping model's twin whose run counter is the stage's (here 0: a new in-process
    emulated stage) is planned from and kept with the counter after the run; the next track, on a new stage
    whose counter is 0 again, does not use it and says why; a twin of another model file is
    not used either."""
    nominal = dc.replace(nominal, creep=cr.Creep(cr.DEFAULT_TAUS_S,
                                                 (0.002,) * len(cr.DEFAULT_TAUS_S)))
    model = tmp_path / "model.toml"
    modelfile.write(nominal, model)
    kept = twin.keep_beside(nominal, timed_sweeps(nominal, (-1, 0)), model)
    assert kept == tmp_path / "model.twin.json"
    before = twinfile.read(kept)
    assert before.run_count == 0
    argv = ["track", "triangle", "--freq", "27.9", "--amplitude", "27.04", "--model", str(model),
            "--filter", "inverse", "--json"]
    res = CliRunner().invoke(main, [*argv, "--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    assert "the stage as the model's twin follows it" in res.stderr
    assert "reading it there" not in res.stderr  # the sweeps are 2 s old
    after = twinfile.read(kept)
    assert after.run_count == 1 and after.ended_s > before.ended_s
    assert json.loads(res.stdout.strip().splitlines()[-1])["filters"]["inverse"]["rms_um"] < 0.5
    res = CliRunner().invoke(main, [*argv, "--out", str(tmp_path / "b")])
    assert res.exit_code == 0, res.output
    assert "model.twin.json not used: the stage ran something since (run 0, the twin saw 1)" \
        in res.stderr
    modelfile.write(nominal, model, header="another identification")
    res = CliRunner().invoke(main, [*argv, "--out", str(tmp_path / "c")])
    assert "not used: it is of another model file" in res.stderr


def test_a_model_without_creep_is_planned_from_its_twin_too(nominal: Transducer,
                                                            tmp_path: Path) -> None:
    """No creep: the twin still carries the hysteresis's memory (a Bouc-Wen stage's, which no
    conditioning wipes) and the readings' frame, and track plans from it as for a creeping
    model; the sweeps' readings are the model's own, so no drift is read and the run is planned
    in the model's zero."""
    model = tmp_path / "model.toml"
    modelfile.write(nominal, model)
    kept = twin.keep_beside(nominal, timed_sweeps(nominal, (-1, 0)), model)
    assert kept is not None and twinfile.read(kept).observations.shape == (2, 2)
    res = CliRunner().invoke(main, ["track", "triangle", "--freq", "27.9", "--amplitude",
                                    "27.04", "--model", str(model), "--filter", "inverse",
                                    "--json", "--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    assert "the stage as the model's twin follows it" in res.stderr
    assert "planned in that frame" not in res.stderr
    assert twinfile.read(kept).run_count == 1
    assert json.loads(res.stdout.strip().splitlines()[-1])["filters"]["inverse"]["rms_um"] < 0.5


def test_no_twin_without_the_holds(nominal: Transducer, tmp_path: Path) -> None:
    """Sweeps without their times leave no twin file (track then starts the model at rest)."""
    model = tmp_path / "model.toml"
    modelfile.write(nominal, model)
    bare = [sweepfile.from_arrays(s.voltage_v, s.displacement_um, RATE, {})
            for s in timed_sweeps(nominal, (0, 1))]
    assert twin.keep_beside(nominal, bare, model) is None
    assert twin.keep_beside(nominal, bare[:1], model) is None  # one sweep, no time either
    assert not (tmp_path / "model.twin.json").exists()


def test_a_stage_idle_since_its_twin_is_read_before_the_run(nominal: Transducer,
                                                           tmp_path: Path) -> None:
    """Sweeps a minute old: track reads the stage where it holds before planning (a run of its
    own on the device's counter and in its own run file), says so and what it read, records it
    in summary.json, and the twin it keeps has followed the reading and the run."""
    model = tmp_path / "model.toml"
    modelfile.write(nominal, model)
    kept = twin.keep_beside(nominal, timed_sweeps(nominal, (-1, 0), 60.0, 0.0), model)
    assert kept is not None
    res = CliRunner().invoke(main, ["track", "triangle", "--freq", "27.9", "--amplitude",
                                    "27.04", "--model", str(model), "--filter", "inverse",
                                    "--json", "--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    said = [ln for ln in res.stderr.splitlines() if "reading it there" in ln]
    assert len(said) == 1 and "held 0 V for 6" in said[0], res.stderr
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["read_file"] == "run_read.csv" and summary["read_after_idle_s"] > 60.0
    assert f"read: the readings sit {summary['read_offset_um']:+.4f} um" in res.stderr
    assert abs(summary["read_offset_um"]) < 0.01  # the stage is where the twin says
    assert summary["filters"]["inverse"]["rms_um"] < 0.5
    assert (tmp_path / "a" / "run_read.csv").is_file()
    after = twinfile.read(kept)  # the read is not saved: it anchored this run's frame only
    assert after.run_count == 2 and after.observations.shape == (3, 2)


def test_learning_starts_where_the_twin_says(nominal: Transducer, tmp_path: Path) -> None:
    """``track --learn``: iteration 0 is planned from the twin as track's runs are (the stage
    read first, its sweeps a minute old), and learning says so; without a twin file it says it
    starts from rest. (A creeping stage's iteration 0 was 0.6-0.9 um off from rest on an
    independent tester's stages, 19-43x the noise.)"""
    nominal = dc.replace(nominal, creep=cr.Creep(cr.DEFAULT_TAUS_S,
                                                 (0.002,) * len(cr.DEFAULT_TAUS_S)))
    model = tmp_path / "model.toml"
    modelfile.write(nominal, model)
    argv = ["track", "triangle", "--freq", "27.9", "--amplitude", "27.04", "--model", str(model),
            "--learn", "1", "--json"]
    res = CliRunner().invoke(main, [*argv, "--out", str(tmp_path / "rest")])
    assert res.exit_code == 0, res.output
    assert "learning starts from rest in the model's zero (no twin file)" in res.stderr
    assert twin.keep_beside(nominal, timed_sweeps(nominal, (-1, 0), 60.0, 0.0), model)
    res = CliRunner().invoke(main, [*argv, "--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    assert "learning starts from the stage as the model's twin follows it" in res.stderr
    assert "reading it there" in res.stderr and (tmp_path / "a" / "run_read.csv").is_file()
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["read_file"] == "run_read.csv"
    assert summary["iterations"][0]["rms_steady_um"] < 0.5


def test_learning_reads_the_stage_even_just_after_a_recording(nominal: Transducer,
                                                             tmp_path: Path) -> None:
    """``track --learn`` reads the stage before iteration 0 even when the twin's last recording
    is seconds old (track itself would not: within ``IDLE_S`` it plans from the recordings'
    line), and iteration 0 is planned in the frame that reading anchors. A line through the
    recordings alone took a 1 um step across a hold for a -4 nm/s drift on a tester's stage."""
    model = tmp_path / "model.toml"
    modelfile.write(nominal, model)
    assert twin.keep_beside(nominal, timed_sweeps(nominal, (-1, 0), top_v=0.0), model)
    res = CliRunner().invoke(main, ["track", "triangle", "--freq", "27.9", "--amplitude", "27.04",
                                    "--model", str(model), "--learn", "1", "--json",
                                    "--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    said = [ln for ln in res.stderr.splitlines() if "reading it there" in ln]
    assert len(said) == 1 and "held 0 V for " in said[0], res.stderr
    assert "iteration 0: readings expected" in res.stderr
    assert "read at the held output" in res.stderr
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["read_file"] == "run_read.csv" and summary["read_after_idle_s"] < 10.0
    assert abs(summary["read_offset_um"]) < 0.01


def test_a_learned_waveform_is_replayed_conditioning_first_and_moved(nominal: Transducer,
                                                                    tmp_path: Path) -> None:
    """``play WAVE --model``: a learned waveform plays its conditioning first
    (run_play_conditioning.csv), says how far the stage has moved since the learned run (here
    nothing: the same emulated plant, so within the noise), and plays the rest moved for it
    (run_play.csv, scored as before); ``--as-learned`` plays it whole in one run, as it was."""
    model = tmp_path / "model.toml"
    modelfile.write(nominal, model)
    res = CliRunner().invoke(main, ["track", "triangle", "--freq", "27.9", "--amplitude",
                                    "27.04", "--model", str(model), "--learn", "1", "--json",
                                    "--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    wave = tmp_path / "a" / "waveform_learned.csv"
    assert "# offset_miss_um:" in wave.read_text()
    learned = json.loads(res.stdout.strip().splitlines()[-1])["iterations"]
    res = CliRunner().invoke(main, ["play", str(wave), "--model", str(model), "--json",
                                    "--out", str(tmp_path / "b")])
    assert res.exit_code == 0, res.output
    assert "replay: the stage has moved" in res.stderr and "moved for it" in res.stderr
    assert (tmp_path / "b" / "run_play_conditioning.csv").is_file()
    data = json.loads(res.stdout.strip().splitlines()[-1])
    assert abs(data["replay_moved_um"]) < 0.01
    assert data["rms_steady_um"] < 1.5 * min(it["rms_steady_um"] for it in learned)
    res = CliRunner().invoke(main, ["play", str(wave), "--model", str(model), "--as-learned",
                                    "--json", "--out", str(tmp_path / "c")])
    assert res.exit_code == 0, res.output
    assert "replay:" not in res.stderr
    assert not (tmp_path / "c" / "run_play_conditioning.csv").exists()
    as_learned = json.loads(res.stdout.strip().splitlines()[-1])
    assert "replay_moved_um" not in as_learned
    # the learned run read 0.2 um higher over the conditioning's end than the stage does now:
    # the stage has moved -0.2 um, and the replay aims 0.2 um higher, where it then reads
    run = tmp_path / "a" / wave.read_text().split("# run_file: ")[1].split()[0]
    lines = run.read_text().splitlines()
    head = next(i for i, ln in enumerate(lines) if ln.startswith("seq,")) + 1
    cols = lines[head - 1].split(",")
    col = cols.index("displacement_um")
    n_prefix = track.conditioning(default_profile().limits, 0.0, 1 / RATE).size
    for i in range(head + n_prefix - 1000, head + n_prefix):
        row = lines[i].split(",")
        row[col] = f"{float(row[col]) + 0.2:.6f}"
        lines[i] = ",".join(row)
    run.write_text("\n".join(lines) + "\n")
    res = CliRunner().invoke(main, ["play", str(wave), "--model", str(model), "--json",
                                    "--out", str(tmp_path / "d")])
    assert res.exit_code == 0, res.output
    moved = json.loads(res.stdout.strip().splitlines()[-1])
    assert moved["replay_moved_um"] == pytest.approx(-0.2, abs=0.01)
    assert moved["mean_error_um"] == pytest.approx(0.2, abs=0.02)
    assert moved["rms_between_um"] == pytest.approx(as_learned["rms_between_um"], abs=0.2)


def test_a_long_run_is_planned_from_a_reading_that_tells_the_drift(nominal: Transducer,
                                                                  tmp_path: Path) -> None:
    """A trajectory of 3.6 s (over :data:`afmctl.cli.track.LONG_RUN_S`) on a stage whose twin
    saw it 2 s ago (no idle reading for a short run then): the stage is read for
    :data:`afmctl.model.frame.RATE_READ_S` where it holds before the run is planned, in a run
    file of the filter's own, and the drift rate it tells (none here: the emulated stage does
    not drift) is said, planned in and recorded in summary.json."""
    from afmctl.cli.track import LONG_RUN_S
    from afmctl.model import frame as fr

    model = tmp_path / "model.toml"
    modelfile.write(nominal, model)
    assert twin.keep_beside(nominal, timed_sweeps(nominal, (-1, 0), 2.0, 0.0), model) is not None
    res = CliRunner().invoke(main, ["track", "triangle", "--freq", "0.279", "--amplitude",
                                    "27.04", "--periods", "1", "--model", str(model),
                                    "--filter", "inverse", "--json", "--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    assert 1 / 0.279 >= LONG_RUN_S
    said = [ln for ln in res.stderr.splitlines() if "reading it there" in ln]
    assert len(said) == 1 and said[0].startswith("the inverse run lasts 3.6 s"), res.stderr
    assert f"for {fr.RATE_READ_S:g} s (run_read_inverse.csv)" in said[0]
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["read_file"] == "run_read_inverse.csv"
    assert summary["read_drift_um_per_s"] == 0.0 and "read_after_idle_s" not in summary
    assert "no drift told over the reading); planned in that frame" in res.stderr
    read = (tmp_path / "a" / "run_read_inverse.csv").read_text().splitlines()
    assert sum(1 for ln in read if ln[:1].isdigit()) == round(fr.RATE_READ_S * RATE)
