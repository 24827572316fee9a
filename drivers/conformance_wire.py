"""Conformance checks of the encodings (docs/reference/protocol.md §3 serial, §4 Modbus) and of the reply
latency (§5(e)).

The edge-case tables (§3.5, §4.3; :mod:`~afmctl.drivers.conformance_rows`) are executed from the
document's own cells: each row starts from the state P (idle at 0 V, 1000 Hz, a complete table of
four 0 V samples, watchdog off, no error), sends its lines or requests and compares the reply to
the last one. On the serial protocol every row is followed by a marker request, whose reply must
come next: a line answered twice, or answered when it must not be, is caught (§3.1(e)).
"""

from __future__ import annotations

import re
import statistics
import time
from collections.abc import Callable

import numpy as np

from afmctl.drivers import ascii_protocol as ap
from afmctl.drivers import register_map as rm
from afmctl.drivers.conformance import (
    SLOW_RATE_HZ,
    Bench,
    Failure,
    HostLate,
    NotApplicable,
    clear_error,
    code_of,
    expect,
    stamped,
)
from afmctl.drivers.conformance_rows import MODBUS_ROWS, SERIAL_ROWS, Row
from afmctl.drivers.modbus_link import ModbusStage
from afmctl.drivers.serial_link import SerialStage
from afmctl.errors import StageError

_SPAN = re.compile(r"`([^`]*)`")
_ESCAPE = re.compile(r"\\t|\\r|\\x([0-9a-fA-F]{2})")
_MARKER = 99_000


def spans(cell: str) -> list[str]:
    """The code spans of a table cell (an empty span counts)."""
    return _SPAN.findall(cell)


def state_p(bench: Bench) -> None:
    """The state P of §3.5: idle at 0 V, 1000 Hz, a complete table of four 0 V samples, watchdog
    off, last error 0 (on a read-only device: what it allows)."""
    stage = bench.stage
    code_of(stage.safe_state)  # a device that refuses it fails §2.10(b) or §2.7, not here
    stage.set_watchdog(0.0)
    if isinstance(stage, ModbusStage) and stage.version >= rm.CHANNELS_MAP_VERSION:
        stage.select_channel(0)  # a row may have selected another (§4.4(b))
    if not stage.status().read_only:
        stage.set_sample_rate(SLOW_RATE_HZ)
        stage._set_table_length(4)
        stage._write_chunk(0, np.zeros(4, np.float32))
    clear_error(stage)


def _rows(rows: tuple[Row, ...], read_only: bool, clause: str | None
          ) -> list[tuple[str, list[str], str, str]]:
    """``(row, sent cells, expected reply, label)`` of the rows ``clause`` runs on this device
    (``None``: every row of the table)."""
    out = []
    for row, sent, reply, ro_reply, label in rows:
        want = ro_reply if read_only else reply
        if clause in (None, row_clause(label, rows is SERIAL_ROWS)) and want != "—":
            out.append((row, spans(sent) if "`" in sent else [sent], want, label))
    return out


# -- §3 serial -----------------------------------------------------------------------------------
def _serial(bench: Bench) -> SerialStage:
    if not isinstance(bench.stage, SerialStage):
        raise NotApplicable("not the serial protocol")
    return bench.stage


def line_bytes(text: str) -> bytes:
    """A line of §3.5's notation as the bytes sent (without its LF)."""
    long = re.fullmatch(r"<(\d+) x>(.*)", text)
    if long:
        text = "x" * int(long.group(1)) + long.group(2)
    line = _ESCAPE.sub(lambda m: {"\\t": "\t", "\\r": "\r"}.get(m.group(0))
                       or chr(int(m.group(1), 16)), text)
    for mark in ("<crc>", "<CRC>", "<bad>"):
        if line.endswith(" *" + mark):
            body = line[:-len(mark) - 2]
            c = ap.crc(body)
            c = {"<crc>": c, "<CRC>": c.upper(), "<bad>": c[:-1] + ("0" if c[-1] != "0" else "1")}[
                mark]
            line = f"{body} *{c}"
    return line.encode("latin-1")


