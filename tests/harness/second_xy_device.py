"""A second device of several channels, written from ``docs/reference/protocol.md`` version 6
(§2.14, §3.6, §3.7) alone: no afmctl import.

It speaks serial protocol 4 (``VER?`` answers 4, ``CHN?`` its number of channels, the ``CH <c>``
prefix on ``SVA``, ``VOL?``, ``WAV``, ``DRR?`` and ``LIM?``) and keeps the line framing, number
grammar and the device's shared state (clock, generator, table length, watchdog, last error,
status) of the one-channel second device (:mod:`tests.harness.second_device`, from the same
document); what §2.14 makes per channel (output, DC set, limits, table slots, recorder, the ramp to
0 V) is its own. Served by :class:`SecondXYStage` on ``socket://127.0.0.1:PORT``, one connection at
a time, with the one-channel device's ticker (its watchdog acts while nobody talks).

Its plant is pluggable (``plant=``: ``idle(v (C,), seconds)``, ``play(v (n, C), dt) -> (raw
(n, C), stack_V (n, C))``, ``start_run()``); the default, :class:`CoupledPlant`, is one
play-hysteresis stack per channel with a static coupling between them. A plant that cannot
measure its amplifier's output records the command and the device declares it (``records_command``,
``;vrec=command`` in ``*IDN?``, §2.3(e)).
"""

from __future__ import annotations


import numpy as np

from tests.harness.second_device import INT, Device, Plant, Refused, floats, ints, num
from tests.harness.second_server import SecondStage

#: The per-channel commands of §3.6; every other command is the device's.
PER_CHANNEL = ("SVA", "VOL?", "WAV", "DRR?", "LIM?")
KNOWN = ("*IDN?", "VER?", "SVA", "VOL?", "WTR", "WTR?", "WTL", "WTL?", "WAV", "WGO", "WGS", "POS?",
         "CAP?", "DRL?", "DRR?", "STA?", "ERR?", "LIM?", "SAFE", "HB", "WDT", "CHN?", "CH")


