"""A stage written from ``docs/protocol.md`` alone: not afmctl's emulator.

A unipolar 0-150 V amplifier and DAQ behind the serial protocol on ``socket://127.0.0.1:PORT``, the
way a serial-to-Ethernet adapter is reached. Its protocol side uses no afmctl or drivers code; its
physics is a foreign stage (:mod:`afmctl.drivers.device.foreign.stage`, a plant written independently of
afmctl's model: relay hysterons, RK4 rod, gauge noise), drawn with a fixed seed, evolving while
idle. The recorder's voltage is the command (this DAQ cannot measure the amplifier's output). Its
table holds 16,384 samples (1.6 s at 10 kHz) and its recorder 65,536, so long runs stream. It logs
the time of every ``WDT``, ``HB``, ``WGO``, ``WGS`` and ``SAFE`` it receives (``commands``), so
tests can see what a host does to it.
"""

from __future__ import annotations

import math
import socket
import threading
import time
import zlib

import numpy as np

from afmctl.drivers.device.foreign import stage as foreign
from afmctl.drivers.device.foreign.stages import random_stage

V_MIN, V_MAX, SLEW_V_PER_MS = 0.0, 150.0, 50.0
TABLE, RECORDER, MAX_LINE = 16384, 65536, 8192
MESSAGES = {1: "unknown command", 2: "bad argument", 3: "voltage outside limits",
            4: "slew limit exceeded", 5: "busy", 6: "index outside table or recorder",
            7: "read-only device", 8: "watchdog expired", 9: "waveform table incomplete",
            10: "stream underrun"}


