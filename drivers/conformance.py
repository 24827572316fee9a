"""The conformance check: exercise a device against ``docs/protocol.md``, clause by clause.

Any device, afmctl's emulated one or a lab's own, over the serial protocol (any pyserial URL) or
Modbus (TCP or RTU), reached through the host links of :mod:`drivers`. Each check drives the device
through its commands and compares what it answers with what the document says; the result is one
:class:`Result` per clause (passed, failed, or not applicable with the reason).

Motion is bounded: every voltage commanded lies within ``[lo, hi]``, at most ``max_voltage`` from
0 V and inside the device's limits, and every step within 90 % of the slew limit. Out-of-range
values are only sent where the device must refuse them (a NaN DC set; table samples that are never
played). The checks leave the device idle at 0 V, with its error cleared, its watchdog off and its
sample rate the profile's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, ExitStack, contextmanager
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from afmctl.drivers import ascii_protocol as ap
from afmctl.drivers import register_map as rm
from afmctl.drivers.modbus_link import ModbusStage
from afmctl.drivers.serial_link import SerialStage
from afmctl.drivers.stage import StageBase
from afmctl.errors import StageError
from afmctl.files.profile import ModbusRtuTransport, ModbusTcpTransport, Profile

#: Sample rate for the stream, busy and table checks, Hz (slow enough for any link to refill).
SLOW_RATE_HZ = 1000.0
#: Table length of the stream checks, samples.
STREAM_TABLE = 256


class Failure(Exception):
    """A clause the device does not meet (the message says how)."""


class NotApplicable(Exception):
    """A clause that does not apply to this device or wire (the message says why)."""


@dataclass(frozen=True)
class Result:
    """One clause: ``passed`` is True, False, or None (not applicable)."""

    clause: str
    title: str
    passed: bool | None
    detail: str


@dataclass
class Bench:
    """The device under test and the bounds of what may be commanded."""

    stage: StageBase
    profile: Profile
    lo: float
    hi: float

    @property
    def rate(self) -> float:
        return self.profile.sample_rate_hz

    def step(self, rate_hz: float | None = None) -> float:
        """The largest step the checks take at ``rate_hz``, V (90 % of the slew limit)."""
        return 0.9 * self.profile.limits.max_step_v(rate_hz or self.rate)

    def ramp(self, target_v: float, rate_hz: float | None = None) -> NDArray[np.float64]:
        """Samples from 0 V to ``target_v`` within the slew limit (``target_v`` excluded if 0)."""
        n = max(1, math.ceil(abs(target_v) / self.step(rate_hz)))
        return np.linspace(0.0, target_v, n + 1)[1:]


def expect(condition: bool, message: str) -> None:
    if not condition:
        raise Failure(message)


def code_of(action: Callable[[], object]) -> int:
    """The device's error code for ``action`` (0: accepted)."""
    try:
        action()
    except StageError as exc:
        return exc.code
    return 0


def expect_code(action: Callable[[], object], want: int, what: str) -> None:
    got = code_of(action)
    expect(got == want, f"{what}: error {got}, the document says {want}")


def clear_error(stage: StageBase) -> None:
    if isinstance(stage, SerialStage):
        stage.last_error()
    elif isinstance(stage, ModbusStage):
        stage.clear_error()


def to_zero(bench: Bench) -> None:
    """Safe state, error cleared, watchdog off, the profile's sample rate."""
    stage = bench.stage
    stage.safe_state()
    stage.set_watchdog(0.0)
    st = stage.status()
    if not st.read_only and not math.isclose(st.sample_rate_hz, bench.rate, rel_tol=1e-6):
        stage.set_sample_rate(bench.rate)
    clear_error(stage)


@contextmanager
def rate(bench: Bench, hz: float) -> Iterator[None]:
    """The device clocked at ``hz`` for the block, at the profile's rate after it."""
    bench.stage.set_sample_rate(hz)
    try:
        yield
    finally:
        bench.stage.safe_state()
        bench.stage.set_sample_rate(bench.rate)


