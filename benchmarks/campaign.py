"""A safety campaign against the emulated device: random waveforms, wire faults, watchdog trials.

Used by ``benchmarks/bench_safety.py`` (thousands of trials) and by the tests (a few hundred).
Each *waveform trial* draws a random waveform from the stage's present output: a good one (random
walk within the limits) or a bad one (over the voltage range, a step over the slew limit, a step
in from the present output, a non-finite sample). The host's guard must refuse every bad one; the
bad one is then sent anyway through the low-level primitives (upload + start), which the device
must refuse too; a good one is played with :meth:`~afmctl.drivers.StageBase.play`. Trials run in-process
(no wire, a device clock that advances by :data:`FAKE_TICK_S` per call, so they are fast) and over
each real wire (serial protocol on a socket and a pty, Modbus TCP, Modbus RTU) with wire faults
injected by the servers. Counted over every trial:

- ``out_of_limit``: samples in the devices' applied logs (every commanded sample that reached the
  stack) outside the voltage range or stepping more than the slew limit allows;
- ``hangs``: calls that ended later than their bound + 1 s (the bound of a play: its timeout,
  plus one request's timeout and the safe state's retries, see :func:`call_bound_s`);
- ``lost``: samples of a played waveform neither received nor flagged missing (``on_block`` must
  hand over every sample exactly once, whatever happened);
- ``wrong``: samples received as valid that differ from what the device recorded (a corrupted
  reply taken for data);
- ``guard_misses``: bad waveforms the host's guard let through, good ones it refused.

*Watchdog trials* (real time, over Modbus TCP or the serial protocol): the host brings the output to
a random voltage (idle, or while a run plays), arms a watchdog of random period, then goes silent
(closes its link). An observer notes when the device's output reached 0 V; the trial passes if the
output (with the ramp's own duration) was 0 V within one watchdog period after it ran out.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from afmctl import guard
from afmctl.drivers import StageBase
from afmctl.drivers.device.emulated import EmulatedDevice
from afmctl.drivers.device.emulator import Emulator, ramp_to_zero
from afmctl.drivers.device.modbus_server import ModbusRtuServer, ModbusTcpServer
from afmctl.drivers.device.serial_server import SerialServer
from afmctl.drivers.inprocess import InProcessStage
from afmctl.drivers.modbus_link import ModbusStage
from afmctl.drivers.player import Player
from afmctl.drivers.serial_link import SerialStage
from afmctl.errors import LinkCapacityError, StageError
from afmctl.files.profile import ModbusRtuTransport, ModbusTcpTransport, Profile, WireFaults

WIRES = ("serial-socket", "serial-pty", "modbus-tcp", "modbus-rtu")
BAD_KINDS = ("over_voltage", "over_slew", "step_in", "not_finite")
#: Device time that passes per call into the in-process device, s.
FAKE_TICK_S = 0.002
#: Per-request timeout of the hosts on faulty wires, s.
WIRE_TIMEOUT_S = 0.15
#: Faults per reply on each wire. RTU has no transaction id, so its delays stay below the timeout
#: (a reply later than that could be taken for the next one: see docs/reference/protocol.md).
WIRE_FAULTS = {
    "serial-socket": WireFaults(0.02, 0.02, 0.02, 0.01, 0.02, delay_s=0.2, seed=1),
    "serial-pty": WireFaults(0.02, 0.02, 0.02, 0.01, 0.02, delay_s=0.2, seed=2),
    "modbus-tcp": WireFaults(0.02, 0.02, 0.02, 0.01, 0.02, delay_s=0.2, seed=3),
    "modbus-rtu": WireFaults(0.02, 0.02, 0.02, 0.01, 0.02, delay_s=0.05, seed=4),
}

Progress = Callable[[str], None]


@dataclass
class Tally:
    """What a campaign counted (see the module docstring)."""

    trials: int = 0
    good: int = 0
    bad: int = 0
    refused_by_host: int = 0
    refused_by_device: int = 0
    refusal_unconfirmed: int = 0
    played_ok: int = 0
    played_failed: int = 0
    link_refused: int = 0
    out_of_limit: int = 0
    hangs: int = 0
    lost: int = 0
    wrong: int = 0
    guard_misses: int = 0
    samples_sent: int = 0
    samples_received: int = 0
    samples_missing: int = 0
    retries: int = 0
    faults: Counter[str] = field(default_factory=Counter)
    longest_overrun_s: float = -math.inf
    watchdog_trials: int = 0
    watchdog_ok: int = 0
    watchdog_worst_fraction: float = 0.0

    def merge(self, other: Tally) -> None:
        """Add ``other``'s counts to this one."""
        for k, v in vars(other).items():
            if k == "longest_overrun_s" or k == "watchdog_worst_fraction":
                setattr(self, k, max(getattr(self, k), v))
            elif k == "faults":
                self.faults.update(v)
            else:
                setattr(self, k, getattr(self, k) + v)

    def as_dict(self) -> dict[str, object]:
        out = {k: v for k, v in vars(self).items() if k != "faults"}
        out["faults_injected"] = sum(self.faults.values())
        out["faults_by_kind"] = dict(self.faults)
        return out


