"""The device's interpreter of the serial (ASCII) protocol: command lines -> an
:class:`~afmctl.drivers.device.emulator.Emulator` -> framed reply lines. No I/O (the servers in
:mod:`afmctl.drivers.device.serial_server` move the bytes). Codec: :mod:`afmctl.drivers.ascii_protocol`."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from afmctl.drivers.ascii_protocol import (
    MAX_CHUNK,
    MAX_LINE,
    PROTOCOL_VERSION,
    fmt,
    frame,
    parse_float32,
    parse_int,
    printable,
    split_frame,
    status_line,
)
from afmctl.drivers.device.emulator import IDENTITY, Emulator
from afmctl.drivers.protocol import ERRORS
from afmctl.errors import DeviceError, FrameError


class AsciiDevice:
    """Interpret command lines for an :class:`~afmctl.drivers.device.emulator.Emulator`.

    Parameters
    ----------
    emulator : Emulator
    clock : callable
        Returns the device time, s (``time.monotonic`` on a server, a fake in tests).
    """

    def __init__(self, emulator: Emulator, clock: Callable[[], float]) -> None:
        self.em = emulator
        self.clock = clock
        self._commands: dict[str, Callable[[list[str], float], str]] = {
            "*IDN?": lambda a, t: self._noargs(a, IDENTITY),
            "VER?": lambda a, t: self._noargs(a, str(PROTOCOL_VERSION)),
            "SVA": lambda a, t: self._ok(self.em.set_voltage(_float(a, 0, 1), t)),
            "VOL?": lambda a, t: self._noargs(a, fmt(self.em.status(t).output_v)),
            "WTR": lambda a, t: self._ok(self.em.set_sample_rate(_float(a, 0, 1), t)),
            "WTR?": lambda a, t: self._noargs(a, fmt(self.em.status(t).sample_rate_hz)),
            "WTL": lambda a, t: self._ok(self.em.set_table_length(_int(a, 0, 1), t)),
            "WTL?": lambda a, t: self._noargs(a, str(self.em.status(t).table_length)),
            "WAV": self._wav,
            "WGO": self._wgo,
            "WGS": lambda a, t: self._ok(self.em.start_stream(_int(a, 0, 1), t)),
            "POS?": lambda a, t: self._noargs(a, str(self.em.status(t).play_position)),
            "CAP?": lambda a, t: self._noargs(a, f"{self.em.table.size} {self.em.rec_u.size}"),
            "DRL?": lambda a, t: self._noargs(a, str(self.em.status(t).recorder_fill)),
            "DRR?": self._drr,
            "STA?": lambda a, t: self._noargs(a, status_line(self.em.status(t))),
            "ERR?": lambda a, t: self._noargs(a, str(self.em.pop_error(t))),
            "LIM?": lambda a, t: self._noargs(a, " ".join(fmt(x) for x in (
                self.em.limits.v_min, self.em.limits.v_max, self.em.limits.slew_v_per_ms))),
            "SAFE": lambda a, t: self._bare(a, lambda: self.em.safe_state(t)),
            "HB": lambda a, t: self._bare(a, lambda: self.em.heartbeat(t)),
            "WDT": lambda a, t: self._ok(self.em.set_watchdog(_float(a, 0, 1), t)),
        }

    def handle_framed(self, line: str) -> str | None:
        """One received line (framed or typed by hand; its CR LF taken off, one character per
        byte) -> the framed reply, or None for a line whose CRC is wrong (discarded unanswered,
        §3.2(c)) or whose payload is empty (§3.1(e)). A line with a byte outside printable ASCII
        and TAB is refused with error 2 before its command word is read (§3.1(c))."""
        try:
            payload, tag = split_frame(line)
        except FrameError:
            return None
        if not printable(line):
            self.em.last_error = 2
            return frame(f"ERR 2 {ERRORS[2]} (a byte outside printable ASCII)", tag)
        return frame(self.handle(payload), tag) if payload.strip(" \t") else None

    def overlong(self) -> str:
        """The framed reply to a line over :data:`~afmctl.drivers.ascii_protocol.MAX_LINE` bytes (its tag
        cannot be trusted: untagged); error 2 becomes the last error."""
        self.em.last_error = 2
        return frame(f"ERR 2 {ERRORS[2]} (line over {MAX_LINE} bytes)", None)

    def handle(self, line: str) -> str:
        """One command (without terminator or framing) -> one reply (without either)."""
        words = line.strip().split()
        now = self.clock()
        try:
            if not words or words[0].upper() not in self._commands:
                raise DeviceError(1, words[0] if words else "empty line")
            return self._commands[words[0].upper()](words[1:], now)
        except DeviceError as exc:
            self.em.last_error = exc.code
            return f"ERR {exc.code} {ERRORS[exc.code]}"

    @staticmethod
    def _ok(_: None) -> str:
        return "OK"

    @staticmethod
    def _bare(args: list[str], action: Callable[[], None]) -> str:
        """A set command without arguments (error 2 if given any, before it acts)."""
        if args:
            raise DeviceError(2, "takes no arguments")
        action()
        return "OK"

    @staticmethod
    def _noargs(args: list[str], reply: str) -> str:
        if args:
            raise DeviceError(2, "query takes no arguments")
        return reply

    def _wav(self, args: list[str], now: float) -> str:
        first, n = _int(args, 0, None), _int(args, 1, None)
        if not 1 <= n <= MAX_CHUNK or len(args) != 2 + n:
            raise DeviceError(2, f"WAV <first> <n <= {MAX_CHUNK}> then n values")
        self.em.write_table(first, np.array([_float(args, i) for i in range(2, 2 + n)]), now)
        return "OK"

    def _wgo(self, args: list[str], now: float) -> str:
        cycles = _int(args, 0, 1)
        if cycles == 0:
            self.em.stop(now)
        else:
            self.em.start(cycles, now)
        return "OK"

    def _drr(self, args: list[str], now: float) -> str:
        first, n = _int(args, 0, 2), _int(args, 1, 2)
        if not 1 <= n <= MAX_CHUNK:
            raise DeviceError(2, f"DRR? <first> <n <= {MAX_CHUNK}>")
        u, v = self.em.read_recorder(first, n, now)
        return f"{first} {n} " + " ".join(f"{fmt(a)} {fmt(b)}" for a, b in zip(u, v, strict=True))


def _arg(args: list[str], i: int, count: int | None) -> str:
    if count is not None and len(args) != count:
        raise DeviceError(2, f"expected {count} argument(s), got {len(args)}")
    if i >= len(args):
        raise DeviceError(2, "missing argument")
    return args[i]


def _float(args: list[str], i: int, count: int | None = None) -> float:
    """Argument ``i`` as a float rounded to float32 (§3.3(a)); error 2 if it is not one."""
    value = parse_float32(_arg(args, i, count))
    if value is None:
        raise DeviceError(2, f"not a number: {args[i]!r}")
    return value


def _int(args: list[str], i: int, count: int | None) -> int:
    """Argument ``i`` as an integer of any size (§3.3(b)); error 2 if it is not one."""
    value = parse_int(_arg(args, i, count))
    if value is None:
        raise DeviceError(2, f"not an integer: {args[i]!r}")
    return value
