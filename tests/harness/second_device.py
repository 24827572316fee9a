"""A second stage device, written from ``docs/reference/protocol.md`` (version 5) alone: no afmctl import.

Served by :class:`~tests.harness.second_server.SecondStage` on ``socket://127.0.0.1:PORT`` (one
connection at a time, like a serial-to-Ethernet adapter), it keeps its own clock: a ticker thread
looks at its watchdog every 2 ms, so it acts with no command arriving. Its plant (:class:`Plant`)
is its own: an amplifier with an optional first-order lag and gain error, whose mean output over
each sample is what the recorder holds (§2.3(b)), driving a stack with play (backlash) hysteresis
read by a noisy gauge.
Another plant can be plugged in (``plant=``: ``idle``, ``play`` and ``start_run``).

Variants (keyword arguments of :class:`Device`): ``lag_hz`` (amplifier bandwidth), ``gain``,
``read_only``, ``records_command`` (the DAQ records the command and says so in ``*IDN?``),
``latency_s`` (a recorder written after the clock: the position trails it, §2.3(c)), limits and
capacities, and ``defect``: one deliberately broken behaviour (:data:`DEFECTS`), so that tests can
show the conformance check catching it. ``commands`` logs ``(time, line)`` of every ``WDT``,
``HB``, ``WGO``, ``WGS`` and ``SAFE``.
"""

from __future__ import annotations

import math
import re
import threading
import time
import zlib
from fractions import Fraction

import numpy as np

MAX_LINE = 8192
MESSAGES = {1: "unknown command", 2: "bad argument", 3: "voltage outside limits",
            4: "slew limit exceeded", 5: "busy", 6: "index outside table or recorder",
            7: "read-only device", 8: "watchdog expired", 9: "waveform table incomplete",
            10: "stream underrun"}
FLOAT = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
INT = re.compile(r"[+-]?[0-9]+")
HEX8 = re.compile(r"[0-9a-fA-F]{8}")
TAG = re.compile(r"#[0-9]{1,9}")

#: One broken behaviour each, by the requirement it breaks (the docstring of each is in the
#: branch that implements it; ``tests/drivers/test_conformance_second.py`` names the label).
DEFECTS = (
    "limits-exclusive", "dc-no-slew-check", "output-is-measured", "rate-as-double",
    "chunk-steps-unchecked", "start-wrap-unchecked", "refused-chunk-stores-some",
    "incomplete-table-starts", "complete-after-stream", "wgo-plays-stale-slots", "clock-fast",
    "position-lags", "stop-reverts-output", "stop-ignored", "recorder-loses-entries",
    "fill-counts-held", "declares-command-records-output", "stream-window-lenient",
    "stream-plays-stale", "stream-slew-unchecked", "wgs-start-slew-unchecked", "safe-no-ramp",
    "watchdog-fed-by-queries", "watchdog-late", "watchdog-rearm-needs-wdt", "wdt-keeps-expired",
    "busy-sva-accepted", "error-cleared-by-success", "busy-before-bad-argument",
    "read-only-refuses-safe", "cr-ends-line", "overlong-accepted", "non-ascii-accepted",
    "tab-not-separator", "blank-line-answered", "bad-crc-answered", "tag-normalised",
    "crc-upper-refused", "reply-crc-upper", "nan-accepted", "int-takes-float", "hb-takes-args",
    "idn-three-fields", "status-out-of-order", "slow-replies", "limits-not-float32",
    "wtl-range-error-2", "recorder-not-cleared", "fault-no-ramp")


