"""Profiles: the shipped ones load; every malformed one fails naming its key (CLI: exit 2)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from afmctl import cli
from afmctl.errors import FileFormatError
from afmctl.files import modelfile
from afmctl.files.profile import (
    EmulatedTransport,
    ModbusTcpTransport,
    SerialTransport,
    default_profile,
    load_profile,
    shipped_profile,
)
from tests.harness.paths import PROFILES

EMULATED = PROFILES / "emulated.toml"


def test_default_profile_is_the_nominal_emulated_stage() -> None:
    p = default_profile()
    assert isinstance(p.transport, EmulatedTransport) and p.emulator is not None
    assert (p.limits.v_min, p.limits.v_max, p.limits.slew_v_per_ms) == (-150.0, 150.0, 50.0)
    assert p.sample_rate_hz == 10_000.0 and p.thickness_um == 100.0
    m = p.emulator.model
    assert (m.polarization.eta, m.rod.k, m.rod.a1) == (1.2, 123370.0, 3.8)
    assert modelfile.to_dict(m)["rod"]["c_Ns_per_m"] == 39.27


def test_lab_examples_load() -> None:
    assert isinstance(shipped_profile("lab-serial").transport, SerialTransport)
    t = shipped_profile("lab-modbus").transport
    assert isinstance(t, ModbusTcpTransport) and t.unit == 1


def test_top_level_profiles_are_the_shipped_ones() -> None:
    top = PROFILES / "emulated.toml"
    assert load_profile(top) == default_profile()


def test_effects_are_read(tmp_path: Path) -> None:
    text = EMULATED.read_text() + """
[emulator.effects.thermal_relaxation]
field_scale_MV_per_m = 0.05
attempt_rate_per_s = 100.0
[emulator.effects.sensor_delay]
samples = 2
[emulator.effects.second_mode]
frequency_Hz = 2500.0
damping_ratio = 0.05
gain = 0.02
"""
    (tmp_path / "p.toml").write_text(text)
    cfg = load_profile(tmp_path / "p.toml").emulator
    assert cfg is not None and cfg.effects.sensor_delay_samples == 2
    assert cfg.model.polarization.thermal is not None
    assert cfg.effects.second_mode is not None and cfg.effects.second_mode.gain == 0.02


BAD = [
    ("v_max_V = 150.0", "v_max_V = -200.0", "amplifier.v_max_V"),
    ("slew_V_per_ms = 50.0", "slew_V_per_ms = 80.0", "amplifier.slew_V_per_ms"),
    ('kind = "emulated"', 'kind = "usb"', "transport.kind"),
    ("m_kg = 0.05", "m_kg = -0.05", "emulator.model.rod.m_kg"),
    ("read_only = false", 'read_only = "no"', "emulator.read_only"),
    ("sample_rate_Hz = 10000.0", "sample_rate_Hz = 0", "sample_rate_Hz"),
    ("scale_um_per_unit = 1.0", "", "sensor.scale_um_per_unit"),
    ("# [emulator.effects.sensor_delay]", "[emulator.effects.sensor_dealy]",
     "emulator.effects.sensor_dealy"),
    ("noise_um = 0.02", "noise = 0.02", "emulator.noise"),  # misspelt: not silently 0
    ("offset_um = 0.0", "ofset_um = 5.0", "sensor.ofset_um"),
    ("m_kg = 0.05", "m_kg = 0.05\nmass_kg = 0.05", "emulator.model.rod.mass_kg"),
]


@pytest.mark.parametrize(("old", "new", "key"), BAD)
def test_bad_profile_names_the_key(tmp_path: Path, old: str, new: str, key: str) -> None:
    text = EMULATED.read_text()
    assert old in text
    path = tmp_path / "bad.toml"
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(FileFormatError, match=re.escape(key)):
        load_profile(path)


def test_cli_bad_profile_exits_2_with_one_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(EMULATED.read_text().replace("current_mA = 100.0", "current_mA = -1"))
    result = CliRunner().invoke(cli.main, ["emulate", "--profile", str(path)])
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "amplifier.current_mA" in lines[0] and result.stdout == ""


LAB_SERIAL = PROFILES / "lab-serial.toml"


@pytest.mark.parametrize(("new", "want"), [
    ("timeout_s = 1.0", 2.0),  # the shipped key
    ("timeout_s = 0.4\nwatchdog_s = 0", 0.0),  # explicitly never armed
    ("timeout_s = 0.3\nwatchdog_s = 0.5", 0.5),
])
def test_transport_watchdog_period(tmp_path: Path, new: str, want: float) -> None:
    text = LAB_SERIAL.read_text()
    text = re.sub(r"timeout_s = 1\.0.*\nwatchdog_s = 2\.0.*\n", new + "\n", text)
    path = tmp_path / "stage.toml"
    path.write_text(text)
    assert load_profile(path).transport.watchdog_s == want  # type: ignore[union-attr]


def test_watchdog_defaults_to_twice_the_timeout_and_must_exceed_it(tmp_path: Path) -> None:
    text = re.sub(r"watchdog_s = 2\.0.*\n", "", LAB_SERIAL.read_text())
    path = tmp_path / "stage.toml"
    path.write_text(text.replace("timeout_s = 1.0", "timeout_s = 0.7"))
    assert load_profile(path).transport.watchdog_s == 1.4  # type: ignore[union-attr]
    path.write_text(text.replace("timeout_s = 1.0", "timeout_s = 0.7\nwatchdog_s = 0.7"))
    with pytest.raises(FileFormatError, match=r"transport\.watchdog_s: must exceed timeout_s"):
        load_profile(path)


def test_shipped_profiles_by_name(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert load_profile("lab-modbus").name == "lab-modbus"
    with pytest.raises(FileFormatError,
                       match="shipped: emulated, emulated-foreign, emulated-xy, emulated-xy-foreign, lab-modbus, lab-serial"):
        load_profile("lab-modbuss")
    monkeypatch.chdir(tmp_path)  # a file of that name in the working directory wins
    (tmp_path / "emulated").write_text(LAB_SERIAL.read_text())
    assert load_profile("emulated").name == "lab-serial"


def test_watchdog_beyond_the_protocol_range_is_refused_at_load(tmp_path: Path) -> None:
    """`watchdog_s = 1e9` loaded, then failed mid-sweep with the device's error 2; now the
    profile names it."""
    path = tmp_path / "stage.toml"
    path.write_text(LAB_SERIAL.read_text().replace("watchdog_s = 2.0", "watchdog_s = 1e9"))
    with pytest.raises(FileFormatError, match=r"transport\.watchdog_s: at most 3600 s"):
        load_profile(path)
    path.write_text(LAB_SERIAL.read_text().replace("watchdog_s = 2.0", "watchdog_s = 3600"))
    assert load_profile(path).transport.watchdog_s == 3600.0  # type: ignore[union-attr]
