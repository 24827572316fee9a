"""What a stage says when something outside afmctl's plan happens (issue 27 items 9 and 12): a
profile whose limits go beyond the device's is refused before anything moves, naming both; a run
stopped from another terminal says so; a device watchdog that expired while the link failed is
named as such, never as pymodbus's "after 0 retries".

Real servers on 127.0.0.1 (serial over ``socket://``, Modbus TCP), real host links, and for the
second terminal a real ``afmctl safe`` subprocess.
"""

from __future__ import annotations

import dataclasses as dc
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.drivers.device.emulated import EmulatedDevice
from afmctl.drivers.device.modbus_server import ModbusTcpServer
from afmctl.drivers.device.serial_server import SerialServer
from afmctl.drivers.modbus_link import ModbusStage
from afmctl.drivers.serial_link import SerialStage
from afmctl.errors import LimitMismatchError, StageError, StoppedError
from afmctl.files.profile import ModbusTcpTransport, Profile, WireFaults
from tests.harness.paths import PROFILES, REPO

LAB = (PROFILES / "lab-serial.toml").read_text()


def unipolar(profile: Profile) -> Profile:
    """The emulated device behind a 0-150 V amplifier."""
    return dc.replace(profile, limits=dc.replace(profile.limits, v_min=0.0))


def lab_profile(folder: Path, url: str, v_min: float = -150.0) -> Path:
    path = folder / "lab.toml"
    path.write_text(LAB.replace('url = "/dev/ttyUSB0"', f'url = "{url}"')
                    .replace("v_min_V = -150.0", f"v_min_V = {v_min:g}"))
    return path


# ----------------------------------------------------------------------------------------------
# item 9: the profile's limits against the device's
# ----------------------------------------------------------------------------------------------


def test_a_profile_beyond_the_devices_limits_is_refused_before_anything_moves(
        profile: Profile, tmp_path: Path) -> None:
    """A -150 V profile on a 0-150 V device: the sweep went ahead until the device refused a raw
    WAV; now it is refused up front (exit 2, one line naming both ranges), the device untouched
    and nothing written."""
    with EmulatedDevice(unipolar(profile)) as dev, \
            SerialServer(dev, "socket://127.0.0.1:0") as ser:
        prof = lab_profile(tmp_path, ser.url)
        res = CliRunner().invoke(main, ["sweep", "--profile", str(prof), "--out",
                                        str(tmp_path / "s")])
        applied = dev.emulator.applied_log(0.0)
        table = dev.emulator.table_length
    assert res.exit_code == 2, res.output
    assert res.stderr.count("\n") == 1, res.stderr
    line = res.stderr.strip()
    assert "voltage range -150 ... 150 V" in line and "device's 0 ... 150 V" in line, line
    assert applied.size == 0 and table == 0  # not one sample sent
    assert not (tmp_path / "s").exists()


def test_a_profile_within_the_devices_limits_plays(profile: Profile, tmp_path: Path) -> None:
    with EmulatedDevice(profile) as dev, SerialServer(dev, "socket://127.0.0.1:0") as ser:
        narrow = dc.replace(profile, limits=dc.replace(profile.limits, v_min=0.0, v_max=100.0,
                                                       slew_v_per_ms=20.0))
        with SerialStage(narrow, ser.url) as stage:
            stage.play(np.linspace(0.0, 10.0, 500))  # a narrower profile is the lab's choice


def test_play_on_a_device_with_a_lower_slew_limit_is_refused(profile: Profile) -> None:
    slow = dc.replace(profile, limits=dc.replace(profile.limits, slew_v_per_ms=10.0,
                                                 current_ma=20.0))
    with EmulatedDevice(slow) as dev, SerialServer(dev, "socket://127.0.0.1:0") as ser, \
            SerialStage(profile, ser.url) as stage:
        with pytest.raises(LimitMismatchError, match=r"slew limit 50 V/ms .* device's 10 V/ms"):
            stage.play(np.linspace(0.0, 10.0, 500))
        assert dev.emulator.applied_log(0.0).size == 0


def test_status_shows_a_limits_mismatch_without_refusing(profile: Profile,
                                                         tmp_path: Path) -> None:
    with EmulatedDevice(unipolar(profile)) as dev, \
            SerialServer(dev, "socket://127.0.0.1:0") as ser:
        res = CliRunner().invoke(main, ["status", "--profile", str(lab_profile(tmp_path,
                                                                                ser.url))])
    assert res.exit_code == 0, res.output
    assert "v_min_V: 0.0" in res.stdout
    assert "warning: profile 'lab-serial': its [amplifier] voltage range" in res.stderr


# ----------------------------------------------------------------------------------------------
# item 12: stopped from elsewhere; the watchdog under a failing link
# ----------------------------------------------------------------------------------------------


