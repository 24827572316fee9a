"""The conformance check: a device against ``docs/reference/protocol.md``, requirement by requirement.

Any device, afmctl's emulated one or a lab's own, over the serial protocol (any pyserial URL) or
Modbus (TCP or RTU), reached through the host links of :mod:`drivers`. Each check drives the device
through its commands and compares what it answers with what the document says; every expectation
names the label of the requirement it holds the device to (``§2.8(e)``), and a failure quotes it.
The result is one :class:`Result` per clause group: passed, failed (with the label), not
applicable (with the reason), or **host fell behind** (no verdict, see below).

Timing is measured from request brackets (docs/reference/protocol.md §5): every request is stamped when it
starts (``sent``) and when its reply has been read (``done``); the device acted within. A timing
requirement fails only when the brackets prove it broken; when they are too wide to tell (a loaded
host), the check raises :class:`HostLate`, is repeated up to :data:`ATTEMPTS` times, and is then
reported as the host falling behind, not as the device failing.

Motion is bounded: every voltage played or set lies within ``[lo, hi]``, at most ``max_voltage``
from 0 V and inside the device's limits, every step within 90 % of the slew limit unless the step
is one the device must refuse. Out-of-range samples are only written where the device must refuse
them or into table slots that are overwritten before any start. The checks leave the device idle at
0 V, with its error cleared, its watchdog off and its sample rate the profile's.

The checks themselves: :mod:`~afmctl.drivers.conformance_device` (§1, §2 on every wire),
:mod:`~afmctl.drivers.conformance_timed` (§2.4 streaming and §2.8 watchdog, judged on the host's
clock), :mod:`~afmctl.drivers.conformance_channels` (§2.14, §3.6-§3.7, §4.4-§4.5: a device of
several channels) and :mod:`~afmctl.drivers.conformance_wire` (§3 serial, §4 Modbus, §5 reply
latency).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Collection, Iterator
from contextlib import AbstractContextManager, ExitStack, contextmanager
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from afmctl.drivers import register_map as rm
from afmctl.drivers.modbus_link import ModbusStage
from afmctl.drivers.protocol import Status
from afmctl.drivers.serial_link import SerialStage
from afmctl.drivers.stage import StageBase
from afmctl.errors import StageError
from afmctl.files.profile import ModbusRtuTransport, ModbusTcpTransport, Profile

T = TypeVar("T")

#: Sample rate of the stream, busy and edge-case checks, Hz (slow enough for any link to refill).
SLOW_RATE_HZ = 1000.0
#: Attempts of a check whose timing the host could not resolve (docs/reference/protocol.md §5).
ATTEMPTS = 3
#: Recorder latency a device may have (§2.2(c), §5(d)) and the slack of t_0 (§2.2(a)), s.
LATENCY_S = 0.010
#: Highest sample rate a device must take, Hz (§3.4).
MAX_RATE_HZ = 100_000.0
#: The model field's ending by which a serial device declares that it records the command.
VREC_COMMAND = ";vrec=command"


class Failure(Exception):
    """A requirement the device does not meet: ``label`` (e.g. ``§2.8(e)``) and how."""

    def __init__(self, label: str, message: str) -> None:
        super().__init__(f"{label}: {message}")
        self.label = label


class NotApplicable(Exception):
    """A clause that does not apply to this device or wire (the message says why)."""


class HostLate(Exception):
    """The host's own timing was too coarse to judge the device (the message says where)."""


@dataclass(frozen=True)
class Result:
    """One clause group: ``passed`` is True, False, or None (not applicable, or the host fell
    behind: ``host_late``). ``label`` is the requirement a failure holds the device to."""

    clause: str
    title: str
    passed: bool | None
    detail: str
    label: str = ""
    host_late: bool = False


@dataclass(frozen=True)
class Stamp:
    """A request on the host's monotonic clock: started at ``sent``, its reply read at ``done``
    (s); the device acted on it at some instant in between."""

    sent: float
    done: float


def stamped(action: Callable[[], T]) -> tuple[T, Stamp]:
    """``action()`` and its bracket."""
    t0 = time.monotonic()
    out = action()
    return out, Stamp(t0, time.monotonic())


