"""Conformance checks of a device of several channels (docs/reference/protocol.md §2.14, §3.6-§3.7,
§4.4-§4.5): each channel's own limits and DC set, held channels, a run and a stream of every
channel on one clock, the safe state and the watchdog bringing every output to 0 V, and the
edge-case rows of the channel prefix (serial protocol 4) and the channel-select register (map 3).

Every clause here is not applicable to a device of one channel (a device of serial protocol 3 /
register map 2 has exactly one): a v5 device passes the rest of the check unchanged. Channel 1
stands for every channel after 0; it is held to its own limits (``LIM?`` / IR 32-37 with it
selected) and moved within the check's bounds and 90 % of its own slew step, like channel 0.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from afmctl.drivers import register_map as rm
from afmctl.drivers.conformance import (
    SLOW_RATE_HZ,
    Bench,
    Failure,
    HostLate,
    NotApplicable,
    clear_error,
    expect,
    expect_code,
    load,
    rate,
    same32,
    settled_position,
    stream_wave,
    table_wave,
    wait_idle,
)
from afmctl.drivers.conformance_rows import CHANNEL_MODBUS_ROWS, CHANNEL_SERIAL_ROWS
from afmctl.drivers.conformance_wire import modbus_rows, serial_rows
from afmctl.drivers.modbus_link import ModbusStage
from afmctl.drivers.serial_link import SerialStage
from afmctl.drivers.stage import StageBase
from afmctl.errors import StageError


@dataclass(frozen=True)
class Axis:
    """Channel ``channel``'s own limits (``v_min``, ``v_max`` V, ``slew`` V/ms) and the bounds the
    check moves it within (``lo``, ``hi``, V)."""

    channel: int
    v_min: float
    v_max: float
    slew: float
    lo: float
    hi: float

    @property
    def top(self) -> float:
        return self.hi if self.hi >= -self.lo else self.lo

    def step(self, rate_hz: float) -> float:
        """90 % of the channel's largest step at ``rate_hz``, V, towards :attr:`top`."""
        return float(np.copysign(0.9 * self.slew * 1000.0 / rate_hz, self.top))


def _several(bench: Bench) -> int:
    channels = bench.stage.channels
    if channels < 2:
        raise NotApplicable("one channel (a device of one channel needs nothing of §2.14 more)")
    return channels


def axis(bench: Bench, channel: int) -> Axis:
    """Channel ``channel``'s limits as the device reports them and the check's bounds in them."""
    v_min, v_max, slew = bench.stage.limits(channel)
    return Axis(channel, v_min, v_max, slew, max(bench.lo, v_min), min(bench.hi, v_max))


def _limits(bench: Bench, channels: int) -> str:
    """§2.14(a): every channel reports its own limits: float32 values, 0 V inside."""
    shown = []
    for c in range(channels):
        a = axis(bench, c)
        expect(all(float(np.float32(x)) == x for x in (a.v_min, a.v_max, a.slew))
               and a.v_min <= 0.0 <= a.v_max and a.slew > 0, "§2.14(a)",
               f"channel {c}'s limits {a.v_min!r}..{a.v_max!r} V, {a.slew!r} V/ms: not float32 "
               f"values with 0 V inside")
        shown.append(f"{a.v_min:g}..{a.v_max:g} V {a.slew:g} V/ms")
    return f"{channels} channels ({'; '.join(shown)})"


def _dc_and_range(bench: Bench, y: Axis) -> None:
    """§2.14(d): a DC set moves only its channel and is checked against that channel's slew; a
    table sample is checked against that channel's range (exactly v_max taken, one float32
    beyond refused), in slots emptied before any start."""
    stage = bench.stage
    near = min(abs(y.step(bench.rate)) / 0.9 * 0.5, abs(y.top)) * np.sign(y.top)
    stage.set_voltage(float(near), channel=1)
    expect(same32(stage.voltage(1), near) and stage.voltage(0) == 0.0, "§2.14(d)",
           f"after a DC set of channel 1 to {near:g} V: outputs {stage.voltages()}")
    far = near + 1.2 * y.step(bench.rate) / 0.9
    if y.v_min <= far <= y.v_max:
        expect_code(lambda: stage.set_voltage(float(far), channel=1), 4, "§2.14(d)",
                    f"a DC set of channel 1 {far - near:g} V away (1.2 of its own slew steps)")
        expect(same32(stage.voltage(1), near), "§2.14(d)", "a refused DC set moved channel 1")
    stage.safe_state()
    beyond = np.nextafter(np.float32(y.v_max), np.float32(np.inf))
    try:
        stage._set_table_length(2)
        expect_code(lambda: stage._write_chunk(1, np.array([y.v_max], np.float32), 1), 0,
                    "§2.14(d)", f"a channel-1 sample of exactly its v_max {y.v_max:g} V")
        expect_code(lambda: stage._write_chunk(1, np.array([beyond], np.float32), 1), 3,
                    "§2.14(d)", f"a channel-1 sample of {float(beyond)!r} V (one float32 beyond)")
    finally:  # nothing beyond the bounds stays in a table
        clear_error(stage)
        stage._set_table_length(1)