def send_raw(stage: SerialStage, data: bytes) -> None:
    stage._buf.clear()
    stage._port.write(data)


def read_reply(stage: SerialStage, what: str, label: str = "§3.1(e)") -> tuple[str, str | None]:
    """The next reply line: ``(payload, tag as sent or None)``; its CRC must be right and in lower
    case (§3.2(d)). No reply within the timeout fails ``label``."""
    try:
        line = stage._readline(time.monotonic() + stage.timeout_s)
    except StageError:
        raise Failure(label, f"{what}: no reply within {stage.timeout_s:g} s") from None
    body, sep, check = line.rpartition(" *")
    expect(bool(sep) and re.fullmatch(r"[0-9a-f]{8}", check) is not None and ap.crc(body) == check,
           "§3.2(d)", f"{what}: the reply {line[:60]!r} does not end in its own lower-case CRC")
    tag = re.fullmatch(r"(.*) #([0-9]{1,9})", body)
    return (tag.group(1), tag.group(2)) if tag else (body, None)


def same_numbers(got: str, want: str) -> bool:
    """Words equal, numbers compared as float32 (``nan`` equals ``nan``, ``0`` equals ``-0``)."""
    a, b = got.split(), want.split()
    if len(a) != len(b):
        return False
    for x, y in zip(a, b, strict=True):
        try:
            fx, fy = np.float32(float(x)), np.float32(float(y))
        except ValueError:
            if x != y:
                return False
            continue
        if not (fx == fy or (np.isnan(fx) and np.isnan(fy))):
            return False
    return True


def reply_matches(payload: str, tag: str | None, want: str) -> bool:
    """Whether a reply is the one a §3.5 reply cell shows."""
    shown = re.fullmatch(r"(.*?)(?: #([0-9]{1,9}))?", spans(want)[0])
    assert shown is not None
    want_payload, want_tag = shown.group(1), shown.group(2)
    if tag != want_tag:
        return False
    if want_payload.startswith("ERR "):
        words = payload.split()
        return words[:2] == want_payload.split()
    if "=" in want_payload:
        key, value = want_payload.split("=")
        fields = dict(w.split("=", 1) for w in payload.split() if "=" in w)
        return key in fields and same_numbers(fields[key], value)
    return same_numbers(payload, want_payload)


def run_serial_row(stage: SerialStage, row: str, lines: list[str], want: str, label: str) -> None:
    """Send a row's lines, compare the reply to the last, then check that nothing else comes
    before the reply to a marker line."""
    for i, text in enumerate(lines):
        send_raw(stage, line_bytes(text) + b"\n")
        if i < len(lines) - 1 and not text.endswith("*<bad>"):  # a wrong CRC gets no reply
            read_reply(stage, f"row {row}, line {text!r}")
    what = f"row {row} ({' '.join(lines)})"
    want = want.replace("<ver>", str(stage.version))  # the version the device reported (§3.6(a))
    if want != "no reply":
        payload, tag = read_reply(stage, what, label)
        expect(not payload.startswith("ERR") or re.fullmatch(r"ERR [0-9]+( .*)?", payload)
               is not None, "§3.3(e)", f"{what}: the error reply {payload[:40]!r} is not "
                                       "ERR <code> [text]")
        expect(reply_matches(payload, tag, want), label,
               f"{what} answered {payload[:40]!r}" + (f" #{tag}" if tag else "") +
               f", the document says {want}")
    send_raw(stage, ap.frame("VER?", _MARKER).encode() + b"\n")
    payload, tag = read_reply(stage, f"{what}, then a marker")
    expect(tag == str(_MARKER), label if want == "no reply" else "§3.1(e)",
           f"{what}: a reply {payload[:40]!r} came where " +
           ("none is due" if want == "no reply" else "only the marker's was due"))


