"""The device's interpreter of the serial (ASCII) protocol: command lines -> an
:class:`~afmctl.drivers.device.emulator.Emulator` -> framed reply lines. No I/O (the servers in
:mod:`afmctl.drivers.device.serial_server` move the bytes). Codec: :mod:`afmctl.drivers.ascii_protocol`."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from afmctl.drivers.ascii_protocol import (
    CHANNEL_COMMANDS,
    CHANNELS_VERSION,
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
from afmctl.drivers.device.emulator import IDENTITY, IDENTITY_CHANNELS, Emulator
from afmctl.drivers.protocol import ERRORS
from afmctl.errors import DeviceError, FrameError
from afmctl.files.profile import Limits


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
        several = emulator.channels > 1
        version = CHANNELS_VERSION if several else PROTOCOL_VERSION
        self._per_channel: dict[str, Callable[[list[str], float, int], str]] = {
            "SVA": lambda a, t, c: self._ok(self.em.set_voltage(_float(a, 0, 1), t, c)),
            "VOL?": lambda a, t, c: self._query(a, lambda: fmt(self.em.output(t, c))),
            "WAV": self._wav,
            "DRR?": self._drr,
            "LIM?": lambda a, t, c: self._query(a, lambda: " ".join(fmt(x) for x in _limits(
                self.em.channel_limits_of(c)))),
        }
        assert set(self._per_channel) == set(CHANNEL_COMMANDS)
        self._commands: dict[str, Callable[[list[str], float], str]] = {
            "*IDN?": lambda a, t: self._noargs(a, IDENTITY_CHANNELS if several else IDENTITY),
            "VER?": lambda a, t: self._noargs(a, str(version)),
            "WTR": lambda a, t: self._ok(self.em.set_sample_rate(_float(a, 0, 1), t)),
            "WTR?": lambda a, t: self._noargs(a, fmt(self.em.status(t).sample_rate_hz)),
            "WTL": lambda a, t: self._ok(self.em.set_table_length(_int(a, 0, 1), t)),
            "WTL?": lambda a, t: self._noargs(a, str(self.em.status(t).table_length)),
            "WGO": self._wgo,
            "WGS": lambda a, t: self._ok(self.em.start_stream(_int(a, 0, 1), t)),
            "POS?": lambda a, t: self._noargs(a, str(self.em.status(t).play_position)),
            "CAP?": lambda a, t: self._noargs(a, f"{self.em.tables.shape[1]} "
                                                 f"{self.em.rec_global.size}"),
            "DRL?": lambda a, t: self._noargs(a, str(self.em.status(t).recorder_fill)),
            "STA?": lambda a, t: self._noargs(a, status_line(self.em.status(t))),
            "ERR?": lambda a, t: self._noargs(a, str(self.em.pop_error(t))),
            "SAFE": lambda a, t: self._bare(a, lambda: self.em.safe_state(t)),
            "HB": lambda a, t: self._bare(a, lambda: self.em.heartbeat(t)),
            "WDT": lambda a, t: self._ok(self.em.set_watchdog(_float(a, 0, 1), t)),
        }
        for word, handler in self._per_channel.items():
            self._commands[word] = lambda a, t, h=handler: h(a, t, 0)  # type: ignore[misc]
        if several:
            self._commands["CHN?"] = lambda a, t: self._noargs(a, str(self.em.channels))
            self._commands["CH"] = self._ch

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

    @staticmethod
    def _query(args: list[str], reply: Callable[[], str]) -> str:
        """A query of one channel: its arguments are checked (error 2) before the channel (6)."""
        if args:
            raise DeviceError(2, "query takes no arguments")
        return reply()

    def _ch(self, args: list[str], now: float) -> str:
        """``CH <c> <command> <arguments>``: a per-channel command applied to channel ``c``
        (§3.6): 2 without a channel that is an integer or without a command, 1 for an unknown
        command word, 2 for a command that is not per-channel; the channel's range (6) is the
        command's to check, after its arguments."""
        channel = _int(args, 0, None)
        if len(args) < 2:
            raise DeviceError(2, "CH <channel> <command> [arguments]")
        word = args[1].upper()
        if word not in self._commands:
            raise DeviceError(1, args[1])
        if word not in self._per_channel:
            raise DeviceError(2, f"{args[1]} is not a per-channel command")
        return self._per_channel[word](args[2:], now, channel)

    def _wav(self, args: list[str], now: float, channel: int) -> str:
        first, n = _int(args, 0, None), _int(args, 1, None)
        if not 1 <= n <= MAX_CHUNK or len(args) != 2 + n:
            raise DeviceError(2, f"WAV <first> <n <= {MAX_CHUNK}> then n values")
        self.em.write_table(first, np.array([_float(args, i) for i in range(2, 2 + n)]), now,
                            channel)
        return "OK"

    def _wgo(self, args: list[str], now: float) -> str:
        cycles = _int(args, 0, 1)
        if cycles == 0:
            self.em.stop(now)
        else:
            self.em.start(cycles, now)
        return "OK"

    def _drr(self, args: list[str], now: float, channel: int) -> str:
        first, n = _int(args, 0, 2), _int(args, 1, 2)
        if not 1 <= n <= MAX_CHUNK:
            raise DeviceError(2, f"DRR? <first> <n <= {MAX_CHUNK}>")
        u, v = self.em.read_recorder(first, n, now, channel)
        return f"{first} {n} " + " ".join(f"{fmt(a)} {fmt(b)}" for a, b in zip(u, v, strict=True))


def _limits(lim: Limits) -> tuple[float, float, float]:
    return lim.v_min, lim.v_max, lim.slew_v_per_ms


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