def wait_idle(stage: StageBase, timeout_s: float) -> float:
    """Poll until the generator stops; the seconds it took. Failure after ``timeout_s``."""
    t0 = time.monotonic()
    while stage.status().running:
        expect(time.monotonic() - t0 < timeout_s, f"still running after {timeout_s:g} s")
        time.sleep(0.01)
    return time.monotonic() - t0


def write_blocks(stage: StageBase, first: int, v: NDArray[np.float64]) -> None:
    """Samples ``first ..`` in the link's largest blocks."""
    for off in range(0, v.size, stage.upload_chunk):
        stage._write_chunk(first + off, v[off:off + stage.upload_chunk].astype(np.float32))


def load(stage: StageBase, v: NDArray[np.float64]) -> None:
    """A new table holding ``v``."""
    stage._set_table_length(v.size)
    write_blocks(stage, 0, v)


# -- clauses of §1-§2 (every wire) ---------------------------------------------------------------
def check_power_on(bench: Bench) -> str:
    """§1, §2.6: the limits the device reports are the profile's; it idles at 0 V."""
    stage = bench.stage
    v_min, v_max, slew = stage.limits()
    lim = bench.profile.limits
    f32 = [float(np.float32(x)) for x in (lim.v_min, lim.v_max, lim.slew_v_per_ms)]
    expect([v_min, v_max, slew] == f32, f"limits {v_min:g}..{v_max:g} V, {slew:g} V/ms; the "
                                        f"profile says {f32[0]:g}..{f32[1]:g} V, {f32[2]:g} V/ms")
    st = stage.status()
    expect(not st.running and st.output_v == 0.0, "not idle at 0 V after the safe state")
    return f"limits {v_min:g}..{v_max:g} V, {slew:g} V/ms"


def check_dc_set(bench: Bench) -> str:
    """§2.5: a DC set is one slew-limited step, rounded to float32; NaN is out of range."""
    stage, step = bench.stage, bench.step()
    target = bench.hi if bench.hi > 0 else bench.lo
    v = math.copysign(min(abs(target), step), target) / 3
    stage.set_voltage(v)
    expect(np.float32(stage.voltage()) == np.float32(v),  # the text reply carries 9 digits
           f"a DC set of {v!r} V reads back {stage.voltage()!r} V")
    over = 1.2 * bench.profile.limits.max_step_v(bench.rate)  # a step that must be refused
    # within the bounds even on a device that would wrongly take it
    to = next((v + d * over for d in (1.0, -1.0) if bench.lo <= v + d * over <= bench.hi), None)
    if to is not None:
        expect_code(lambda: stage.set_voltage(to), 4, f"a DC step of 1.2 slew steps to {to:.4g} V")
    expect_code(lambda: stage.set_voltage(math.nan), 3, "a NaN DC set")
    expect(np.float32(stage.voltage()) == np.float32(v), "a refused DC set changed the output")
    stage.safe_state()
    slew = ("a 1.2-step set refused (4)" if to is not None else
            f"the slew refusal NOT checked: a 1.2-step set ({over:.3g} V) does not fit the bounds "
            f"[{bench.lo:g}, {bench.hi:g}] V (raise --max-voltage)")
    return f"DC set {v:.4g} V applied as float32; NaN refused (3); {slew}"


def check_limits(bench: Bench) -> str:
    """§2.6: the range is inclusive and compared on float32 (table samples, never played)."""
    stage = bench.stage
    v_max = float(np.float32(bench.profile.limits.v_max))
    stage._set_table_length(2)
    over = np.nextafter(np.float32(v_max), np.float32(np.inf))
    try:
        stage._write_chunk(1, np.array([v_max], dtype=np.float32))  # exactly the limit: accepted
        expect_code(lambda: stage._write_chunk(1, np.array([over], dtype=np.float32)), 3,
                    f"a table sample one float32 step above v_max ({over!r})")
    finally:  # overwrite the samples at the limit: a device that keeps stale slots plays 0 V
        clear_error(stage)
        load(stage, np.zeros(2))
        stage._set_table_length(1)
    return f"{v_max:g} V accepted, {float(over)!r} V refused"


