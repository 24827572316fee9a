"""The stage commands on a two-axis profile (issue 25): status per axis, set by axis or channel
within that axis's own limits, safe ramping every output; malformed two-axis profiles refused with
one line naming the key (exit 2)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from afmctl.cli import main
from tests.harness.paths import PROFILES
from tests.harness.sigint import interrupt

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
        _, err = interrupt(proc)
    assert proc.returncode == 0, err
