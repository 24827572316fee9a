"""Shared fixtures: the shipped emulated profile and its true model, emulated sweeps recorded by the
emulated device's own physics (true parameters hidden from fits), a slew-safe test waveform, and
servers on 127.0.0.1 / ptys that start and stop cleanly."""

from __future__ import annotations

import dataclasses as dc
import logging
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from typing import TYPE_CHECKING

import numpy as np
import pytest

from afmctl import identify as idf
from afmctl import sweeps as sw
from afmctl.profile import ModbusRtuTransport, ModbusTcpTransport, Profile, default_profile
from afmctl.transducer import Transducer
from drivers.device import emulator, plant

if TYPE_CHECKING:
    from drivers import StageBase

PROFILE = default_profile()
assert PROFILE.emulator is not None
SAMPLE_RATE_HZ = PROFILE.sample_rate_hz
NOISE_UM = PROFILE.emulator.noise_um
SENSOR_ZERO_UM = 2.0  # an arbitrary sensor zero the fits must find
TRANSPORTS = ["modbus-tcp", "modbus-rtu", "serial-pty", "serial-socket", "inprocess"]


@pytest.fixture(autouse=True)
def _quiet_pymodbus() -> None:
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


@pytest.fixture(scope="session")
def profile() -> Profile:
    return PROFILE


@pytest.fixture(scope="session")
def nominal(profile: Profile) -> Transducer:
    """The emulated stage's true model (the nominal AFM stage)."""
    assert profile.emulator is not None
    return profile.emulator.model


@pytest.fixture(scope="session")
def true_model(nominal: Transducer) -> Transducer:
    """The truth as a sweep sees it: the nominal stage with the sensor zero added."""
    return dc.replace(nominal, rod=dc.replace(nominal.rod, offset_um=SENSOR_ZERO_UM))


@pytest.fixture(scope="session")
def emulate() -> Callable[..., sw.Sweep]:
    """``emulate(voltage, frequency_hz, seed, meta=True)``: a sweep recorded by the emulated device
    (its physics and seeded sensor noise), with the sensor zero shifted by SENSOR_ZERO_UM."""
    assert PROFILE.emulator is not None
    cfg = PROFILE.emulator

    def make(voltage_v: np.ndarray, frequency_hz: float, seed: int,
             meta: bool = True) -> sw.Sweep:
        u, _ = plant.expected_readback(dc.replace(cfg, seed=seed), SAMPLE_RATE_HZ, voltage_v)
        md = {"frequency_hz": f"{frequency_hz:g}", "layer_thickness_um": "100.0",
              "profile": "emulated"} if meta else {}
        return sw.from_arrays(voltage_v, u + SENSOR_ZERO_UM, SAMPLE_RATE_HZ, md,
                              f"triangle_{frequency_hz:g}hz")

    return make


@pytest.fixture(scope="session")
def standard_sweeps(emulate: Callable[..., sw.Sweep]) -> list[sw.Sweep]:
    return [emulate(v, f, seed) for seed, (_, f, v) in
            enumerate(sw.standard_set(150.0, SAMPLE_RATE_HZ)[:3])]


@pytest.fixture(scope="session")
def standard_fit(standard_sweeps: list[sw.Sweep]) -> idf.FitResult:
    return idf.fit(standard_sweeps)


@pytest.fixture(scope="session")
def waveform() -> np.ndarray:
    """20,000 samples (2 s at 10 kHz) with a decaying envelope, so hysteresis minor loops show."""
    n = 20_000
    return 100.0 * np.sin(2 * np.pi * 5.0 * np.arange(n) / 10_000.0) * np.linspace(1.0, 0.3, n)


@pytest.fixture
def device(profile: Profile) -> Iterator[object]:
    from drivers.device.emulated import EmulatedDevice
    with EmulatedDevice(profile) as dev:
        yield dev


@contextmanager
def stage_on(kind: str, profile: Profile, read_only: bool | None = None
             ) -> Iterator[tuple[StageBase, emulator.Emulator]]:
    """A host stage talking to a fresh emulated device over ``kind`` (see TRANSPORTS)."""
    from drivers.device.emulated import EmulatedDevice
    from drivers.device.modbus_server import ModbusRtuServer, ModbusTcpServer
    from drivers.device.serial_server import SerialServer
    from drivers.inprocess import InProcessStage
    from drivers.modbus_link import ModbusStage
    from drivers.serial_link import SerialStage

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