class CoupledPlant:
    """One :class:`~tests.harness.second_device.Plant` per channel (no lag), and channel ``j``'s
    reading moved by ``coupling[i][j]`` um per um of channel ``i``'s stack."""

    def __init__(self, channels: int = 2, coupling: float = 0.02) -> None:
        self.stacks = [Plant(seed=3 + c) for c in range(channels)]
        self.coupling = coupling

    def start_run(self) -> None:
        pass

    def idle(self, v: np.ndarray, seconds: float) -> None:
        for p, vc in zip(self.stacks, v, strict=True):
            p.idle(float(vc), seconds)

    def play(self, v: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        u, mean = np.empty_like(v), np.empty_like(v)
        for c, p in enumerate(self.stacks):
            u[:, c], mean[:, c] = p.play(v[:, c], dt)
        own = u.copy()
        for c in range(v.shape[1]):
            u[:, c] += self.coupling * (own.sum(axis=1) - own[:, c])
        return u, mean


class XYDevice(Device):
    """A device of ``channels`` channels (§2.14); per-channel ``limits`` [(v_min, v_max, slew
    V/ms), ...] (the first also the one-channel keywords' defaults)."""

    def __init__(self, *, channels: int = 2, limits: list[tuple[float, float, float]] | None
                 = None, plant: object | None = None, records_command: bool = False,
                 **device: object) -> None:
        super().__init__(records_command=records_command, **device)  # type: ignore[arg-type]
        self.C = channels
        lim = limits or [(self.v_min, self.v_max, self.slew)] * channels
        self.lim = np.array([[float(np.float32(x)) for x in row] for row in lim])
        self.plant = plant or CoupledPlant(channels)  # type: ignore[assignment]
        self.outs = np.zeros(channels)
        self.values = np.zeros((channels, self.table_cap))
        self.holds = np.full((channels, self.table_cap), -1, dtype=np.int64)
        self.written = np.zeros(channels, dtype=bool)
        self.rec = np.full((channels, self.rec_cap, 2), np.nan)
        self._ch = 0

    # -- per-channel state: channel 0 is what the one-channel text calls "the output" ------------
    @property
    def out(self) -> float:  # type: ignore[override]
        return float(self.outs[0]) if hasattr(self, "outs") else 0.0

    @out.setter
    def out(self, v: float) -> None:
        if hasattr(self, "outs"):
            self.outs[0] = v

    def steps(self) -> np.ndarray:
        """Largest step per sample of each channel, V, with §2.6(d)'s tolerance."""
        return self.lim[:, 2] * 1000.0 / self.rate * (1 + 1e-6)

    def channel(self) -> int:
        """The channel the command names (§2.14(g): outside 0 … C-1 is error 6)."""
        if not 0 <= self._ch < self.C:
            raise Refused(6)
        return self._ch

    def dac(self) -> np.ndarray:  # type: ignore[override]
        return self.outs.copy()

    def batch(self, ks: np.ndarray, run: dict) -> np.ndarray:
        """Samples ``ks`` of every channel (n, C): a written channel's slots, a held one's output
        at the start (§2.14(c))."""
        out = np.tile(run["held"], (ks.size, 1))
        for c in np.flatnonzero(run["written"]):
            out[:, c] = self.values[c, ks % self.length]
        return out

    def stream_faults(self, ks: np.ndarray, batch: np.ndarray, run: dict
                      ) -> tuple[np.ndarray, np.ndarray]:
        """§2.14(h): a stale slot of any written channel, a step beyond any channel's slew."""
        cols = np.flatnonzero(run["written"])
        stale = np.flatnonzero((self.holds[cols][:, ks % self.length] != ks).any(axis=0))
        step = np.abs(np.diff(np.vstack([run["last"], batch]), axis=0))
        return stale, np.flatnonzero((step > self.steps()).any(axis=1))

    def record(self, ks: np.ndarray, v: np.ndarray, u: np.ndarray, mean: np.ndarray) -> None:
        stack = v if self.records_command else mean
        self.rec[:, ks % self.rec_cap, 0] = u.T
        self.rec[:, ks % self.rec_cap, 1] = stack.T
        self.rec_k[ks % self.rec_cap] = ks

    def hold(self, sample: np.ndarray) -> np.ndarray:  # type: ignore[override]
        self.outs[:] = sample
        return self.outs.copy()

    def ramp(self, at: float) -> None:
        """Every output to 0 V together, each at 90 % of its own slew, then 0 V until the longest
        ramp ends (§2.14(e))."""
        step = 0.9 * self.lim[:, 2] * 1000.0 / self.rate
        n = np.ceil(np.abs(self.outs) / step).astype(int)
        if at > self.t_plant:
            self.plant.idle(self.outs.copy(), at - self.t_plant)
        longest = int(n.max())
        if longest:
            i = np.arange(1, longest + 1)[:, None]
            frac = np.where(i < n[None, :], 1 - i / np.maximum(n, 1)[None, :], 0.0)
            self.plant.play(self.outs[None, :] * frac, 1.0 / self.rate)
        self.outs[:] = 0.0
        self.t_plant = max(at, self.t_plant) + longest / self.rate

    # -- checks ----------------------------------------------------------------------------------
    def check(self, c: int, values: np.ndarray, previous: float | None) -> None:
        """Channel ``c``'s range (3) and steps (4), from ``previous`` if given (§2.14(d))."""
        v_min, v_max, _ = self.lim[c]
        if not np.all((values >= v_min) & (values <= v_max)):
            raise Refused(3)
        seq = values if previous is None else np.concatenate(([previous], values))
        if seq.size > 1 and np.abs(np.diff(seq)).max() > self.steps()[c]:
            raise Refused(4)

    def complete(self, n: int) -> bool:
        """§2.14(c): ``n >= 1``, a channel written, every written channel's slots hold theirs."""
        if n == 0 or not self.written.any():
            return False
        want = np.arange(n)
        return all(np.array_equal(self.holds[c, :n], want) for c in np.flatnonzero(self.written))

    def start_check(self, count: int, wrap: bool) -> None:
        for c in np.flatnonzero(self.written):
            v = self.values[c, :count]
            self.check(int(c), np.concatenate([v, v[:1]]) if wrap else v, float(self.outs[c]))

    # -- commands --------------------------------------------------------------------------------
    def execute(self, words: list[str], now: float) -> str:
        cmd, args = words[0].upper(), words[1:]
        self._ch = 0
        if cmd == "CHN?":
            if args:
                raise Refused(2)
            return str(self.C)
        if cmd == "VER?":
            if args:
                raise Refused(2)
            return "4"
        if cmd != "CH":
            return super().execute(words, now)
        if len(args) < 2 or not INT.fullmatch(args[0]):
            raise Refused(2)
        sub = args[1].upper()
        if sub not in KNOWN:
            raise Refused(1)
        if sub not in PER_CHANNEL:
            raise Refused(2)
        self._ch = int(args[0])
        return super().execute(args[1:], now)

    def idn(self) -> str:
        return "second," + "second-xy-stage" + (";vrec=command" if self.records_command else "") \
            + ",2,fw-6"

    def limits(self) -> str:
        return " ".join(num(x) for x in self.lim[self.channel()])

    def output(self) -> float:
        return float(self.outs[self.channel()]) if self._cmd == "VOL?" else float(self.outs[0])

    def sva(self, args: list[str], now: float) -> str:
        v = floats(args, 1)[0]
        self.writable(now)
        c = self.channel()
        self.check(c, np.array([v]), float(self.outs[c]))
        self.outs[c] = v
        return "OK"

    def wtl(self, args: list[str], now: float) -> str:
        reply = super().wtl(args, now)
        self.written[:] = False
        return reply

    def in_range(self, values: np.ndarray, previous: float | None) -> None:
        """The named channel's range and steps (its number checked first: 6, §2.14(g))."""
        self.check(self.channel(), values, previous)

    def store(self, first: int, values: np.ndarray, run: dict | None) -> None:
        c = self.channel()
        for i, v in enumerate(values):
            k = first + i
            if run is not None and k <= run["played"]:  # played or on the DAC: ignored
                continue
            self.values[c, k % self.length], self.holds[c, k % self.length] = v, k
        self.written[c] = True

    def begin(self, n: int, stream: bool, now: float) -> None:
        super().begin(n, stream, now)
        self.run.update(written=self.written.copy(), held=self.outs.copy(),
                        last=self.outs.copy())

    def recorder(self) -> np.ndarray:
        return self.rec[self.channel()]


class SecondXYStage(SecondStage):
    """:class:`XYDevice` on ``socket://127.0.0.1:PORT`` (``url``); keyword arguments go to it."""

    def __init__(self, **device: object) -> None:
        super().__init__()
        self.device = XYDevice(**device)  # type: ignore[arg-type]