@dataclass
class Bench:
    """The device under test, its own limits (``LIM?``, float32) and the bounds of what may be
    commanded."""

    stage: StageBase
    profile: Profile
    lo: float
    hi: float
    v_min: float
    v_max: float
    slew: float
    records_command: bool = False

    @property
    def rate(self) -> float:
        return self.profile.sample_rate_hz

    @property
    def top(self) -> float:
        """The bound the checks move towards (the larger side of the bounds), V."""
        return self.hi if self.hi >= -self.lo else self.lo

    def max_step(self, rate_hz: float | None = None) -> float:
        """The device's largest step per sample at ``rate_hz``, V (§2.6(d))."""
        return self.slew * 1000.0 / (rate_hz or self.rate)

    def step(self, rate_hz: float | None = None) -> float:
        """The step the checks take, V (90 % of the limit)."""
        return 0.9 * self.max_step(rate_hz)

    def ramp(self, target_v: float, rate_hz: float | None = None) -> NDArray[np.float64]:
        """Samples from 0 V to ``target_v`` within the slew limit (0 V itself excluded)."""
        n = max(1, math.ceil(abs(target_v) / self.step(rate_hz)))
        return np.linspace(0.0, target_v, n + 1)[1:]

    def rate_for(self, steps: float) -> float | None:
        """The lowest rate, at least the profile's, at which ``steps`` full slew steps fit in the
        bounds (a step the device must refuse stays within them); None if none up to 100 kHz."""
        need = self.slew * 1000.0 * steps / abs(self.top) if self.top else math.inf
        rate = max(self.rate, math.ceil(need))
        return float(rate) if rate <= MAX_RATE_HZ else None


def expect(condition: bool, label: str, message: str) -> None:
    """Fail with ``label`` (the requirement) unless ``condition``."""
    if not condition:
        raise Failure(label, message)


def code_of(action: Callable[[], object]) -> int:
    """The device's error code for ``action`` (0: accepted)."""
    try:
        action()
    except StageError as exc:
        return exc.code
    return 0


def expect_code(action: Callable[[], object], want: int, label: str, what: str) -> int:
    got = code_of(action)
    expect(got == want, label, f"{what}: error {got}, the document says {want}")
    return got


def clear_error(stage: StageBase) -> None:
    if isinstance(stage, SerialStage):
        stage.last_error()
    elif isinstance(stage, ModbusStage):
        stage.clear_error()


def to_zero(bench: Bench) -> None:
    """Safe state, error cleared, watchdog off, the profile's sample rate (a device that refuses
    one of these is left to the checks to name)."""
    stage = bench.stage
    for step in (stage.safe_state, lambda: stage.set_watchdog(0.0)):
        code_of(step)
    st = stage.status()
    if not st.read_only and st.sample_rate_hz != np.float32(bench.rate):
        code_of(lambda: stage.set_sample_rate(bench.rate))
    clear_error(stage)


@contextmanager
def rate(bench: Bench, hz: float) -> Iterator[None]:
    """The device clocked at ``hz`` for the block, at the profile's rate after it."""
    bench.stage.safe_state()
    bench.stage.set_sample_rate(hz)
    try:
        yield
    finally:
        bench.stage.safe_state()
        bench.stage.set_sample_rate(bench.rate)


def write_blocks(stage: StageBase, first: int, v: NDArray[np.float64]) -> list[Stamp]:
    """Samples ``first ..`` in the link's largest blocks; the bracket of each write."""
    stamps = []
    for off in range(0, v.size, stage.upload_chunk):
        block = v[off:off + stage.upload_chunk].astype(np.float32)
        _, s = stamped(lambda off=off, block=block: stage._write_chunk(first + off, block))
        stamps.append(s)
    return stamps


def load(stage: StageBase, v: NDArray[np.float64]) -> None:
    """A new table holding ``v``."""
    stage._set_table_length(v.size)
    write_blocks(stage, 0, v)


def records_command(stage: StageBase) -> bool:
    """Whether the device declares that its recorder holds the command (§2.3(e))."""
    if isinstance(stage, SerialStage):
        fields = stage.identify().split(",")
        return len(fields) == 4 and fields[1].endswith(VREC_COMMAND)
    if isinstance(stage, ModbusStage):
        bits = stage._request("read_input_registers", rm.IR.STATUS, count=1)[0]
        return bool(bits & rm.StatusBit.RECORDS_COMMAND)
    return False


# -- waveforms, polls and timing judgements shared by the checks ----------------------------------
f32 = np.float32


def same32(a: float, b: float) -> bool:
    """Whether two voltages are the same float32 (a serial reply carries 9 digits, §3.3(d))."""
    return bool(f32(a) == f32(b))


def triangle(bench: Bench, rate_hz: float, end_v: float = 0.0) -> NDArray[np.float64]:
    """One triangle between 0 V and the bound at ``rate_hz``: from its first step up to the bound
    and down to ``end_v`` (at most 0.9 slew steps from 0 V, so periods tile and wrap within the
    slew limit; consecutive samples differ)."""
    up = bench.ramp(bench.top, rate_hz)
    return np.concatenate([up, up[::-1][1:], [end_v]])


def stream_wave(bench: Bench, n: int, rate_hz: float) -> NDArray[np.float64]:
    """``n`` samples of triangles (:func:`triangle`), cut at ``n`` (for a stream: never wrapped)."""
    return np.resize(triangle(bench, rate_hz), n)


