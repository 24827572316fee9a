"""The stage interface: :class:`StageBase` (chunked upload, streamed play with readback, retries,
safe state on any error) on a few primitives per transport, and :func:`open_stage`.

Units on this interface: volts, micrometres (sensor scale and offset from the profile applied),
seconds. Every blocking call has a timeout; none can hang.

Reliability: a request that fails on the wire (no reply within the timeout, a corrupted or stale
reply, a dropped connection: :class:`StageError` code -1) is retried up to :attr:`StageBase.attempts`
times, after a resync of the link, when repeating it is harmless: queries, absolute set points,
heartbeats, stop, safe state, and table blocks (they carry their sample index). A start is never
repeated blindly: the host reads the run counter to see whether it took effect. A refusal by the
device (code >= 1) is never retried. During :meth:`~StageBase.play` no attempt starts after the
run's deadline, and recorder reads that still fail leave their samples missing (NaN,
``valid=False``) instead of failing the run; every sample of the waveform is handed to ``on_block``
exactly once, measured or missing, whatever happens.
"""

from __future__ import annotations

import abc
import math
import time
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from afmctl import guard
from afmctl.drivers.player import BlockCallback, Player, Recording
from afmctl.drivers.protocol import Status
from afmctl.errors import (
    LimitMismatchError,
    LinkCapacityError,
    StageError,
    StageTimeoutError,
    StoppedError,
)
from afmctl.files.profile import (
    EmulatedTransport,
    ModbusRtuTransport,
    ModbusTcpTransport,
    Profile,
    SerialTransport,
)

__all__ = ["StageError", "StoppedError", "LinkCapacityError", "LimitMismatchError", "Recording",
           "Status", "StageBase", "BlockCallback", "open_stage"]

T = TypeVar("T")
#: Slack when comparing the profile's limits with the device's (V, V/ms): float32 on the wire.
LIMIT_SLACK = 1e-3