class Refused(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


def crc32(data: bytes) -> str:
    return f"{zlib.crc32(data):08x}"


def nearest_f32(text: str) -> float:
    """A decimal rounded to the nearest float32, ties to even (strtof)."""
    d = float(text)
    with np.errstate(over="ignore"):
        f = np.float32(d)
        if not np.isfinite(f) or float(f) == d:
            return float(f)
        lo, hi = sorted((f, np.nextafter(f, np.float32(math.copysign(np.inf, d - float(f))))))
    if not np.isfinite(hi):
        return float(lo)
    mid = (Fraction(float(lo)) + Fraction(float(hi))) / 2
    if abs(Fraction(d) - mid) > abs(mid) * Fraction(1, 10 ** 12):
        return float(f)  # far from a midpoint: the double's rounding is the decimal's
    exact = Fraction(text)
    if exact == mid:
        return float(lo if int(np.float32(lo).view(np.uint32)) % 2 == 0 else hi)
    return float(hi if exact > mid else lo)


class Plant:
    """Amplifier (gain, optional first-order lag ``lag_hz``) and stack (0.6 um/V with play
    hysteresis of ``width_um``), read by a gauge with ``noise_um`` of noise; in device time."""

    def __init__(self, lag_hz: float | None = None, gain: float = 1.0, width_um: float = 1.5,
                 noise_um: float = 0.005, seed: int = 3) -> None:
        self.tau = None if lag_hz is None else 1.0 / (2 * math.pi * lag_hz)
        self.gain, self.width, self.noise = gain, width_um, noise_um
        self.rng = np.random.default_rng(seed)
        self.amp = 0.0  # amplifier output, V
        self.x = 0.0    # stack displacement, um

    def _settle(self, v_end: float) -> None:
        target = 0.6 * v_end
        half = self.width / 2
        self.x = min(max(self.x, target - half), target + half)

    def _hold(self, v_cmd: float, seconds: float) -> float:
        """Hold ``v_cmd`` for ``seconds``: the mean output over it (the output moves on)."""
        u = self.gain * v_cmd
        if self.tau is None or seconds <= 0:
            self.amp = u
            return u
        a = math.exp(-seconds / self.tau)
        mean = u + (self.amp - u) * self.tau / seconds * (1 - a)
        self.amp = u + (self.amp - u) * a
        return mean

    def idle(self, v_cmd: float, seconds: float) -> None:
        self._hold(v_cmd, seconds)
        self._settle(self.amp)

    def start_run(self) -> None:
        pass

    def play(self, v_cmd: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Gauge reading at the start of each sample and the stack's mean voltage during it."""
        u = np.empty(v_cmd.size)
        mean = np.empty(v_cmd.size)
        for i, v in enumerate(v_cmd):
            u[i] = self.x + self.noise * self.rng.standard_normal()
            mean[i] = self._hold(float(v), dt)
            self._settle(self.amp)
        return u, mean


class Device:
    """The device: lines in, replies out, its own clock (``time.monotonic``)."""

    def __init__(self, *, lag_hz: float | None = None, gain: float = 1.0,
                 read_only: bool = False, records_command: bool = False, latency_s: float = 0.0,
                 v_min: float = 0.0, v_max: float = 150.0, slew: float = 50.0,
                 table: int = 16384, recorder: int = 65536, rate: float = 10_000.0,
                 defect: str | None = None, plant: Plant | None = None) -> None:
        assert defect is None or defect in DEFECTS, defect
        self.defect = defect
        self.lock = threading.RLock()
        if defect == "output-is-measured" and lag_hz is None:
            lag_hz = 66.0  # so that the measured output visibly differs from the command
        self.plant = plant or Plant(lag_hz, gain)
        self.read_only, self.records_command, self.latency = read_only, records_command, latency_s
        self.v_min, self.v_max, self.slew = (float(np.float32(x)) for x in (v_min, v_max, slew))
        self.table_cap, self.rec_cap = table, recorder
        self.rate = float(np.float32(rate))
        self.values = np.zeros(table)
        self.holds = np.full(table, -1, dtype=np.int64)  # the global index each slot holds
        self.length = 0
        self.rec = np.full((recorder, 2), np.nan)
        self.rec_k = np.full(recorder, -1, dtype=np.int64)
        self.out = 0.0       # the commanded output: what the DAC holds (§2.2(f))
        self.t_plant = time.monotonic()
        self.error = 0
        self.runs = 0
        self.run: dict | None = None
        self.period, self.armed, self.expired, self.last_beat = 0.0, False, False, 0.0
        self.commands: list[tuple[float, str]] = []
        self._cmd = ""
        self._now = 0.0

    # -- time ------------------------------------------------------------------------------------
    def step_limit(self) -> float:
        return self.slew * 1000.0 / self.rate * (1 + 1e-6)

    def clock(self) -> float:
        """Device time, s: never earlier than a time already acted on (call with the lock)."""
        t = time.monotonic()
        if self.defect == "clock-fast" and self.run:
            t = self.run["t0"] + (t - self.run["t0"]) * 1.2
        self._now = max(self._now, t)
        return self._now

    def advance(self, now: float) -> None:
        """Everything the device does by ``now``: the watchdog, then the run."""
        late = 0.03 if self.defect == "watchdog-late" else 0.0
        if self.armed and now > self.last_beat + self.period + late:
            when = self.last_beat + self.period + late
            self.play_until(when)
            self.halt()
            self.ramp(when)
            self.armed, self.expired, self.error = False, True, 8
        self.play_until(now)
        run = self.run
        if (run is None or not run["active"] or run["played"] >= run["n"]) and now > self.t_plant:
            self.plant.idle(self.dac(), now - self.t_plant)  # the output held while idle
            self.t_plant = now

    def dac(self) -> float:
        """What the DAC holds (what the plant sees while idle)."""
        return self.out

    def play_until(self, now: float) -> None:
        """Each sample is checked when its hold begins (a stale slot or a steep step in a stream
        stops the run there); the samples whose hold is complete go through the plant."""
        run = self.run
        if run is None or not run["active"]:
            return
        dt = 1.0 / run["rate"]
        elapsed = math.floor((now - run["t0"]) / dt + 1e-9)
        begun = min(run["n"], elapsed + 1)
        first = run["played"]
        ks = np.arange(first, max(first, begun))
        batch = self.batch(ks, run)
        fault, k = 0, begun
        if run["stream"]:
            for code, where in zip((10, 4), self.stream_faults(ks, batch, run), strict=True):
                if where.size and first + int(where[0]) < k:
                    fault, k = code, first + int(where[0])
        done = min(k, elapsed) - first  # holds complete: played
        if done > 0:
            v = batch[:done]
            u, mean = self.plant.play(v, dt)
            self.record(np.arange(first, first + done), v, u, mean)
            run["played"], run["last"] = first + done, self.hold(v[-1])
        if fault:
            return self.fault(run, k, fault)
        if k - first > done:
            self.hold(batch[done])  # the sample being held (§2.2(f))
        if run["played"] >= run["n"]:
            run["active"] = run["n"] > self.visible(now)  # running until the last is readable
            self.t_plant = run["t0"] + run["n"] * dt

    def batch(self, ks: np.ndarray, run: dict) -> np.ndarray:
        """The samples ``ks`` of the run."""
        return self.values[ks % self.length] if self.length else np.zeros(0)

    def stream_faults(self, ks: np.ndarray, batch: np.ndarray, run: dict
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Offsets into ``ks`` of stale slots (§2.4(d)) and of steps beyond the slew (§2.4(e))."""
        stale = np.flatnonzero(self.holds[ks % self.length] != ks)
        steep = np.flatnonzero(np.abs(np.diff(batch, prepend=run["last"])) > self.step_limit())
        if self.defect == "stream-plays-stale":
            stale = stale[:0]
        if self.defect == "stream-slew-unchecked":
            steep = steep[:0]
        return stale, steep

    def record(self, ks: np.ndarray, v: np.ndarray, u: np.ndarray, mean: np.ndarray) -> None:
        """The recorder's entries of the played samples ``ks``: reading and stack voltage."""
        stack = v if self.records_command else mean
        if self.defect == "declares-command-records-output":
            stack = mean + 0.01
        keep = ks % 997 != 996 if self.defect == "recorder-loses-entries" else ks >= 0
        self.rec[ks[keep] % self.rec_cap] = np.column_stack([u, stack])[keep]
        self.rec_k[ks[keep] % self.rec_cap] = ks[keep]

    def hold(self, sample: np.ndarray) -> float:
        """Put ``sample`` on the DAC (the output, §2.2(f)); returns it."""
        self.out = float(sample)
        return self.out

    def visible(self, now: float) -> int:
        """The play position: samples played and readable (§2.2(c))."""
        run = self.run
        if run is None:
            return 0
        lag = self.latency + (0.05 if self.defect == "position-lags" else 0.0)
        due = math.floor((now - run["t0"] - lag) * run["rate"] + 1e-9)
        return max(0, min(run["played"], due))

    def fault(self, run: dict, k: int, code: int) -> None:
        run["active"] = False
        self.t_plant = run["t0"] + k / run["rate"]
        if self.defect != "fault-no-ramp":
            self.ramp(self.t_plant)
        self.error = code

    def halt(self) -> None:
        run = self.run
        if run is not None and run["active"]:
            run["active"] = False
            self.t_plant = run["t0"] + run["played"] / run["rate"]
            if self.defect == "stop-reverts-output" and run["played"]:
                self.out = run["last"]

    def ramp(self, at: float) -> None:
        if self.defect == "safe-no-ramp":
            return
        step = 0.9 * self.slew * 1000.0 / self.rate
        n = math.ceil(abs(self.out) / step)
        if at > self.t_plant:
            self.plant.idle(self.out, at - self.t_plant)
        if n:
            self.plant.play(self.out * (1 - np.arange(1, n + 1) / n), 1.0 / self.rate)
        self.out = 0.0
        self.t_plant = max(at, self.t_plant) + n / self.rate

    def running(self, now: float) -> bool:
        run = self.run
        return run is not None and (run["active"] or (run["played"] >= run["n"] > self.visible(now)))

    # -- checks ----------------------------------------------------------------------------------
    def writable(self, now: float) -> None:
        if self.read_only:
            raise Refused(7)
        if self.running(now) and not (self.defect == "busy-sva-accepted" and self._cmd == "SVA"):
            raise Refused(5)

    def in_range(self, values: np.ndarray, previous: float | None) -> None:
        inside = (values >= self.v_min) & ((values < self.v_max) if
                                           self.defect == "limits-exclusive" else
                                           (values <= self.v_max))
        if not np.all(inside):
            raise Refused(3)
        seq = values if previous is None else np.concatenate(([previous], values))
        if seq.size > 1 and np.abs(np.diff(seq)).max() > self.step_limit():
            raise Refused(4)

    def complete(self, n: int) -> bool:
        if n == 0:
            return False
        if self.defect == "complete-after-stream":
            return bool((self.holds[:n] >= 0).all())
        return bool(np.array_equal(self.holds[:n], np.arange(n)))

    # -- commands --------------------------------------------------------------------------------
    def execute(self, words: list[str], now: float) -> str:
        cmd, args = words[0].upper(), words[1:]
        self._cmd = cmd
        if cmd in ("WDT", "HB", "WGO", "WGS", "SAFE"):
            self.commands.append((now, " ".join(words)))
        if self.defect == "watchdog-fed-by-queries" and cmd.endswith("?") and self.armed:
            self.last_beat = now
        queries = {"*IDN?": self.idn, "VER?": lambda: "3", "VOL?": lambda: num(self.output()),
                   "WTR?": lambda: num(self.rate), "WTL?": lambda: str(self.length),
                   "POS?": lambda: str(self.visible(now)),
                   "CAP?": lambda: f"{self.table_cap} {self.rec_cap}",
                   "DRL?": lambda: str(self.fill(now)),
                   "LIM?": self.limits,
                   "STA?": lambda: self.status(now), "ERR?": self.pop_error}
        if cmd in queries:
            if args:
                raise Refused(2)
            return queries[cmd]()
        handler = {"SVA": self.sva, "WTR": self.wtr, "WTL": self.wtl, "WAV": self.wav,
                   "WGO": self.wgo, "WGS": self.wgs, "DRR?": self.drr, "SAFE": self.safe,
                   "HB": self.hb, "WDT": self.wdt}.get(cmd)
        if handler is None:
            raise Refused(1)
        if cmd in ("SAFE", "HB") and args and self.defect != "hb-takes-args":
            raise Refused(2)
        return handler(args, now)

    def idn(self) -> str:
        model = "second-stage" + (";vrec=command" if self.records_command or
                                  self.defect == "declares-command-records-output" else "")
        return f"second,{model},2" if self.defect == "idn-three-fields" else \
            f"second,{model},2,fw-5"

    def limits(self) -> str:
        slew = f"{self.slew + 1e-5:.9g}" if self.defect == "limits-not-float32" else num(self.slew)
        return f"{num(self.v_min)} {num(self.v_max)} {slew}"

    def fill(self, now: float) -> int:
        held = self.defect == "fill-counts-held" and self.run is not None
        return min(self.visible(now) + held, self.rec_cap)

    def output(self) -> float:
        if self.defect == "output-is-measured":
            return self.plant.amp
        return self.out

    def status(self, now: float) -> str:
        run = self.run
        fields = [("running", int(self.running(now))),
                  ("fill", self.fill(now)), ("error", self.error),
                  ("out", num(self.output())), ("runs", self.runs), ("len", self.length),
                  ("complete", int(self.complete(self.length))), ("wd", int(self.armed)),
                  ("expired", int(self.expired)), ("ro", int(self.read_only)),
                  ("rate", num(self.rate)), ("pos", self.visible(now)),
                  ("total", run["n"] if run else 0), ("wdt", num(self.period))]
        if self.defect == "status-out-of-order":
            fields[0], fields[1] = fields[1], fields[0]
        return " ".join(f"{k}={v}" for k, v in fields)

    def pop_error(self) -> str:
        code, self.error = self.error, 0
        return str(code)

    def sva(self, args: list[str], now: float) -> str:
        v = floats(args, 1, self.defect)[0]
        self.writable(now)
        self.in_range(np.array([v]), None if self.defect == "dc-no-slew-check" else self.out)
        self.out = v
        return "OK"

    def wtr(self, args: list[str], now: float) -> str:
        hz = float(args[0]) if self.defect == "rate-as-double" and len(args) == 1 and \
            FLOAT.fullmatch(args[0]) else floats(args, 1, self.defect)[0]
        if self.defect == "busy-before-bad-argument" and self.running(now):
            raise Refused(5)
        if not 100.0 <= hz <= 100_000.0:
            raise Refused(2)
        self.writable(now)
        self.rate = hz
        return "OK"

    def wtl(self, args: list[str], now: float) -> str:
        n = ints(args, 1, self.defect)[0]
        self.writable(now)
        if not 1 <= n <= self.table_cap:
            raise Refused(2 if self.defect == "wtl-range-error-2" else 6)
        self.length = n
        self.holds[:] = -1
        return "OK"

    def wav(self, args: list[str], now: float) -> str:
        first, n = ints(args[:2], 2, self.defect)
        if not 1 <= n <= 256 or len(args) != n + 2:
            raise Refused(2)
        values = np.array(floats(args[2:], n, self.defect))
        if self.read_only:
            raise Refused(7)
        run = self.run
        streaming = run is not None and run["active"] and run["stream"]
        if self.running(now) and not streaming:
            raise Refused(5)
        lenient = self.defect == "stream-window-lenient" and streaming
        total, pos = (run["n"], self.visible(now)) if streaming else (self.length, 0)
        if first < 0 or first + n > total or (first + n > pos + self.length and not lenient):
            raise Refused(6)
        if self.defect == "refused-chunk-stores-some":
            ok = (values >= self.v_min) & (values <= self.v_max)
            bad = int(np.argmin(ok)) if not ok.all() else n
            self.store(first, values[:bad], run if streaming else None)
        if self.defect == "chunk-steps-unchecked":
            for v in values:
                self.in_range(np.array([v]), None)
        else:
            self.in_range(values, None)
        self.store(first, values, run if streaming else None)
        return "OK"

    def store(self, first: int, values: np.ndarray, run: dict | None) -> None:
        for i, v in enumerate(values):
            k = first + i
            if run is not None and k <= run["played"]:  # played or on the DAC: ignored
                continue
            self.values[k % self.length], self.holds[k % self.length] = v, k

    def begin(self, n: int, stream: bool, now: float) -> None:
        self.advance(now)
        self.plant.start_run()
        if self.defect != "recorder-not-cleared":
            self.rec[:] = np.nan
            self.rec_k[:] = -1
        self.runs += 1
        self.expired = self.expired and self.defect == "wdt-keeps-expired"
        self.run = {"t0": now, "n": n, "stream": stream, "played": 0, "active": True,
                    "rate": self.rate, "last": self.out}

    def start_check(self, count: int, wrap: bool) -> None:
        """A start's checks (§2.6(e)): the first ``count`` samples, from the output, and the
        wrap from the last to the first when ``wrap``."""
        table = self.values[:count]
        first = None if self.defect == "wgs-start-slew-unchecked" else self.out
        self.in_range(np.concatenate([table, table[:1]]) if wrap else table, first)

    def wgo(self, args: list[str], now: float) -> str:
        cycles = ints(args, 1, self.defect)[0]
        if cycles == 0:
            if self.defect != "stop-ignored":
                self.advance(now)
                self.halt()
            return "OK"
        self.writable(now)
        if cycles < 1 or max(self.length, 1) * cycles > self.rec_cap:
            raise Refused(6)
        stale_ok = self.defect == "wgo-plays-stale-slots" and (self.holds[:self.length] >= 0).all()
        if not (self.complete(self.length) or stale_ok or
                self.defect == "incomplete-table-starts" and self.length):
            raise Refused(9)
        self.start_check(self.length, cycles > 1 and self.defect != "start-wrap-unchecked")
        self.begin(self.length * cycles, False, now)
        return "OK"

    def wgs(self, args: list[str], now: float) -> str:
        n = ints(args, 1, self.defect)[0]
        self.writable(now)
        if not 1 <= n <= 1 << 29:
            raise Refused(6)
        need = min(self.length, n)
        if need == 0 or not self.complete(need):
            raise Refused(9)
        self.start_check(need, False)
        self.begin(n, True, now)
        return "OK"

    def drr(self, args: list[str], now: float) -> str:
        first, n = ints(args, 2, self.defect)
        if not 1 <= n <= 256:
            raise Refused(2)
        rec = self.recorder()
        if first < 0:
            raise Refused(6)
        seen = self.visible(now)
        words = [str(first), str(n)]
        for k in range(first, first + n):
            if (k < seen or self.defect == "recorder-not-cleared") and \
                    self.rec_k[k % self.rec_cap] == k:
                words += [num(x) for x in rec[k % self.rec_cap]]
            else:
                words += ["nan", "nan"]
        return " ".join(words)

    def recorder(self) -> np.ndarray:
        """The recorder ``DRR?`` reads: (capacity, 2) entries."""
        return self.rec

    def safe(self, args: list[str], now: float) -> str:
        if self.read_only and self.defect == "read-only-refuses-safe":
            raise Refused(7)
        self.advance(now)
        self.halt()
        self.ramp(now)
        return "OK"

    def hb(self, args: list[str], now: float) -> str:
        self.last_beat = now
        if not (self.expired and self.defect == "watchdog-rearm-needs-wdt"):
            self.armed = self.period > 0
        return "OK"

    def wdt(self, args: list[str], now: float) -> str:
        t = floats(args, 1, self.defect)[0]
        if not 0 <= t <= 3600:
            raise Refused(2)
        self.period, self.armed = t, False
        self.expired = self.expired and self.defect == "wdt-keeps-expired"
        return "OK"

    # -- lines -----------------------------------------------------------------------------------
    def line(self, raw: bytes) -> bytes | None:
        """One received line (its LF taken off) -> the reply line, or None."""
        upper = self.defect == "reply-crc-upper"
        if len(raw) > MAX_LINE and self.defect != "overlong-accepted":
            self.error = 2
            return frame(f"ERR 2 {MESSAGES[2]}", None, upper)
        if raw.endswith(b"\r"):
            raw = raw[:-1]
        body, tag = raw, None
        if len(raw) >= 10 and raw[-10:-8] == b" *" and HEX8.fullmatch(raw[-8:].decode("latin-1")):
            body = raw[:-10]
            check = raw[-8:].decode("latin-1")
            if self.defect == "crc-upper-refused" and check != check.lower():
                return None
            if crc32(body) != check.lower() and self.defect != "bad-crc-answered":
                return None
        text = body.decode("latin-1")
        words = re.split(r"[ \t]+" if self.defect != "tab-not-separator" else " ", text.strip(" \t"))
        if words and TAG.fullmatch(words[-1]):
            tag = words.pop()[1:]
            if self.defect == "tag-normalised":
                tag = str(int(tag))
        words = [w for w in words if w]
        if not words:
            return frame("OK", tag, upper) if self.defect == "blank-line-answered" else None
        printable = re.fullmatch(r"[\x20-\x7e\t]*", text) is not None
        with self.lock:
            now = self.clock()
            self.advance(now)
            try:
                if not printable and self.defect != "non-ascii-accepted":
                    raise Refused(2)
                reply = self.execute(words, now)
                if self.defect == "error-cleared-by-success":
                    self.error = 0 if words[0].upper() != "ERR?" else self.error
            except Refused as exc:
                self.error = exc.code
                reply = f"ERR {exc.code} {MESSAGES[exc.code]}"
        if self.defect == "slow-replies" and words[0].upper() == "VER?":
            time.sleep(0.015)
        return frame(reply, tag, upper)


def frame(payload: str, tag: str | None, upper: bool = False) -> bytes:
    body = (payload if tag is None else f"{payload} #{tag}").encode("latin-1")
    c = crc32(body)
    return body + b" *" + (c.upper() if upper else c).encode() + b"\n"


def num(x: float) -> str:
    return "nan" if x != x else f"{float(np.float32(x)):.9g}"


def parsed(args: list[str], n: int, pattern: re.Pattern[str], convert) -> list:  # noqa: ANN001
    if len(args) != n or not all(pattern.fullmatch(a) for a in args):
        raise Refused(2)
    return [convert(a) for a in args]


def floats(args: list[str], n: int, defect: str | None = None) -> list[float]:
    if defect == "nan-accepted" and len(args) == n and all(a.lower() == "nan" for a in args):
        return [math.nan] * n
    return parsed(args, n, FLOAT, nearest_f32)


def ints(args: list[str], n: int, defect: str | None = None) -> list[int]:
    if defect == "int-takes-float" and len(args) == n:
        try:
            return [int(float(a)) for a in args]
        except ValueError:
            raise Refused(2) from None
    return parsed(args, n, INT, int)