def table_wave(bench: Bench, n_max: int, rate_hz: float, end_v: float = 0.0) -> NDArray[np.float64]:
    """Whole triangles, at most ``n_max`` samples (at least one period): a table that may be
    played for several cycles."""
    period = triangle(bench, rate_hz, end_v)
    return np.tile(period, max(1, n_max // period.size))


def wait_idle(stage: StageBase, timeout_s: float) -> tuple[Status, Stamp]:
    """Poll until the generator stops: its status and the bracket of the poll that saw it."""
    t_end = time.monotonic() + timeout_s
    while True:
        st, poll = stamped(stage.status)
        if not st.running:
            return st, poll
        expect(poll.sent < t_end, "§2.2(d)", f"still running {timeout_s:g} s later")
        time.sleep(0.005)


def settled_position(stage: StageBase) -> Status:
    """The status once the play position has stopped moving (the recorder latency, §2.2(c))."""
    time.sleep(2 * LATENCY_S)
    st = stage.status()
    for _ in range(20):
        time.sleep(LATENCY_S)
        again = stage.status()
        if again.play_position == st.play_position:
            return again
        st = again
    return st


def position_within(p: int, poll: Stamp, start: Stamp, n: int, dt: float, late: str) -> None:
    """§2.2(a), (c): the position at a poll lies between the samples that can have been played
    and recorded (start at most dt + 10 ms after the start's reply, 10 ms recorder latency) and
    those that can have been played since the start was sent (§2.2(a)). ``late`` labels a
    position behind."""
    most = math.floor((poll.done - start.sent) / dt) + 1
    expect(p <= min(n, most), "§2.2(a)", f"position {p} when at most {min(n, most)} samples can have "
                                     f"been played since the start was sent (faster than dt)")
    least = math.floor((poll.sent - start.done - dt - 2 * LATENCY_S) / dt) - 1
    expect(p >= min(n, least), late,
           f"position {p} when at least {min(n, least)} samples were due "
           f"{(poll.sent - start.done) * 1000:.1f} ms after the start was answered (more than "
           f"dt + 10 ms start slack + 10 ms recorder latency behind the clock)")


def late_or_fail(label: str, proven: bool, message: str, late: str) -> None:
    """Fail with ``label`` when the brackets prove the device wrong, else the host fell behind."""
    expect(not proven, label, message)
    raise HostLate(late)


#: (clause, title, check, changes the output or table) in the document's order; filled by
#: :func:`_clauses` from the check modules.
CLAUSES: tuple[tuple[str, str, Callable[[Bench], str], bool], ...]


def _clauses() -> tuple[tuple[str, str, Callable[[Bench], str], bool], ...]:
    from afmctl.drivers import conformance_channels as channels
    from afmctl.drivers import conformance_device as dev
    from afmctl.drivers import conformance_wire as wire
    return dev.CLAUSES + channels.CLAUSES + wire.CLAUSES


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


def bench_for(stage: StageBase, profile: Profile, max_voltage: float | None = None) -> Bench:
    """The bench: the profile's bounds within the device's own limits (``LIM?``)."""
    lo, hi = bounds(profile, max_voltage)
    v_min, v_max, slew = stage.limits()
    return Bench(stage, profile, max(lo, v_min), min(hi, v_max), v_min, v_max, slew,
                 records_command(stage))


def run_clause(bench: Bench, check: Callable[[Bench], str]) -> tuple[bool | None, str, str, bool]:
    """One check, repeated while the host falls behind: ``(passed, detail, label, host_late)``."""
    late = ""
    for _ in range(ATTEMPTS):
        try:
            return True, check(bench), "", False
        except NotApplicable as exc:
            return None, str(exc), "", False
        except HostLate as exc:
            late = str(exc)
        except Failure as exc:
            return False, str(exc), exc.label, False
        except (StageError, TimeoutError, ValueError) as exc:
            return False, str(exc), "", False
        finally:
            to_zero(bench)
    return None, f"host fell behind ({ATTEMPTS} attempts): {late}", "", True


def run(stage: StageBase, profile: Profile, max_voltage: float | None = None,
        progress: Callable[[str], None] | None = None,
        only: Collection[str] | None = None) -> list[Result]:
    """Every clause (or those named in ``only``) against ``stage``, left idle at 0 V after each;
    one :class:`Result` each."""
    bench = bench_for(stage, profile, max_voltage)
    results = []
    read_only = stage.status().read_only
    to_zero(bench)
    for clause, title, check, writes in _clauses():
        if only is not None and clause not in only:
            continue
        if progress is not None:
            progress(f"{clause} {title}")
        if writes and read_only:
            results.append(Result(clause, title, None, "the device is read-only"))
            continue
        passed, detail, label, late = run_clause(bench, check)
        results.append(Result(clause, title, passed, detail, label, late))
    return results


def __getattr__(name: str) -> object:
    """``CLAUSES`` and the checks by name (``check_limits``), from the check modules."""
    if name == "CLAUSES":
        return _clauses()
    from afmctl.drivers import conformance_channels as channels
    from afmctl.drivers import conformance_device as dev
    from afmctl.drivers import conformance_timed as timed
    from afmctl.drivers import conformance_wire as wire
    for module in (dev, timed, wire, channels):
        if hasattr(module, name):
            return getattr(module, name)
    raise AttributeError(name)
