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

Wire faults (:class:`FaultInjector`, configured by a profile's ``[emulator.faults]``) hit what the
device sends: the serial server applies them to each reply line; Modbus replies pass through a
faulty relay (:class:`FaultyTcpProxy` in front of the TCP server, the :class:`PtyBridge` of the RTU
server), which applies them to each chunk of bytes on the way to the host. Faults are off unless
configured; the relays are not used then.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import select
import socket
import termios
import threading
import time
import tty
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer
from pymodbus.server import ModbusTcpServer as _PymodbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from afmctl.emulator import Emulator
from afmctl.profile import Profile, WireFaults
from drivers import ascii_protocol as ap
from drivers import register_map as rm

LOOPBACK = "127.0.0.1"
TICK_S = 0.01


class FaultInjector:
    """Draws at most one fault per reply, from a seeded generator (thread-safe).

    Parameters
    ----------
    faults : WireFaults
        Probabilities per reply and the delay, s.

    Attributes
    ----------
    counts : Counter
        Faults injected so far, by kind.
    """

    def __init__(self, faults: WireFaults) -> None:
        self.counts: Counter[str] = Counter()
        self._lock = threading.Lock()
        self.reconfigure(faults)

    def reconfigure(self, faults: WireFaults) -> None:
        """Inject ``faults`` from now on (a new generator from its seed). The Modbus relays exist
        only if faults were active when their server started."""
        with self._lock:
            self.faults = faults
            self._cumulative = np.cumsum(faults.probabilities())
            self._rng = np.random.default_rng(faults.seed)

    @property
    def active(self) -> bool:
        return self.faults.active

    def draw(self) -> str | None:
        """The fault for the next reply (a kind of :attr:`WireFaults.KINDS`), or None."""
        if not self.active:
            return None
        with self._lock:
            k = int(np.searchsorted(self._cumulative, self._rng.random(), side="right"))
            if k >= len(WireFaults.KINDS):
                return None
            kind = WireFaults.KINDS[k]
            self.counts[kind] += 1
            return kind

    def corrupt(self, data: bytes, within: int | None = None) -> bytes:
        """``data`` with one byte (of the first ``within``, if given) changed (XOR with a random
        non-zero value)."""
        with self._lock:
            i = int(self._rng.integers(min(len(data), within or len(data))))
            flip = int(self._rng.integers(1, 256))
        out = bytearray(data)
        out[i] ^= flip
        return bytes(out)

    def garbage(self) -> bytes:
        """1-32 random bytes."""
        with self._lock:
            return self._rng.integers(0, 256, int(self._rng.integers(1, 33))).astype(
                np.uint8).tobytes()


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
        self.ascii = ap.AsciiDevice(self.emulator, clock)
        self.registers = rm.RegisterDevice(self.emulator, clock)
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

    def __enter__(self) -> EmulatedDevice:
        self._ticker.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._ticker.join()


class _SelectLoop:
    """A select loop (``_serve``) in a background thread, started on entry and stopped on exit
    through a wake-up pipe (``_wake_r`` is among the descriptors it watches)."""

    def __init__(self, name: str) -> None:
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._serve, name=name, daemon=True)

    def _serve(self) -> None:
        raise NotImplementedError

    def _select(self, watch: list[Any]) -> list[Any] | None:
        """The ready ones of ``watch``; None when asked to stop."""
        ready, _, _ = select.select([self._wake_r, *watch], [], [])
        return None if self._wake_r in ready else ready

    def __enter__(self) -> Any:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        os.write(self._wake_w, b"x")
        self._thread.join()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)


