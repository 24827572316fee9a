"""``afmctl emulate`` in a subprocess: prints where it serves, answers there, stops on Ctrl-C."""

from __future__ import annotations

import os
import subprocess
import sys

from afmctl.drivers.modbus_link import ModbusStage
from afmctl.drivers.serial_link import SerialStage
from afmctl.files.profile import ModbusTcpTransport, Profile
from tests.harness.paths import REPO
from tests.harness.sigint import interrupt

ROOT = REPO


def test_emulate_serves_until_interrupted(profile: Profile) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "afmctl", "emulate", "--modbus-port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout is not None
        where = dict(proc.stdout.readline().strip().split(": ", 1) for _ in range(3))
        host, port = where["modbus-tcp"].rsplit(":", 1)
        assert host == "127.0.0.1"
        with ModbusStage(profile, ModbusTcpTransport(host, int(port), timeout_s=5.0)) as stage:
            stage.set_voltage(2.0)
        with SerialStage(profile, where["serial"], timeout_s=5.0) as stage:
            assert stage.voltage() == 2.0  # one device behind both wires
        assert where["modbus-rtu"].startswith("/dev/")
    finally:
        _, err = interrupt(proc)
    assert proc.returncode == 0, err
    assert "stopped" in err


def test_emulate_on_a_port_in_use_names_the_port() -> None:
    """One line naming the address, exit 1 (not pymodbus's text alone), nothing left running."""
    import socket
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        res = subprocess.run([sys.executable, "-m", "afmctl", "emulate", "--modbus-port",
                              str(port), "--no-rtu"], capture_output=True, text=True, env=env,
                             timeout=60)
    assert res.returncode == 1, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and f"127.0.0.1:{port}" in lines[0], res.stderr
    assert lines[0].startswith("afmctl: error: cannot serve:")
    assert lines[0].endswith(f"another program holds port {port}: give --modbus-port another "
                             f"port, or 0 for any free one")  # issue 27 item 18: the way out
