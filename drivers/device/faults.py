"""Fault injection: wire faults drawn per reply, and the relays that apply them.

:class:`FaultInjector` (configured by a profile's ``[emulator.faults]``) draws at most one fault per
reply. The serial server applies it to each reply line itself; Modbus replies pass through a faulty
relay (:class:`FaultyTcpProxy` in front of the TCP server, the :class:`PtyBridge` of the RTU
server), which applies it to each chunk of bytes on the way to the host. Faults are off unless
configured; the relays then pass everything through (the TCP proxy is not used at all).
"""

from __future__ import annotations

import contextlib
import os
import socket
import termios
import threading
import time
from collections import Counter

import numpy as np

from afmctl.drivers.device.wire import LOOPBACK, SelectLoop, open_pty, write_all
from afmctl.files.profile import WireFaults


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

def relay(data: bytes, to_fd: int, faults: FaultInjector | None,
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
    write_all(to_fd, data)
    return True


class PtyBridge(SelectLoop):
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
                    write_all(peer[fd], data)
                elif not relay(data, peer[fd], self.faults):
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


class FaultyTcpProxy(SelectLoop):
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
            keep = bool(data) and relay(data, dst.fileno(), self.faults, MBAP_BYTES)
        else:
            keep = bool(data)
            if keep:
                write_all(dst.fileno(), data)
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
