"""The serial (ASCII) protocol served on a pty or on ``socket://host:port``."""

from __future__ import annotations

import contextlib
import os
import socket
import time
from typing import TYPE_CHECKING

from afmctl.drivers import ascii_protocol as ap
from afmctl.drivers.device.wire import LOOPBACK, SelectLoop, open_pty, write_all

if TYPE_CHECKING:
    from afmctl.drivers.device.emulated import EmulatedDevice


class SerialServer(SelectLoop):
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
        #: Descriptors whose current line is over-long: answered once, skipped up to its LF.
        self._skipping: set[int] = set()
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
            raw = bytes(buf[:end])
            del buf[:end + 1]
            if fd in self._skipping:  # the rest of an over-long line, already answered
                self._skipping.discard(fd)
                continue
            reply = (self.device.overlong_line() if len(raw) > ap.MAX_LINE else  # CR counted
                     self.device.handle_line(raw.removesuffix(b"\r").decode("latin-1")))
            if reply is not None:
                self._send(fd, reply.encode("ascii") + b"\n")
        if fd in self._fds and len(buf) > ap.MAX_LINE:
            buf.clear()
            if fd not in self._skipping:
                self._skipping.add(fd)
                self._send(fd, self.device.overlong_line().encode("ascii") + b"\n")

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
        write_all(fd, reply)

