"""One emulated device behind its wires: the device's lock, clock and watchdog ticker, and
:func:`serve_all`, which serves it on every wire at once.

:class:`EmulatedDevice` owns one :class:`~afmctl.drivers.device.emulator.Emulator`, the interpreters of
both protocols, a lock that serializes every request from every server, the device clock
(``time.monotonic``) and a ticker thread that lets the watchdog expire while nobody talks. The
servers (:mod:`afmctl.drivers.device.serial_server`, :mod:`afmctl.drivers.device.modbus_server`) are context
managers that start on entry and stop (joining their threads, closing every descriptor) on exit.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator

from afmctl.drivers.device.ascii_device import AsciiDevice
from afmctl.drivers.device.emulator import Emulator
from afmctl.drivers.device.faults import FaultInjector
from afmctl.drivers.device.modbus_server import ModbusRtuServer, ModbusTcpServer
from afmctl.drivers.device.register_device import RegisterDevice
from afmctl.drivers.device.serial_server import SerialServer
from afmctl.drivers.device.wire import LOOPBACK
from afmctl.files.profile import Profile, WireFaults

TICK_S = 0.01


class EmulatedDevice:
    """One emulated device shared by any number of servers.

    Parameters
    ----------
    profile : Profile
    read_only : bool, optional
        Override the profile's ``emulator.read_only``.
    faults : WireFaults, optional
        Override the profile's ``emulator.faults`` (what the servers inject).
    """

    def __init__(self, profile: Profile, read_only: bool | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 faults: WireFaults | None = None) -> None:
        self.emulator = Emulator(profile, read_only=read_only)
        self.faults = FaultInjector(self.emulator.config.faults if faults is None else faults)
        self.clock = clock
        self.lock = threading.Lock()
        self.ascii = AsciiDevice(self.emulator, clock)
        self.registers = RegisterDevice(self.emulator, clock)
        self._stop = threading.Event()
        self._ticker = threading.Thread(target=self._tick, name="emulator-tick", daemon=True)

    def _tick(self) -> None:
        while not self._stop.wait(TICK_S):
            with self.lock:
                self.emulator.tick(self.clock())

    def handle_line(self, line: str) -> str | None:
        """A received line -> the framed reply (None: nothing to answer)."""
        with self.lock:
            return self.ascii.handle_framed(line)

    def overlong_line(self) -> str:
        """The reply to a line longer than the protocol allows (untagged ``ERR 2``)."""
        with self.lock:
            return self.ascii.overlong()

    def __enter__(self) -> EmulatedDevice:
        self._ticker.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._ticker.join()


@contextlib.contextmanager
def serve_all(profile: Profile, *, host: str = LOOPBACK, modbus_port: int = 0,
              serial: str = "pty", rtu: bool = True, read_only: bool | None = None,
              faults: WireFaults | None = None) -> Iterator[dict[str, str]]:
    """Serve one emulated device on every wire; yields ``{name: address}`` for the hosts.
    ``faults`` overrides the profile's ``[emulator.faults]``."""
    with contextlib.ExitStack() as stack:
        dev = stack.enter_context(EmulatedDevice(profile, read_only=read_only, faults=faults))
        tcp = stack.enter_context(ModbusTcpServer(dev, host, modbus_port))
        where = {"modbus-tcp": f"{host}:{tcp.port}"}
        if rtu:
            where["modbus-rtu"] = stack.enter_context(ModbusRtuServer(dev)).url
        where["serial"] = stack.enter_context(SerialServer(dev, serial)).url
        yield where