def check_table(bench: Bench) -> str:
    """§2.1, §2.2, §2.3: an incomplete table does not start; a run plays N samples in N dt, then
    ``running`` drops, the position is N and the recorder holds N entries (NaN beyond)."""
    stage = bench.stage
    runs = stage.status().run_count
    stage._set_table_length(4)
    stage._write_chunk(0, np.zeros(2, dtype=np.float32))
    expect_code(lambda: stage._start(1), 9, "a start with 2 of 4 samples written")
    expect(stage.status().run_count == runs, "a refused start counted a run")
    up = bench.ramp(bench.hi if bench.hi > 0 else bench.lo)
    v = np.concatenate([up, up[::-1], [0.0]])
    v = np.concatenate([v, np.zeros(max(0, int(0.1 * bench.rate) - v.size))])
    load(stage, v)
    stage._start(1)
    took = wait_idle(stage, v.size / bench.rate + 2.0)
    st = stage.status()
    expect(st.play_position == v.size and st.run_samples == v.size,
           f"position {st.play_position}, run length {st.run_samples} after a {v.size}-sample run")
    expect(took >= 0.8 * v.size / bench.rate,
           f"a {v.size / bench.rate:.3g} s run ended in {took:.3g} s")
    expect(st.recorder_fill == v.size, f"recorder fill {st.recorder_fill}, not {v.size}")
    stage._last_run_samples = v.size
    rec = stage.read_recorder(v.size + 2)
    expect(bool(rec.valid[:v.size].all()), "recorder entries of played samples missing")
    expect(not rec.valid[v.size:].any(), "recorder entries beyond the run are not NaN")
    gap = float(np.max(np.abs(rec.voltage_v[:v.size] - v)))
    tol = 0.1 * max(abs(bench.hi), abs(bench.lo)) + 0.05
    expect(gap <= tol, f"recorded stack voltage off the command by {gap:.3g} V (> {tol:.3g} V)")
    return f"{v.size} samples in {took:.3g} s; recorder voltage within {gap:.3g} V of the command"


def _stream_wave(bench: Bench, n: int) -> NDArray[np.float64]:
    """``n`` samples: a slow triangle between 0 and the bound, at :data:`SLOW_RATE_HZ`."""
    top = bench.hi if bench.hi > 0 else bench.lo
    up = bench.ramp(top, SLOW_RATE_HZ)
    period = np.concatenate([up, up[::-1][1:], [0.0]])
    return np.resize(period, n)


