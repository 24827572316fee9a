"""The serial (ASCII) protocol, version 3: codec and the device-side interpreter. No I/O.

Lines are ASCII, terminated by LF (a trailing CR is ignored). Version 3 frames every line: the host
ends a command with `` #<tag> *<crc>`` and the device ends its reply with the same tag and its own
CRC (:func:`frame`, :func:`unframe`; CRC-32 of everything before `` *``, 8 hex digits). The device
discards a command whose CRC is wrong (unanswered: the host times out and retries); the host
discards a reply whose CRC is wrong or whose tag is not the one it is waiting for (a corrupted
line, line noise, or a late reply to an earlier request). Commands without a CRC (typed by hand)
are still accepted. Every command line gets exactly one reply line: ``OK`` for a set command, the
value(s) for a query, or ``ERR <code> <text>`` when the device refuses (codes in
:data:`afmctl.drivers.protocol.ERRORS`; the last one also stays readable with ``ERR?``). Numbers are
decimal; float32 values are written with 9 significant digits, which round-trips float32 exactly; a
sample not yet recorded (or overwritten) is ``nan``. Version 2 adds streaming: ``WGS <n>`` plays
``n`` samples through the table as a ring while the host keeps writing ``WAV`` blocks at global
indices; ``DRR?`` and ``POS?`` use global indices. See ``docs/reference/protocol.md``.
"""

from __future__ import annotations

import re
import zlib
from fractions import Fraction

import numpy as np
from numpy.typing import NDArray

from afmctl.drivers.protocol import Status
from afmctl.errors import FrameError

PROTOCOL_VERSION = 3
#: The serial protocol of devices with several channels (``CH <c> <command>``, ``CHN?``).
CHANNELS_VERSION = 4
#: The versions a host speaks (docs/reference/protocol.md §7: the one the device reports).
PROTOCOL_VERSIONS = (PROTOCOL_VERSION, CHANNELS_VERSION)
#: Commands that act on one channel: ``CH <c> <command>`` applies one to channel ``c``; without
#: the prefix they act on channel 0 (§2.14, §3.6).
CHANNEL_COMMANDS = ("SVA", "VOL?", "WAV", "DRR?", "LIM?")
MAX_LINE = 8192
#: Largest chunk per WAV or DRR? line, samples.
MAX_CHUNK = 256
#: Bytes per sample on the wire for a full ``WAV`` line of volts (9 significant digits, e.g.
#: ``-149.999985``, and a space; the line's own framing spread over its samples).
UPLOAD_BYTES_PER_SAMPLE = 12.5
#: Bytes per sample of a full ``DRR?`` reply (a sensor value and a voltage, each with a space).
READBACK_BYTES_PER_SAMPLE = 24.5

STATUS_KEYS = ("running", "fill", "error", "out", "runs", "len", "complete", "wd", "expired", "ro",
               "rate", "pos", "total", "wdt")


#: A float argument (docs/reference/protocol.md §3.3(a)) and an integer argument (§3.3(b)), ASCII digits.
FLOAT_SYNTAX = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
INT_SYNTAX = re.compile(r"[+-]?[0-9]+")
_CRC_DIGITS = re.compile(r"[0-9a-fA-F]{8}")
_TAG = re.compile(r"#[0-9]{1,9}")
#: Bytes a line may hold (§3.1(c)): printable ASCII and TAB.
_PRINTABLE = re.compile(r"[\x20-\x7e\t]*")


def crc(text: str) -> str:
    """CRC-32 of ``text`` (its bytes: each character one byte, as received), 8 lower-case hex
    digits."""
    return f"{zlib.crc32(text.encode('latin-1', errors='replace')):08x}"


def frame(payload: str, tag: int | str | None) -> str:
    """``payload [#tag] *crc`` (no terminator); a tag given as text is written as it is."""
    body = payload if tag is None else f"{payload} #{tag}"
    return f"{body} *{crc(body)}"


def split_frame(line: str) -> tuple[str, str | None]:
    """The device's reading of a received line (its CR LF taken off; one character per byte):
    ``(payload, tag as received or None)``, by §3.2(a), (b). FrameError if it carries a CRC that
    is wrong. The payload may still hold bytes §3.1(c) refuses (:func:`printable`)."""
    body = line
    if len(line) >= 10 and line[-10:-8] == " *" and _CRC_DIGITS.fullmatch(line[-8:]):
        body = line[:-10]
        if crc(body) != line[-8:].lower():
            raise FrameError(f"CRC mismatch: {line[:40]!r}")
    words = body.rstrip(" \t")
    cut = max(words.rfind(" "), words.rfind("\t"))
    if _TAG.fullmatch(words[cut + 1:]):
        return words[:cut + 1], words[cut + 2:]
    return body, None