# -- waveforms ------------------------------------------------------------------------------------
def _walk(rng: np.random.Generator, start_v: float, n: int, step_v: float,
          limits: guard.Limits) -> NDArray[np.float64]:
    """A random walk from ``start_v`` with steps below ``step_v``, inside 99 % of the range."""
    steps = rng.uniform(-0.95, 0.95, n) * step_v * rng.uniform(0.05, 1.0)
    return np.clip(start_v + np.cumsum(steps), 0.99 * limits.v_min, 0.99 * limits.v_max)


def random_waveform(rng: np.random.Generator, start_v: float, limits: guard.Limits,
                    rate_hz: float) -> tuple[str, NDArray[np.float64]]:
    """(kind, voltages V): ``"good"`` (about 3 in 5) or one of :data:`BAD_KINDS`."""
    step = limits.max_rate_v_per_ms * 1e3 / rate_hz
    n = int(rng.integers(20, 600))
    v = _walk(rng, start_v, n, step, limits)
    kind = "good" if rng.random() < 0.6 else str(rng.choice(BAD_KINDS))
    i = int(rng.integers(1, n))
    if kind == "over_voltage":  # a slew-safe ramp to just beyond one end of the range
        end = (limits.v_max + rng.uniform(1e-3, 10.0) if rng.random() < 0.5
               else limits.v_min - rng.uniform(1e-3, 10.0))
        v = np.linspace(start_v, end, math.ceil(abs(end - start_v) / (0.9 * step)) + 1)[1:]
    elif kind == "over_slew":  # step i becomes a jump toward 0 V of 1.01-3 times the limit
        v[i:] += -math.copysign(step * rng.uniform(1.01, 3.0), v[i]) - (v[i] - v[i - 1])
    elif kind == "step_in":  # the same for the step in from the present output
        v += -math.copysign(step * rng.uniform(1.01, 3.0), start_v or 1.0) - (v[0] - start_v)
    elif kind == "not_finite":
        v[i] = rng.choice([np.nan, np.inf, -np.inf])
    return kind, v


def applied_violations(log: NDArray[np.float64], limits: guard.Limits, rate_hz: float) -> int:
    """Samples of an applied log (from power-on at 0 V) outside the range or over the slew."""
    v = np.concatenate([[0.0], log])
    outside = ~np.isfinite(v) | (v < limits.v_min) | (v > limits.v_max)
    steep = ~(np.abs(np.diff(v)) <= limits.max_step_v(rate_hz) * (1 + 1e-6))  # NaN counts
    return int(outside.sum() + steep.sum())


