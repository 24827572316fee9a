"""Conformance checks of the device model (docs/reference/protocol.md §1, §2), on every wire.

Each check returns a one-line summary or raises :class:`~afmctl.drivers.conformance.Failure` with
the label of the requirement broken, :class:`~afmctl.drivers.conformance.HostLate` when the host's
timing could not resolve a timing requirement, or
:class:`~afmctl.drivers.conformance.NotApplicable`. Timing is judged from request brackets only
(§5): a device fails a timing requirement only when the brackets prove it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from afmctl.drivers import register_map as rm
from afmctl.drivers.conformance import (
    LATENCY_S,
    SLOW_RATE_HZ,
    Bench,
    HostLate,
    NotApplicable,
    clear_error,
    code_of,
    expect,
    expect_code,
    late_or_fail,
    load,
    position_within,
    rate,
    same32,
    settled_position,
    stamped,
    table_wave,
    wait_idle,
    write_blocks,
)
from afmctl.drivers.conformance_timed import check_stream, check_watchdog
from afmctl.drivers.modbus_link import ModbusStage
from afmctl.drivers.serial_link import SerialStage
from afmctl.drivers.stage import StageBase
from afmctl.errors import StageError


# -- §1, §2.6(a): what the device says of itself ------------------------------------------------
def check_power_on(bench: Bench) -> str:
    """§1(a) as far as a host sees it, §2.6(a), §2.3(h): limits as float32 with 0 V inside,
    capacities at least the minimum, idle at 0 V after the safe state."""
    stage = bench.stage
    v_min, v_max, slew = bench.v_min, bench.v_max, bench.slew
    expect(all(float(np.float32(x)) == x for x in (v_min, v_max, slew)), "§2.6(a)",
           f"LIM? {v_min!r} {v_max!r} {slew!r} are not float32 values")
    expect(v_min <= 0.0 <= v_max and slew > 0, "§1(a)",
           f"limits {v_min:g}..{v_max:g} V, {slew:g} V/ms: 0 V (power-on, safe state) outside")
    table, recorder = stage._capacities()
    expect(table >= 1024 and recorder >= 8192, "§2.3(h)",
           f"capacities {table} (table), {recorder} (recorder): at least 1024 and 8192")
    st = stage.status()
    expect(not st.running and st.output_v == 0.0, "§2.7(d)", "not idle at 0 V after SAFE")
    if st.table_length == 0:
        expect(not st.table_complete, "§2.1(c)", "complete with no table")
    lim = bench.profile.limits
    prof = [float(np.float32(x)) for x in (lim.v_min, lim.v_max, lim.slew_v_per_ms)]
    note = ("" if prof == [v_min, v_max, slew] else
            f" (the profile says {prof[0]:g}..{prof[1]:g} V, {prof[2]:g} V/ms: the checks use "
            f"the device's)")
    return f"limits {v_min:g}..{v_max:g} V, {slew:g} V/ms; capacities {table}, {recorder}{note}"


# -- §2.5, §2.6: DC set and limits -------------------------------------------------------------
def check_dc_set(bench: Bench) -> str:
    """§2.5(a), §2.6(b), (f): a DC set is one slew-limited step applied as float32; a zero step is
    accepted; a step of 1.2 slew steps is refused (4) and moves nothing."""
    stage = bench.stage
    r = bench.rate_for(2.5)
    if r is None:
        raise NotApplicable(f"no rate up to 100 kHz puts a refused step within the bounds "
                            f"[{bench.lo:g}, {bench.hi:g}] V (raise --max-voltage)")
    with rate(bench, r):
        s = bench.max_step(r)
        v = math.copysign(0.3 * s, bench.top) * 0.999
        stage.set_voltage(v)
        expect(same32(stage.voltage(), v), "§2.2(f)",
               f"a DC set of {v!r} V reads back {stage.voltage()!r} V, not the command (its "
               f"float32, §2.6(b))")
        expect_code(lambda: stage.set_voltage(v), 0, "§2.5(a)", "a DC set to the output itself")
        near = v + math.copysign(0.99 * s, v)
        expect_code(lambda: stage.set_voltage(near), 0, "§2.5(a)",
                    f"a DC step of 0.99 slew steps to {near:.4g} V")
        far = near + math.copysign(1.2 * s, v)
        expect_code(lambda: stage.set_voltage(far), 4, "§2.5(a)",
                    f"a DC step of 1.2 slew steps to {far:.4g} V")
        expect(same32(stage.voltage(), near), "§2.6(f)", "a refused DC set moved the output")
    return (f"at {r:g} Hz: {v:.4g} V applied as float32, a 0.99-step set taken, a 1.2-step set "
            f"refused (4)")


def check_limits(bench: Bench) -> str:
    """§2.6(c)-(f): the range is inclusive and exact on float32; steps within a chunk and at the
    start are checked with the (1 + 1e-6) tolerance; a refused chunk or start applies nothing.
    Samples beyond the bounds go only into slots that are overwritten before any start."""
    stage = bench.stage
    try:
        for edge, beyond in ((bench.v_max, np.nextafter(np.float32(bench.v_max), np.float32(np.inf))),
                             (bench.v_min, np.nextafter(np.float32(bench.v_min), np.float32(-np.inf))
                              if bench.v_min else np.float32(-2.0 ** -126))):
            stage._set_table_length(2)
            expect_code(lambda e=edge: stage._write_chunk(1, np.array([e], np.float32)), 0,
                        "§2.6(c)", f"a table sample of exactly {edge:g} V (the limit)")
            expect_code(lambda b=beyond: stage._write_chunk(1, np.array([b], np.float32)), 3,
                        "§2.6(c)", f"a table sample of {float(beyond)!r} V (one float32 beyond)")
            expect_code(lambda b=beyond: stage._write_chunk(0, np.array([0, b], np.float32)), 3,
                        "§2.6(c)", "a chunk holding a sample beyond the range")
            expect(not stage.status().table_complete, "§2.6(f)",
                   "a refused chunk stored its first sample (the table became complete)")
        s = bench.max_step()
        side = 1.0 if 1.01 * s <= bench.v_max else -1.0
        steep = ""
        if abs(1.01 * s) <= max(bench.v_max, -bench.v_min):
            expect_code(lambda: stage._write_chunk(0, np.array([0, side * s], np.float32)), 0,
                        "§2.6(d)", f"a chunk stepping exactly one slew step ({s:g} V)")
            expect_code(lambda: stage._write_chunk(0, np.array([0, side * 1.01 * s], np.float32)),
                        4, "§2.6(d)", f"a chunk stepping 1.01 slew steps ({1.01 * s:g} V)")
            steep = "a 1-step chunk taken, a 1.01-step chunk refused (4); "
    finally:  # no sample beyond the bounds stays in the table
        clear_error(stage)
        load(stage, np.zeros(2))
        stage._set_table_length(1)
    return steep + "v_min and v_max taken, one float32 beyond refused (3); " + _start_steps(bench)


def _start_steps(bench: Bench) -> str:
    """§2.6(e), (f): a start checks the step from the output into sample 0 and, for two cycles, the
    wrap from the last sample to the first."""
    stage = bench.stage
    r = bench.rate_for(2.0)
    if r is None:
        return "the steps at the start NOT checked (bounds too tight; raise --max-voltage)"
    with rate(bench, r):
        s = math.copysign(bench.max_step(r), bench.top)
        runs = stage.status().run_count
        load(stage, np.array([1.2 * s]))
        expect_code(lambda: stage._start(1), 4, "§2.6(e)",
                    "a start whose sample 0 is 1.2 slew steps from the output")
        expect(stage.status().run_count == runs, "§2.6(f)", "a refused start counted as a run")
        load(stage, np.array([0.0, 0.9 * s, 1.8 * s]))
        expect_code(lambda: stage._start(2), 4, "§2.6(e)",
                    "two cycles of a table whose wrap steps 1.8 slew steps")
        expect_code(lambda: stage._start(1), 0, "§2.6(e)", "one cycle of that table")
        wait_idle(stage, 2.0)
    clear_error(stage)
    return f"at {r:g} Hz the step into sample 0 and the wrap of two cycles refused (4)"


# -- §2.1-§2.3: a table run ---------------------------------------------------------------------
def check_table(bench: Bench) -> str:
    """§2.1(a), (c), (d), §2.2(a)-(d), §2.3(c)-(g), §5(a), (b), (d): an incomplete table does not
    start; a run of N samples keeps its position within the brackets of its clock, ends at N,
    holds its last sample, and records N finite entries (NaN beyond), readable as counted."""
    stage, r = bench.stage, bench.rate
    dt = 1.0 / float(np.float32(r))
    runs = stage.status().run_count
    stage._set_table_length(4)
    expect(not stage.status().table_complete, "§2.1(a)", "a new table of 4 is complete")
    stage._write_chunk(0, np.zeros(2, np.float32))
    expect_code(lambda: stage._start(1), 9, "§2.1(d)", "a start with 2 of 4 samples written")
    expect(stage.status().run_count == runs, "§2.6(f)", "a refused start counted a run")
    table_cap, rec_cap = stage._capacities()
    end_v = math.copysign(bench.step() / 3, bench.top)
    period = table_wave(bench, min(1000, table_cap), r, end_v)
    m = period.size
    cycles = max(1, min(rec_cap // m, math.ceil(0.3 * r / m)))
    n = m * cycles
    v = np.tile(period, cycles)
    stage._set_table_length(m)
    stage._write_chunk(m - 1, np.zeros(1, np.float32))  # written again below, as end_v
    write_blocks(stage, 0, period)
    expect(stage.status().table_complete, "§2.1(b)", "a table with every slot written is not "
                                                      "complete")
    _, start = stamped(lambda: stage._start(cycles))
    polls, read_mid = 0, False
    while True:
        st, poll = stamped(stage.status)
        polls += 1
        p = st.play_position
        position_within(p, poll, start, n, dt, "§2.2(c)" if polls > 1 else "§5(b)")
        if not st.running:
            break
        expect(poll.sent <= start.done + (n + 1) * dt + 2 * LATENCY_S, "§5(d)",
               f"still running {(poll.sent - start.done) * 1000:.0f} ms after a "
               f"{n * dt * 1000:.0f} ms run started")
        if not read_mid and p > 8:
            rec = stage.read_recorder(8, first=p - 8)
            expect(bool(rec.valid.all()), "§2.3(c)",
                   f"entries {p - 8}..{p - 1} below the position {p} not readable mid-run")
            read_mid = True
        time.sleep(0.01)
    expect(p == n and st.run_samples == n, "§2.2(d)",
           f"position {p}, run length {st.run_samples} when a {n}-sample run stopped running")
    expect(poll.done >= start.sent + n * dt, "§2.2(d)",
           f"a {n * dt * 1000:.1f} ms run was over {(poll.done - start.sent) * 1000:.1f} ms "
           f"after its start was sent")
    expect(st.run_count == runs + 1, "§3.4(a)", f"runs={st.run_count}, not {runs + 1}")
    expect(not same32(st.output_v, 0.0), "§2.1(b)",
           "the run played the first value written to its last slot, not the last")
    expect(same32(st.output_v, v[-1]), "§2.2(d)",
           f"output {st.output_v!r} V after the run, not its last sample {float(np.float32(v[-1]))!r}")
    expect(st.recorder_fill == n, "§2.3(g)", f"recorder fill {st.recorder_fill}, not {n}")
    stage._last_run_samples = n
    rec = stage.read_recorder(n + 2)
    expect(bool(rec.valid[:n].all()), "§2.3(a)",
           "recorder entries of played samples missing (two finite numbers each, §2.3(d))")
    expect(not np.isfinite(rec.voltage_v[n:]).any() and not np.isfinite(
        rec.displacement_um[n:]).any(), "§2.3(g)", "recorder entries beyond the run are not NaN")
    expect_code(lambda: stage._start(rec_cap), 6, "§2.12(a)", "cycles over the recorder")
    expect(stage.status().recorder_fill == n, "§2.3(f)", "a refused start changed the recorder")
    load(stage, np.array([v[-1]]))
    stage._start(1)
    wait_idle(stage, 2.0)
    again = stage.read_recorder(2, first=n - 1)
    expect(stage.status().recorder_fill == 1 and not again.valid.any(), "§2.3(f)",
           "an accepted start did not clear the recorder")
    gap = float(np.max(np.abs(rec.voltage_v[:n] - v.astype(np.float32))))
    if bench.records_command:
        expect(gap == 0.0, "§2.3(e)",
               f"declares that it records the command, yet records {gap:.3g} V off it")
        voltage = "the recorded voltage is the command (declared)"
    else:
        voltage = (f"recorded voltage up to {gap:.3g} V from the command (the amplifier's; "
                   f"no bound, §2.3(b))")
    return (f"{n} samples in {cycles} cycles at {r:g} Hz, position within its clock's brackets at "
            f"{polls} polls, over after {(poll.done - start.sent) * 1000:.0f} ms; {voltage}")


# -- §2.7, §2.9-§2.12: safe state, busy, stop, read-only ---------------------------------------
def check_safe_state(bench: Bench) -> str:
    """§2.7(a), (d): SAFE ramps to 0 V before it answers, stops a run without touching the last
    error, the position or the recorder; SAFE at 0 V answers OK."""
    stage = bench.stage
    for v in bench.ramp(bench.top):
        stage.set_voltage(float(v))
    expect(same32(stage.voltage(), bench.top), "§2.5(a)",
           f"a DC ramp reached {stage.voltage():g} V, not {bench.top:g} V")
    stage.safe_state()
    expect(stage.voltage() == 0.0, "§2.7(d)", f"output {stage.voltage():g} V when SAFE answered")
    expect_code(stage.safe_state, 0, "§2.7(d)", "SAFE at 0 V")
    with rate(bench, SLOW_RATE_HZ):
        load(stage, table_wave(bench, 1000, SLOW_RATE_HZ))
        stage._start(1)
        time.sleep(0.05)
        stage.safe_state()
        st = settled_position(stage)
        expect(not st.running and st.output_v == 0.0, "§2.7(a)",
               f"after SAFE during a run: running {st.running}, output {st.output_v:g} V")
        expect(st.last_error == 0, "§2.7(d)", f"SAFE set the last error to {st.last_error}")
        p = st.play_position
        rec = stage.read_recorder(4, first=max(0, p - 2))
        expect(not rec.valid[2 if p >= 2 else p:].any(), "§2.7(d)",
               f"entries at or past the position {p} recorded after SAFE (the ramp)")
    return f"from {bench.top:g} V to 0 V before the reply; a run stopped at {p} by SAFE"


def _busy(stage: StageBase) -> list[tuple[str, Callable[[], object], int, str]]:
    """Commands refused while running: (what, action, code, label)."""
    cases: list[tuple[str, Callable[[], object], int, str]] = [
        ("SVA", lambda: stage.set_voltage(0.0), 5, "§2.9(a)"),
        ("WTL", lambda: stage._set_table_length(4), 5, "§2.9(a)"),
        ("WTR", lambda: stage.set_sample_rate(SLOW_RATE_HZ), 5, "§2.9(a)"),
        ("WGO 1", lambda: stage._start(1), 5, "§2.9(a)"),
        ("WGS", lambda: stage._start_stream(10), 5, "§2.9(a)"),
        ("WAV during a table run", lambda: stage._write_chunk(0, np.zeros(1, np.float32)), 5,
         "§2.9(a)"),
        ("WTR 5 Hz (2 before 5)", lambda: stage.set_sample_rate(5.0), 2, "§2.12(a)"),
        ("WTL 0 (5 before 6)", lambda: stage._set_table_length(0), 5, "§2.12(a)")]
    if isinstance(stage, SerialStage):
        cases.append(("WGO -1", lambda: stage._start(-1), 5, "§2.12(b)"))
    return cases


def check_busy(bench: Bench) -> str:
    """§2.9, §2.11(a), §2.12, §2.2(e): while running the busy commands answer 5 (2 and 5 before 6),
    the others are accepted, the last error is sticky; WGO 0 stops at once, the output keeps the
    sample being held, the position ends at the samples played."""
    stage = bench.stage
    dt, cycles = 1.0 / SLOW_RATE_HZ, 4
    period = table_wave(bench, 500, SLOW_RATE_HZ)
    m = period.size
    n = m * cycles
    with rate(bench, SLOW_RATE_HZ):
        load(stage, period)
        _, start = stamped(lambda: stage._start(cycles))
        over_at = start.sent + n * dt  # the run cannot be over before this
        if isinstance(stage, ModbusStage):
            got = stage.write_exception(rm.HR.DC_VOLTAGE, rm.f32_regs([0.0]))
            expect(got == rm.DEVICE_BUSY, "§4(b)", f"a busy DC write: exception {got}, not 6")
        for what, action, want, label in _busy(stage):
            got, s = stamped(lambda action=action: code_of(action))
            if got != want:
                late_or_fail(label, s.done < over_at, f"{what} while running: error {got}, the "
                              f"document says {want}", f"{what} was answered after the run "
                                                       "could have ended")
        expect(stage.status().last_error == 5, "§2.11(a)", "the last error is not sticky")
        for what, action in (("STA?", stage.status), ("HB", stage.heartbeat),
                             ("WDT 0", lambda: stage.set_watchdog(0.0)),
                             ("DRR?", lambda: stage.read_recorder(1)), ("LIM?", stage.limits)):
            expect_code(action, 0, "§2.9(b)", f"{what} while running")
        st, s = stamped(stage.status)
        if not st.running:
            late_or_fail("§2.2(d)", s.done < over_at, "the run stopped early",
                          "the run was over before the host stopped it")
        _, stop = stamped(stage.stop)
        expect(not stage.status().running, "§2.2(e)", "WGO 0 did not stop the run")
        st = settled_position(stage)
        p = st.play_position
        if p >= n:
            raise HostLate("the run was over before the host stopped it")
        position_within(p, stop, start, n, dt, "§2.2(e)")
        held = float(np.float32(period[p % m]))
        expect(same32(st.output_v, held), "§2.2(e)",
               f"stopped at position {p}: output {st.output_v!r} V, not the sample being held "
               f"({held!r} V, sample {p})")
        rec = stage.read_recorder(2, first=p - 1) if p else stage.read_recorder(1)
        expect(not p or bool(rec.valid[0]), "§2.3(d)", f"entry {p - 1} (played) missing after "
                                                       "the stop")
        expect(not rec.valid[-1], "§2.2(b)", f"entry {p} (cut short) recorded after the stop")
    clear_error(stage)
    expect(stage.status().last_error == 0, "§2.11(a)", "the last error was not cleared")
    return ("5 for SVA, WTL, WTR, WGO, WGS, WAV; 2 before 5 before 6; queries, HB, WDT taken; "
            f"WGO 0 stopped at {p} with sample {p} held")


def check_read_only(bench: Bench) -> str:
    """§2.10, §2.12(a): a read-only device refuses changes of output, rate and table (7, after 2),
    accepts queries, SAFE, WGO 0, HB, WDT."""
    stage = bench.stage
    if not stage.status().read_only:
        raise NotApplicable("the device is not read-only")
    for what, action in (("SVA", lambda: stage.set_voltage(0.0)),
                         ("WTL", lambda: stage._set_table_length(4)),
                         ("WTR", lambda: stage.set_sample_rate(bench.rate)),
                         ("WAV", lambda: stage._write_chunk(0, np.zeros(1, np.float32))),
                         ("WGO 1", lambda: stage._start(1)), ("WGS", lambda: stage._start_stream(4))):
        expect_code(action, 7, "§2.10(a)", f"{what} on a read-only device")
    expect_code(lambda: stage.set_sample_rate(5.0), 2, "§2.12(a)", "WTR 5 Hz (2 before 7)")
    for what, action in (("SAFE", stage.safe_state), ("WGO 0", stage.stop),
                         ("HB", stage.heartbeat), ("WDT", lambda: stage.set_watchdog(0.0)),
                         ("STA?", stage.status), ("LIM?", stage.limits)):
        expect_code(action, 0, "§2.10(b)", f"{what} on a read-only device")
    clear_error(stage)
    return "7 for SVA, WTL, WTR, WAV, WGO, WGS (2 first); SAFE, WGO 0, HB, WDT, queries taken"


def check_error_codes(bench: Bench) -> str:
    """The error table and §2.12(a) item 6: the code of each refusal both wires can express."""
    stage = bench.stage
    table, recorder = stage._capacities()
    cases = [("WTL 0", lambda: stage._set_table_length(0), 6),
             ("WTL over the capacity", lambda: stage._set_table_length(table + 1), 6),
             ("WTR 5 Hz", lambda: stage.set_sample_rate(5.0), 2),
             ("WTR 200 kHz", lambda: stage.set_sample_rate(200_000.0), 2),
             ("WDT -1 s", lambda: stage.set_watchdog(-1.0), 2),
             ("WDT 4000 s", lambda: stage.set_watchdog(4000.0), 2),
             ("WGS 0", lambda: stage._start_stream(0), 6),
             ("WGS 2^29 + 1", lambda: stage._start_stream((1 << 29) + 1), 6)]
    for what, action, want in cases:
        expect_code(action, want, "§2.12(a)", what)
    stage._set_table_length(2)
    expect_code(lambda: stage._write_chunk(1, np.zeros(2, np.float32)), 6, "§2.12(a)",
                "a block past the end of the table")
    expect_code(lambda: stage._start(recorder // 2 + 1), 6, "§2.12(a)",
                "cycles whose samples overflow the recorder (6 before 9)")
    write_blocks(stage, 0, np.zeros(2))
    expect_code(lambda: stage._start(recorder // 2 + 1), 6, "§2.12(a)",
                "cycles whose samples overflow the recorder")
    clear_error(stage)
    return ", ".join(f"{what}: {want}" for what, _, want in cases) + \
        ", past the table: 6, cycles over the recorder: 6 (before 9)"


#: (clause, title, check, changes the output or table) in the document's order.
CLAUSES: tuple[tuple[str, str, Callable[[Bench], str], bool], ...] = (
    ("§1 §2.6(a)", "limits, capacities, idle at 0 V", check_power_on, False),
    ("§2.5", "DC set: one slew-limited step", check_dc_set, True),
    ("§2.6", "limits: float32, inclusive, slew", check_limits, True),
    ("§2.1-2.3", "table run, clock, position, recorder", check_table, True),
    ("§2.4", "streaming, stale slots, underrun", check_stream, True),
    ("§2.7", "safe state ramps to 0 V", check_safe_state, True),
    ("§2.8", "watchdog", check_watchdog, False),
    ("§2.9 §2.11 §2.12", "busy, sticky error, stop", check_busy, True),
    ("§2.10", "read-only", check_read_only, False),
    ("errors", "error codes", check_error_codes, True),
)

__all__ = ["CLAUSES", "StageError"]