def _recorded(stage: StageBase, n: int, channels: int, what: str) -> None:
    """§2.14(b): every channel's recorder holds finite entries for the ``n`` samples played."""
    rec = stage.read_recorder(n, 0, channels=channels)
    bad = np.flatnonzero(~rec.valid.all(axis=0))
    expect(bad.size == 0, "§2.14(b)",
           f"{what}: channel(s) {bad.tolist()} lack recorder entries of the {n} samples played")


def _held_run(bench: Bench, y: Axis, channels: int) -> str:
    """§2.14(c), (i), (b): a table on channel 0 alone plays while channel 1 holds its DC value (a
    DC set of it is busy meanwhile), and every channel records every sample."""
    stage = bench.stage
    with rate(bench, SLOW_RATE_HZ):
        hold = float(np.float32(min(abs(y.step(SLOW_RATE_HZ)), abs(y.top)) * np.sign(y.top) / 2))
        stage.set_voltage(hold, channel=1)
        wave = table_wave(bench, 300, SLOW_RATE_HZ)
        load(stage, wave)
        stage._start(1)
        expect_code(lambda: stage.set_voltage(0.0, channel=1), 5, "§2.14(i)",
                    "a DC set of channel 1 while a run plays")
        clear_error(stage)
        wait_idle(stage, wave.size / SLOW_RATE_HZ + 2.0)
        settled_position(stage)
        expect(same32(stage.voltage(1), hold), "§2.14(c)",
               f"channel 1 (no table) ended at {stage.voltage(1):g} V, not its {hold:g} V")
        _recorded(stage, wave.size, channels, "a run of channel 0's table")
        if bench.records_command:
            rec = stage.read_recorder(wave.size, 0, channels=2)
            expect(bool(np.all(rec.voltage_v[:, 1] == hold)), "§2.14(c)",
                   "channel 1 (no table) recorded other commands than its held output")
    return f"channel 1 held at {hold:g} V through {wave.size} samples of channel 0"


def _both_run(bench: Bench, y: Axis, channels: int) -> str:
    """§2.14(b), (c): a table on channels 0 and 1 plays both on one clock to the same position; a
    channel written in part leaves the table incomplete and a start refused (9)."""
    stage = bench.stage
    with rate(bench, SLOW_RATE_HZ):
        x_wave = table_wave(bench, 200, SLOW_RATE_HZ)
        y_wave = x_wave * min(1.0, abs(y.top / bench.top)) * np.sign(y.top * bench.top)
        stage.upload(np.stack([x_wave, y_wave], axis=1))
        stage._start(1)
        st, _ = wait_idle(stage, x_wave.size / SLOW_RATE_HZ + 2.0)
        st = settled_position(stage)
        expect(st.play_position == x_wave.size and st.last_error == 0, "§2.14(b)",
               f"a run of two channels' tables ended at {st.play_position} of {x_wave.size}, "
               f"error {st.last_error}")
        _recorded(stage, x_wave.size, channels, "a run of two channels")
        stage._set_table_length(2)
        stage._write_chunk(0, np.zeros(2, np.float32), 0)
        stage._write_chunk(0, np.zeros(1, np.float32), 1)
        expect(not stage.status().table_complete, "§2.14(c)",
               "complete with channel 1 written in part")
        expect_code(lambda: stage._start(1), 9, "§2.14(c)", "a start with channel 1 written in part")
    clear_error(stage)
    return f"both channels over {x_wave.size} samples, one position"