def call_bound_s(stage: StageBase, timeout_s: float) -> float:
    """Longest a :meth:`StageBase.play` with ``timeout_s`` may take by its own timeouts: the two
    queries before its deadline is set (the guard's output voltage, the capacities), the timeout,
    then the one request in flight and the safe state's attempts. Each attempt may take the
    request timeout plus a resync (a pause and a reconnect within the timeout)."""
    per_attempt = 2 * getattr(stage, "timeout_s", 0.0) + 0.05
    return timeout_s + (3 * stage.attempts + 1) * per_attempt


# -- one trial ------------------------------------------------------------------------------------
class _Blocks:
    """An ``on_block`` that checks the blocks are in order, contiguous and never overlap."""

    def __init__(self, n: int) -> None:
        self.next = 0
        self.broken = False
        self.volt = np.full(n, np.nan)
        self.disp = np.full(n, np.nan)
        self.valid = np.zeros(n, dtype=bool)

    def __call__(self, first: int, volt: NDArray[np.float64], disp: NDArray[np.float64],
                 valid: NDArray[np.bool_]) -> None:
        self.broken |= first != self.next
        sl = slice(first, first + len(disp))
        self.volt[sl], self.disp[sl], self.valid[sl] = volt, disp, valid
        self.next = max(self.next, sl.stop)


