"""A real stage, opt-in: ``pytest --device PROFILE`` (a profile file or a shipped name) runs the
tests marked ``device`` against the stage the profile names; without ``--device`` they skip.

They move nothing: the link, the device's limits against the profile's, and the sensor read at
the present output (a 10 ms run holding it). `afmctl conformance --profile PROFILE --yes` is the
check that moves the stage. The last test here runs this module against an emulated stage served
on 127.0.0.1 (issue 27 item 18: `pytest --device` ran no test).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from afmctl.files.profile import Profile, load_profile
from tests.harness.paths import PROFILES, REPO


@pytest.fixture(scope="module")
def device_profile(request: pytest.FixtureRequest) -> Profile:
    return load_profile(request.config.getoption("--device"))


@pytest.mark.device
def test_the_stage_answers_and_its_limits_contain_the_profiles(device_profile: Profile) -> None:
    from afmctl.drivers import open_stage
    with open_stage(device_profile) as stage:
        st = stage.status()
        stage.check_limits()  # LimitMismatchError names both if not
    assert not st.running and math.isfinite(st.output_v)


@pytest.mark.device
def test_the_sensor_reads_at_the_present_output(device_profile: Profile) -> None:
    from afmctl.drivers import open_stage
    from afmctl.experiment import runner
    with open_stage(device_profile) as stage:
        before = stage.voltage()
        r = runner.move_and_read(stage, before, device_profile.limits,
                                 device_profile.sample_rate_hz, 0.01)
        after = stage.voltage()
    assert after == pytest.approx(before, abs=1e-3) and r.samples > 0
    assert math.isfinite(r.mean_um) and r.sd_um < 1.0


def test_pytest_device_runs_the_device_tests(tmp_path: Path) -> None:
    from afmctl.drivers.device.emulated import EmulatedDevice
    from afmctl.drivers.device.serial_server import SerialServer
    from afmctl.files.profile import default_profile
    with EmulatedDevice(default_profile()) as dev, \
            SerialServer(dev, "socket://127.0.0.1:0") as ser:
        prof = tmp_path / "lab.toml"
        prof.write_text((PROFILES / "lab-serial.toml").read_text().replace(
            'url = "/dev/ttyUSB0"', f'url = "{ser.url}"'))
        res = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                              "--device", str(prof), "-m", "device", str(Path(__file__))],
                             cwd=REPO, capture_output=True, text=True, timeout=300,
                             env={**os.environ, "PYTHONPATH": str(REPO)})
    assert res.returncode == 0, res.stdout + res.stderr
    assert "2 passed" in res.stdout and "skipped" not in res.stdout, res.stdout