def _stream(bench: Bench, y: Axis, channels: int) -> str:
    """§2.14(h): a stream of channels 0 and 1 through a 256-sample table, refilled per channel as
    it plays, ends at N with every channel recorded (an underrun the host caused: host late)."""
    stage, n, length = bench.stage, 768, 256
    block = min(64, stage.upload_chunk)
    with rate(bench, SLOW_RATE_HZ):
        x_wave = stream_wave(bench, n, SLOW_RATE_HZ)
        y_wave = x_wave * min(1.0, abs(y.top / bench.top)) * np.sign(y.top * bench.top)
        waves = np.stack([x_wave, y_wave], axis=1).astype(np.float32)
        stage.upload(waves[:length])
        stage._start_stream(n)
        written = length
        try:
            while (st := stage.status()).running:
                if written < n and written + block <= st.play_position + length:
                    for c in range(2):
                        stage._write_chunk(written, waves[written:written + block, c], c)
                    written += block
                else:
                    time.sleep(0.002)
        except StageError as refused:  # refused: the run stopped meanwhile (the refusal's code
            st = settled_position(stage)  # is now the last error), or a wrong refusal
            if st.running or st.play_position < written:
                raise Failure("§2.14(h)", f"a block of samples {written}.. refused ({refused}) "
                                          f"with the stream at {st.play_position}") from None
            raise HostLate(f"the stream's refill fell behind: stopped at sample "
                           f"{st.play_position}, the first not yet written") from None
        st = settled_position(stage)
        if st.last_error == 10 and st.play_position >= written:
            raise HostLate(f"the stream's refill fell behind at sample {st.play_position}")
        expect(st.play_position == n and st.last_error == 0, "§2.14(h)",
               f"a stream of two channels ended at {st.play_position} of {n}, error "
               f"{st.last_error}")
        _recorded(stage, n, channels, "a stream of two channels")
    return f"a {n}-sample stream of both channels through a {length}-sample table"


def _all_to_zero(bench: Bench, y: Axis) -> str:
    """§2.14(e): SAFE and a watchdog expiry bring every output to 0 V, each within its own slew."""
    stage = bench.stage
    x_step, y_step = bench.step(), y.step(bench.rate)
    for cause in ("SAFE", "watchdog"):
        stage.set_voltage(float(np.copysign(min(abs(x_step), abs(bench.top)), bench.top)))
        stage.set_voltage(float(np.copysign(min(abs(y_step), abs(y.top)), y.top)), channel=1)
        if cause == "SAFE":
            stage.safe_state()
        else:
            stage.set_watchdog(0.05)
            stage.heartbeat()
            deadline = time.monotonic() + 2.0
            while not stage.status().watchdog_expired and time.monotonic() < deadline:
                time.sleep(0.01)
        out = stage.voltages()
        expect(bool(np.all(out == 0.0)), "§2.14(e)",
               f"after {cause}: outputs {out.tolist()} V, not every one 0 V")
        clear_error(stage)
        stage.set_watchdog(0.0)
    return "SAFE and the watchdog brought every output to 0 V"


def check_channels(bench: Bench) -> str:
    """§2.14: each channel's limits, DC set and range; a held channel; a run and a stream of
    every channel on one clock; every output to 0 V on SAFE and on the watchdog."""
    channels = _several(bench)
    y = axis(bench, 1)
    parts = [_limits(bench, channels)]
    _dc_and_range(bench, y)
    parts += [_held_run(bench, y, channels), _both_run(bench, y, channels),
              _stream(bench, y, channels), _all_to_zero(bench, y)]
    return "; ".join(parts)


def check_channel_prefix(bench: Bench) -> str:
    """§3.6, §3.7: protocol 4 answers VER? 4 and CHN? its channels; the rows of §3.7."""
    _several(bench)
    stage = bench.stage
    if not isinstance(stage, SerialStage):
        raise NotApplicable("not the serial protocol")
    version, count = stage.query("VER?"), stage.query("CHN?")
    expect(version == "4" and count == str(stage.channels), "§3.6(a)",
           f"VER? {version!r}, CHN? {count!r} on a device of {stage.channels} channels")
    return f"{serial_rows(bench, None, CHANNEL_SERIAL_ROWS)} rows of §3.7 as documented"


def check_channel_select(bench: Bench) -> str:
    """§4.4, §4.5: map 3 reads 3 in IR 0 and the channels in IR 29; the rows of §4.5."""
    _several(bench)
    stage = bench.stage
    if not isinstance(stage, ModbusStage):
        raise NotApplicable("not Modbus")
    regs = stage._request("read_input_registers", rm.IR.MAP_VERSION, count=rm.IR.CHANNELS + 1)
    expect(regs[0] == rm.CHANNELS_MAP_VERSION and regs[rm.IR.CHANNELS] == stage.channels,
           "§4.4(a)", f"IR 0 {regs[0]}, IR 29 {regs[rm.IR.CHANNELS]} on a device of "
                      f"{stage.channels} channels")
    return f"{modbus_rows(bench, None, CHANNEL_MODBUS_ROWS)} rows of §4.5 as documented"


#: (clause, title, check, changes the output or table) in the document's order.
CLAUSES: tuple[tuple[str, str, Callable[[Bench], str], bool], ...] = (
    ("§2.14", "channels: limits, held, run, stream, safe", check_channels, True),
    ("§3.6 §3.7", "channel prefix (serial protocol 4)", check_channel_prefix, False),
    ("§4.4 §4.5", "channel select (register map 3)", check_channel_select, False),
)
