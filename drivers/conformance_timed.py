"""Conformance checks whose verdict rests on time (docs/reference/protocol.md §2.4 streaming, §2.8 watchdog,
§5(f)-(h)), on every wire.

Both are judged from request brackets only: an underrun counts against the device when the
missing sample had been written before it could be due, the watchdog's expiry is bracketed by the
last query that saw it armed and the first that saw it expired; when the host's own timing is too
coarse, :class:`~afmctl.drivers.conformance.HostLate` (the host fell behind) instead of a verdict.
"""

from __future__ import annotations

import math
import time

import numpy as np

from afmctl.drivers import register_map as rm
from afmctl.drivers.conformance import (
    LATENCY_S,
    SLOW_RATE_HZ,
    Bench,
    HostLate,
    clear_error,
    code_of,
    expect,
    expect_code,
    late_or_fail,
    load,
    rate,
    settled_position,
    stamped,
    stream_wave,
    wait_idle,
    write_blocks,
)
from afmctl.drivers.modbus_link import ModbusStage
from afmctl.drivers.stage import StageBase

# -- §2.4 streaming --------------------------------------------------------------------------------
STREAM_TABLE = 512
STREAM_BLOCK = 64


def check_stream(bench: Bench) -> str:
    """§2.4(a)-(h), §2.1(c), (d), §5(f), (h): a stream refilled as it plays ends at N; a block a
    table ahead is refused (6), a block already played is taken; stale slots refuse WGS and WGO
    (9); WGS N < L plays N; an unfed stream underruns at L (10); a steep step between blocks
    stops it at that sample (4)."""
    stage = bench.stage
    L, dt = STREAM_TABLE, 1.0 / SLOW_RATE_HZ
    n = 3 * L
    with rate(bench, SLOW_RATE_HZ):
        v = stream_wave(bench, n, SLOW_RATE_HZ)
        load(stage, v[:L])
        _, start = stamped(lambda: stage._start_stream(n))
        got, ahead = stamped(lambda: code_of(lambda: write_blocks(stage, n - 8, v[n - 8:])))
        if got != 6:
            late_or_fail("§2.4(b)", ahead.done - start.sent < (n - L) * dt,
                          f"a block ending {L} samples or more past the position: error {got}",
                          "the host sent the too-far block after the position had moved on")
        if stage.status().last_error == 6:  # not an underrun's 10: that one is judged below
            clear_error(stage)
        written, rewrote = L, False
        done_at = {b: -math.inf for b in range(0, L, STREAM_BLOCK)}  # loaded before the start
        while (st := stage.status()).running:
            p = st.play_position
            if not rewrote and p > STREAM_BLOCK:
                expect_code(lambda: write_blocks(stage, 0, v[:STREAM_BLOCK]), 0, "§2.4(c)",
                            "a block of samples already played")
                rewrote = True
            while written < n and written + STREAM_BLOCK <= p + L:
                got = code_of(lambda w=written: done_at.update(
                    {w: write_blocks(stage, w, v[w:w + STREAM_BLOCK])[-1].done}))
                if got:
                    st = stage.status()
                    expect(not st.running and st.play_position < n, "§2.4(b)",
                           f"a block ending within a table of the position {p}: error {got}")
                    break  # the stream had stopped before the block came: judged below
                written += STREAM_BLOCK
            else:
                expect(time.monotonic() - start.done < n * dt + 5.0, "§2.2(d)",
                       "the stream never ended")
                time.sleep(0.005)
                continue
            break
        st = settled_position(stage)
        p = st.play_position
        if p < n:
            at = done_at.get(p - p % STREAM_BLOCK, math.inf)
            late_or_fail("§2.4(d)", at < start.sent + p * dt,
                          f"the stream stopped at sample {p} (error {st.last_error}), which was "
                          f"written {(start.sent + p * dt - at) * 1000:.0f} ms before it could be "
                          f"due", f"the host wrote sample {p} too late")
        expect(st.last_error == 0, "§2.4(b)",
               f"the refilled stream played {n} samples with error {st.last_error}")
        rec = stage.read_recorder(n)
        expect(bool(rec.valid.all()), "§2.4(g)", "a streamed run did not record every sample")
        expect(not stage.status().table_complete, "§2.4(h)",
               "the table counts as complete after a stream wrapped it")
        expect_code(lambda: stage._start_stream(L), 9, "§2.4(h)", "a stream started on stale slots")
        expect_code(lambda: stage._start(1), 9, "§2.1(d)", "a table run started on stale slots")
        clear_error(stage)
        stage._set_table_length(L)
        write_blocks(stage, 0, v[:50])
        stage._start_stream(50)
        wait_idle(stage, 2.0)
        st = settled_position(stage)
        expect(st.play_position == 50 and st.last_error == 0, "§2.4(a)",
               f"WGS 50 with L = {L}: stopped at {st.play_position}, error {st.last_error}")
        short = 127  # its last sample is not 0 V: the ramp after the underrun shows
        load(stage, v[:short])
        _, start = stamped(lambda: stage._start_stream(2 * short))
        _, poll = wait_idle(stage, 2.0)
        st = settled_position(stage)
        expect(st.play_position == short and st.last_error == 10,
               "§2.4(d)", f"an unfed stream stopped at {st.play_position} (not {short}), error "
                          f"{st.last_error}")
        expect(st.output_v == 0.0, "§2.7(b)", f"output {st.output_v:g} V after an underrun")
        expect(poll.done >= start.sent + short * dt, "§5(h)", "the underrun came early")
    clear_error(stage)
    return f"{n} samples through a {L}-sample table refilled as played; 6, 9, 10 as documented; " \
           + _stream_slew(bench)