class StageBase(abc.ABC):
    """The stage interface. Subclasses supply the primitives; chunking and units live here.

    Parameters
    ----------
    profile : Profile
        Limits, sample rate and sensor calibration of the stage.
    """

    #: Samples per upload and readback request of this transport.
    upload_chunk: int = 61
    read_chunk: int = 62
    #: Attempts per idempotent request (the first one included).
    attempts: int = 4
    #: Watchdog period armed for every :meth:`play`, s (0: not armed); the links take it from the
    #: profile's ``[transport] watchdog_s``.
    watchdog_s: float = 0.0

    def __init__(self, profile: Profile) -> None:
        self.profile = profile
        #: The device's channels, as negotiated when the link opened (1 on a device of serial
        #: protocol 3 / register map 2).
        self._channels = 1
        self._last_run_samples = 0
        #: when the last run's first sample went out, on :meth:`now_s`'s clock, s
        self.run_started_s: float | None = None
        #: the last run's number on the device's run counter (``Status.run_count`` once started)
        self.run_count: int | None = None
        #: Requests repeated after a transport failure, since the stage was opened.
        self.retries = 0
        self._deadline: float | None = None

    # -- the run seam: what a :class:`~afmctl.drivers.player.Player` drives ------------------------
    def capacities(self) -> tuple[int, int]:
        """The device's waveform table and recorder capacities, samples."""
        return self._capacities()

    def set_deadline(self, at: float | None) -> None:
        """The monotonic time (``time.monotonic``) after which no request of the run starts, or
        None (no run: requests are bounded by their own timeouts only)."""
        self._deadline = at

    def past_deadline(self) -> bool:
        """Whether the run's deadline (:meth:`set_deadline`) has passed."""
        return self._deadline is not None and time.monotonic() > self._deadline

    @property
    def channels(self) -> int:
        """The device's channels (outputs with their sensors on one sample clock)."""
        return self._channels

    def write_block(self, first: int, values: NDArray[np.float32], channel: int = 0) -> None:
        """Write ``channel``'s table samples from global index ``first`` (one request: at most
        :attr:`upload_chunk` samples), already checked by the guard."""
        self._write_chunk(first, values, channel)

    def start_run(self, n: int, streamed: bool) -> None:
        """Start the generator on the uploaded table for an ``n``-sample run: streamed through the
        table as a ring, or one pass of it. A start is not idempotent: after a transport failure
        the run counter says whether it took effect before it is tried again."""
        sent = self.now_s()
        self._start_checked(lambda: self._start_stream(n) if streamed else self._start(1))
        self._last_run_samples = n
        self.run_started_s = self._started_at(sent)

    def now_s(self) -> float:
        """The stage's clock, s: the host's monotonic clock (a device on a link plays in real
        time; an in-process device has a clock of its own)."""
        return time.monotonic()

    def _started_at(self, sent_s: float) -> float:
        """When the run just started went out, given when its start was sent (``sent_s``,
        :meth:`now_s`): the device starts on its next sample tick, within a sample period."""
        return sent_s

    # -- reliability -----------------------------------------------------------------------------
    def _resync(self) -> None:
        """Bring the link back to a known state after a failed request (discard anything in
        flight, reconnect). The default does nothing (no wire)."""
        return None

    def _retrying(self, attempt: Callable[[], T], idempotent: bool = True) -> T:
        """``attempt()``, repeated after a resync on transport failure (``StageError`` -1) up to
        :attr:`attempts` times if ``idempotent``; no attempt starts after a run's deadline."""
        tries = self.attempts if idempotent else 1
        for i in range(tries):
            if self.past_deadline():
                raise StageTimeoutError("the run's deadline passed while the link was failing")
            try:
                return attempt()
            except StageError as exc:
                if exc.code != -1 or i == tries - 1:
                    raise
            self.retries += 1
            self._resync_quietly()
        raise AssertionError("unreachable")

    def _resync_quietly(self) -> None:
        """:meth:`_resync`; if that fails too, the next attempt will find out."""
        try:
            self._resync()
        except StageError:
            pass

    def _start_checked(self, start: Callable[[], None]) -> None:
        """Start a run (not idempotent): on a transport failure, read the run counter to learn
        whether the start took effect before trying again."""
        before = self.status().run_count
        self.run_count = before + 1  # this run's number on the device's counter
        for i in range(self.attempts):
            try:
                return start()
            except StageError as exc:
                if exc.code != -1 or i == self.attempts - 1:
                    raise
            self.retries += 1
            self._resync_quietly()
            if self.status().run_count > before:
                return None
        return None

    # -- primitives ----------------------------------------------------------------------------
    @abc.abstractmethod
    def identify(self) -> str: ...

    @abc.abstractmethod
    def status(self) -> Status: ...

    @abc.abstractmethod
    def limits(self, channel: int = 0) -> tuple[float, float, float]:
        """The device's own limits of ``channel``: v_min (V), v_max (V), slew (V/ms)."""

    def voltage(self, channel: int = 0) -> float:
        """Output voltage of ``channel`` now, V (this default knows channel 0's only)."""
        if channel:
            raise NotImplementedError(f"{type(self).__name__} reads channel 0's output only")
        return self.status().output_v

    def voltages(self) -> NDArray[np.float64]:
        """Every channel's output now, V, shape (C,)."""
        return np.array([self.voltage(c) for c in range(self.channels)])

    def check_limits(self) -> None:
        """Compare each axis profile's voltage range and slew limit with its channel's own limits
        on the device (once per opened stage; :meth:`play` does it before anything is sent).

        Raises
        ------
        LimitMismatchError
            The profile names more axes than the device has channels, or an axis's range is not
            within its channel's, or its slew limit above the channel's: a waveform the guard
            passes would be refused by the device mid-run.
        """
        if getattr(self, "_limits_checked", False):
            return
        names = self.profile.axis_names
        if len(names) > self.channels:
            raise LimitMismatchError(
                f"profile {self.profile.name!r} describes {len(names)} axes ({', '.join(names)}); "
                f"the device has {self.channels} channel(s) (CHN?, IR 29): use a profile of "
                f"{self.channels} axis; nothing was sent")
        for c, name in enumerate(names):
            self._check_channel_limits(c, name)
        self._limits_checked = True

    def _check_channel_limits(self, channel: int, name: str) -> None:
        """:meth:`check_limits` for one channel and its axis ``name``."""
        lo, hi, slew = self.limits(channel)
        p = self.profile.axis(name).limits
        wrong = []
        if p.v_min < lo - LIMIT_SLACK or p.v_max > hi + LIMIT_SLACK:
            wrong.append(f"voltage range {p.v_min:g} ... {p.v_max:g} V (v_min_V, v_max_V) is not "
                         f"within the device's {lo:g} ... {hi:g} V")
        if p.slew_v_per_ms > slew + LIMIT_SLACK:
            wrong.append(f"slew limit {p.slew_v_per_ms:g} V/ms (slew_V_per_ms) is above the "
                         f"device's {slew:g} V/ms")
        if wrong:
            section = "[amplifier]" if channel == 0 else f"[axis.{name}.amplifier]"
            where = "" if channel == 0 else f" of channel {channel}"
            raise LimitMismatchError(
                f"profile {self.profile.name!r}: its {section} " + "; its ".join(wrong)
                + f" (the device's own limits{where}, LIM?): set the profile's {section} to the "
                  "stage's; nothing was sent")

    @abc.abstractmethod
    def set_voltage(self, v: float, channel: int = 0) -> None:
        """DC output of ``channel``, V (refused outside its limits or beyond one slew-limited
        step)."""

    @abc.abstractmethod
    def stop(self) -> None: ...

    @abc.abstractmethod
    def safe_state(self) -> None:
        """Stop the generator and ramp the output to 0 V within the slew limit."""

    @abc.abstractmethod
    def heartbeat(self) -> None: ...

    @abc.abstractmethod
    def set_watchdog(self, period_s: float) -> None:
        """Watchdog period, s (0 disarms); the next heartbeat arms it."""

    @abc.abstractmethod
    def set_sample_rate(self, hz: float) -> None: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    @abc.abstractmethod
    def _set_table_length(self, n: int) -> None: ...

    @abc.abstractmethod
    def _write_chunk(self, first: int, values: NDArray[np.float32], channel: int = 0) -> None: ...

    @abc.abstractmethod
    def _start(self, cycles: int) -> None: ...

    @abc.abstractmethod
    def _read_chunk(self, first: int, n: int, channel: int = 0
                    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Raw sensor and voltage of ``channel``'s samples ``first .. first+n-1``, float32, NaN if
        missing."""

    @abc.abstractmethod
    def _start_stream(self, n_total: int) -> None:
        """Play ``n_total`` samples through the table as a ring (``_write_chunk`` then takes
        global sample indices)."""

    @abc.abstractmethod
    def _capacities(self) -> tuple[int, int]:
        """The device's table and recorder capacities, samples."""

    def uart_rates(self) -> tuple[float, float] | None:
        """Upload and readback rates, samples/s, that a real UART's baud rate allows (None: the
        link is not a UART; its rates are only measured)."""
        return None

    # -- composed operations -------------------------------------------------------------------
    def upload(self, waveform_v: ArrayLike) -> NDArray[np.float64]:
        """Load the waveform tables, V, shape (N,) (channel 0) or (N, C) (channels ``0 .. C-1``),
        sent as float32, in chunks.

        Returns
        -------
        ndarray, shape (chunks,)
            Seconds each chunk took (one channel's samples), retries included (what the link
            carries).
        """
        v = np.asarray(waveform_v, dtype=np.float32)
        v = v.ravel() if v.ndim < 2 else v
        if v.size == 0:
            raise ValueError("empty waveform")
        self._set_table_length(len(v))
        cols = v[:, None] if v.ndim == 1 else v
        took = []
        for c in range(cols.shape[1]):  # channel by channel: a link that selects one, once
            for first in range(0, len(v), self.upload_chunk):
                t0 = time.monotonic()
                self.write_block(first, np.ascontiguousarray(cols[first:first + self.upload_chunk,
                                                                  c]), c)
                took.append(time.monotonic() - t0)
        return np.array(took)

    def run(self, cycles: int = 1) -> None:
        """Start clocking out the table ``cycles`` times, recording every sample."""
        n = self.status().table_length
        self._start_checked(lambda: self._start(cycles))
        self._last_run_samples = n * cycles

    def wait(self, timeout_s: float | None = None, poll_s: float = 0.02) -> Status:
        """Poll until the generator stops; TimeoutError after ``timeout_s`` (default: the run's
        duration + 5 s)."""
        deadline: float | None = None
        while (st := self.status()).running:
            if deadline is None:
                limit = timeout_s if timeout_s is not None else (
                    self._last_run_samples / st.sample_rate_hz + 5.0)
                deadline = time.monotonic() + limit
            elif time.monotonic() > deadline:
                raise StageTimeoutError(f"stage still running after {limit:.3g} s")
            time.sleep(poll_s)
        return st

    def read_recorder(self, n: int | None = None, first: int = 0, *,
                      missing_ok: bool = False, channels: int | None = None) -> Recording:
        """Read ``n`` recorder samples from global index ``first`` (default: all of the last run):
        channel 0's, shape (n,), or with ``channels`` those of channels ``0 .. channels-1``,
        shape (n, channels), each with its axis's sensor scale and offset.

        With ``missing_ok``, a request that still fails on the wire after its retries leaves its
        samples missing (NaN, ``valid=False``) instead of raising."""
        n = self._last_run_samples - first if n is None else n
        cols = 1 if channels is None else channels
        raw = np.full((n, cols), np.nan, dtype=np.float32)
        volt = np.full((n, cols), np.nan, dtype=np.float32)
        for c, off in ((c, off) for c in range(cols) for off in range(0, n, self.read_chunk)):
            m = min(self.read_chunk, n - off)
            try:
                raw[off:off + m, c], volt[off:off + m, c] = self._read_chunk(first + off, m, c)
            except StageError as exc:
                if not (missing_ok and exc.code == -1):
                    raise
        axes = [self.profile.axis(name) for name in self.profile.axis_names[:cols]]
        axes += [self.profile] * (cols - len(axes))
        scale = np.array([a.sensor_scale_um for a in axes])
        offset = np.array([a.sensor_offset_um for a in axes])
        u = scale * raw.astype(float) + offset
        v = volt.astype(float)
        valid = np.isfinite(u) & np.isfinite(v)
        if channels is None:
            return Recording(v[:, 0], u[:, 0], valid[:, 0])
        return Recording(v, u, valid)

    def play(self, waveform_v: ArrayLike, on_block: BlockCallback | None = None, *,
             poll_s: float = 0.01, timeout_s: float | None = None) -> Recording:
        """Play a waveform of any length and read back what the stage did, block by block.

        A waveform that fits the device's table is uploaded and run once; a longer one is
        streamed: the first table-full is uploaded, the stream started, and each half of the table
        is refilled as soon as the generator has played it (double buffering). The recorder is
        read while the stage runs and every new contiguous block is handed to ``on_block`` in
        order, so the caller can write it to disk as it arrives.

        Link capacity: before a streamed run starts, the link's upload rate (timed on the first
        table) and readback rate (timed on a few recorder reads; capped by the baud rate on a real
        UART, :meth:`uart_rates`) are compared with what the run needs at the sample rate. If
        refilling and reading along do not both fit, the recorder is read after the run instead
        (when it holds the whole run); if even that does not fit, :class:`LinkCapacityError`.

        Watchdog: with :attr:`watchdog_s` > 0 the device's watchdog is set to it and armed (a
        heartbeat) just before the start, fed with four heartbeats per period (also between the
        blocks of a refill or readback) while the run plays, and disarmed (period 0) once the
        device reports the run over. A host that dies mid-run stops feeding it: the device stops
        and ramps to 0 V within one period.

        Parameters
        ----------
        waveform_v : array_like, shape (N,) or (N, C)
            Voltage per sample, V (sent as float32): shape (N,) plays channel 0 (any other channel
            holds its output); (N, C) plays every channel, C = :attr:`channels`, column ``c``
            on channel ``c`` (the profile's axis ``axis_names[c]``).
        on_block : callable, optional
            ``on_block(first_index, voltage_v, displacement_um, valid)`` with arrays of shape (m,)
            or (m, C) like the waveform (V, um, bool) for samples ``first_index ..
            first_index+m-1``; the blocks are in order, contiguous and cover ``[0, N)`` even when
            the run fails (samples never measured are NaN with ``valid=False``), unless on_block
            itself raised.
        poll_s : float
            Pause between polls when there is nothing to do, s.
        timeout_s : float, optional
            Longest time the call may take, s (default: the first table at
            :data:`~afmctl.drivers.player.UPLOAD_FLOOR`, then N / sample rate + 5 s + N at the measured
            readback rate). No request is attempted after it; the call then ends within one
            request's timeout, plus the safe state's retries.

        Returns
        -------
        Recording
            All N samples, each array of the waveform's shape (per channel, each with its axis's
            sensor calibration); samples the recorder no longer (or never) held are NaN with
            ``valid=False``.

        Raises
        ------
        StageError
            The device refused a command or stopped early (e.g. code 10: underrun, the host fell
            behind; the device has ramped to 0 V).
        TimeoutError
            The run did not finish by its deadline.

        afmctl.guard.LimitError
            The waveform (as float32, from the stage's present output) violates the profile's
            voltage, slew or current limits on some channel (each against its own axis's);
            nothing was sent.
        LinkCapacityError
            The link cannot carry this streamed run; nothing was played (the first table was
            uploaded), ``on_block`` was not called.

        Before anything is sent the waveform is checked against the profile's limits (the device
        checks again). Recorder reads that fail after their retries leave those samples missing
        (``valid=False``) and the run goes on. On any exception or KeyboardInterrupt the stage is
        put in the safe state (best effort: a failure of that is attached as a note), the samples
        not yet delivered are handed to ``on_block`` (read back if the link still works, else
        missing), and the exception propagates.
        """
        v = self._as_sent(waveform_v)
        player = Player(self, v, on_block, poll_s)
        try:
            self.check_limits()
            self.check_waveform(v)
            self._ensure_rate()
            return player.run(timeout_s)
        except (guard.LimitError, LinkCapacityError, LimitMismatchError):
            raise  # refused before anything played: the stage stays where it is
        except BaseException as exc:
            self._deadline = None
            self._safe_state_quietly(exc)
            link = isinstance(exc, TimeoutError) or (isinstance(exc, StageError) and exc.code < 0)
            expired = link and player.started and self._watchdog_expired_quietly()
            player.disarm_after(exc)
            player.abandon(exc)
            if expired:
                raise StageError(8, f"during the run, after the link failed ({exc}): the device "
                                    f"had no heartbeat for {self.watchdog_s:g} s (the host fell "
                                    f"behind, e.g. a loaded machine): raise [transport] "
                                    f"watchdog_s, or lighten the load") from exc
            raise
        finally:
            self._deadline = None

    def _as_sent(self, waveform_v: ArrayLike) -> NDArray[np.float32]:
        """``waveform_v`` as :meth:`play` sends it (float32, shape (N,) or (N, C)); ValueError
        for an empty one or one of another number of channels than the device and profile."""
        v = np.asarray(waveform_v, dtype=np.float32)
        v = v.ravel() if v.ndim < 2 else v
        if v.size == 0:
            raise ValueError("empty waveform")
        names = self.profile.axis_names
        if v.ndim == 2 and not v.shape[1] == self.channels == len(names):
            raise ValueError(f"a waveform of {v.shape[1]} channels for a device of "
                             f"{self.channels} and a profile of {len(names)} axes: give shape "
                             f"(N,) or (N, C) with C channels and axes")
        return v

    def check_waveform(self, waveform_v: ArrayLike) -> None:
        """The guard of :meth:`play`: every channel of ``waveform_v`` (shape (N,) or (N, C), V, as
        sent: float32) against its own axis profile's limits, from the channel's present output
        (:func:`afmctl.guard.check`). Nothing is sent; a command calls it to refuse a waveform
        before it writes anything, and :meth:`play` calls it again before it sends.

        Raises
        ------
        afmctl.guard.LimitError
            A sample or step outside the limits (the message names the axis on two).
        """
        v = self._as_sent(waveform_v)
        cols = v[:, None] if v.ndim == 1 else v
        names = self.profile.axis_names
        for c in range(cols.shape[1]):
            what = "waveform" if v.ndim == 1 else f"waveform, axis {names[c]} (channel {c})"
            guard.check(cols[:, c].astype(float), 1.0 / self.profile.sample_rate_hz,
                        self.profile.axis(names[c]).limits, self.voltage(c), what)

    def _ensure_rate(self) -> None:
        """Clock the device at the profile's sample rate: timestamps, the model's discretization
        and the slew check all assume it. StageError if the device will not take it."""
        want = self.profile.sample_rate_hz
        if math.isclose(self.status().sample_rate_hz, want, rel_tol=1e-6):
            return
        self.set_sample_rate(want)
        got = self.status().sample_rate_hz
        if not math.isclose(got, want, rel_tol=1e-6):
            raise StageError(-1, f"the device clocks {got:g} Hz; the profile says {want:g} Hz")

    def _watchdog_expired_quietly(self) -> bool:
        """Whether the device says its watchdog expired (False if the link cannot tell)."""
        try:
            st = self.status()
        except (StageError, TimeoutError):
            return False
        return st.watchdog_expired or st.last_error == 8

    def _safe_state_quietly(self, cause: BaseException) -> None:
        """Best-effort safe state after ``cause``; never replaces it (a failure becomes a note)."""
        try:
            self.safe_state()
        except BaseException as exc:  # noqa: BLE001 - the original exception is what matters
            cause.add_note(f"safe_state() after this failed too: {exc!r}")

    def __enter__(self) -> StageBase:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


#: The stage interface (an abstract base class: implementations inherit the composed operations).



def open_stage(profile: Profile, **options: Any) -> StageBase:
    """Open the stage a profile describes.

    Parameters
    ----------
    profile : Profile
    **options
        Passed to the implementation, e.g. ``emulator=`` for the in-process stage or ``url=``
        to override a serial URL.
    """
    t = profile.transport
    if isinstance(t, EmulatedTransport):
        from afmctl.drivers.inprocess import InProcessStage
        return InProcessStage(profile, **options)
    if isinstance(t, SerialTransport):
        from afmctl.drivers.serial_link import SerialStage
        return SerialStage(profile, **options)
    if isinstance(t, ModbusTcpTransport | ModbusRtuTransport):
        from afmctl.drivers.modbus_link import ModbusStage
        return ModbusStage(profile, **options)
    raise TypeError(f"unknown transport {t!r}")