@dataclass
class Bench:
    """A stage and the emulated device behind it, for trials."""

    stage: StageBase
    device: Emulator
    lock: threading.Lock
    clock: Callable[[], float]

    def recorded(self, n: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """What the device's recorder holds for samples 0 .. n-1 of its last run."""
        with self.lock:
            return self.device.read_recorder(0, n, self.clock())


def trial(bench: Bench, rng: np.random.Generator, tally: Tally) -> None:
    """One waveform trial (see the module docstring); updates ``tally``."""
    stage, prof = bench.stage, bench.stage.profile
    tally.trials += 1
    try:
        start_v = stage.voltage()
    except StageError:
        tally.played_failed += 1
        return
    kind, v = random_waveform(rng, start_v, prof.limits, prof.sample_rate_hz)
    try:
        guard.check(v.astype(np.float32).astype(float), 1 / prof.sample_rate_hz, prof.limits,
                    start_v)
        refused = False
    except guard.LimitError:
        refused = True
    tally.guard_misses += refused == (kind == "good")
    if kind == "good":
        tally.good += 1
        _play(bench, v, tally)
    else:
        tally.bad += 1
        tally.refused_by_host += refused
        _bypass_guard(stage, v, tally)


def _play(bench: Bench, v: NDArray[np.float64], tally: Tally) -> None:
    stage, n = bench.stage, v.size
    blocks = _Blocks(n)
    timeout = n / stage.profile.sample_rate_hz + 2.0
    t0 = time.monotonic()
    try:
        stage.play(v, blocks, poll_s=0.0 if isinstance(stage, InProcessStage) else 0.002,
                   timeout_s=timeout)
        tally.played_ok += 1
    except LinkCapacityError:  # refused before it started: nothing sent, nothing to hand over
        tally.link_refused += 1
        return
    except (StageError, TimeoutError):
        tally.played_failed += 1
    overrun = time.monotonic() - t0 - call_bound_s(stage, timeout)
    tally.longest_overrun_s = max(tally.longest_overrun_s, overrun)
    tally.hangs += overrun > 1.0
    received, missing = int(blocks.valid.sum()), int((~blocks.valid[:blocks.next]).sum())
    tally.samples_sent += n
    tally.samples_received += received
    tally.samples_missing += missing
    tally.lost += n if blocks.broken else n - received - missing
    u, volt = bench.recorded(n)
    ok = blocks.valid
    tally.wrong += int((blocks.disp[ok].astype(np.float32) != u[ok]).sum()
                       + (blocks.volt[ok].astype(np.float32) != volt[ok]).sum())


def _bypass_guard(stage: StageBase, v: NDArray[np.float64], tally: Tally) -> None:
    """Play a bad waveform past the host's guard (the path of :meth:`StageBase.play` without its
    check); the device must refuse it: code 3 or 4 at upload, start, or (a steep step between
    streamed blocks) when it comes to play it."""
    try:
        Player(stage, v.astype(np.float32), None, 0.002).run(v.size / stage.profile.sample_rate_hz
                                                               + 2.0)
        tally.refusal_unconfirmed += 1
    except StageError as exc:
        if exc.code in (3, 4):
            tally.refused_by_device += 1
        else:
            tally.refusal_unconfirmed += 1
    except (TimeoutError, LinkCapacityError):
        tally.refusal_unconfirmed += 1
    finally:
        stage._deadline = None
    _stop_if_running(stage)


def _stop_if_running(stage: StageBase) -> None:
    """Safe state if the stage is running (a start that was not refused must not play on)."""
    try:
        if stage.status().running:
            stage.safe_state()
    except StageError:
        pass


# -- benches --------------------------------------------------------------------------------------
class FakeClock:
    """Device time that advances by ``tick`` s at every reading (thread-safe)."""

    def __init__(self, tick: float) -> None:
        self.t, self.tick, self._lock = 0.0, tick, threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            self.t += self.tick
            return self.t


@contextmanager
def bench_on(kind: str, profile: Profile, faults: WireFaults | None = None,
             timeout_s: float = WIRE_TIMEOUT_S) -> Iterator[tuple[Bench, EmulatedDevice | None]]:
    """A :class:`Bench` over ``kind`` (``"inprocess"`` or one of :data:`WIRES`), faults injected
    on the wire as given (default: :data:`WIRE_FAULTS`)."""
    with ExitStack() as stack:
        if kind == "inprocess":
            clock = FakeClock(FAKE_TICK_S)
            em, lock = Emulator(profile), threading.Lock()
            stage: StageBase = InProcessStage(profile, em, clock, lock)
            yield Bench(stage, em, lock, clock), None
            return
        dev = stack.enter_context(EmulatedDevice(
            profile, faults=WIRE_FAULTS[kind] if faults is None else faults))
        if kind == "modbus-tcp":
            port = stack.enter_context(ModbusTcpServer(dev)).port
            stage = ModbusStage(profile, ModbusTcpTransport("127.0.0.1", port,
                                                            timeout_s=timeout_s))
        elif kind == "modbus-rtu":
            url = stack.enter_context(ModbusRtuServer(dev, baudrate=921_600)).url
            stage = ModbusStage(profile, ModbusRtuTransport(url, baudrate=921_600,
                                                            timeout_s=timeout_s))
        else:
            where = "pty" if kind == "serial-pty" else "socket://127.0.0.1:0"
            url = stack.enter_context(SerialServer(dev, where)).url
            stage = SerialStage(profile, url, timeout_s=timeout_s)
        stack.enter_context(stage)
        yield Bench(stage, dev.emulator, dev.lock, dev.clock), dev


def waveform_trials(kind: str, profile: Profile, n: int, seed: int, tally: Tally,
                    progress: Progress | None = None) -> None:
    """``n`` waveform trials over ``kind``; adds the device's applied-log violations, the host's
    retries and the faults injected to ``tally``."""
    rng = np.random.default_rng(seed)
    with bench_on(kind, profile) as (bench, dev):
        for i in range(n):
            trial(bench, rng, tally)
            if progress is not None and (i + 1) % max(1, n // 5) == 0:
                progress(f"{kind}: {i + 1}/{n} trials, {tally.hangs} hangs, {tally.lost} lost")
        with bench.lock:
            log = bench.device.applied_log(bench.clock())
        tally.out_of_limit += applied_violations(log, profile.limits, profile.sample_rate_hz)
        tally.retries += bench.stage.retries
        if dev is not None:
            tally.faults.update(dev.faults.counts)


# -- watchdog ---------------------------------------------------------------------------------------
class _ZeroObserver(threading.Thread):
    """Notes (every ms, without touching the device) when its output first reads 0 V."""

    def __init__(self, em: Emulator, until: float) -> None:
        super().__init__(name="zero-observer", daemon=True)
        self.em, self.until, self.zero_at = em, until, math.inf
        self.start()

    def run(self) -> None:
        while time.monotonic() < self.until:
            if self.em.output_v == 0.0:
                self.zero_at = time.monotonic()
                return
            time.sleep(0.001)

    def join(self, timeout: float | None = None) -> float:  # type: ignore[override]
        super().join(timeout)
        return self.zero_at


def watchdog_trial(kind: str, profile: Profile, rng: np.random.Generator, tally: Tally) -> None:
    """One watchdog trial (see the module docstring) on a fresh device over ``kind``."""
    period = float(rng.uniform(0.05, 0.3))
    target = float(rng.uniform(0.2, 0.95) * profile.limits.v_max * rng.choice([-1, 1]))
    running = bool(rng.random() < 0.5)
    with bench_on(kind, profile, faults=WireFaults(), timeout_s=2.0) as (bench, dev):
        assert dev is not None
        stage, em = bench.stage, bench.device
        step = 0.9 * profile.limits.max_step_v(profile.sample_rate_hz)
        ramp = np.linspace(0.0, target, math.ceil(abs(target) / step) + 1)[1:]
        wave = np.concatenate([ramp, np.full(int(profile.sample_rate_hz), target)])
        if running:
            stage.upload(wave)
            stage.run(1)
        else:
            stage.play(ramp)
        stage.set_watchdog(period)
        stage.heartbeat()
        observer = _ZeroObserver(em, em.last_heartbeat + 3 * period)
        stage.close()  # the link is lost: no more heartbeats
        zero_at = observer.join()
        held = em.output_v
        expired = em.expired
    ramp_s = ramp_to_zero(target, profile.limits, profile.sample_rate_hz).size / \
        profile.sample_rate_hz
    late = zero_at + ramp_s - (em.last_heartbeat + period)
    tally.watchdog_trials += 1
    ok = held == 0.0 and expired and late <= period
    tally.watchdog_ok += ok
    tally.watchdog_worst_fraction = max(tally.watchdog_worst_fraction, late / period)


def watchdog_trials(profile: Profile, n: int, seed: int, tally: Tally,
                    progress: Progress | None = None) -> None:
    rng = np.random.default_rng(seed)
    for i in range(n):
        watchdog_trial(("modbus-tcp", "serial-socket")[i % 2], profile, rng, tally)
        if progress is not None and (i + 1) % max(1, n // 5) == 0:
            progress(f"watchdog: {tally.watchdog_ok}/{tally.watchdog_trials} ok")


def small_table(profile: Profile, samples: int) -> Profile:
    """The profile with a table of ``samples``, so that longer waveforms stream."""
    assert profile.emulator is not None
    return replace(profile, emulator=replace(profile.emulator, table_capacity=samples))


def campaign(inprocess: int, per_wire: int, watchdog: int, seed: int = 0,
             progress: Progress | None = None, wires: tuple[str, ...] = WIRES) -> Tally:
    """The whole campaign: ``inprocess`` trials without a wire (256-sample table: most stream),
    ``per_wire`` trials over each of ``wires`` with faults (512-sample table; the wires run in
    parallel threads, each with its own device), ``watchdog`` watchdog trials, on the shipped
    emulated profile."""
    from concurrent.futures import ThreadPoolExecutor

    from afmctl.files.profile import default_profile

    prof, tally = default_profile(), Tally()

    def on(kind: str, n: int, seed_k: int) -> Tally:
        part = Tally()
        table = 256 if kind == "inprocess" else 512
        waveform_trials(kind, small_table(prof, table), n, seed_k, part, progress)
        return part

    with ThreadPoolExecutor(len(wires) + 1) as pool:
        jobs = [pool.submit(on, "inprocess", inprocess, seed)]
        jobs += [pool.submit(on, kind, per_wire, seed + 1 + i) for i, kind in enumerate(wires)]
        for job in jobs:
            tally.merge(job.result())
    watchdog_trials(prof, watchdog, seed + 99, tally, progress)
    return tally