def failed_rows(failures: list[Failure]) -> Failure:
    """One failure naming every requirement the failed rows hold the device to."""
    labels = ", ".join(dict.fromkeys(f.label for f in failures))
    shown = "; ".join(str(f) for f in failures[:4])
    more = f" (and {len(failures) - 4} more rows)" if len(failures) > 4 else ""
    return Failure(labels, f"{len(failures)} rows fail: {shown}{more}")


def run_rows(bench: Bench, table: tuple[Row, ...], clause: str | None,
             run_row: Callable[[str, list[str], str, str], None]) -> int:
    """Every row of ``table`` that ``clause`` runs, each from the state P; one failure naming
    all the rows that fail. The number of rows run."""
    rows = _rows(table, bench.stage.status().read_only, clause)
    failures = []
    for row, sent, want, label in rows:
        state_p(bench)
        try:
            run_row(row, sent, want, label)
        except Failure as exc:
            failures.append(exc)
    state_p(bench)
    if failures:
        raise failed_rows(failures)
    return len(rows)


def serial_rows(bench: Bench, clause: str | None, table: tuple[Row, ...] = SERIAL_ROWS) -> int:
    """The rows of ``table`` that ``clause`` runs (None: all) on the serial protocol."""
    stage = _serial(bench)

    def run_row(row: str, lines: list[str], want: str, label: str) -> None:
        try:
            run_serial_row(stage, row, lines, want, label)
        except Failure:
            time.sleep(0.05)  # let stray replies arrive, then forget them
            stage._buf.clear()
            stage._port.reset_input_buffer()
            raise
    return run_rows(bench, table, clause, run_row)


def row_clause(label: str, serial: bool) -> str:
    """The clause (a row of :data:`CLAUSES`) that runs an edge-case row holding a device to
    ``label``: its own section for §3.1-§3.4, §4 (with §4.2) and §4.1, else §3.5 (serial rows)
    or §4.3 (Modbus rows)."""
    section = label.partition("(")[0]
    if section in (("§3.1", "§3.2", "§3.3", "§3.4") if serial else ("§4", "§4.1")):
        return section
    return "§4" if section == "§4.2" else ("§3.5" if serial else "§4.3")


def check_lines(bench: Bench) -> str:
    """§3.1: line ends, over-long lines, bytes, separators, empty lines (rows of §3.5)."""
    return f"{serial_rows(bench, '§3.1')} rows of §3.5 as documented"


def check_framing(bench: Bench) -> str:
    """§3.2: CRC, tags, wrong CRCs, the reply's tag and CRC (rows of §3.5)."""
    return f"{serial_rows(bench, '§3.2')} rows of §3.5 as documented"


def check_numbers(bench: Bench) -> str:
    """§3.3: the number grammar, float32 rounding, -0 (rows of §3.5)."""
    return f"{serial_rows(bench, '§3.3')} rows of §3.5 as documented"


def check_serial_edges(bench: Bench) -> str:
    """§3.5: the rows that hold §2's rules on the serial protocol (precedence, codes, flags)."""
    return f"{serial_rows(bench, '§3.5')} rows of §3.5 as documented"