class Refused(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


def crc(text: str) -> str:
    return f"{zlib.crc32(text.encode('ascii', 'replace')):08x}"


def f32(x: float) -> float:
    return float(np.float32(x))


def num(x: float) -> str:
    return "nan" if x != x else f"{f32(x):.9g}"


class Plant:
    """The foreign stage drawn from ``seed`` (drive range 0-150 V, displacement span 90 um), in
    device time."""

    def __init__(self, rate_hz: float, seed: int = 5) -> None:
        self.rng = np.random.default_rng(seed)
        self.stage = random_stage(self.rng, span_um=90.0)  # 0-90 um: 45 +- 13.5 um in reach
        self.state = foreign.initial_state(self.stage, "poled+")
        self.rate_hz = rate_hz
        self.t = time.monotonic()  # device time the plant has reached, s

    def play(self, v: np.ndarray) -> np.ndarray:
        """Gauge readings at each sample instant, um, while ``v`` (V) is held sample by sample."""
        _, reading, self.state = foreign.run(self.stage, v, self.rate_hz, self.state, self.rng)
        self.t += v.size / self.rate_hz
        return reading

    def start(self, now: float, held_v: float) -> None:
        """A run starts at ``now``: the plant idles at the held output until then."""
        if now > self.t:
            self.state = foreign.idle(self.stage, self.state, now - self.t, held_v)
        self.state = foreign.start_run(self.stage, self.state, self.rng)
        self.t = now


class Device:
    """The device: commands in, replies out, time from ``time.monotonic``."""

    def __init__(self, rate_hz: float = 10_000.0) -> None:
        self.lock = threading.Lock()
        self.rate = rate_hz
        self.plant = Plant(rate_hz)
        self.table = np.zeros(TABLE)
        self.slot = np.full(TABLE, -1)
        self.length = 0
        self.rec = np.full((RECORDER, 2), np.nan)
        self.rec_k = np.full(RECORDER, -1)
        self.out = 0.0
        self.error = 0
        self.runs = 0
        self.run: dict | None = None
        self.pos = self.total = 0
        self.wd_period, self.wd_armed, self.wd_expired, self.last_beat = 0.0, False, False, 0.0
        self.commands: list[tuple[float, str]] = []

    # -- time --------------------------------------------------------------------------------
    def advance(self, now: float) -> None:
        if self.wd_armed and now - self.last_beat > self.wd_period:
            self.play_until(self.last_beat + self.wd_period)
            self.run = None
            self.ramp()
            self.wd_armed, self.wd_expired, self.error = False, True, 8
        self.play_until(now)

    def play_until(self, now: float) -> None:
        run = self.run
        if run is None:
            return
        due = min(run["n"], math.floor((now - run["t0"]) * self.rate + 1e-9))
        k = np.arange(self.pos, max(self.pos, due))
        slots = k % self.length
        n, fault = k.size, 0
        if run["stream"]:
            stale = np.flatnonzero(self.slot[slots] != k)
            if stale.size:
                n, fault = int(stale[0]), 10
        v = self.table[slots[:n]]
        steep = np.flatnonzero(np.abs(np.diff(v, prepend=self.out))
                               > SLEW_V_PER_MS * 1000.0 / self.rate * (1 + 1e-6))
        if steep.size:
            n, fault = int(steep[0]), 4
        if n:
            self.rec[k[:n] % RECORDER] = np.column_stack([self.plant.play(v[:n]), v[:n]])
            self.rec_k[k[:n] % RECORDER] = k[:n]
            self.out = float(v[n - 1])
            self.pos += n
        if fault:
            self.fault(fault)
        elif self.pos >= run["n"]:
            self.run = None

    def fault(self, code: int) -> None:
        self.run = None
        self.ramp()
        self.error = code

    def ramp(self) -> None:
        step = 0.9 * SLEW_V_PER_MS * 1000.0 / self.rate
        ramp = np.linspace(self.out, 0.0, math.ceil(abs(self.out) / step) + 1)[1:]
        if ramp.size:
            self.plant.play(ramp)
        self.out = 0.0

    # -- commands ----------------------------------------------------------------------------
    def idle(self) -> None:
        if self.run is not None:
            raise Refused(5)

    def check(self, values: np.ndarray, previous: float | None) -> None:
        if not np.all((values >= V_MIN) & (values <= V_MAX)):
            raise Refused(3)
        seq = values if previous is None else np.concatenate(([previous], values))
        if seq.size > 1 and np.abs(np.diff(seq)).max() > SLEW_V_PER_MS * 1000 / self.rate * (1 + 1e-6):
            raise Refused(4)

    def execute(self, words: list[str], now: float) -> str:
        cmd, args = words[0].upper(), words[1:]
        if cmd in ("WDT", "HB", "WGO", "WGS", "SAFE"):
            self.commands.append((now, " ".join(words)))
        queries = {"*IDN?": lambda: "ind,stage-0-150,7,fw-1", "VER?": lambda: "3",
                   "VOL?": lambda: num(self.out), "WTR?": lambda: num(self.rate),
                   "WTL?": lambda: str(self.length), "POS?": lambda: str(self.pos),
                   "CAP?": lambda: f"{TABLE} {RECORDER}", "DRL?": lambda: str(min(self.pos, RECORDER)),
                   "LIM?": lambda: f"{num(V_MIN)} {num(V_MAX)} {num(SLEW_V_PER_MS)}",
                   "STA?": self.status, "ERR?": self.pop_error}
        if cmd in queries:
            if args:
                raise Refused(2)
            return queries[cmd]()
        handler = {"SVA": self.sva, "WTR": self.wtr, "WTL": self.wtl, "WAV": self.wav,
                   "WGO": self.wgo, "WGS": self.wgs, "DRR?": self.drr, "SAFE": self.safe,
                   "HB": self.hb, "WDT": self.wdt}.get(cmd)
        if handler is None:
            raise Refused(1)
        return handler(args, now)

    def status(self) -> str:
        complete = self.length > 0 and bool((self.slot[:self.length] >= 0).all())
        return (f"running={int(self.run is not None)} fill={min(self.pos, RECORDER)} "
                f"error={self.error} out={num(self.out)} runs={self.runs} len={self.length} "
                f"complete={int(complete)} wd={int(self.wd_armed)} expired={int(self.wd_expired)} "
                f"ro=0 rate={num(self.rate)} pos={self.pos} total={self.total} "
                f"wdt={num(self.wd_period)}")

    def pop_error(self) -> str:
        code, self.error = self.error, 0
        return str(code)

    def sva(self, args: list[str], now: float) -> str:
        v = f32(floats(args, 1)[0])
        self.idle()
        self.check(np.array([v]), self.out)
        self.plant.play(np.array([v]))
        self.out = v
        return "OK"

    def wtr(self, args: list[str], now: float) -> str:
        hz = floats(args, 1)[0]
        if not 100 <= hz <= 100_000:
            raise Refused(2)
        self.idle()
        self.rate = hz
        self.plant.rate_hz = hz
        return "OK"

    def wtl(self, args: list[str], now: float) -> str:
        n = ints(args, 1)[0]
        self.idle()
        if not 1 <= n <= TABLE:
            raise Refused(6)
        self.length = n
        self.slot[:] = -1
        return "OK"

    def wav(self, args: list[str], now: float) -> str:
        first, n = ints(args[:2], 2)
        if not 1 <= n <= 256 or len(args) != n + 2:
            raise Refused(2)
        values = np.array([f32(x) for x in floats(args[2:], n)])
        run = self.run
        if run is not None and not run["stream"]:
            raise Refused(5)
        total, pos = (run["n"], self.pos) if run else (self.length, 0)
        if first < 0 or first + n > total or first + n > pos + self.length:
            raise Refused(6)
        self.check(values, None)
        for i, v in enumerate(values):
            k = first + i
            if k >= pos:
                self.table[k % self.length], self.slot[k % self.length] = v, k
        return "OK"

    def start(self, n: int, stream: bool, need: int, now: float) -> None:
        if self.length == 0 or not np.array_equal(self.slot[:need], np.arange(need)):
            raise Refused(9)
        first = self.table[:need]
        wraps = not stream and n > need  # several cycles: the wrap to sample 0 is a step too
        self.check(np.concatenate([first, first[:1]]) if wraps else first, self.out)
        self.rec[:] = np.nan
        self.rec_k[:] = -1
        self.plant.start(now, self.out)
        self.pos, self.total, self.runs = 0, n, self.runs + 1
        self.wd_expired = False
        self.run = {"t0": now, "n": n, "stream": stream}

    def wgo(self, args: list[str], now: float) -> str:
        cycles = ints(args, 1)[0]
        if cycles == 0:
            self.run = None
            return "OK"
        self.idle()
        if cycles < 1 or max(self.length, 1) * cycles > RECORDER:
            raise Refused(6)
        self.start(self.length * cycles, False, self.length, now)
        return "OK"

    def wgs(self, args: list[str], now: float) -> str:
        n = ints(args, 1)[0]
        self.idle()
        if not 1 <= n <= 2 ** 29:
            raise Refused(6)
        self.start(n, True, min(self.length, n), now)
        return "OK"

    def drr(self, args: list[str], now: float) -> str:
        first, n = ints(args, 2)
        if not 1 <= n <= 256:
            raise Refused(2)
        if first < 0:
            raise Refused(6)
        k = np.arange(first, first + n)
        held = self.rec_k[k % RECORDER] == k
        pairs = np.where(held[:, None], self.rec[k % RECORDER], np.nan)
        return f"{first} {n} " + " ".join(f"{num(a)} {num(b)}" for a, b in pairs)

    def safe(self, args: list[str], now: float) -> str:
        self.run = None
        self.ramp()
        return "OK"

    def hb(self, args: list[str], now: float) -> str:
        self.last_beat = now
        self.wd_armed = self.wd_period > 0
        return "OK"

    def wdt(self, args: list[str], now: float) -> str:
        t = floats(args, 1)[0]
        if not 0 <= t <= 3600:
            raise Refused(2)
        self.wd_period, self.wd_armed, self.wd_expired = t, False, False
        return "OK"

    # -- lines -------------------------------------------------------------------------------
    def line(self, raw: bytes) -> str | None:
        if len(raw) > MAX_LINE:
            self.error = 2
            return framed(f"ERR 2 {MESSAGES[2]}", None)
        text = raw.decode("ascii", "replace").removesuffix("\r")
        body, sep, check = text.rpartition(" *")
        if not sep or len(check) != 8:
            body = text
        elif crc(body) != check:
            return None
        payload, sep, tag = body.rpartition(" #")
        if not (sep and tag.isdigit()):
            payload, tag = body, ""
        if not payload.strip():
            return None
        now = time.monotonic()
        with self.lock:
            self.advance(now)
            try:
                reply = self.execute(payload.split(), now)
            except Refused as exc:
                self.error = exc.code
                reply = f"ERR {exc.code} {MESSAGES[exc.code]}"
        return framed(reply, int(tag) if tag else None)


def framed(payload: str, tag: int | None) -> str:
    body = payload if tag is None else f"{payload} #{tag}"
    return f"{body} *{crc(body)}"


def parsed(args: list[str], n: int, kind: type) -> list:
    """``n`` arguments of type ``kind`` (error 2 if the count or a value is wrong)."""
    if len(args) != n:
        raise Refused(2)
    try:
        return [kind(a) for a in args]
    except ValueError:
        raise Refused(2) from None


def floats(args: list[str], n: int) -> list[float]:
    return parsed(args, n, float)


def ints(args: list[str], n: int) -> list[int]:
    return parsed(args, n, int)


class SocketStage:
    """The device on ``socket://127.0.0.1:PORT`` (``url``), one client at a time, with a 5 ms
    ticker for the watchdog. A context manager."""

    def __init__(self) -> None:
        self.device = Device()
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self.listener.getsockname()[1]}"
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self.serve, daemon=True),
                        threading.Thread(target=self.tick, daemon=True)]

    def tick(self) -> None:
        while not self.stop.wait(0.005):
            with self.device.lock:
                self.device.advance(time.monotonic())

    def serve(self) -> None:
        self.listener.settimeout(0.05)
        while not self.stop.is_set():
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            with conn:
                self.talk(conn)

    def talk(self, conn: socket.socket) -> None:
        conn.settimeout(0.05)
        buf, skipping = b"", False
        while not self.stop.is_set():
            try:
                data = conn.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                return
            buf += data
            while b"\n" in buf:
                raw, buf = buf.split(b"\n", 1)
                if skipping:
                    skipping = False
                    continue
                reply = self.device.line(raw)
                if reply is not None:
                    conn.sendall(reply.encode() + b"\n")
            if len(buf) > MAX_LINE and not skipping:
                buf, skipping = b"", True
                conn.sendall(self.device.line(b"x" * (MAX_LINE + 1)).encode() + b"\n")
            elif skipping:
                buf = b""

    def __enter__(self) -> SocketStage:
        for t in self.threads:
            t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        for t in self.threads:
            t.join()
        self.listener.close()
