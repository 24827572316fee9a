"""afmctl track at the command line: dry runs, and bad input refused with exit 2 and no files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.files import modelfile
from afmctl.model.transducer import Transducer
from tests.harness.paths import PROFILES


@pytest.fixture(scope="module")
def model_file(tmp_path_factory: pytest.TempPathFactory, nominal: Transducer) -> Path:
    path = tmp_path_factory.mktemp("model") / "model.toml"
    modelfile.write(nominal, path)
    return path


def read_waveform(path: Path) -> tuple[list[str], np.ndarray]:
    """The header and the columns time_s, desired_um, voltage_V of a waveform file."""
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    header = lines[0].split(",")
    rows = [[float(c) if c else np.nan for c in ln.split(",")] for ln in lines[1:]]
    order = [header.index(c) for c in ("time_s", "desired_um", "voltage_V")]
    return header, np.array(rows)[:, order]


def test_dry_run_writes_guarded_waveforms_and_sends_nothing(model_file: Path,
                                                            tmp_path: Path) -> None:
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["track", "triangle", "--freq", "27.9", "--amplitude", "27.04",
                                    "--periods", "2", "--model", str(model_file), "--dry-run",
                                    "--out", str(out)])
    assert res.exit_code == 0, res.output
    for name in ("inverse", "linear"):
        header, data = read_waveform(out / f"waveform_{name}.csv")
        assert header == ["time_s", "voltage_V", "desired_um"]  # a waveform file for play
        t, d, v = data.T
        assert np.isnan(d[0]) and np.isnan(d[-1]) and np.isfinite(d).sum() == round(2 / 27.9 * 1e4) + 1
        assert abs(v[0]) < 1.0 and v[-1] == 0.0  # ramps from and to the output (0 V)
        assert np.abs(v).max() <= 150 and np.abs(np.diff(v)).max() / 0.1 <= 50  # V/ms
    assert not list(out.glob("run*.csv"))


@pytest.mark.parametrize(("args", "message"), [
    (["--amplitude", "400"], "out of the stage's reach"),
    (["--amplitude", "-3"], "Invalid value for '--amplitude'"),
    (["--freq", "0"], "Invalid value for '--freq'"),
])
def test_bad_trajectory_is_refused(model_file: Path, tmp_path: Path, args: list[str],
                                   message: str) -> None:
    base = {"--freq": "27.9", "--amplitude": "27.04"}
    base.update(dict(zip(args[::2], args[1::2], strict=True)))
    argv = ["track", "triangle", *sum(([k, v] for k, v in base.items()), []), "--model",
            str(model_file), "--dry-run", "--out", str(tmp_path / "out")]
    res = CliRunner().invoke(main, argv)
    assert res.exit_code == 2, res.output
    assert message in res.output
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())


def test_bad_model_file_is_one_line_exit_2(model_file: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(model_file.read_text().replace("k_N_per_m = 123370.0", "k_N_per_m = nan"))
    res = CliRunner().invoke(main, ["track", "sine", "--freq", "5", "--amplitude", "10",
                                    "--model", str(bad), "--dry-run", "--out",
                                    str(tmp_path / "o")])
    assert res.exit_code == 2
    assert res.stderr.strip().count("\n") == 0 and "k_N_per_m: must be finite" in res.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(("content", "message"), [
    ("time_s,voltage_V\n0,1\n1,2\n", "missing column desired_um"),
    ("time_s,desired_um\n0,1\n0,2\n", "time not strictly increasing"),
    ("time_s,desired_um\n0,1\n1,nan\n", "non-finite value"),
])
def test_bad_trajectory_file(model_file: Path, tmp_path: Path, content: str,
                             message: str) -> None:
    wave = tmp_path / "wave.csv"
    wave.write_text(content)
    res = CliRunner().invoke(main, ["track", "file", str(wave), "--model", str(model_file),
                                    "--dry-run", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and message in res.stderr, res.output


def test_file_trajectory_dry_run(model_file: Path, tmp_path: Path) -> None:
    wave = tmp_path / "wave.csv"
    t = np.linspace(0, 0.5, 51)
    wave.write_text("# any metadata: ok\ntime_s,desired_um\n"
                    + "".join(f"{a},{10 * np.sin(2 * np.pi * 4 * a)}\n" for a in t))
    res = CliRunner().invoke(main, ["track", "file", str(wave), "--model", str(model_file),
                                    "--filter", "inverse", "--dry-run", "--out",
                                    str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "o" / "waveform_inverse.csv").exists()
    assert not (tmp_path / "o" / "waveform_linear.csv").exists()


def test_no_condition_skips_the_full_range_excursion(model_file: Path, tmp_path: Path) -> None:
    peaks = {}
    for flag in ("--condition", "--no-condition"):
        out = tmp_path / flag
        res = CliRunner().invoke(main, ["track", "triangle", "--freq", "27.9", "--amplitude",
                                        "27.04", "--periods", "1", "--model", str(model_file),
                                        "--filter", "inverse", "--dry-run", "--out", str(out),
                                        flag])
        assert res.exit_code == 0, res.output
        peaks[flag] = np.nanmax(np.abs(read_waveform(out / "waveform_inverse.csv")[1][:, 2]))
    assert peaks["--condition"] == pytest.approx(150.0)
    assert peaks["--no-condition"] < 100.0


def test_track_run_writes_files_and_json(model_file: Path, tmp_path: Path) -> None:
    """A full run on the embedded emulated stage (real time): run files, run.csv, summary.json,
    track.png and the --json summary agree."""
    import json
    out = tmp_path / "run"
    res = CliRunner().invoke(main, ["track", "triangle", "--freq", "27.9", "--amplitude", "27.04",
                                    "--periods", "2", "--model", str(model_file), "--out",
                                    str(out), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    assert json.loads((out / "summary.json").read_text()) == doc
    assert set(doc["filters"]) == {"inverse", "linear"} and doc["ratio_linear_over_inverse"] > 10
    for name in ("inverse", "linear"):
        f = doc["filters"][name]
        assert f["complete"] and f["missing_samples"] == 0 and f["rms_um"] > 0
    header = (out / "run.csv").read_text().splitlines()[0].split(",")
    assert header == ["time_s", "desired_um", "voltage_V_inverse", "displacement_um_inverse",
                      "voltage_V_linear", "displacement_um_linear"]
    assert (out / "track.png").stat().st_size > 10_000
    assert (out / "run_inverse.csv").exists() and (out / "run_linear.csv").exists()


def test_headline_figures_equal_the_benchmarks_steady_state(model_file: Path,
                                                            tmp_path: Path) -> None:
    """`track`'s printed and JSON figures are the benchmark's steady-state figures (computed there
    from the raw arrays) for the same run: same model, a fresh emulated stage each (same seed)."""
    import json

    from afmctl.drivers import open_stage
    from afmctl.files.profile import default_profile
    from benchmarks import bench_track

    out = tmp_path / "run"
    res = CliRunner().invoke(main, ["track", "triangle", "--freq", "27.9", "--amplitude", "27.04",
                                    "--model", str(model_file), "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    prof = default_profile()
    with open_stage(prof) as stage:
        bench = bench_track.run_experiment(stage, modelfile.read(model_file), prof, 27.9, 27.04,
                                           3.0, tmp_path / "bench")
    for name in ("inverse", "linear"):
        f = doc["filters"][name]
        assert f["steady"] and f["rms_um"] == pytest.approx(bench[f"{name}_rms_um"], rel=1e-12)
        assert f["max_um"] == pytest.approx(bench[f"{name}_max_um"], rel=1e-12)
        assert f["rms_transient_um"] is not None  # the first period, reported apart
        assert f"{name:8s} RMS {f['rms_um']:.4f} um" in res.stderr
    assert doc["ratio_linear_over_inverse"] == pytest.approx(bench["ratio"], rel=1e-12)
    assert doc["between_samples_from"] == "emulator truth"
    assert "horizon 2 samples" in res.stderr  # the corners' longer horizons stay local


def test_between_samples_on_a_real_stage_are_not_judged(model_file: Path,
                                                        tmp_path: Path) -> None:
    """Issue 27 item 4: a lab profile (serial, no [emulator] table) has no plant to simulate
    between the samples; the model's own simulation (it was printed as a "model estimate") only
    shows the model inverting itself (0.023 um beside a measured 0.153 um), so it is dropped and
    the reason said."""
    import json

    from afmctl.drivers.device.emulated import EmulatedDevice
    from afmctl.drivers.device.serial_server import SerialServer
    from afmctl.files.profile import default_profile

    text = (PROFILES / "emulated.toml").read_text()
    text = text[:text.index("[emulator]")]
    with EmulatedDevice(default_profile()) as dev, \
            SerialServer(dev, "socket://127.0.0.1:0") as ser:
        prof = tmp_path / "lab.toml"
        prof.write_text(text.replace('kind = "emulated"', f'kind = "serial"\nurl = "{ser.url}"'))
        res = CliRunner().invoke(main, ["track", "sine", "--freq", "27.9", "--amplitude", "20",
                                        "--profile", str(prof), "--model", str(model_file),
                                        "--filter", "inverse", "--out", str(tmp_path / "o"),
                                        "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    assert doc["between_samples_from"].startswith("not judged: a real stage")
    assert doc["filters"]["inverse"]["rms_between_um"] is None
    assert "model estimate" not in res.stderr
    lines = [ln for ln in res.stderr.splitlines() if "between samples" in ln]
    assert lines == ["between samples: " + doc["between_samples_from"]]


def test_between_samples_on_a_foreign_plant_are_not_the_profiles_model(model_file: Path,
                                                                       tmp_path: Path) -> None:
    """Issue 27 item 3: in-process `--profile emulated-foreign` printed "between samples 8.85 um
    (the emulator's true plant)" from [emulator.model], which the profile calls not this device;
    only the plant actually simulated may be the truth between samples."""
    import json
    res = CliRunner().invoke(main, ["track", "sine", "--freq", "27.9", "--amplitude", "20",
                                    "--offset", "30", "--profile", "emulated-foreign",
                                    "--model", str(model_file), "--filter", "inverse",
                                    "--periods", "1", "--out", str(tmp_path / "o"), "--json",
                                    "--extrapolate"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    assert doc["between_samples_from"].startswith("not judged: the emulated device's plant is a "
                                                  "foreign stage")
    assert doc["filters"]["inverse"]["rms_between_um"] is None
    assert "true plant" not in res.stderr