def check_commands(bench: Bench) -> str:
    """§3.4: VER? is 3, *IDN? four printable fields, STA? its 14 fields in order; word case,
    argument counts (rows of §3.5)."""
    stage = _serial(bench)
    version = stage.query("VER?")
    expect(version in [str(v) for v in ap.PROTOCOL_VERSIONS], "§3.4(b)",
           f"VER? answers {version!r}")
    idn = stage.identify()
    fields = idn.split(",")
    expect(len(fields) == 4 and all(f and ap.printable(f) and "\t" not in f for f in fields),
           "§3.4(b)", f"*IDN? {idn!r} is not four non-empty fields maker,model,serial,firmware")
    lim = stage.query("LIM?").split()
    expect(len(lim) == 3 and all(ap.parse_float32(x) == float(x) for x in lim), "§3.3(d)",
           f"LIM? {' '.join(lim)!r}: not three floats that are float32 values")
    sta = stage.query("STA?")
    words = sta.split(" ")
    keys = [w.split("=", 1)[0] for w in words]
    expect(keys == list(ap.STATUS_KEYS) and all("=" in w for w in words), "§3.4(a)",
           f"STA? {sta!r}: not the 14 fields {' '.join(ap.STATUS_KEYS)} in order, single spaces")
    kv = dict(w.split("=", 1) for w in words)
    flags = ("running", "complete", "wd", "expired", "ro")
    ints = ("fill", "error", "runs", "len", "pos", "total")
    expect(all(kv[k] in ("0", "1") for k in flags)
           and all(re.fullmatch(r"[0-9]+", kv[k]) for k in ints)
           and all(ap.parse_float32(kv[k]) is not None for k in ("out", "rate", "wdt")),
           "§3.4(a)", f"STA? {sta!r}: a field of the wrong type")
    n = serial_rows(bench, "§3.4")
    return f"{idn}; STA? fields in order; {n} rows of §3.5 as documented"


# -- §4 Modbus -----------------------------------------------------------------------------------
def _modbus(bench: Bench) -> ModbusStage:
    if not isinstance(bench.stage, ModbusStage):
        raise NotApplicable("not Modbus")
    return bench.stage


def _registers(items: str) -> list[int]:
    """``1, u32 0, f32 nan`` -> registers."""
    regs: list[int] = []
    for item in (x.strip() for x in items.split(",")):
        kind, _, value = item.partition(" ")
        if kind == "f32":
            regs += rm.f32_regs([float(value)])
        elif kind == "u32":
            regs += rm.u32_regs(int(value, 0))
        else:
            regs.append(int(item, 0))
    return regs


def modbus_request(stage: ModbusStage, text: str) -> object:
    """One request of §4.3's notation (``FC16 5 = [f32 nan]``, ``FC4 0x1001 ×2``); the reply."""
    write = re.fullmatch(r"FC(6|16) (\S+) = (.+)", text)
    if write:
        fc, address, value = write.groups()
        if fc == "6":
            return stage._call("write_register", int(address, 0), int(value, 0))
        return stage._call("write_registers", int(address, 0), _registers(value.strip("[]")))
    read = re.fullmatch(r"FC(3|4) (\S+) ×(\d+)", text)
    assert read is not None, text
    name = "read_holding_registers" if read.group(1) == "3" else "read_input_registers"
    return stage._call(name, int(read.group(2), 0), count=int(read.group(3)))


def modbus_matches(stage: ModbusStage, res: object, want: str) -> bool:
    """Whether a reply is the one a §4.3 reply cell shows."""
    exc = re.fullmatch(r"exception (\d+)(?:, error (\d+))?", want)
    if exc:
        if not (res.isError() and getattr(res, "exception_code", None) == int(exc.group(1))):  # type: ignore[attr-defined]
            return False
        return exc.group(2) is None or stage.status().last_error == int(exc.group(2))
    if res.isError():  # type: ignore[attr-defined]
        return False
    regs = list(res.registers)  # type: ignore[attr-defined]
    if want.startswith("echo "):
        return regs[:1] == _registers(spans(want)[0])
    if want in ("bit 2 clear", "bit 2 set"):
        return bool(regs[0] & rm.StatusBit.TABLE_COMPLETE) == (want == "bit 2 set")
    shown = spans(want)[0]
    if shown.startswith("f32 "):
        return bool(rm.regs_f32(regs)[0] == np.float32(float(shown[4:])))
    return regs == _registers(shown)