def printable(text: str) -> bool:
    """Whether ``text`` holds only printable ASCII and TAB (§3.1(c))."""
    return _PRINTABLE.fullmatch(text) is not None


def parse_float32(text: str) -> float | None:
    """A float argument (§3.3(a)) rounded to the nearest float32, ties to even, as C's ``strtof``
    (±inf beyond float32); None if ``text`` is not one."""
    if not FLOAT_SYNTAX.fullmatch(text):
        return None
    d = float(text)
    with np.errstate(over="ignore"):
        f = np.float32(d)
        if float(f) == d or not np.isfinite(f):
            return float(f)
        other = np.nextafter(f, np.float32(np.inf) if d > float(f) else np.float32(-np.inf))
    if (float(f) + float(other)) / 2 != d:  # not on a midpoint: one rounding is exact enough
        return float(f)
    exact = Fraction(text)  # the decimal sits within a double of a float32 midpoint: decide exactly
    mid = (Fraction(float(f)) + Fraction(float(other))) / 2
    if exact == mid:
        even = f if int(f.view(np.uint32)) % 2 == 0 else other
        return float(even)
    return float(other if (exact > mid) == (float(other) > float(f)) else f)


def parse_int(text: str) -> int | None:
    """An integer argument (§3.3(b)), any number of digits; None if ``text`` is not one."""
    return int(text) if INT_SYNTAX.fullmatch(text) else None


def unframe(line: str, required: bool = True) -> tuple[str, int | None]:
    """Inverse of :func:`frame`: (payload, tag or None); FrameError if the CRC is wrong, or
    missing when ``required``."""
    body, sep, check = line.rpartition(" *")
    if not sep or len(check) != 8:
        if required:
            raise FrameError(f"no CRC: {line[:40]!r}")
        body = line
    elif crc(body) != check.lower():  # hex digits in either case (docs/reference/protocol.md §3.2(a))
        raise FrameError(f"CRC mismatch: {line[:40]!r}")
    payload, sep, tag = body.rpartition(" #")
    if sep and tag.isdigit():
        return payload, int(tag)
    return body, None


def fmt(x: float) -> str:
    """A float32-exact decimal (``nan`` for NaN)."""
    return "nan" if x != x else f"{float(np.float32(x)):.9g}"


def status_line(s: Status) -> str:
    vals = (int(s.running), s.recorder_fill, s.last_error, fmt(s.output_v), s.run_count,
            s.table_length, int(s.table_complete), int(s.watchdog_armed),
            int(s.watchdog_expired), int(s.read_only), fmt(s.sample_rate_hz), s.play_position,
            s.run_samples, fmt(s.watchdog_s))
    return " ".join(f"{k}={v}" for k, v in zip(STATUS_KEYS, vals, strict=True))


def parse_status(line: str) -> Status:
    """Inverse of :func:`status_line`; ValueError if a key is missing."""
    kv = dict(item.split("=", 1) for item in line.split())
    missing = [k for k in STATUS_KEYS if k not in kv]
    if missing:
        raise ValueError(f"status reply lacks {', '.join(missing)}: {line!r}")
    return Status(running=kv["running"] == "1", recorder_fill=int(kv["fill"]),
                  last_error=int(kv["error"]), output_v=float(kv["out"]),
                  run_count=int(kv["runs"]), table_length=int(kv["len"]),
                  table_complete=kv["complete"] == "1", watchdog_armed=kv["wd"] == "1",
                  watchdog_expired=kv["expired"] == "1", read_only=kv["ro"] == "1",
                  sample_rate_hz=float(kv["rate"]), play_position=int(kv["pos"]),
                  run_samples=int(kv["total"]), watchdog_s=float(kv["wdt"]))


def wav_line(first: int, values: NDArray[np.float32]) -> str:
    return f"WAV {first} {len(values)} " + " ".join(fmt(v) for v in values)


def parse_recorder(reply: str, first: int, n: int) -> tuple[NDArray[np.float32],
                                                           NDArray[np.float32]]:
    """``DRR?`` reply ``<first> <n> u0 v0 u1 v1 ...`` -> (raw sensor, voltage), float32."""
    parts = reply.split()
    if len(parts) != 2 + 2 * n or int(parts[0]) != first or int(parts[1]) != n:
        raise ValueError(f"DRR? reply does not hold samples {first}+{n}: {reply[:60]!r}...")
    data = np.array(parts[2:], dtype=np.float32).reshape(n, 2)
    return data[:, 0].copy(), data[:, 1].copy()
