"""Serve an emulated device over the real wires: ASCII on a pty or socket, Modbus TCP, Modbus RTU.

:class:`EmulatedDevice` owns one :class:`~afmctl.emulator.Emulator`, a lock that serializes every
request from every server, the device clock (``time.monotonic``) and a ticker thread that lets the
watchdog expire while nobody talks. The servers are context managers that start on entry and stop
(joining their threads, closing every descriptor) on exit:

- :class:`SerialServer`: the ASCII protocol on a pty (``url`` is the path for the host) or on
  ``socket://host:port`` (TCP listener; port 0 picks a free one);
- :class:`ModbusTcpServer`: the register map on Modbus TCP (``port`` after start);
- :class:`ModbusRtuServer`: the register map with RTU framing on a pty pair (a null-modem bridge:
  pymodbus opens one end, the host the other, ``url``).

Every server binds 127.0.0.1 unless given another host explicitly.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import select
import socket
import threading
import time
import tty
from collections.abc import Callable, Iterator
from typing import Any

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer
from pymodbus.server import ModbusTcpServer as _PymodbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from afmctl.emulator import Emulator
from afmctl.profile import Profile
from drivers import ascii_protocol as ap
from drivers import register_map as rm

LOOPBACK = "127.0.0.1"
TICK_S = 0.01


class EmulatedDevice:
    """One emulated device shared by any number of servers.

    Parameters
    ----------
    profile : Profile
    read_only : bool, optional
        Override the profile's ``emulator.read_only``.
    """

    def __init__(self, profile: Profile, read_only: bool | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.emulator = Emulator(profile, read_only=read_only)
        self.clock = clock
        self.lock = threading.Lock()
        self.ascii = ap.AsciiDevice(self.emulator, clock)
        self.registers = rm.RegisterDevice(self.emulator, clock)
        self._stop = threading.Event()
        self._ticker = threading.Thread(target=self._tick, name="emulator-tick", daemon=True)

    def _tick(self) -> None:
        while not self._stop.wait(TICK_S):
            with self.lock:
                self.emulator.tick(self.clock())

    def handle_line(self, line: str) -> str:
        with self.lock:
            return self.ascii.handle(line)

    def __enter__(self) -> EmulatedDevice:
        self._ticker.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._ticker.join()


# -- ASCII protocol on a pty or a socket ----------------------------------------------------------
def open_pty() -> tuple[int, int, str]:
    """A raw pty pair: (master fd, slave fd, slave path)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


class SerialServer:
    """The ASCII protocol on a pty (``where="pty"``) or ``socket://host:port``.

    Attributes
    ----------
    url : str
        What the host passes to pyserial (pty path or ``socket://127.0.0.1:PORT``).
    """

    def __init__(self, device: EmulatedDevice, where: str = "pty") -> None:
        self.device = device
        self._wake_r, self._wake_w = os.pipe()
        self._listener: socket.socket | None = None
        self._fds: dict[int, bytearray] = {}
        self._owned: list[int] = []
        if where == "pty":
            master, slave, path = open_pty()
            self._fds[master] = bytearray()
            self._owned = [master, slave]  # holding the slave open keeps the master readable
            self.url = path
        elif where.startswith("socket://"):
            host, _, port = where[len("socket://"):].rpartition(":")
            self._listener = socket.create_server((host or LOOPBACK, int(port or 0)))
            self.url = "socket://{}:{}".format(*self._listener.getsockname()[:2])
        else:
            raise ValueError(f"serve the serial protocol on 'pty' or 'socket://host:port', "
                             f"not {where!r}")
        self._thread = threading.Thread(target=self._serve, name="ascii-server", daemon=True)

    def __enter__(self) -> SerialServer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        os.write(self._wake_w, b"x")
        self._thread.join()
        for fd in [*self._fds, *self._owned, self._wake_r, self._wake_w]:
            with contextlib.suppress(OSError):
                os.close(fd)
        if self._listener is not None:
            self._listener.close()

    def _serve(self) -> None:
        while True:
            watch = [self._wake_r, *self._fds] + ([self._listener] if self._listener else [])
            ready, _, _ = select.select(watch, [], [])
            if self._wake_r in ready:
                return
            for r in ready:
                if r is self._listener:
                    conn, _ = self._listener.accept()  # type: ignore[union-attr]
                    self._fds[conn.detach()] = bytearray()
                else:
                    self._receive(r)

    def _receive(self, fd: int) -> None:
        try:
            data = os.read(fd, 65536)
        except OSError:
            data = b""
        if not data:
            if fd not in self._owned:  # a socket client left
                del self._fds[fd]
                os.close(fd)
            else:
                time.sleep(0.01)  # pty with no host: nothing to read yet
            return
        buf = self._fds[fd]
        buf += data
        while (end := buf.find(b"\n")) >= 0:
            line = buf[:end].decode("ascii", errors="replace").rstrip("\r")
            del buf[:end + 1]
            reply = self.device.handle_line(line) if line.strip() else None
            if reply is not None:
                _write_all(fd, reply.encode("ascii") + b"\n")
        if len(buf) > ap.MAX_LINE * 8:
            buf.clear()
            _write_all(fd, b"ERR 2 bad argument\n")


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        try:
            view = view[os.write(fd, view):]
        except BlockingIOError:
            select.select([], [fd], [], 1.0)
        except OSError:
            return


