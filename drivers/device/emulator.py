"""The emulated device's logic: waveform table, generator, recorder, DC output, limits, watchdog.

No I/O, no clock, no device library: every method that depends on time takes ``now`` (s, any
monotonic origin) explicitly, so tests step the clock by hand and the servers
(:mod:`afmctl.drivers.device.emulated`) pass ``time.monotonic()``. The plant it drives is
:class:`~afmctl.drivers.device.plant.Physics`, or the foreign stage of a profile's ``[emulator.foreign]``
(:class:`~afmctl.drivers.device.foreign.physics.ForeignPhysics`): :func:`plant`.

Global sample ``k`` of a run is table slot ``k mod L`` (the table tiled over the cycles, or in a
stream the ring the host refills while it plays). The generator plays lazily: advancing to ``now``
runs the plant over the samples due since the last call, in device time (so calls must be
serialized: one lock per device). The recorder stores ``raw = (u - offset) / scale`` (sensor
units). The plant's state (hysteresis memory, rod, filter states) persists across runs and DC
sets, like a real stage.

Safety (issue 7): every commanded sample that reached the stack is logged
(:meth:`Emulator.applied_log`); waveforms and DC sets outside the voltage range or the slew limit
are refused with an error code and nothing applied; a watchdog, armed by the first heartbeat after a
period is set, ramps to 0 V if heartbeats stop; a read-only device refuses every output change.
A stream whose next sample is not in the table when its time comes (the host fell behind) stops,
sets error 10 and ramps to 0 V: it never plays stale table content.

Sample ``k`` of a run goes on the DAC at ``t_k`` and counts as played at ``t_k + dt``
(docs/reference/protocol.md §2.2): while a run plays, the output is the sample being held, which is checked
(stale slot, slew) when its hold begins; stopping keeps it on the output without counting it.
Limits and the sample rate are float32 values (§2.6).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl.drivers.device.foreign.family_physics import FamilyPhysics
from afmctl.drivers.device.foreign.physics import ForeignPhysics
from afmctl.drivers.device.foreign.xy_physics import ForeignXYPhysics
from afmctl.drivers.device.plant import Physics
from afmctl.drivers.device.xy_plant import CoupledPhysics
from afmctl.drivers.protocol import Status
from afmctl.errors import DeviceError
from afmctl.files.profile import Limits, Profile

FloatArray = NDArray[np.float64]

IDENTITY = "afmctl,emulated-stage,0,protocol-3"
#: What a device of several channels answers to ``*IDN?`` (serial protocol 4).
IDENTITY_CHANNELS = "afmctl,emulated-xy-stage,0,protocol-4"
#: Longest idle stretch the plant is simulated through, s: beyond it the hold is taken as settled
#: (ringing decays in ms; the thermal kernel of the hidden effects, attempt rates 30-300 /s, relaxes
#: mostly within 0.3 s). It also bounds the work a start does after a long pause (about 55 ms with
#: the thermal kernel), which an accelerated device clock would otherwise count as played time.
IDLE_HORIZON_S = 1.0
MIN_RATE_HZ, MAX_RATE_HZ = 100.0, 100_000.0
#: Longest stream, samples (2**29: what the 16-bit Modbus recorder page addresses; 14.9 h at 10 kHz).
MAX_STREAM_SAMPLES = 1 << 29




def f32(x: float) -> float:
    """``x`` rounded to the nearest float32 (docs/reference/protocol.md §2.6(b))."""
    return float(np.float32(x))


def max_step(limits: Limits, sample_rate_hz: float) -> float:
    """The largest step one sample may take, V: ``slew × 1000 × dt`` with the float32 slew limit
    (V/ms) and ``dt`` in s (§2.6(d); the 1e-6 tolerance is applied by the comparisons)."""
    return f32(limits.slew_v_per_ms) * 1000.0 / sample_rate_hz


def check_waveform(v: FloatArray, limits: Limits, sample_rate_hz: float,
                   previous_v: float | None = None) -> None:
    """Raise :class:`DeviceError` 3 or 4 if ``v`` leaves the voltage range or the slew limit.

    ``previous_v`` is the output before the first sample (the step into the waveform counts).
    The limits are their float32 values, the range inclusive (§2.6(a), (c)).
    """
    v = np.asarray(v, dtype=float)
    lo, hi = f32(limits.v_min), f32(limits.v_max)
    bad = not np.all(np.isfinite(v)) or (v.size > 0 and (v.min() < lo or v.max() > hi))
    if bad:
        raise DeviceError(3, f"range [{lo:g}, {hi:g}] V")
    seq = v if previous_v is None else np.concatenate(([previous_v], v))
    step = max_step(limits, sample_rate_hz)
    if seq.size > 1 and np.max(np.abs(np.diff(seq))) > step * (1 + 1e-6):
        i = int(np.argmax(np.abs(np.diff(seq))))
        raise DeviceError(4, f"step {abs(seq[i + 1] - seq[i]):.4g} V > {step:.4g} V at {i}")


def ramp_to_zero(v0: float, limits: Limits, sample_rate_hz: float) -> FloatArray:
    """Samples from ``v0`` to 0 V at 90 % of the slew limit (empty if already at 0)."""
    step = 0.9 * max_step(limits, sample_rate_hz)
    n = math.ceil(abs(v0) / step)
    return np.linspace(v0, 0.0, n + 1)[1:] if n else np.zeros(0)


def ramps_to_zero(outputs: FloatArray, limits: list[Limits], sample_rate_hz: float) -> FloatArray:
    """Every channel's ramp to 0 V together (each at 90 % of its own slew limit, §2.7(a)), shape
    (n, C): channel ``c`` reaches 0 V after its own ``n_c`` samples and stays there."""
    ramps = [ramp_to_zero(float(v), lim, sample_rate_hz) for v, lim in zip(outputs, limits,
                                                                            strict=True)]
    n = max(r.size for r in ramps)
    out = np.zeros((n, len(ramps)))
    for c, r in enumerate(ramps):
        out[:r.size, c] = r
    return out


@dataclass
class _Run:
    """A run in progress: global samples ``[0, total)`` clocked from device time ``start``, the first
    ``pos`` of them played. Global sample ``k`` is table slot ``k mod table_length``; a stream run
    also requires that slot to hold global sample ``k`` (else: underrun) on every written channel.
    ``last_v`` (shape (C,)) is the value of the last sample played (the outputs before the start
    until one is): the slew check of the next sample starts from it; ``held`` marks the channels
    with no table (they hold ``last_v`` through the run)."""

    start: float
    total: int
    index: int
    gain: float | FloatArray
    stream: bool
    last_v: FloatArray
    held: NDArray[np.bool_]
    pos: int = 0


def first_steep(v: FloatArray, previous_v: float, limits: Limits, sample_rate_hz: float) -> int:
    """Index of the first sample of ``v`` whose step from its predecessor (``previous_v`` before
    sample 0) exceeds the slew limit; ``v.size`` if none does."""
    step = max_step(limits, sample_rate_hz) * (1 + 1e-6)
    bad = np.flatnonzero(np.abs(np.diff(v, prepend=previous_v)) > step)
    return int(bad[0]) if bad.size else v.size


def plant(profile: Profile, sample_rate_hz: float) -> Any:
    """The device's plant: afmctl's own model and effects, or the foreign stage of the profile's
    ``[emulator.foreign]``, or the out-of-family stage of its ``[emulator.family]`` (either driven
    over the profile's voltage range); for a profile of several axes, each axis's own plant
    coupled by the profile's ``[emulator.coupling]``
    (:class:`~afmctl.drivers.device.xy_plant.CoupledPhysics`), or the foreign x/y stage of its
    ``[emulator.xy_foreign]`` (:class:`~afmctl.drivers.device.foreign.xy_physics.ForeignXYPhysics`)."""
    config = profile.emulator
    assert config is not None
    if config.xy_foreign is not None:
        return ForeignXYPhysics(config.xy_foreign, sample_rate_hz,
                                (profile.limits.v_min, profile.limits.v_max))
    if len(profile.axis_names) > 1:
        plants = [plant(profile.axis(name), sample_rate_hz) for name in profile.axis_names]
        return CoupledPhysics(plants, config.coupling, sample_rate_hz)
    drive = (profile.limits.v_min, profile.limits.v_max)
    if config.family is not None:
        return FamilyPhysics(config, sample_rate_hz, drive)
    if config.foreign is None:
        return Physics(config, sample_rate_hz)
    return ForeignPhysics(config, sample_rate_hz, drive)


class Emulator:
    """The emulated device: waveform tables, generator, recorders, DC outputs, limits and watchdog.

    Parameters
    ----------
    profile : Profile
        Must carry an ``emulator`` section (the device's truth); one channel per axis of the
        profile (:attr:`Profile.axis_names`), each with its axis's limits, sensor and plant.
    read_only : bool, optional
        Override the profile: refuse every output change.

    Every public method takes ``now`` (s, monotonic), first advances the device to ``now`` and
    raises :class:`DeviceError` (also remembered as the sticky last error) when it refuses.
    Methods of one channel take ``channel`` (default 0; outside the channels: error 6).

    The generator plays lazily: advancing to ``now`` runs the model over the samples due since the
    last advance, so a stream's table may change while it runs. Each channel's table is a ring:
    slot ``s`` remembers which global sample it holds (``slot_global[c, s]``, -1 if none); a
    channel none of whose slots is written since the table length was declared is *held*: it
    keeps its output through a run (docs/reference/protocol.md §2.14). The recorders are rings of
    ``recorder_capacity`` entries addressed by global sample index (``rec_global``, shared).
    ``table``, ``rec_u``, ``rec_v``, ``output_v`` and ``limits`` are channel 0's.
    """

    def __init__(self, profile: Profile, read_only: bool | None = None) -> None:
        if profile.emulator is None:
            raise ValueError(f"profile {profile.name!r} has no [emulator] section")
        self.profile = profile
        self.config = profile.emulator
        self.axes = [profile.axis(name) for name in profile.axis_names]
        self.channels = len(self.axes)
        self.channel_limits = [a.limits for a in self.axes]
        self.limits = self.channel_limits[0]
        self.read_only = self.config.read_only if read_only is None else read_only
        self.sample_rate_hz = f32(profile.sample_rate_hz)
        self.physics = plant(self.profile, self.sample_rate_hz)
        self.state = self.physics.initial()
        #: The plant's state when the last run began (what a bench's truth probe re-simulates the
        #: run's true position from; on no wire).
        self.run_state = self.state
        c, cap, rec = self.channels, self.config.table_capacity, self.config.recorder_capacity
        self.tables = np.zeros((c, cap), dtype=np.float32)
        self.slot_global = np.full((c, cap), -1, dtype=np.int64)
        self.table_length = 0
        self.rec_us = np.full((c, rec), np.nan, dtype=np.float32)
        self.rec_vs = np.full((c, rec), np.nan, dtype=np.float32)
        self.rec_global = np.full(rec, -1, dtype=np.int64)
        self.position = 0
        self.run_samples = 0
        self.outputs = np.zeros(c)
        self.run_count = 0
        self.last_error = 0
        self.watchdog_s = self.config.watchdog_s
        self.armed = False
        self.expired = False
        self.last_heartbeat = 0.0
        self._run: _Run | None = None
        self._applied: list[FloatArray] = []
        #: Device time up to which the plant has evolved (None: not since power-on), s.
        self.plant_time: float | None = None

    @property
    def table(self) -> NDArray[np.float32]:
        """Channel 0's waveform table."""
        return self.tables[0]

    @property
    def rec_u(self) -> NDArray[np.float32]:
        """Channel 0's recorded raw sensor readings."""
        return self.rec_us[0]

    @property
    def rec_v(self) -> NDArray[np.float32]:
        """Channel 0's recorded stack voltages."""
        return self.rec_vs[0]

    @property
    def output_v(self) -> float:
        """Channel 0's output, V."""
        return float(self.outputs[0])

    @property
    def written(self) -> NDArray[np.bool_]:
        """Which table slots hold a sample, per channel (shape (C, capacity))."""
        return self.slot_global >= 0

    def _held(self) -> NDArray[np.bool_]:
        """Channels with no table: none of their slots written since the length was declared."""
        return ~self.written.any(axis=1)

    def _holds_own(self, n: int) -> bool:
        """Whether some channel is written and every written one holds global samples ``0 ..
        n-1`` in slots ``0 .. n-1`` (§2.1(c), §2.4(h), §2.14)."""
        written = ~self._held()
        return n > 0 and bool(written.any()) and bool(
            np.array_equal(self.slot_global[written, :n],
                           np.broadcast_to(np.arange(n), (int(written.sum()), n))))

    # -- bookkeeping ---------------------------------------------------------------------------
    def _fail(self, code: int, detail: str = "") -> DeviceError:
        self.last_error = code
        return DeviceError(code, detail)

    def _writable(self) -> None:
        if self.read_only:
            raise self._fail(7)

    def _idle(self) -> None:
        if self._run is not None:
            raise self._fail(5)

    def _channel(self, channel: int) -> int:
        """``channel`` if the device has it, else error 6."""
        if not 0 <= channel < self.channels:
            raise self._fail(6, f"channel {channel} outside 0 .. {self.channels - 1}")
        return channel

    def _check(self, v: FloatArray, channel: int, previous_v: float | None = None) -> None:
        try:
            check_waveform(v, self.channel_limits[channel], self.sample_rate_hz, previous_v)
        except DeviceError as exc:
            raise self._fail(exc.code, str(exc)) from None

    def _respond(self, v: FloatArray, state: Any, gain: float | FloatArray = 1.0,
                 noise: FloatArray | None = None) -> tuple[FloatArray, FloatArray, Any]:
        """The plant on samples of every channel (V, shape (n, C)): readings (um) and stack
        voltages (V), each (n, C), and its new state (a one-channel plant takes columns)."""
        if self.channels > 1:
            return self.physics.respond(v, state, gain, noise)  # type: ignore[no-any-return]
        u, va, state = self.physics.respond(v[:, 0], state, gain,
                                            None if noise is None else noise[:, 0])
        return u[:, None], va[:, None], state

    def _noise(self, run: _Run, n: int) -> FloatArray:
        noise = self.physics.noise(run.index, run.pos, n)
        return noise if self.channels > 1 else noise[:, None]

    def _apply(self, v: FloatArray) -> None:
        """Log commanded samples (shape (n, C)) that reached the stacks."""
        if v.size:
            self._applied.append(np.asarray(v, dtype=float))
            self.outputs = np.array(v[-1], dtype=float)

    def _catch_up(self, now: float) -> None:
        """Idle time: while no run plays, the plant goes on evolving at the held outputs (ringing
        decays, the thermal kernel relaxes) in device time, sample by sample up to ``now`` (the
        first :data:`IDLE_HORIZON_S` of a longer hold; a plant with an ``elapse`` method, e.g. one
        that creeps or drifts, is told the rest). Lazy: done before the plant is driven
        again. Nothing is recorded or logged (the outputs do not change)."""
        if self._run is not None:
            return
        if self.plant_time is None:
            self.plant_time = now
            return
        k = math.floor((now - self.plant_time) * self.sample_rate_hz + 1e-9)
        if k <= 0:
            return
        m = min(k, math.ceil(IDLE_HORIZON_S * self.sample_rate_hz))
        _, _, self.state = self._respond(np.tile(self.outputs, (m, 1)), self.state)
        elapse = getattr(self.physics, "elapse", None)  # a plant that goes on past the horizon
        if k > m and elapse is not None:
            self.state = elapse(self.state, (k - m) / self.sample_rate_hz, self.output_v)
        self.plant_time += k / self.sample_rate_hz

    def _hold(self, v: FloatArray, now: float) -> None:
        """Apply samples (shape (n, C)) outside a run (DC set, ramp) from ``now``, after the idle
        time before it: the state advances, nothing is recorded."""
        self._catch_up(now)
        _, _, self.state = self._respond(v, self.state)
        self._apply(v)
        self.plant_time = max(self.plant_time or now, now) + len(v) / self.sample_rate_hz

    def _ramp(self, now: float) -> None:
        """Every output to 0 V together, each at 90 % of its slew limit (§2.7(a))."""
        self._hold(ramps_to_zero(self.outputs, self.channel_limits, self.sample_rate_hz), now)

    def _end(self, run: _Run) -> None:
        """The generator stops after ``run.pos`` samples; the plant idles from their end."""
        self._run = None
        self.plant_time = run.start + run.pos / self.sample_rate_hz

    def _due(self, run: _Run, now: float) -> int:
        """Samples of ``run`` whose start time has come by ``now``."""
        k = math.floor((now - run.start) * self.sample_rate_hz + 1e-9)
        return max(run.pos, min(run.total, k))

    def _samples(self, run: _Run, g: NDArray[np.int64]) -> tuple[FloatArray, int, int]:
        """The samples ``g`` of ``run`` on every channel (shape (len(g), C)), and the first that
        must not be played with its fault code (``len(g), 0`` if none): a stale slot of a
        streamed channel (10) or a step beyond a channel's slew limit (4; §2.4(d), (e))."""
        slots = g % self.table_length
        v = np.where(run.held[:, None], run.last_v[:, None],
                     self.tables[:, slots].astype(float)).T
        fault, n = 0, g.size
        if run.stream:
            stale = np.flatnonzero((self.slot_global[~run.held][:, slots] != g).any(axis=0))
            if stale.size:
                fault, n = 10, int(stale[0])
        for c in range(self.channels):
            steep = first_steep(v[:n, c], float(run.last_v[c]), self.channel_limits[c],
                                self.sample_rate_hz)
            if steep < n:
                fault, n = 4, steep
        return v, n, fault

    def _advance(self, now: float) -> None:
        """Play the samples due by ``now``: those whose hold has ended are played (run through the
        plant, recorded); the one whose hold has begun is the output. Each is checked when its hold
        begins (§2.4(d), (e)): the first that is stale (underrun, error 10) or too steep (error 4)
        on any channel stops the run before it goes on the DAC, and every output ramps to 0 V."""
        run = self._run
        if run is None:
            return
        due = self._due(run, now)
        g = np.arange(run.pos, min(due + 1, run.total))  # played by now, and the one being held
        v, n, fault = self._samples(run, g)
        played = min(n, due - run.pos)
        self._play(run, v[:played])
        if fault:  # the faulty sample's hold has begun by now: it never goes on the DAC
            self._end(run)
            self._ramp(self.plant_time)  # type: ignore[arg-type]
            self.last_error = fault
        elif run.pos == run.total:
            self._end(run)
        elif played < n:
            self.outputs = v[played].copy()  # the sample being held is the output (§2.2(f))

    def _play(self, run: _Run, v: FloatArray) -> None:
        """Clock out ``v`` (the run's next samples, shape (n, C)) through the plant into the
        recorder rings."""
        if len(v) == 0:
            return
        u, va, self.state = self._respond(v, self.state, run.gain, self._noise(run, len(v)))
        cap = self.rec_global.size
        g = np.arange(run.pos, run.pos + len(v))[-cap:]
        slots = g % cap
        for c, axis in enumerate(self.axes):
            self.rec_us[c, slots] = ((u[:, c] - axis.sensor_offset_um)
                                     / axis.sensor_scale_um)[-cap:]
            self.rec_vs[c, slots] = va[-cap:, c]
        self.rec_global[slots] = g
        self._apply(v)
        run.last_v = np.array(v[-1], dtype=float)
        run.pos += len(v)
        self.position = run.pos

    def tick(self, now: float) -> None:
        """Advance to ``now``: play what is due, expire the watchdog."""
        if self.armed and now - self.last_heartbeat > self.watchdog_s:
            self._expire(self.last_heartbeat + self.watchdog_s)
        self._advance(now)

    def _expire(self, when: float) -> None:
        self.armed = False
        self.expired = True
        self._halt(when)
        self._ramp(when)
        self.last_error = 8

    def _halt(self, now: float) -> None:
        """Stop the generator at ``now``: the samples played by then stay played, the one being
        held stays on the outputs without counting as played (§2.2(b), (e))."""
        self._advance(now)
        if self._run is not None:
            if self._run.pos < self._run.total:
                self._applied.append(self.outputs[None, :].copy())  # it reached the stacks
            self._end(self._run)

    def _begin(self, total: int, stream: bool, now: float) -> None:
        """Start a run of ``total`` samples from ``now``, with empty recorders."""
        self._catch_up(now)
        self.run_state = self.state
        self.rec_us[:] = np.nan
        self.rec_vs[:] = np.nan
        self.rec_global[:] = -1
        self.position = 0
        self.run_samples = total
        self._run = _Run(now, total, self.run_count, self.physics.gain(self.run_count), stream,
                         self.outputs.copy(), self._held())
        self.run_count += 1
        self.expired = False

    # -- commands ------------------------------------------------------------------------------
    def status(self, now: float) -> Status:
        self.tick(now)
        n = self.table_length
        return Status(
            running=self._run is not None, recorder_fill=min(self.position, self.rec_global.size),
            last_error=self.last_error, output_v=self.output_v,
            run_count=self.run_count, table_length=n,
            table_complete=self._holds_own(n),
            watchdog_armed=self.armed, watchdog_expired=self.expired, read_only=self.read_only,
            sample_rate_hz=self.sample_rate_hz, play_position=self.position,
            run_samples=self.run_samples, watchdog_s=self.watchdog_s)

    def output(self, now: float, channel: int = 0) -> float:
        """Channel ``channel``'s output, V (§2.2(f))."""
        self.tick(now)
        return float(self.outputs[self._channel(channel)])

    def channel_limits_of(self, channel: int) -> Limits:
        """Channel ``channel``'s limits (error 6 outside the channels)."""
        return self.channel_limits[self._channel(channel)]

    def pop_error(self, now: float) -> int:
        """The last error code, cleared by reading (GCS ``ERR?``)."""
        self.tick(now)
        code, self.last_error = self.last_error, 0
        return code

    def set_voltage(self, v: float, now: float, channel: int = 0) -> None:
        """DC output ``v`` (V) of ``channel``: refused outside its range or if the step exceeds
        its slew limit; the other channels hold theirs."""
        self.tick(now)
        self._writable()
        self._idle()
        c = self._channel(channel)
        v = float(np.float32(v))  # what the DAC gets, as every voltage on the wire
        self._check(np.array([v]), c, float(self.outputs[c]))
        sample = self.outputs.copy()
        sample[c] = v
        self._hold(sample[None, :], now)

    def set_sample_rate(self, hz: float, now: float) -> None:
        self.tick(now)
        hz = f32(hz)  # stored as float32 (§2.6(b))
        if not MIN_RATE_HZ <= hz <= MAX_RATE_HZ:  # a bad argument comes first (precedence)
            raise self._fail(2, f"sample rate must be in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}] Hz")
        self._writable()
        self._idle()
        self._catch_up(now)  # the idle time so far, at the old rate
        self.sample_rate_hz = hz
        self.physics = plant(self.profile, self.sample_rate_hz)

    def set_table_length(self, n: int, now: float) -> None:
        """Declare the waveform length (every channel's); every index in [0, n) must then be
        written once on each channel that plays a table."""
        self.tick(now)
        self._writable()
        self._idle()
        if not 1 <= n <= self.tables.shape[1]:
            raise self._fail(6, f"table length must be in [1, {self.tables.shape[1]}]")
        self.table_length = int(n)
        self.slot_global[:] = -1

    def write_table(self, first: int, values: FloatArray, now: float, channel: int = 0) -> None:
        """Store samples ``first .. first+len-1`` of ``channel`` (V, global indices); idempotent,
        refused as a whole if any is outside the channel's voltage range.

        Idle, global index = table slot and the block must lie in the table. While a stream runs,
        the block must lie in ``[0, N_total)`` and no sample may be a table length or more ahead of
        the play position (its slot's previous sample must have been played); samples already
        played, and the one being held, are ignored (a repeated write is harmless; §2.4(b), (c)).
        """
        self.tick(now)
        self._writable()
        run = self._run
        if run is not None and not run.stream:
            raise self._fail(5)
        c = self._channel(channel)
        vals = np.asarray(values, dtype=np.float32)
        end = first + vals.size
        total, pos = (run.total, run.pos) if run is not None else (self.table_length, 0)
        if first < 0 or end > total or end > pos + self.table_length:
            raise self._fail(6, f"samples {first}..{end - 1} outside [{pos}, "
                                f"{min(total, pos + self.table_length)})")
        self._check(vals, c)
        g = np.arange(max(first, pos + (run is not None)), end)  # sample `pos` is on the DAC
        slots = g % self.table_length
        self.tables[c, slots] = vals[g - first]
        self.slot_global[c, slots] = g

    def _check_start(self, n: int, wrap: bool) -> None:
        """The range and steps of the first ``n`` samples of every written channel's table, from
        its output (and, with ``wrap``, the step from the last sample into the first)."""
        for c in np.flatnonzero(~self._held()):
            first = self.tables[c, :n].astype(float)
            self._check(np.tile(first, 2)[:n + 1] if wrap else first, int(c),
                        float(self.outputs[c]))

    def start(self, cycles: int, now: float) -> None:
        """Clock out the tables ``cycles`` times from ``now``, recording every sample."""
        self.tick(now)
        self._writable()
        self._idle()
        n = self.table_length
        if not 1 <= cycles or max(n, 1) * cycles > self.rec_global.size:
            raise self._fail(6, f"cycles x length must be in [1, {self.rec_global.size}]")
        if not self._holds_own(n):  # the stale-slot rule binds WGO too (§2.1(d))
            raise self._fail(9)
        self._check_start(n, cycles >= 2)
        self._begin(n * cycles, False, now)

    def start_stream(self, n_total: int, now: float) -> None:
        """Play ``n_total`` samples from ``now`` through the tables used as rings (one cycle).

        Every written channel's table must hold global samples ``0 .. min(L, n_total)-1`` (error
        9); the host writes the rest while it runs (:meth:`write_table`). A sample whose slot does
        not hold it when its time comes stops the stream: error 10, ramp to 0 V.
        """
        self.tick(now)
        self._writable()
        self._idle()
        if not 1 <= n_total <= MAX_STREAM_SAMPLES:
            raise self._fail(6, f"stream length must be in [1, {MAX_STREAM_SAMPLES}]")
        m = min(self.table_length, n_total)
        if not self._holds_own(m):
            raise self._fail(9)
        self._check_start(m, False)
        self._begin(n_total, True, now)

    def stop(self, now: float) -> None:
        """Stop the generator; the outputs hold their last sample."""
        self.tick(now)
        self._halt(now)

    def safe_state(self, now: float) -> None:
        """Stop the generator and ramp every output to 0 V within its slew limit."""
        self.tick(now)
        self._halt(now)
        self._ramp(now)

    def heartbeat(self, now: float) -> None:
        """Refresh (and, if a period is set, arm) the watchdog."""
        self.tick(now)
        self.last_heartbeat = now
        self.armed = self.watchdog_s > 0

    def set_watchdog(self, period_s: float, now: float) -> None:
        """Set the watchdog period (s); 0 disarms. Armed by the next heartbeat."""
        self.tick(now)
        period_s = f32(period_s)
        if not 0 <= period_s <= 3600:  # NaN too
            raise self._fail(2, "watchdog period must be in [0, 3600] s")
        self.watchdog_s = period_s
        self.armed = False
        self.expired = False

    def read_recorder(self, first: int, n: int, now: float, channel: int = 0
                      ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Raw sensor reading and stack voltage (float32) of ``channel``'s global samples ``first
        .. first+n-1``; NaN for samples not yet recorded or already overwritten in the ring."""
        self.tick(now)
        c = self._channel(channel)
        if first < 0 or n < 0:
            raise self._fail(6, "negative recorder index or count")
        if first > 1 << 62:  # beyond any run: never recorded (§2.3(g))
            return np.full(n, np.nan, np.float32), np.full(n, np.nan, np.float32)
        g = np.arange(first, first + n)
        slots = g % self.rec_global.size
        held = self.rec_global[slots] == g
        u = np.where(held, self.rec_us[c, slots], np.float32(np.nan)).astype(np.float32)
        v = np.where(held, self.rec_vs[c, slots], np.float32(np.nan)).astype(np.float32)
        return u, v

    def applied_log(self, now: float) -> FloatArray:
        """Every commanded sample that has reached the stacks since power-on, V: shape (M,) on a
        one-channel device, (M, C) on one of several channels."""
        self.tick(now)
        log = np.concatenate(self._applied) if self._applied else np.zeros((0, self.channels))
        return log[:, 0] if self.channels == 1 else log