def _stream_slew(bench: Bench) -> str:
    """§2.4(e), (f): a steep first sample refuses the stream (4); a steep step into the first
    refilled sample stops it there (4, ramp to 0 V)."""
    stage = bench.stage
    r = bench.rate_for(1.3)
    if r is None:
        return "the slew of a stream NOT checked (bounds too tight; raise --max-voltage)"
    with rate(bench, r):
        step = math.copysign(1.2 * bench.max_step(r), bench.top)
        length = min(4096, stage._capacities()[0])  # the host's margin: length / r
        load(stage, np.full(length, step))
        runs = stage.status().run_count
        expect_code(lambda: stage._start_stream(2 * length), 4, "§2.4(f)",
                    "a stream whose sample 0 is 1.2 slew steps from the output")
        expect(stage.status().run_count == runs, "§2.6(f)", "a refused stream counted as a run")
        load(stage, np.zeros(length))
        _, start = stamped(lambda: stage._start_stream(length + 8))
        due = start.sent + length / r  # the earliest the steep sample can be due
        while stage.status().play_position < 8:  # the block's slots are those of samples 0..7
            time.sleep(0.0005)
        got, wrote = stamped(lambda: code_of(
            lambda: write_blocks(stage, length, np.full(8, step))))
        if got:
            late_or_fail("§2.4(b)", wrote.done < due, f"a block within the stream window: "
                         f"error {got}", "the host wrote the steep block after it was due")
        wait_idle(stage, 2.0)
        st = settled_position(stage)
        if st.last_error == 10:
            late_or_fail("§2.4(d)", wrote.done < due, "underrun at a sample written before it "
                         "was due", "the host wrote the steep block after it was due")
        expect(st.play_position == length and st.last_error == 4 and st.output_v == 0.0,
               "§2.4(e)", f"a step of 1.2 slew steps into sample {length}: stopped at "
                          f"{st.play_position}, error {st.last_error}, output {st.output_v:g} V")
    return f"at {r:g} Hz a steep sample 0 refused and a steep refill stopped at it (4)"


# -- §2.8 watchdog -------------------------------------------------------------------------------
WATCHDOG_S = 0.2


