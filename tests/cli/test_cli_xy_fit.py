"""Two-axis commands: identify on a foreign two-axis set (the --json contract and the coupling
against the plant's own formulas), refusals, and track --axis on the emulated x/y stage."""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.drivers.device.foreign import xy_stage as xst
from afmctl.drivers.device.foreign import xy_sweeps as xsw
from afmctl.files import xymodelfile
from afmctl.files.profile import shipped_profile
from afmctl.model.xy import XYModel

#: A quick fit: the parametric model only, one start (the axes' fit is not what is judged here).
QUICK = (resources.files("afmctl.profiles") / "emulated.toml").read_text() + """
[identify]
representation = "hem"
restarts = 0
density = "parametric"
max_nfev = 15
n_coercive_fit = 24
field_step = 0.02
"""


@pytest.fixture(scope="module")
def foreign_set(tmp_path_factory: pytest.TempPathFactory) -> tuple[xst.XYStage, list[Path]]:
    """A small set of xy-foreign's design on its stage 7 (relay and Prandtl-Ishlinskii axes, shared
    mode 750 Hz): the 3.3 and 23 Hz triangles and the excitation of each axis."""
    stage = xst.xy_stages()[6]
    plans = [p for p in xsw.design_plans(stage, "held") if "0.21Hz" not in p.name]
    out = tmp_path_factory.mktemp("xyset")
    paths = []
    for plan, reading in zip(plans, xsw.record(stage, plans, np.random.default_rng(3)),
                             strict=True):
        paths.append(out / f"{plan.name}.csv")
        paths[-1].write_text(xsw.format_rows(plan, reading))
    return stage, paths


def test_identify_two_axes_json_contract_and_coupling(foreign_set, tmp_path: Path) -> None:
    stage, paths = foreign_set
    (tmp_path / "quick.toml").write_text(QUICK)
    model = tmp_path / "xy.toml"
    res = CliRunner().invoke(main, ["identify", *map(str, paths), "-o", str(model), "--json",
                                    "--profile", str(tmp_path / "quick.toml")])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    for a in ("x", "y"):
        assert {"sweeps", "parameters", "envelope", "uncertainty", "at_noise_floor"} <= set(
            doc["axes"][a])
        assert len(doc["axes"][a]["sweeps"]) == 2  # triangles; the excitation is the coupling's
        mode = doc["axes"][a]["representations"]["second_mode"]  # tried, or why not
        if mode.get("kept"):  # x here: the shared mode, found from the coupling's estimate
            assert abs(mode["frequency_Hz"] / xst.mode_hz(stage.structure) - 1) < 0.05, mode
            assert max(mode["per_sweep_over_noise_with"]) < max(
                mode["per_sweep_over_noise_identified"])
        else:
            assert "skipped" in mode or "kept" in mode, mode
    c = doc["coupling"]
    mode = xst.mode_hz(stage.structure)
    for d in ("yx", "xy"):
        frf = c[f"{d}_frf"]
        freq = np.array([p["freq_hz"] for p in frf])
        assert len(frf) >= 30 and freq[0] == pytest.approx(1.0) and freq[-1] >= 200.0
        assert np.allclose(np.diff(np.log(freq)), np.log(freq[1] / freq[0]))
        true = xst.true_coupling(stage, freq)
        assert abs(20 * np.log10(c[f"{d}_static"] / true[f"{d}_static"])) < 1.0
        low = freq <= 0.2 * mode
        h = np.array([p["gain"] * np.exp(1j * np.radians(p["phase_deg"])) for p in frf])
        ratio = h[low] / true[f"{d}_frf"][low]
        assert np.max(np.abs(20 * np.log10(np.abs(ratio)))) < 2.0
        assert np.max(np.abs(np.degrees(np.angle(ratio)))) < 10.0
    back = xymodelfile.read(model)
    assert back.coupling["yx"].static == pytest.approx(c["yx_static"])


def test_identify_two_axes_reports_in_words(foreign_set, tmp_path: Path) -> None:
    """Without ``--json`` each axis's one-axis report, where an axis's figures hold only its
    second mode's (the paper's model alone: no representation chosen)."""
    _, paths = foreign_set
    (tmp_path / "quick.toml").write_text(QUICK)
    res = CliRunner().invoke(main, ["identify", *map(str, paths), "-o", str(tmp_path / "m.toml"),
                                    "--profile", str(tmp_path / "quick.toml")])
    assert res.exit_code == 0, res.output
    assert "--- axis x" in res.stdout and "--- axis y" in res.stdout
    assert "noise floor" in res.stdout and (tmp_path / "m.toml").is_file()


def test_malformed_and_mixed_sets_exit_2_with_one_line(foreign_set, tmp_path: Path) -> None:
    _, paths = foreign_set
    bad = tmp_path / "bad.csv"
    bad.write_text(paths[0].read_text().replace("displacement_y_um", "displacement_z_um"))
    one = tmp_path / "one.csv"
    one.write_text("time_s,voltage_V,displacement_um\n0,0,0\n0.1,1,1\n0.2,2,2\n")
    for files, words in (([bad], "missing column displacement_y_um"),
                         ([paths[0], one], "one-axis sweep file in a set of two-axis")):
        res = CliRunner().invoke(main, ["identify", *map(str, files), "-o",
                                        str(tmp_path / "m.toml")])
        assert res.exit_code == 2 and words in res.stderr
        assert len(res.stderr.strip().splitlines()) == 1
        assert not (tmp_path / "m.toml").exists()


def test_track_one_axis_holds_the_other_and_reports_its_motion(tmp_path: Path) -> None:
    """track --axis y on the emulated x/y stage with its true model: x holds its output, and its
    sensor moves by the coupling (static -0.008 um/um) of y's motion, plus its noise."""
    prof = shipped_profile("emulated-xy")
    truth = XYModel({a: prof.axis(a).emulator.model for a in ("x", "y")},  # type: ignore[union-attr]
                    dict(prof.emulator.coupling))  # type: ignore[union-attr]
    xymodelfile.write(truth, tmp_path / "xy.toml")
    out = tmp_path / "run"
    res = CliRunner().invoke(main, ["track", "triangle", "--profile", "emulated-xy", "--axis", "y",
                                    "--model", str(tmp_path / "xy.toml"), "--freq", "27.9",
                                    "--amplitude", "20", "--offset", "centre", "--periods", "2",
                                    "--filter", "inverse", "--no-condition", "--out", str(out),
                                    "--json"])
    assert res.exit_code == 0, res.output
    held = json.loads(res.stdout.strip().splitlines()[-1])["held_axis"]
    assert held == json.loads((out / "summary.json").read_text())["held_axis"]
    assert held["axis"] == "x" and held["held_voltage_V"] == 0.0
    noise = prof.axis("x").emulator.noise_um  # type: ignore[union-attr]
    # y moved at most about 20 um (and its ramps to the centre): x by the coupling of it
    assert 0.5 * noise < held["rms_um"] < 0.008 * 40 + 2 * noise
    assert held["rms_um"] <= held["peak_um"] < 0.05 * 40 + 6 * noise
    assert (out / "model_y.toml").exists() and "held axis x" in res.stderr
