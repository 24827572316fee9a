"""The shipped emulated profile and a host stage on a fresh emulated device over any wire.

Shared by the tests (``from tests.harness.emulated import stage_on``) and the fixtures of
``tests/conftest.py``; servers bind to 127.0.0.1 or a pty and stop when the block ends.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from afmctl.drivers import ascii_protocol as ap
from afmctl.drivers.device import emulator
from afmctl.files.profile import ModbusRtuTransport, ModbusTcpTransport, Profile, default_profile

if TYPE_CHECKING:
    from afmctl.drivers import StageBase

PROFILE = default_profile()
assert PROFILE.emulator is not None
SAMPLE_RATE_HZ = PROFILE.sample_rate_hz
NOISE_UM = PROFILE.emulator.noise_um
SENSOR_ZERO_UM = 2.0  # an arbitrary sensor zero the fits must find
TRANSPORTS = ["modbus-tcp", "modbus-rtu", "serial-pty", "serial-socket", "inprocess"]


@contextmanager
def stage_on(kind: str, profile: Profile, read_only: bool | None = None
             ) -> Iterator[tuple[StageBase, emulator.Emulator]]:
    """A host stage talking to a fresh emulated device over ``kind`` (see TRANSPORTS)."""
    from afmctl.drivers.device.emulated import EmulatedDevice
    from afmctl.drivers.device.modbus_server import ModbusRtuServer, ModbusTcpServer
    from afmctl.drivers.device.serial_server import SerialServer
    from afmctl.drivers.inprocess import InProcessStage
    from afmctl.drivers.modbus_link import ModbusStage
    from afmctl.drivers.serial_link import SerialStage

    with ExitStack() as stack:
        dev = stack.enter_context(EmulatedDevice(profile, read_only=read_only))
        if kind == "modbus-tcp":
            srv = stack.enter_context(ModbusTcpServer(dev))
            stage: StageBase = ModbusStage(profile, ModbusTcpTransport("127.0.0.1", srv.port))
        elif kind == "modbus-rtu":  # 921,600 baud: 115,200 cannot carry 10 kHz both ways
            rtu = stack.enter_context(ModbusRtuServer(dev, baudrate=921_600))
            stage = ModbusStage(profile, ModbusRtuTransport(rtu.url, baudrate=921_600))
        elif kind.startswith("serial"):
            where = "pty" if kind == "serial-pty" else "socket://127.0.0.1:0"
            ser = stack.enter_context(SerialServer(dev, where))
            stage = SerialStage(profile, ser.url)
        else:
            stage = InProcessStage(profile, emulator=dev.emulator, lock=dev.lock)
        with stage:
            yield stage, dev.emulator


def small_buffers(profile: Profile) -> Profile:
    """The profile with a 4,096-sample table and an 8,192-sample recorder."""
    assert profile.emulator is not None
    cfg = replace(profile.emulator, table_capacity=4096, recorder_capacity=8192)
    return replace(profile, emulator=cfg)


def long_waveform(n: int) -> np.ndarray:
    """``n`` samples of a slew-safe sine with a decaying envelope, V."""
    return 100.0 * np.sin(2 * np.pi * 5.0 * np.arange(n) / 10_000.0) * np.linspace(1.0, 0.3, n)


class ScriptedPort:
    """A pyserial stand-in that checks each line sent against a script and answers from it
    (protocol v3: the command's payload is checked, the answer framed with the command's tag)."""

    def __init__(self, script: list[tuple[str, str]]) -> None:
        self.script = list(script)
        self.pending = b""

    @property
    def in_waiting(self) -> int:
        return len(self.pending)

    def write(self, data: bytes) -> int:
        sent, answer = self.script.pop(0)
        assert data.endswith(b"\n"), data
        payload, tag = ap.unframe(data[:-1].decode())
        assert payload == sent and tag is not None, (data, sent)
        self.pending += ap.frame(answer, tag).encode() + b"\n"
        return len(data)

    def read(self, n: int) -> bytes:
        out, self.pending = self.pending[:n], self.pending[n:]
        return out

    def close(self) -> None:
        pass