def test_safe_from_a_second_terminal_is_reported_as_stopped_from_elsewhere(
        profile: Profile, tmp_path: Path) -> None:
    with EmulatedDevice(profile) as dev, SerialServer(dev, "socket://127.0.0.1:0") as ser:
        prof = lab_profile(tmp_path, ser.url)
        env = {**os.environ, "PYTHONPATH": str(REPO)}

        def second_terminal() -> None:
            while True:  # until the run is under way
                with dev.lock:
                    if dev.emulator.status(time.monotonic()).play_position > 2000:
                        break
                time.sleep(0.01)
            done.append(subprocess.run([sys.executable, "-m", "afmctl", "safe", "--profile",
                                        str(prof)], env=env, capture_output=True, text=True,
                                       timeout=120))

        done: list[subprocess.CompletedProcess[str]] = []
        other = threading.Thread(target=second_terminal)
        v = 50.0 * np.sin(2 * np.pi * 2.0 * np.arange(300_000) / 10_000.0)  # 30 s, streamed
        with SerialStage(profile, ser.url) as stage:
            other.start()
            with pytest.raises(StoppedError) as info:
                stage.play(v)
            other.join()
    assert done[0].returncode == 0, done[0].stderr
    text = str(info.value)
    assert "the stage was stopped from elsewhere" in text and "afmctl safe" in text
    assert "transport or protocol failure" not in text and info.value.code == 0


def test_a_watchdog_that_expired_while_the_link_failed_is_named(profile: Profile) -> None:
    """The host stalls past the device's watchdog while the link drops every reply (a loaded
    machine): the run ends as the watchdog's expiry, and pymodbus's own text is not shown."""
    with EmulatedDevice(profile, faults=WireFaults(delay=1e-12)) as dev, \
            ModbusTcpServer(dev) as srv:
        wire = ModbusTcpTransport("127.0.0.1", srv.port, timeout_s=0.2, watchdog_s=0.5)
        with ModbusStage(dc.replace(profile, transport=wire), wire) as stage:
            stalled = [False]

            def restore() -> None:
                time.sleep(2.0)
                dev.faults.reconfigure(WireFaults())

            def on_block(first: int, *_: object) -> None:
                if not stalled[0]:
                    stalled[0] = True
                    dev.faults.reconfigure(WireFaults(drop=1.0))
                    threading.Thread(target=restore).start()
                    time.sleep(1.0)  # the host falls behind: no heartbeat for 1 s

            v = 20.0 * np.sin(2 * np.pi * 2.0 * np.arange(30_000) / 10_000.0)
            with pytest.raises(StageError) as info:
                stage.play(v, on_block)
            st = stage.status()
    assert info.value.code == 8, info.value
    assert "no heartbeat" in str(info.value) and "retries" not in str(info.value)
    assert not st.running and st.output_v == 0.0


def test_a_modbus_link_that_gets_no_reply_says_so_in_afmctls_words(profile: Profile) -> None:
    with EmulatedDevice(profile, faults=WireFaults(drop=1.0)) as dev, ModbusTcpServer(dev) as srv:
        wire = ModbusTcpTransport("127.0.0.1", srv.port, timeout_s=0.2)
        with pytest.raises(StageError) as info:
            ModbusStage(profile, wire)
    assert "no reply within 0.2 s" in str(info.value) and "retries" not in str(info.value)


# ----------------------------------------------------------------------------------------------
# item 14: bring a stage up by hand; item 18: the last error with its text
# ----------------------------------------------------------------------------------------------


def test_set_a_dc_voltage_by_hand_and_read_the_sensor(profile: Profile, tmp_path: Path) -> None:
    """`afmctl set --voltage V` ramps there, reads the sensor over the hold and leaves the output
    there; `status` shows the reading at the present output (a 10 ms hold: nothing moves) and
    the last error with its text."""
    import json
    with EmulatedDevice(profile) as dev, SerialServer(dev, "socket://127.0.0.1:0") as ser:
        prof = str(lab_profile(tmp_path, ser.url))
        before = CliRunner().invoke(main, ["status", "--profile", prof, "--json"])
        res = CliRunner().invoke(main, ["set", "--voltage", "60", "--profile", prof, "--json"])
        after = CliRunner().invoke(main, ["status", "--profile", prof])
        again = CliRunner().invoke(main, ["status", "--profile", prof, "--json"])
        with dev.lock:
            out_v = dev.emulator.status(time.monotonic()).output_v
        refused = CliRunner().invoke(main, ["set", "--voltage", "200", "--profile", prof])
    for r in (before, res, after, again):
        assert r.exit_code == 0, r.output
    at_0, at_60 = json.loads(before.stdout), json.loads(res.stdout)
    assert at_0["output_V"] == 0.0 and at_60["output_V"] == 60.0 and out_v == 60.0
    assert at_60["samples"] == 1000 and at_60["reading_sd_um"] < 0.05  # the noise: 0.02 um
    assert at_60["reading_um"] - at_0["reading_um"] > 5.0  # the stage moved up
    assert json.loads(again.stdout)["reading_um"] == pytest.approx(at_60["reading_um"], abs=0.05)
    assert "reading_um: " in after.stdout and "(mean of 100 samples at 60 V" in after.stdout
    assert "last_error: 0 (no error)" in after.stdout
    assert refused.exit_code == 2 and "outside profile 'lab-serial'" in refused.stderr