# -- Modbus -----------------------------------------------------------------------------------
def sim_device(device: EmulatedDevice, unit: int = 1) -> SimDevice:
    """A pymodbus SimDevice whose every access is answered by the device's register map."""

    async def action(function_code: int, start_address: int, address: int, count: int,
                     registers: list[int], set_values: list[int] | list[bool] | None
                     ) -> ExcCodes | None:
        with device.lock:
            if set_values is not None:
                res = device.registers.write(address, [int(x) for x in set_values])
                return None if res is None else ExcCodes(res)
            regs = (device.registers.read_input(address, count) if function_code == 4
                    else device.registers.read_holding(address, count))
        if isinstance(regs, int):
            return ExcCodes(regs)
        registers[address - start_address:address - start_address + count] = regs
        return None

    bits = [SimData(0, count=16, values=False, datatype=DataType.BITS)]
    holding = [SimData(0, count=rm.HR.END, values=0, datatype=DataType.REGISTERS)]
    inputs = [SimData(0, count=rm.IR.END, values=0, datatype=DataType.REGISTERS)]
    return SimDevice(unit, simdata=(bits, list(bits), holding, inputs), action=action)


class _LoopThread:
    """An asyncio loop in a background thread, for pymodbus servers."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="modbus-loop",
                                        daemon=True)
        self._thread.start()

    def run(self, coro: Any, timeout_s: float = 10.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout_s)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join()
        self.loop.close()


class _ModbusServerBase:
    def __init__(self) -> None:
        self._loop: _LoopThread | None = None
        self._server: Any = None

    def _make(self) -> Any:
        raise NotImplementedError

    def __enter__(self) -> Any:
        self._loop = _LoopThread()

        async def start() -> Any:
            server = self._make()
            await server.serve_forever(background=True)
            return server

        self._server = self._loop.run(start())
        return self

    def __exit__(self, *exc: object) -> None:
        assert self._loop is not None
        self._loop.run(self._shutdown())
        self._loop.close()

    async def _shutdown(self) -> None:
        await self._server.shutdown()
        await asyncio.sleep(0)
        pending = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for t in pending:
            t.cancel()
        await asyncio.gather(*pending, return_exceptions=True)


class ModbusTcpServer(_ModbusServerBase):
    """The register map on Modbus TCP at ``host:port`` (port 0: a free one, see ``.port``)."""

    def __init__(self, device: EmulatedDevice, host: str = LOOPBACK, port: int = 0,
                 unit: int = 1) -> None:
        super().__init__()
        self.device, self.host, self.port, self.unit = device, host, port, unit

    def _make(self) -> Any:
        return _PymodbusTcpServer(sim_device(self.device, self.unit),
                                  address=(self.host, self.port))

    def __enter__(self) -> ModbusTcpServer:
        super().__enter__()
        self.port = self._server.transport.sockets[0].getsockname()[1]
        return self


class ModbusRtuServer(_ModbusServerBase):
    """The register map with RTU framing on a pty pair; the host opens ``url``."""

    def __init__(self, device: EmulatedDevice, unit: int = 1, baudrate: int = 115200) -> None:
        super().__init__()
        self.device, self.unit, self.baudrate = device, unit, baudrate
        self._bridge = PtyBridge()
        self.url = self._bridge.host_path

    def _make(self) -> Any:
        return ModbusSerialServer(sim_device(self.device, self.unit), framer=FramerType.RTU,
                                  port=self._bridge.device_path, baudrate=self.baudrate)

    def __enter__(self) -> ModbusRtuServer:
        self._bridge.__enter__()
        super().__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        super().__exit__(*exc)
        self._bridge.__exit__(*exc)


class PtyBridge:
    """Two raw ptys joined master to master: a null-modem cable with a path at each end."""

    def __init__(self) -> None:
        self._a = open_pty()
        self._b = open_pty()
        self.device_path, self.host_path = self._a[2], self._b[2]
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._pump, name="pty-bridge", daemon=True)

    def _pump(self) -> None:
        peer = {self._a[0]: self._b[0], self._b[0]: self._a[0]}
        while True:
            ready, _, _ = select.select([self._wake_r, *peer], [], [])
            if self._wake_r in ready:
                return
            for fd in ready:
                try:
                    data = os.read(fd, 65536)
                except OSError:
                    data = b""
                if data:
                    _write_all(peer[fd], data)
                else:
                    time.sleep(0.005)

    def __enter__(self) -> PtyBridge:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        os.write(self._wake_w, b"x")
        self._thread.join()
        for fd in (*self._a[:2], *self._b[:2], self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)


@contextlib.contextmanager
def serve_all(profile: Profile, *, host: str = LOOPBACK, modbus_port: int = 0,
              serial: str = "pty", rtu: bool = True, read_only: bool | None = None
              ) -> Iterator[dict[str, str]]:
    """Serve one emulated device on every wire; yields ``{name: address}`` for the hosts."""
    with contextlib.ExitStack() as stack:
        dev = stack.enter_context(EmulatedDevice(profile, read_only=read_only))
        tcp = stack.enter_context(ModbusTcpServer(dev, host, modbus_port))
        where = {"modbus-tcp": f"{host}:{tcp.port}"}
        if rtu:
            where["modbus-rtu"] = stack.enter_context(ModbusRtuServer(dev)).url
        where["serial"] = stack.enter_context(SerialServer(dev, serial)).url
        yield where