def check_watchdog(bench: Bench) -> str:
    """§2.8(b)-(g), §5(g): WDT disarms and clears the flag; HB arms; left alone it expires within
    10 ms of its period, idle, ramping to 0 V with error 8; queries do not feed it; a heartbeat
    re-arms it; the next start clears the flag. The expiry instant is bracketed by the last query
    that saw it armed and the first that saw it expired."""
    stage, period = bench.stage, WATCHDOG_S
    writable = not stage.status().read_only
    stage.set_watchdog(period / 2)
    expect(not stage.status().watchdog_armed, "§2.8(b)", "armed by WDT alone")
    if writable:
        stage.set_voltage(math.copysign(bench.step() / 3, bench.top))
    _, beat = stamped(stage.heartbeat)
    st, look = stamped(stage.status)
    if not st.watchdog_armed:  # or it has already expired again: the host was that slow
        late_or_fail("§2.8(c)", look.done < beat.sent + period / 2, "not armed by a heartbeat",
                     "the host asked only after the period had run out")
    time.sleep(max(0.0, beat.done + period / 2 + 0.015 - time.monotonic()))
    st, look = stamped(stage.status)
    expect(st.watchdog_expired, "§5(g)", f"still armed {(look.sent - beat.done - period / 2) * 1e3:.0f}"
                                           f" ms after its {period / 2:g} s period ran out, left alone")
    expect(st.output_v == 0.0 and st.last_error == 8 and not st.watchdog_armed, "§2.8(e)",
           f"after expiry: output {st.output_v:g} V, error {st.last_error}, armed "
           f"{st.watchdog_armed}")
    _, beat = stamped(stage.heartbeat)
    st, look = stamped(stage.status)
    if not st.watchdog_armed:
        late_or_fail("§2.8(g)", look.done < beat.sent + period / 2, "a heartbeat after an expiry "
                     "did not re-arm it", "the host asked only after the period had run out")
    expect(st.watchdog_expired, "§2.8(f)", "a heartbeat cleared the expired flag")
    stage.set_watchdog(0.0)
    st = stage.status()
    expect(not st.watchdog_expired and not st.watchdog_armed, "§2.8(b)",
           "WDT did not clear the expired flag and disarm")
    clear_error(stage)
    lo, hi = _expiry_bracket(stage, period)
    if writable:
        load(stage, np.zeros(1))
        stage._start(1)
        expect(not stage.status().watchdog_expired, "§2.8(f)", "a start did not clear the flag")
        wait_idle(stage, 2.0)
    stage.set_watchdog(0.0)
    clear_error(stage)
    return (f"expired {lo * 1e3:.1f}-{hi * 1e3:.1f} ms after its {period:g} s period under "
            f"queries (idle), ramped to 0 V")


#: Expiries bracketed per attempt of the watchdog clause before the host is said to fall behind.
BRACKET_TRIES = 5


def _expired(stage: StageBase) -> bool:
    """The expired flag, by the shortest query the wire has (Modbus: IR 1 alone)."""
    if isinstance(stage, ModbusStage):
        bits = stage._request("read_input_registers", rm.IR.STATUS, count=1)[0]
        return bool(bits & rm.StatusBit.WATCHDOG_EXPIRED)
    return stage.status().watchdog_expired


def _expiry_bracket(stage: StageBase, period: float) -> tuple[float, float]:
    """§2.8(d), (e), §5(g): arm the watchdog and query until it expires; the expiry's delay past
    the period, bracketed (s). Tried :data:`BRACKET_TRIES` times for a bracket within the 10 ms
    allowed; HostLate if none is."""
    widest = (0.0, 0.0)
    for _ in range(BRACKET_TRIES):
        stage.set_watchdog(period)  # disarms and clears the flag of the try before
        _, beat = stamped(stage.heartbeat)
        armed_at: float | None = None
        while True:
            now = time.monotonic()
            if now < beat.done + period - 0.02:
                time.sleep(min(0.02, beat.done + period - 0.02 - now))
            expired, poll = stamped(lambda: _expired(stage))
            if expired:
                expect(poll.done >= beat.sent + period, "§2.8(e)",
                       f"expired {(beat.sent + period - poll.done) * 1e3:.1f} ms before its period")
                break
            armed_at = poll.sent
            expect(poll.sent - beat.done <= period + LATENCY_S, "§2.8(d)",
                   f"still armed {(poll.sent - beat.done - period) * 1e3:.1f} ms after its "
                   "period, queried but without heartbeats (queries must not feed it)")
            time.sleep(0.001)
        lo = max(0.0, (armed_at - beat.done - period) if armed_at is not None else 0.0)
        hi = poll.done - beat.sent - period
        if hi <= LATENCY_S:
            return lo, hi
        widest = max(widest, (lo, hi), key=lambda b: b[1])
    raise HostLate(f"{BRACKET_TRIES} expiries bracketed up to {widest[0] * 1e3:.1f}-"
                   f"{widest[1] * 1e3:.1f} ms after the period: too wide to judge the 10 ms")
