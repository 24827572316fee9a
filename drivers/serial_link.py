"""Host side of the ASCII protocol (``afmctl.drivers.ascii_protocol``) on pyserial.

Works on any pyserial URL: a real port, a pty path, ``socket://host:port``. Each command waits for
its one reply line (protocol v3: matched by tag, checked by CRC); a read that times out, a reply
without terminator or a malformed reply raises :class:`~afmctl.drivers.StageError` (code -1) instead of
hanging, after the retries that are safe (see :mod:`drivers`).
"""

from __future__ import annotations

import contextlib
import os
import time
from typing import Any

import numpy as np
import serial
from numpy.typing import NDArray
from serial.urlhandler.protocol_socket import Serial as SocketSerial

from afmctl.drivers import StageBase
from afmctl.drivers import ascii_protocol as ap
from afmctl.drivers.protocol import ERRORS, Status
from afmctl.errors import StageError
from afmctl.files.profile import Profile, SerialTransport

#: Most bytes one non-blocking read drains from a ``socket://`` port.
DRAIN_BYTES = 1 << 16


class SerialStage(StageBase):
    """A stage on the ASCII protocol.

    Parameters
    ----------
    profile : Profile
    url : str, optional
        Overrides the profile's serial URL.
    port : object, optional
        An already open pyserial-like port (tests); ``url`` is then ignored.
    timeout_s : float, optional
        Per-reply timeout (also pyserial's ``write_timeout``); the profile's by default.

    Every command is framed with a tag and a CRC (protocol v3); a reply with a bad CRC or another
    tag is discarded (counted in ``discarded``) and the host keeps waiting for its own until the
    timeout. A failed idempotent command is retried after a resync: the input is flushed, and a
    port this stage opened is reopened if the link itself failed (e.g. a socket closed).
    """

    upload_chunk = 200
    read_chunk = 200

    def __init__(self, profile: Profile, url: str | None = None, *, port: Any = None,
                 timeout_s: float | None = None) -> None:
        super().__init__(profile)
        t = profile.transport
        cfg = t if isinstance(t, SerialTransport) else SerialTransport(url or "")
        self.timeout_s = cfg.timeout_s if timeout_s is None else timeout_s
        self.watchdog_s = cfg.watchdog_s
        self.baudrate = cfg.baudrate
        self._buf = bytearray()
        self._tag = 0
        self._broken = False
        #: Reply lines thrown away (bad CRC, another request's tag).
        self.discarded = 0
        self._open = None if port is not None else (
            lambda: serial.serial_for_url(url or cfg.url, baudrate=cfg.baudrate,
                                          timeout=self.timeout_s, write_timeout=self.timeout_s))
        self._port = port if self._open is None else self._open()
        #: The port's ``in_waiting`` says only whether bytes wait, not how many (``socket://``).
        self._counts_one = isinstance(self._port, SocketSerial)
        try:
            version = self.query("VER?")
        except StageError:
            self.close()  # nothing answers: leave no port open behind the error
            raise
        if version not in [str(v) for v in ap.PROTOCOL_VERSIONS]:
            self.close()
            raise StageError(-1, f"device speaks protocol {version!r}, afmctl speaks "
                                 f"{' or '.join(map(str, ap.PROTOCOL_VERSIONS))}")
        #: The serial protocol version the device reports, which this link speaks.
        self.version = int(version)
        if self.version >= ap.CHANNELS_VERSION:
            try:
                self._channels = int(self.query("CHN?"))
            except (StageError, ValueError) as exc:
                self.close()
                raise StageError(-1, f"CHN? on a device of protocol {version}: {exc}") from None

    # -- line I/O ------------------------------------------------------------------------------
    def _readline(self, deadline: float) -> str:
        while (end := self._buf.find(b"\n")) < 0:
            if len(self._buf) > ap.MAX_LINE * 8:
                raise StageError(-1, "reply line too long")
            try:
                chunk = self._read_block()
            except (serial.SerialException, OSError) as exc:
                self._broken = True
                raise StageError(-1, f"link failed: {exc}") from None
            if not chunk and time.monotonic() > deadline:
                raise StageError(-1, f"no complete reply within {self.timeout_s:g} s")
            self._buf += chunk
        line = bytes(self._buf[:end])
        del self._buf[:end + 1]
        return line.decode("ascii", errors="replace").rstrip("\r")

    def _read_block(self) -> bytes:
        """What has arrived, as one block; waits up to the port's timeout for the first byte.

        A UART or pty driver counts the bytes waiting; pyserial's ``socket://`` handler only says
        whether any are (``in_waiting`` is 0 or 1), so there the first byte is awaited and the
        rest drained with a non-blocking read (timeout 0) instead of one byte per call."""
        port = self._port
        waiting = port.in_waiting
        if waiting > 1 or not self._counts_one:
            return bytes(port.read(max(1, waiting)))
        first = port.read(1)
        if not first:
            return b""
        port.timeout = 0
        try:
            return bytes(first) + bytes(port.read(DRAIN_BYTES))
        finally:
            port.timeout = self.timeout_s

    def _exchange(self, line: str) -> str:
        """One attempt: send ``line`` framed with a new tag, return the payload of its reply."""
        self._tag = (self._tag + 1) % 100_000
        try:
            self._port.write(ap.frame(line, self._tag).encode("ascii") + b"\n")
        except serial.SerialTimeoutException:
            raise StageError(-1, f"write timed out after {self.timeout_s:g} s") from None
        except (serial.SerialException, OSError) as exc:
            self._broken = True
            raise StageError(-1, f"link failed: {exc}") from None
        deadline = time.monotonic() + self.timeout_s
        while True:
            try:
                payload, tag = ap.unframe(self._readline(deadline))
            except ap.FrameError:
                self.discarded += 1
                continue
            if tag == self._tag:
                return payload
            self.discarded += 1

    def _resync(self) -> None:
        """Forget buffered input; reopen a port this stage opened if the link itself failed."""
        self._buf.clear()
        if self._open is None or not self._broken:
            with contextlib.suppress(serial.SerialException, OSError, AttributeError):
                self._port.reset_input_buffer()
            return
        self._broken = False
        with contextlib.suppress(serial.SerialException, OSError):
            self._port.close()
        try:
            self._port = self._open()
        except (serial.SerialException, OSError) as exc:
            raise StageError(-1, f"cannot reopen the link: {exc}") from None

    def query(self, line: str, idempotent: bool = True) -> str:
        """Send one command line, return its reply; StageError for an ``ERR`` reply. A transport
        failure is retried (see :class:`SerialStage`) if ``idempotent``."""
        reply = self._retrying(lambda: self._exchange(line), idempotent)
        if reply.startswith("ERR "):
            parts = reply.split(maxsplit=2)
            code = int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else -1
            raise StageError(code if code in ERRORS else -1, f"{line[:40]!r}")
        return reply

    def _command(self, line: str, idempotent: bool = True) -> None:
        reply = self.query(line, idempotent)
        if reply != "OK":
            raise StageError(-1, f"expected OK to {line[:40]!r}, got {reply[:40]!r}")

    def uart_rates(self) -> tuple[float, float] | None:
        """At the baud rate of a real UART (10 bits per byte): upload at
        :data:`~afmctl.drivers.ascii_protocol.UPLOAD_BYTES_PER_SAMPLE`, readback at
        :data:`~afmctl.drivers.ascii_protocol.READBACK_BYTES_PER_SAMPLE` bytes per sample. None for a
        socket or a pty (no baud rate limits them)."""
        if not is_uart(self._port):
            return None
        bytes_per_s = self.baudrate / 10
        return (bytes_per_s / ap.UPLOAD_BYTES_PER_SAMPLE,
                bytes_per_s / ap.READBACK_BYTES_PER_SAMPLE)

    # -- Stage primitives ----------------------------------------------------------------------
    def identify(self) -> str:
        return self.query("*IDN?")

    def status(self) -> Status:
        try:
            return ap.parse_status(self.query("STA?"))
        except ValueError as exc:
            raise StageError(-1, str(exc)) from None

    @staticmethod
    def on_channel(line: str, channel: int) -> str:
        """A per-channel command for ``channel``: as it is for channel 0 (every protocol version),
        ``CH <c> <command>`` for another (protocol 4, §3.6)."""
        return line if channel == 0 else f"CH {channel} {line}"

    def voltage(self, channel: int = 0) -> float:
        return float(self.query(self.on_channel("VOL?", channel)))

    def limits(self, channel: int = 0) -> tuple[float, float, float]:
        """Device limits of ``channel``: v_min (V), v_max (V), slew (V/ms)."""
        a, b, c = (float(x) for x in self.query(self.on_channel("LIM?", channel)).split())
        return a, b, c

    def last_error(self) -> int:
        """The sticky last error code (cleared by reading, so never retried)."""
        return int(self.query("ERR?", idempotent=False))

    def set_voltage(self, v: float, channel: int = 0) -> None:
        self._command(self.on_channel(f"SVA {ap.fmt(v)}", channel))

    def stop(self) -> None:
        self._command("WGO 0")

    def safe_state(self) -> None:
        self._command("SAFE")

    def heartbeat(self) -> None:
        self._command("HB")

    def set_watchdog(self, period_s: float) -> None:
        self._command(f"WDT {period_s!r}")

    def set_sample_rate(self, hz: float) -> None:
        self._command(f"WTR {hz!r}")

    def close(self) -> None:
        self._port.close()

    def _set_table_length(self, n: int) -> None:
        self._command(f"WTL {n}")

    def _write_chunk(self, first: int, values: NDArray[np.float32], channel: int = 0) -> None:
        self._command(self.on_channel(ap.wav_line(first, values), channel))

    def _start(self, cycles: int) -> None:
        self._command(f"WGO {cycles}", idempotent=False)

    def _read_chunk(self, first: int, n: int, channel: int = 0
                    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        try:
            return ap.parse_recorder(self.query(self.on_channel(f"DRR? {first} {n}", channel)),
                                     first, n)
        except ValueError as exc:
            raise StageError(-1, str(exc)) from None

    def _start_stream(self, n_total: int) -> None:
        self._command(f"WGS {n_total}", idempotent=False)

    def _capacities(self) -> tuple[int, int]:
        try:
            table, recorder = (int(x) for x in self.query("CAP?").split())
        except ValueError as exc:
            raise StageError(-1, f"CAP? reply: {exc}") from None
        return table, recorder


def is_uart(port: Any) -> bool:
    """Whether a pyserial port is a real UART: a local serial device that is not a pseudo-terminal
    (``/dev/pts/N``, ``/dev/ptmx``). Sockets, ``loop://`` and ptys carry bytes at memory speed."""
    path = getattr(port, "port", None)
    if not isinstance(port, serial.Serial) or not isinstance(path, str) or "://" in path:
        return False
    real = os.path.realpath(path)
    return not (real.startswith("/dev/pts/") or real == "/dev/ptmx")