def modbus_rows(bench: Bench, clause: str | None, table: tuple[Row, ...] = MODBUS_ROWS) -> int:
    """The rows of ``table`` that ``clause`` runs (None: all) on Modbus."""
    stage = _modbus(bench)

    def run_row(row: str, requests: list[str], want: str, label: str) -> None:
        res = None
        for text in requests:
            res = modbus_request(stage, text)
        expect(modbus_matches(stage, res, want), label,
               f"row {row} ({' then '.join(requests)}) answered {res}, the document says {want}")
    return run_rows(bench, table, clause, run_row)


def check_fc6_echo(bench: Bench) -> str:
    """§4.1: FC6 is answered with the value written (rows of §4.3)."""
    return f"{modbus_rows(bench, '§4.1')} rows of §4.3 as documented"


def check_registers(bench: Bench) -> str:
    """§4: whole fields, reads within the map, exceptions and IR 2, multi-field writes (rows of
    §4.3)."""
    return f"{modbus_rows(bench, '§4')} rows of §4.3 as documented"


def check_modbus_edges(bench: Bench) -> str:
    """§4.3: the rows that hold §2's and §3.3's rules on Modbus."""
    n = modbus_rows(bench, "§4.3")
    return f"{n} rows of §4.3 as documented"


# -- §5(e) reply latency ---------------------------------------------------------------------------
ROUND_TRIPS = 20


def check_latency(bench: Bench) -> str:
    """§5(e): the shortest of 20 round trips, less the bytes' time on a UART, is within 10 ms; if
    not, the host's own 1 ms sleeps tell whether it kept its clock."""
    stage = bench.stage
    if isinstance(stage, SerialStage):
        def query() -> object:
            return stage.query("VER?")
        wire_bytes, baud = 40, stage.baudrate
    elif isinstance(stage, ModbusStage):
        def query() -> object:
            return stage._request("read_input_registers", rm.IR.MAP_VERSION, count=1)
        wire_bytes, baud = 22, getattr(stage._transport, "baudrate", 0)
    else:
        raise NotApplicable("no wire")
    wire_s = wire_bytes * 10 / baud if stage.uart_rates() is not None and baud else 0.0
    trips, late = [], []
    for _ in range(ROUND_TRIPS):
        t = time.monotonic()
        time.sleep(0.001)
        late.append(time.monotonic() - t - 0.001)
        _, s = stamped(query)
        trips.append(s.done - s.sent)
    best = min(trips) - wire_s
    if best > 0.010:
        if statistics.median(late) > 0.001:
            raise HostLate(f"shortest round trip {best * 1e3:.1f} ms while the host's 1 ms sleeps "
                           f"overslept by {statistics.median(late) * 1e3:.1f} ms")
        raise Failure("§5(e)", f"the shortest of {ROUND_TRIPS} round trips took {best * 1e3:.1f} ms "
                               f"beyond the bytes' time: more than 10 ms")
    return (f"round trips {min(trips) * 1e3:.2f} ms shortest, {statistics.median(trips) * 1e3:.2f}"
            f" ms median" + (f" ({wire_s * 1e3:.1f} ms of it the UART's bytes)" if wire_s else ""))


#: (clause, title, check, changes the output or table) in the document's order.
CLAUSES: tuple[tuple[str, str, Callable[[Bench], str], bool], ...] = (
    ("§3.1", "lines: ends, bytes, separators", check_lines, False),
    ("§3.2", "framing: CRC and tags", check_framing, False),
    ("§3.3", "numbers", check_numbers, False),
    ("§3.4", "commands, identity, status line", check_commands, False),
    ("§3.5", "edge cases of §2 (serial)", check_serial_edges, False),
    ("§4", "register fields and exceptions", check_registers, False),
    ("§4.1", "FC6 echo", check_fc6_echo, False),
    ("§4.3", "edge cases of §2 (Modbus)", check_modbus_edges, False),
    ("§5(e)", "reply latency", check_latency, False),
)