def check_stream(bench: Bench) -> str:
    """§2.4: a stream through a small table plays N samples with refills; a block a table ahead
    is refused (6); stale slots refuse the next stream (9); an unfed stream underruns (10) and
    ramps to 0 V after exactly one table."""
    stage, L = bench.stage, STREAM_TABLE
    n = 4 * L
    v = _stream_wave(bench, n)
    with rate(bench, SLOW_RATE_HZ):
        load(stage, v[:L])
        stage._start_stream(n)
        ahead = n - L // 2
        expect_code(lambda: write_blocks(stage, ahead, v[ahead:ahead + 8]), 6,
                    "a block a table or more ahead of the play position")
        clear_error(stage)
        written = L
        while (st := stage.status()).running:
            if written < n and written + L // 2 <= st.play_position + L:
                write_blocks(stage, written, v[written:written + L // 2])
                written += L // 2
            time.sleep(0.005)
        expect(st.play_position == n and st.last_error == 0,
               f"the stream stopped at {st.play_position} of {n} with error {st.last_error}")
        expect_code(lambda: stage._start_stream(L), 9, "a stream started on stale slots")
        load(stage, v[:L])
        stage._start_stream(n)
        wait_idle(stage, n / SLOW_RATE_HZ + 2.0)
        st = stage.status()
        expect(st.play_position == L and st.last_error == 10 and st.output_v == 0.0,
               f"an unfed stream stopped at {st.play_position} (not {L}), error {st.last_error}, "
               f"output {st.output_v:g} V")
    clear_error(stage)
    return f"{n} samples through a {L}-sample table; 6, 9 and 10 as documented"


def check_safe_state(bench: Bench) -> str:
    """§2.7: SAFE stops and ramps to 0 V before it answers (the ramp is atomic)."""
    stage = bench.stage
    target = bench.hi if bench.hi > 0 else bench.lo
    for v in bench.ramp(target):
        stage.set_voltage(float(v))
    expect(abs(stage.voltage() - target) < 1e-3, f"DC ramp reached {stage.voltage():g} V")
    stage.safe_state()
    expect(stage.voltage() == 0.0, f"output {stage.voltage():g} V when SAFE answered")
    stage.safe_state()  # again, at 0 V: nothing to do
    return f"from {target:g} V to 0 V before the reply"


def check_watchdog(bench: Bench) -> str:
    """§2.8: WDT disarms, HB arms, queries do not feed it, it acts while idle within the period
    (+10 ms), sets error 8 and the expired flag, which the next WDT clears."""
    stage, period = bench.stage, 0.2
    stage.set_watchdog(period)
    expect(not stage.status().watchdog_armed, "armed by WDT alone")
    stage.set_voltage(bench.step() / 3 if bench.hi > 0 else -bench.step() / 3)
    stage.heartbeat()
    beat = time.monotonic()
    expect(stage.status().watchdog_armed, "not armed by a heartbeat")
    while not (st := stage.status()).watchdog_expired:  # queries only: they must not feed it
        expect(time.monotonic() - beat < period + 0.5, "did not expire without heartbeats")
        time.sleep(0.005)
    late = time.monotonic() - beat - period
    expect(st.output_v == 0.0 and st.last_error == 8 and not st.watchdog_armed,
           f"after expiry: output {st.output_v:g} V, error {st.last_error}, "
           f"armed {st.watchdog_armed}")
    expect(late <= 0.1, f"expired {late:.3g} s after its period")  # 10 ms + two polls' latency
    stage.set_watchdog(0.0)
    expect(not stage.status().watchdog_expired, "expired flag not cleared by WDT")
    clear_error(stage)
    return (f"expired {max(late, 0.0) * 1000:.0f} ms after its {period:g} s period (idle), "
            f"ramped to 0 V")


def check_busy(bench: Bench) -> str:
    """§2.9, §2.12: while running SVA, WTL, WTR, WGO n, WGS are busy (5), a bad argument wins
    over busy (2), busy over an index (5); WGO 0 stops; the last error is sticky until read."""
    stage = bench.stage
    with rate(bench, SLOW_RATE_HZ):
        load(stage, _stream_wave(bench, int(0.5 * SLOW_RATE_HZ)))
        stage._start(1)
        for what, action in (("SVA", lambda: stage.set_voltage(0.0)),
                             ("WTL", lambda: stage._set_table_length(4)),
                             ("WTR", lambda: stage.set_sample_rate(SLOW_RATE_HZ)),
                             ("WGO 1", lambda: stage._start(1)),
                             ("WGS", lambda: stage._start_stream(10))):
            expect_code(action, 5, f"{what} while running")
        expect_code(lambda: stage.set_sample_rate(5.0), 2, "WTR 5 Hz while running (2 wins)")
        expect_code(lambda: stage._set_table_length(0), 5, "WTL 0 while running (5 wins)")
        expect(stage.status().last_error == 5, "the last error is not sticky")
        expect(stage.status().running, "the run stopped early")
        stage.stop()
        expect(not stage.status().running, "WGO 0 did not stop the run")
    clear_error(stage)
    expect(stage.status().last_error == 0, "the last error was not cleared")
    return "5 for SVA, WTL, WTR, WGO, WGS; 2 before 5 before 6; WGO 0 stops"


def check_read_only(bench: Bench) -> str:
    """§2.10: a read-only device refuses output and table changes (7), accepts SAFE and WGO 0."""
    stage = bench.stage
    if not stage.status().read_only:
        raise NotApplicable("the device is not read-only")
    for what, action in (("SVA", lambda: stage.set_voltage(0.0)),
                         ("WTL", lambda: stage._set_table_length(4)),
                         ("WTR", lambda: stage.set_sample_rate(bench.rate)),
                         ("WGO 1", lambda: stage._start(1))):
        expect_code(action, 7, f"{what} on a read-only device")
    expect_code(stage.safe_state, 0, "SAFE on a read-only device")
    expect_code(stage.stop, 0, "WGO 0 on a read-only device")
    clear_error(stage)
    return "7 for SVA, WTL, WTR, WGO; SAFE and WGO 0 accepted"


def check_error_codes(bench: Bench) -> str:
    """Error table: the code of each refusal the document lists for both wires."""
    stage = bench.stage
    table, _ = stage._capacities()
    cases = (("WTL 0", lambda: stage._set_table_length(0), 6),
             ("WTL over the capacity", lambda: stage._set_table_length(table + 1), 6),
             ("WTR 5 Hz", lambda: stage.set_sample_rate(5.0), 2),
             ("WDT -1 s", lambda: stage.set_watchdog(-1.0), 2),
             ("WDT 4000 s", lambda: stage.set_watchdog(4000.0), 2),
             ("WGS 0", lambda: stage._start_stream(0), 6))
    for what, action, want in cases:
        expect_code(action, want, what)
    stage._set_table_length(2)
    expect_code(lambda: stage._write_chunk(1, np.zeros(2, dtype=np.float32)), 6,
                "a block past the end of the table")
    clear_error(stage)
    return ", ".join(f"{what}: {want}" for what, _, want in cases) + ", past the table: 6"


# -- §3 serial only ------------------------------------------------------------------------------
def _serial(bench: Bench) -> SerialStage:
    if not isinstance(bench.stage, SerialStage):
        raise NotApplicable("not the serial protocol")
    return bench.stage


def _raw(stage: SerialStage, data: bytes) -> None:
    stage._buf.clear()
    stage._port.reset_input_buffer()
    stage._port.write(data)


def _reply(stage: SerialStage) -> tuple[str, int | None]:
    """The next reply line (its CRC checked): payload and tag."""
    try:
        return ap.unframe(stage._readline(time.monotonic() + stage.timeout_s))
    except ap.FrameError as exc:
        raise Failure(f"a reply with a bad CRC: {exc}") from None


def check_identity(bench: Bench) -> str:
    """§3.4: VER? is 3; *IDN? has four comma-separated fields."""
    stage = _serial(bench)
    version = stage.query("VER?")
    expect(version == str(ap.PROTOCOL_VERSION), f"VER? answers {version!r}")
    idn = stage.identify()
    expect(len(idn.split(",")) == 4 and all(f.strip() for f in idn.split(",")),
           f"*IDN? {idn!r} is not maker,model,serial,firmware")
    return idn


def check_lines(bench: Bench) -> str:
    """§3.1: CR LF ends a line, a CR alone does not; a blank line is unanswered; a line over 8192
    bytes is answered once with an untagged ERR 2."""
    stage = _serial(bench)
    _raw(stage, ap.frame("VER?", 901).encode() + b"\r\n")
    expect(_reply(stage) == (str(ap.PROTOCOL_VERSION), 901), "no reply to a CR LF line")
    _raw(stage, b"VER?\r" + ap.frame("VER?", 902).encode() + b"\n\n"
         + ap.frame("VER?", 903).encode() + b"\n")
    expect(_reply(stage)[1] == 903, "a CR alone ended a line, or a blank line was answered")
    _raw(stage, b"X" * (ap.MAX_LINE + 100) + b" #904\n" + ap.frame("VER?", 905).encode() + b"\n")
    payload, tag = _reply(stage)
    expect(payload.startswith("ERR 2") and tag is None, f"an over-long line got {payload[:30]!r}")
    expect(_reply(stage)[1] == 905, "the line after an over-long one was lost")
    clear_error(stage)
    return "CR LF, CR, blank and over-long lines as documented"


def check_framing(bench: Bench) -> str:
    """§3.2: a bad CRC is unanswered; hand-typed lines are answered with a CRC; a tag without a
    CRC is echoed; a CRC without a tag gets an untagged reply."""
    stage = _serial(bench)
    good = ap.frame("VER?", 911)
    bad = good[:-1] + ("0" if good[-1] != "0" else "1")
    _raw(stage, bad.encode() + b"\n" + ap.frame("VER?", 912).encode() + b"\n")
    expect(_reply(stage)[1] == 912, "a line with a bad CRC was answered")
    for line, tag in (("VER?", None), ("VER? #913", 913), (ap.frame("VER?", None), None)):
        _raw(stage, line.encode() + b"\n")
        payload, got = _reply(stage)
        expect(payload == str(ap.PROTOCOL_VERSION) and got == tag,
               f"{line!r} answered {payload!r} with tag {got}")
    return "bad CRC unanswered; untagged, tag-only and CRC-only lines answered with a CRC"


def check_numbers(bench: Bench) -> str:
    """§3.3, error table: 9 significant digits (float32-exact); strtod input; 1 for an unknown
    command, 2 for a bad number or count, 6 for a negative recorder index."""
    stage = _serial(bench)
    typed = f"{min(bench.step() / 3, 0.1) * (1 if bench.hi > 0 else -1):.3e}"  # e.g. 1.000e-01
    v = float(typed)
    stage._command(f"SVA {typed}")
    expect(stage.query("VOL?") == ap.fmt(v), f"VOL? {stage.query('VOL?')!r}, not {ap.fmt(v)!r}")
    for line, want in (("FOO?", 1), ("SVA abc", 2), ("VOL? 1", 2), ("DRR? 0 0", 2),
                       ("DRR? 0 257", 2), ("DRR? -1 1", 6)):
        expect_code(lambda line=line: stage.query(line), want, line)
    stage.safe_state()
    clear_error(stage)
    return f"VOL? {ap.fmt(v)}; FOO? 1, bad numbers and counts 2, negative DRR? 6"


# -- §4 Modbus only ----------------------------------------------------------------------------
def _modbus(bench: Bench) -> ModbusStage:
    if not isinstance(bench.stage, ModbusStage):
        raise NotApplicable("not Modbus")
    return bench.stage


def check_fc6_echo(bench: Bench) -> str:
    """§4.1: FC6 is answered with the value written (COMMAND, HEARTBEAT)."""
    stage = _modbus(bench)
    for address, value in ((rm.HR.HEARTBEAT, 0x1234), (rm.HR.COMMAND, rm.Cmd.STOP)):
        echo = stage.echo(address, value)
        expect(echo == value, f"FC6 {value} at {address} echoed {echo}")
    return "HEARTBEAT 0x1234 and COMMAND 2 echoed"


def check_registers(bench: Bench) -> str:
    """§4: a write must cover whole fields (exception 2); a refused write answers exception 3 with
    the device's code in IR 2; an unknown command is error 1."""
    stage = _modbus(bench)
    got = stage.write_exception(rm.HR.DC_VOLTAGE + 1, [0])
    expect(got == rm.ILLEGAL_ADDRESS, f"half a float32 field: exception {got}, not 2")
    got = stage.write_exception(rm.HR.TABLE_LENGTH, rm.u32_regs(0))
    expect(got == rm.ILLEGAL_VALUE and stage.status().last_error == 6,
           f"table length 0: exception {got}, error {stage.status().last_error} (not 3, 6)")
    got = stage.write_exception(rm.HR.COMMAND, [99])
    expect(got == rm.ILLEGAL_VALUE and stage.status().last_error == 1,
           f"command 99: exception {got}, error {stage.status().last_error} (not 3, 1)")
    stage.clear_error()
    return "partial field 2; refusals 3 with the code in IR 2"


#: (clause, title, check, changes the output or table) in the document's order.
CLAUSES: tuple[tuple[str, str, Callable[[Bench], str], bool], ...] = (
    ("§1 §2.6", "power-on limits, idle at 0 V", check_power_on, False),
    ("§3.4", "identity and version", check_identity, False),
    ("§2.5", "DC set: one slew-limited step", check_dc_set, True),
    ("§2.6", "limits: float32, inclusive", check_limits, True),
    ("§2.1-2.3", "table run, position, recorder", check_table, True),
    ("§2.4", "streaming, stale slots, underrun", check_stream, True),
    ("§2.7", "safe state ramps to 0 V", check_safe_state, True),
    ("§2.8", "watchdog", check_watchdog, True),
    ("§2.9 §2.11 §2.12", "busy, sticky error, precedence", check_busy, True),
    ("§2.10", "read-only", check_read_only, False),
    ("errors", "error codes", check_error_codes, True),
    ("§3.1", "line ends, blank and over-long lines", check_lines, False),
    ("§3.2", "framing: CRC and tags", check_framing, False),
    ("§3.3", "numbers and error codes", check_numbers, True),
    ("§4.1", "FC6 echo", check_fc6_echo, False),
    ("§4", "register fields and exceptions", check_registers, True),
)


#: The wires the emulated device is checked on.
EMULATED_WIRES = ("serial-pty", "serial-socket", "modbus-tcp", "modbus-rtu")


@contextmanager
def emulated_stage(profile: Profile, wire: str) -> Iterator[StageBase]:
    """A fresh emulated device served on ``wire`` (one of :data:`EMULATED_WIRES`) and the host's
    link to it."""
    from afmctl.drivers.device.emulated import EmulatedDevice
    from afmctl.drivers.device.modbus_server import ModbusRtuServer, ModbusTcpServer
    from afmctl.drivers.device.serial_server import SerialServer

    with ExitStack() as stack:
        dev = stack.enter_context(EmulatedDevice(profile))
        if wire == "modbus-tcp":
            port = stack.enter_context(ModbusTcpServer(dev)).port
            stage: StageBase = ModbusStage(profile, ModbusTcpTransport("127.0.0.1", port))
        elif wire == "modbus-rtu":
            url = stack.enter_context(ModbusRtuServer(dev)).url
            stage = ModbusStage(profile, ModbusRtuTransport(url))
        else:
            where = "pty" if wire == "serial-pty" else "socket://127.0.0.1:0"
            stage = SerialStage(profile, stack.enter_context(SerialServer(dev, where)).url)
        with stage:
            yield stage


def wires(profile: Profile, emulated: bool
          ) -> Iterator[tuple[str, AbstractContextManager[StageBase]]]:
    """What to check: the emulated device on every wire, or the stage the profile names."""
    if emulated:
        for wire in EMULATED_WIRES:
            yield f"emulated device, {wire}", emulated_stage(profile, wire)
        return
    from afmctl.drivers import open_stage
    yield f"{profile.name}: {profile.transport}", open_stage(profile)


def bounds(profile: Profile, max_voltage: float | None) -> tuple[float, float]:
    """``(lo, hi)``: the voltages the checks may command, V (default bound: 10 % of the span)."""
    lim = profile.limits
    bound = 0.1 * (lim.v_max - lim.v_min) if max_voltage is None else max_voltage
    if not bound > 0:
        raise ValueError(f"--max-voltage must be > 0 V, got {bound:g}")
    return max(lim.v_min, -bound), min(lim.v_max, bound)


def run(stage: StageBase, profile: Profile, max_voltage: float | None = None,
        progress: Callable[[str], None] | None = None) -> list[Result]:
    """Every clause against ``stage`` (left idle at 0 V after each); one :class:`Result` each."""
    lo, hi = bounds(profile, max_voltage)
    bench = Bench(stage, profile, lo, hi)
    results = []
    read_only = stage.status().read_only
    to_zero(bench)
    for clause, title, check, writes in CLAUSES:
        if progress is not None:
            progress(f"{clause} {title}")
        try:
            if writes and read_only:
                raise NotApplicable("the device is read-only")
            results.append(Result(clause, title, True, check(bench)))
        except NotApplicable as exc:
            results.append(Result(clause, title, None, str(exc)))
        except (Failure, StageError, TimeoutError, ValueError) as exc:
            results.append(Result(clause, title, False, str(exc)))
        to_zero(bench)
    return results
