"""Two-axis commands (issue 25): status per axis, set by axis or channel within that axis's own
limits, safe ramping every output; malformed two-axis profiles refused with one line naming the
key (exit 2); identify on a foreign two-axis set (the --json contract and the coupling against the
plant's own formulas), refusals, and track --axis on the emulated x/y stage."""

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
from tests.harness.paths import PROFILES

XY_TEXT = (PROFILES / "emulated-xy.toml").read_text()


def test_status_reports_every_axis_with_its_own_limits_and_reading() -> None:
    res = CliRunner().invoke(main, ["status", "--profile", "emulated-xy", "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert out["channels"] == 2 and set(out["axes"]) == {"x", "y"}
    x, y = out["axes"]["x"], out["axes"]["y"]
    assert (x["channel"], y["channel"]) == (0, 1)
    assert (x["v_max_V"], y["v_max_V"], y["slew_V_per_ms"]) == (150.0, 120.0, 40.0)
    assert 0 < y["reading_sd_um"] < 0.05 and x["reading_um"] == out["reading_um"]


def test_set_moves_the_axis_named_within_its_own_limits() -> None:
    runner = CliRunner()
    res = runner.invoke(main, ["set", "--profile", "emulated-xy", "--axis", "y", "--voltage",
                               "20", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["output_V"] == 20.0
    beyond = runner.invoke(main, ["set", "--profile", "emulated-xy", "--channel", "1",
                                  "--voltage", "130"])
    assert beyond.exit_code == 2 and "axis y limits [-120, 120] V" in beyond.stderr
    for args, what in ((["--axis", "z"], "has axes x, y"), (["--channel", "2"], "channels 0 .. 1"),
                       (["--axis", "y", "--channel", "1"], "not both")):
        res = runner.invoke(main, ["set", "--profile", "emulated-xy", "--voltage", "1", *args])
        assert res.exit_code == 2 and what in res.output, (args, res.output)
    safe = runner.invoke(main, ["safe", "--profile", "emulated-xy"])
    assert safe.exit_code == 0 and "outputs x 0 V, y 0 V" in safe.stdout


@pytest.mark.parametrize(("old", "new", "key"), [
    ('names = ["x", "y"]', 'names = ["x", "z"]', "axes.names"),
    ('names = ["x", "y"]', 'names = ["y", "x"]', "axes.names"),
    ("[axis.y.sensor]", "[axis.z.sensor]", "axis.z"),
    ("[axis.y.sensor]", "[axis.y.transport]", "axis.y.transport"),
    ("offset_um = 1.5", "ofset_um = 1.5", "axis.y.sensor.ofset_um"),
    ("slew_V_per_ms = 40.0", "slew_V_per_ms = 90.0", "axis.y.amplifier.slew_V_per_ms"),
    ("static_um_per_um = 0.012", "static = 0.012", "emulator.coupling.yx.static"),
    ("[emulator.coupling.xy]", "[emulator.coupling.zx]", "emulator.coupling.zx"),
    ('[axes]\nnames = ["x", "y"]', "", "axis"),
])
def test_a_malformed_two_axis_profile_is_one_line_naming_the_key(
        old: str, new: str, key: str, tmp_path: Path) -> None:
    assert old in XY_TEXT
    path = tmp_path / "xy.toml"
    path.write_text(XY_TEXT.replace(old, new, 1))
    res = CliRunner().invoke(main, ["status", "--profile", str(path), "--no-read"])
    assert res.exit_code == 2 and len(res.stderr.strip().splitlines()) == 1, res.output
    assert key in res.stderr and "Traceback" not in res.output


@pytest.mark.parametrize(("old", "new", "key"), [
    ("coupling_dB = -35.0", "coupling_dB = -20.0", "emulator.xy_foreign.coupling_dB"),
    ("v_min_V = 0.0", "v_min_V = -100.0", "emulator.xy_foreign.seed"),
    ("seed = 25", "sead = 25", "emulator.xy_foreign.sead"),
])
def test_a_malformed_foreign_xy_profile_is_one_line_naming_the_key(
        old: str, new: str, key: str, tmp_path: Path) -> None:
    text = (PROFILES / "emulated-xy-foreign.toml").read_text()
    assert old in text
    path = tmp_path / "xyf.toml"
    path.write_text(text.replace(old, new, 1))
    res = CliRunner().invoke(main, ["safe", "--profile", str(path)])
    assert res.exit_code == 2 and key in res.stderr and "Traceback" not in res.output, res.output


def test_emulate_serves_the_xy_stage_on_serial_protocol_4_and_map_3() -> None:
    """``afmctl emulate --profile emulated-xy``: one device of two channels behind both wires."""
    import os
    import signal
    import subprocess
    import sys

    from afmctl.drivers.modbus_link import ModbusStage
    from afmctl.drivers.serial_link import SerialStage
    from afmctl.files.profile import ModbusTcpTransport, shipped_profile
    from tests.harness.paths import REPO

    xy = shipped_profile("emulated-xy")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "afmctl", "emulate", "--profile", "emulated-xy",
                             "--modbus-port", "0", "--no-rtu"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout is not None
        where = dict(proc.stdout.readline().strip().split(": ", 1) for _ in range(2))
        host, port = where["modbus-tcp"].rsplit(":", 1)
        with ModbusStage(xy, ModbusTcpTransport(host, int(port), timeout_s=5.0)) as stage:
            assert (stage.version, stage.channels) == (3, 2)
            stage.set_voltage(2.0, channel=1)
        with SerialStage(xy, where["serial"], timeout_s=5.0) as stage:
            assert (stage.version, stage.channels) == (4, 2)
            assert stage.voltages().tolist() == [0.0, 2.0]  # one device behind both wires
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err


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