# -- ASCII protocol on a pty or a socket ----------------------------------------------------------
def open_pty() -> tuple[int, int, str]:
    """A raw pty pair: (master fd, slave fd, slave path)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


class SerialServer(_SelectLoop):
    """The ASCII protocol on a pty (``where="pty"``) or ``socket://host:port``.

    Attributes
    ----------
    url : str
        What the host passes to pyserial (pty path or ``socket://127.0.0.1:PORT``).
    """

    def __init__(self, device: EmulatedDevice, where: str = "pty") -> None:
        super().__init__("ascii-server")
        self.device = device
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

    def __enter__(self) -> SerialServer:
        return super().__enter__()  # type: ignore[no-any-return]

    def __exit__(self, *exc: object) -> None:
        super().__exit__(*exc)
        for fd in [*self._fds, *self._owned]:
            with contextlib.suppress(OSError):
                os.close(fd)
        if self._listener is not None:
            self._listener.close()

    def _serve(self) -> None:
        while True:
            ready = self._select([*self._fds] + ([self._listener] if self._listener else []))
            if ready is None:
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
        while fd in self._fds and (end := buf.find(b"\n")) >= 0:
            line = buf[:end].decode("ascii", errors="replace").rstrip("\r")
            del buf[:end + 1]
            reply = self.device.handle_line(line)
            if reply is not None:
                self._send(fd, reply.encode("ascii") + b"\n")
        if len(buf) > ap.MAX_LINE * 8:
            buf.clear()
            self._send(fd, ap.frame("ERR 2 bad argument", None).encode("ascii") + b"\n")

    def _send(self, fd: int, reply: bytes) -> None:
        """Send one reply line, through the device's fault injector."""
        faults = self.device.faults
        kind = faults.draw()
        if kind == "drop":
            return
        if kind == "disconnect":
            self._fds[fd].clear()
            if fd not in self._owned:  # a socket: hang up on the host
                del self._fds[fd]
                os.close(fd)
            return
        if kind == "delay":
            time.sleep(faults.faults.delay_s)
        elif kind == "corrupt":
            reply = faults.corrupt(reply)
        elif kind == "garbage":
            reply = faults.garbage() + b"\n" + reply
        _write_all(fd, reply)


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
    """The register map on Modbus TCP at ``host:port`` (port 0: a free one, see ``.port``).

    With wire faults configured, ``host:port`` is a :class:`FaultyTcpProxy` and pymodbus listens
    on a free loopback port behind it.
    """

    def __init__(self, device: EmulatedDevice, host: str = LOOPBACK, port: int = 0,
                 unit: int = 1) -> None:
        super().__init__()
        self.device, self.host, self.port, self.unit = device, host, port, unit
        self._proxy: FaultyTcpProxy | None = None

    def _make(self) -> Any:
        where = (LOOPBACK, 0) if self.device.faults.active else (self.host, self.port)
        return _PymodbusTcpServer(sim_device(self.device, self.unit), address=where)

    def __enter__(self) -> ModbusTcpServer:
        super().__enter__()
        backend = self._server.transport.sockets[0].getsockname()[1]
        if self.device.faults.active:
            self._proxy = FaultyTcpProxy(backend, self.device.faults, self.host, self.port)
            self._proxy.__enter__()
            backend = self._proxy.port
        self.port = backend
        return self

    def __exit__(self, *exc: object) -> None:
        if self._proxy is not None:
            self._proxy.__exit__(*exc)
        super().__exit__(*exc)


class ModbusRtuServer(_ModbusServerBase):
    """The register map with RTU framing on a pty pair; the host opens ``url``."""

    def __init__(self, device: EmulatedDevice, unit: int = 1, baudrate: int = 115200) -> None:
        super().__init__()
        self.device, self.unit, self.baudrate = device, unit, baudrate
        self._bridge = PtyBridge(device.faults if device.faults.active else None)
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


def _relay(data: bytes, to_fd: int, faults: FaultInjector | None,
           corrupt_within: int | None = None) -> bool:
    """Forward bytes the device sent toward the host through ``faults``; False: hang up.
    ``corrupt_within``: a corruption hits one of the first that many bytes."""
    kind = faults.draw() if faults is not None else None
    if kind == "drop":
        return True
    if kind == "disconnect":
        return False
    if kind == "delay":
        time.sleep(faults.faults.delay_s)  # type: ignore[union-attr]
    elif kind == "corrupt":
        data = faults.corrupt(data, corrupt_within)  # type: ignore[union-attr]
    elif kind == "garbage":
        data = faults.garbage() + data  # type: ignore[union-attr]
    _write_all(to_fd, data)
    return True


class PtyBridge(_SelectLoop):
    """Two raw ptys joined master to master: a null-modem cable with a path at each end.

    With ``faults``, what the device end sends is relayed through them (a "disconnect" loses
    whatever the device sent and what is buffered toward the host: a pulled cable).
    """

    def __init__(self, faults: FaultInjector | None = None) -> None:
        super().__init__("pty-bridge")
        self._a = open_pty()
        self._b = open_pty()
        self.device_path, self.host_path = self._a[2], self._b[2]
        self.faults = faults

    def _serve(self) -> None:
        peer = {self._a[0]: self._b[0], self._b[0]: self._a[0]}
        while True:
            ready = self._select(list(peer))
            if ready is None:
                return
            for fd in ready:
                try:
                    data = os.read(fd, 65536)
                except OSError:
                    data = b""
                if not data:
                    time.sleep(0.005)
                elif fd != self._a[0]:
                    _write_all(peer[fd], data)
                elif not _relay(data, peer[fd], self.faults):
                    with contextlib.suppress(termios.error):
                        termios.tcflush(self._b[1], termios.TCIFLUSH)

    def __enter__(self) -> PtyBridge:
        return super().__enter__()  # type: ignore[no-any-return]

    def __exit__(self, *exc: object) -> None:
        super().__exit__(*exc)
        for fd in (*self._a[:2], *self._b[:2]):
            with contextlib.suppress(OSError):
                os.close(fd)


#: Bytes of the Modbus TCP header (MBAP: transaction id, protocol id, length, unit id).
MBAP_BYTES = 7


class FaultyTcpProxy(_SelectLoop):
    """A TCP relay on ``host:port`` in front of a server at 127.0.0.1:``backend_port``, injecting
    ``faults`` into what the server sends (a "disconnect" closes both connections).

    TCP checksums its segments, so a byte corrupted on the wire never reaches a Modbus TCP host
    (the segment is resent: a delay); what can reach it is a wrong header from a confused device,
    so a corruption here hits the MBAP header (transaction id, length, unit id).
    """

    def __init__(self, backend_port: int, faults: FaultInjector, host: str = LOOPBACK,
                 port: int = 0) -> None:
        super().__init__("tcp-fault-proxy")
        self.backend_port, self.faults = backend_port, faults
        self._listener = socket.create_server((host, port))
        self.port: int = self._listener.getsockname()[1]
        self._peer: dict[socket.socket, socket.socket] = {}
        self._toward_host: set[socket.socket] = set()

    def _serve(self) -> None:
        while True:
            ready = self._select([self._listener, *self._peer])
            if ready is None:
                return
            for r in ready:
                if r is self._listener:
                    self._accept()
                elif r in self._peer:
                    self._forward(r)

    def _accept(self) -> None:
        host_side, _ = self._listener.accept()
        try:
            server_side = socket.create_connection((LOOPBACK, self.backend_port), timeout=5.0)
        except OSError:
            host_side.close()
            return
        self._peer[host_side], self._peer[server_side] = server_side, host_side
        self._toward_host.add(server_side)

    def _forward(self, src: socket.socket) -> None:
        try:
            data = src.recv(65536)
        except OSError:
            data = b""
        dst = self._peer[src]
        if src in self._toward_host:
            keep = bool(data) and _relay(data, dst.fileno(), self.faults, MBAP_BYTES)
        else:
            keep = bool(data)
            if keep:
                _write_all(dst.fileno(), data)
        if not keep:
            self._hang_up(src)

    def _hang_up(self, sock: socket.socket) -> None:
        for s in (sock, self._peer[sock]):
            self._peer.pop(s, None)
            self._toward_host.discard(s)
            s.close()

    def __enter__(self) -> FaultyTcpProxy:
        return super().__enter__()  # type: ignore[no-any-return]

    def __exit__(self, *exc: object) -> None:
        super().__exit__(*exc)
        for sock in list(self._peer):
            if sock in self._peer:
                self._hang_up(sock)
        self._listener.close()


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
