"""One :meth:`afmctl.drivers.StageBase.play`: the host's side of a (possibly streamed) run.

Uploads the first table, checks that the link can carry the run (:class:`~afmctl.drivers.stage.
LinkCapacityError` if not), arms the device's watchdog, starts the run, refills the table as the
generator plays it (double buffering), feeds the watchdog, reads the recorder back block by block
and hands every sample to ``on_block`` exactly once, measured or missing.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from afmctl.errors import LinkCapacityError, StageError, StageTimeoutError, StoppedError

if TYPE_CHECKING:
    from afmctl.drivers.stage import StageBase

#: ``on_block(first_index, voltage_v, displacement_um, valid)`` of :meth:`StageBase.play`.
BlockCallback = Callable[[int, NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]], None]


@dataclass(frozen=True)
class Recording:
    """Recorder contents of one run.

    Attributes
    ----------
    voltage_v : ndarray, shape (N,) or (N, C)
        Voltage on the stack during each sample, V (NaN where missing); one column per channel
        when the waveform played had one.
    displacement_um : ndarray, shape (N,) or (N, C)
        Sensor displacement at each sample instant, um (NaN where missing).
    valid : ndarray of bool, shape (N,) or (N, C)
        False for samples the device had not recorded.
    started_s : float or None
        When the first sample went out, s, on the stage's clock (:meth:`StageBase.now_s`;
        None where not known): what tells a model how long the stage held between two runs
        (creep keeps moving through a hold).
    run_count : int or None
        The run's number on the device's run counter (``Status.run_count`` once it started):
        a later reading of the counter says whether anything ran since.
    """

    voltage_v: NDArray[np.float64]
    displacement_um: NDArray[np.float64]
    valid: NDArray[np.bool_]
    started_s: float | None = None
    run_count: int | None = None

    @property
    def complete(self) -> bool:
        return bool(self.valid.all())


#: Seconds a run may overrun its nominal duration before :meth:`StageBase.play` gives up.
PLAY_MARGIN_S = 5.0
#: Upload rate, samples/s, that :meth:`StageBase.play`'s default timeout allows for the first table
#: (below every transport's measured rate).
UPLOAD_FLOOR = 2000.0
#: Recorder reads timed to measure a link's readback rate before a run (the median counts).
RATE_PROBES = 3


class Player:
    """One :meth:`StageBase.play`: the host's side of a (possibly streamed) run.

    ``written`` is the next global sample to send, ``delivered`` the next one to read back. ``v``
    is (N,) for channel 0 alone or (N, C) for channels ``0 .. C-1``; the arrays kept and handed
    over have its shape.
    """

    def __init__(self, stage: StageBase, v: NDArray[np.float32], on_block: BlockCallback | None,
                 poll_s: float) -> None:
        if v.size == 0:
            raise ValueError("empty waveform")
        self.stage, self.v, self.on_block, self.poll_s = stage, v, on_block, poll_s
        self.n = len(v)
        #: Channels read back (None: channel 0 alone, arrays of shape (N,)).
        self.columns = None if v.ndim == 1 else v.shape[1]
        #: Channels written: the waveform's columns (channel ``c`` in column ``c``).
        self.width = self.columns or 1
        self.table = self.half = self.recorder_capacity = 0  # the device's, once run() starts
        self.started = False  # whether a run of this waveform was started on the device
        self.written = self.delivered = 0
        self.in_callback = False
        self.read_along = True  # read the recorder while the run plays (else after it)
        self.period = 0.0  # the device's watchdog period while this run plays, s
        self.armed = False  # whether this play armed the watchdog (and must disarm it)
        self.last_heartbeat = -np.inf
        self.u = np.full(v.shape, np.nan)
        self.volt = np.full(v.shape, np.nan)
        self.valid = np.zeros(v.shape, dtype=bool)

    def run(self, timeout_s: float | None) -> Recording:
        stage, n = self.stage, self.n
        fs = stage.profile.sample_rate_hz
        table, self.recorder_capacity = stage.capacities()
        self.table = min(table, n)
        self.half = max(1, self.table // 2)
        t0 = time.monotonic()
        limit = self.table / UPLOAD_FLOOR + PLAY_MARGIN_S if timeout_s is None else timeout_s
        stage.set_deadline(t0 + limit)
        took = stage.upload(self.v[:self.table])
        up_rate = min(self.table, stage.upload_chunk) / max(float(np.median(took)) * self.width,
                                                            1e-9)
        down_rate = self._readback_rate()
        self.read_along = self._plan(up_rate, down_rate)
        if timeout_s is None:
            limit = time.monotonic() - t0 + n / fs + PLAY_MARGIN_S + n / down_rate
            stage.set_deadline(t0 + limit)
        self.written = self.table
        self._arm()
        self.started = True  # from here on the device may be playing this waveform
        stage.start_run(n, streamed=n > self.table or n > self.recorder_capacity)
        while True:
            st = stage.status()
            if st.running and st.watchdog_s > 0:
                self.period = st.watchdog_s
            elif not st.running:
                self._disarm()
            self._feed()
            busy = self._refilled(st.play_position) if st.running else False
            busy |= self._deliver(st.play_position, st.running)
            if not st.running and self.delivered >= st.play_position:
                break
            if stage.past_deadline():
                raise StageTimeoutError(f"run not done after {limit:.3g} s ({st.play_position} of {n} "
                                   f"samples played, {self.delivered} read back)")
            if not busy:
                time.sleep(self.poll_s)
        if st.play_position < n:
            raise self._stopped(st)
        return Recording(self.volt, self.u, self.valid, stage.run_started_s,
                         stage.run_count)

    def _stopped(self, st: Any, refusal: StageError | None = None) -> StageError:
        """Why the device stopped the run early (``st``: its status after it stopped): its
        watchdog, an underrun, an error of its own, or, with none, something else stopped it
        (:class:`StoppedError`). After a refused refill (``refusal``) the device's last error is
        the refusal's own; the play position then tells: an underrun stops at the first sample
        not yet written."""
        played = f"the run stopped after {st.play_position} of {self.n} samples"
        if st.watchdog_expired or st.last_error == 8:
            return StageError(8, f"{played}: the device had no heartbeat for {self.stage.watchdog_s:g} s "
                                 f"(the host fell behind, e.g. a loaded machine)")
        streamed = self.n > self.table
        if st.last_error == 10 or (refusal is not None and streamed
                                   and st.play_position >= self.written):
            return StageError(10, f"{played}: the host fell behind refilling the table")
        if refusal is None and st.last_error:
            return StageError(st.last_error, played)
        return StoppedError(played)

    # -- link capacity ---------------------------------------------------------------------------
    def _readback_rate(self) -> float:
        """The link's readback rate, samples/s: one request's samples over the median time of
        :data:`RATE_PROBES` timed recorder reads (a failed read counts as its time; the median
        ignores a single delayed or retried reply, as the upload's rate ignores a few chunks)."""
        m = max(1, min(self.stage.read_chunk, self.recorder_capacity))
        took = []
        for _ in range(RATE_PROBES):
            t0 = time.monotonic()
            self.stage.read_recorder(m, 0, missing_ok=True, channels=self.columns)
            took.append(time.monotonic() - t0)
        return m / max(float(np.median(took)), 1e-9)

    def _plan(self, up_rate: float, down_rate: float) -> bool:
        """Whether to read the recorder while the run plays (True) or after it (False).

        A run played from the table needs nothing from the link while it plays. A streamed one
        longer than the table needs ``fs`` samples/s up (each half table is refilled while the
        other half plays; an excess ``e`` of less than a half table ``h`` needs ``fs e / h``). One
        longer than the recorder (``R`` samples) needs ``fs (N - R) / N`` down: sample ``j`` is read
        at ``j / rate`` and overwritten at ``(j + R) / fs``, the worst ``j`` being ``N - R``. On one
        link: ``up_needed / up + down_needed / down <= 1``. If reading along does not fit but the
        recorder holds the whole run, only the refill must: ``up_needed / up <= 1``.

        Raises
        ------
        LinkCapacityError
            Neither fits.
        """
        n, fs = self.n, self.stage.profile.sample_rate_hz
        uart = self.stage.uart_rates()
        if uart is not None:
            up_rate, down_rate = min(up_rate, uart[0]), min(down_rate, uart[1])
        refill, read = n > self.table, n > self.recorder_capacity
        if not (refill or read):
            return True
        up_needed = fs * min(1.0, (n - self.table) / self.half)
        down_needed = fs * max(0, n - self.recorder_capacity) / n
        load_up = up_needed / up_rate
        if load_up + (down_needed if read else fs) / down_rate <= 1.0:
            return True
        if not read and load_up <= 1.0:
            return False
        needs = " and ".join(f"{rate:.0f} samples/s {way}" for rate, way, on in (
            (up_needed, "up (refilling the table)", refill),
            (down_needed, "down (reading the recorder)", read)) if on)
        raise LinkCapacityError(
            f"the link cannot carry this run: {n} samples at {fs:g} Hz stream through a "
            f"{self.table}-sample table and a {self.recorder_capacity}-sample recorder, which "
            f"needs {needs}; the link carries about {up_rate:.0f} samples/s up and "
            f"{down_rate:.0f} down (measured{', capped by the baud rate' if uart else ''}). "
            f"Lower the sample rate, shorten the run to the table, or use a faster link")

    # -- watchdog ----------------------------------------------------------------------------
    def _arm(self) -> None:
        """Set and arm the device's watchdog (period :attr:`StageBase.watchdog_s`) for the run."""
        period = self.stage.watchdog_s
        if period <= 0:
            return
        self.stage.set_watchdog(period)
        self.stage.heartbeat()
        self.period, self.armed, self.last_heartbeat = period, True, time.monotonic()

    def _feed(self) -> None:
        """Keep the device's watchdog fed while the run plays (four heartbeats per period)."""
        now = time.monotonic()
        if self.period > 0 and now - self.last_heartbeat >= self.period / 4:
            self.stage.heartbeat()
            self.last_heartbeat = now

    def _disarm(self) -> None:
        """The run is over: disarm the watchdog this play armed (period 0), stop feeding it."""
        if self.armed:
            self.stage.set_watchdog(0.0)
            self.armed = False
        self.period = 0.0

    def disarm_after(self, cause: BaseException) -> None:
        """After a failed run (the stage already safe): disarm the watchdog this play armed, so
        that it does not expire on the idle device later and leave error 8 (watchdog expired)
        behind an interrupt; skipped when the link itself failed. A failure becomes a note."""
        if not self.armed or isinstance(cause, TimeoutError) or (
                isinstance(cause, StageError) and cause.code < 1):
            return
        try:
            self._disarm()
        except (StageError, TimeoutError) as exc:
            cause.add_note(f"disarming the watchdog after this failed too: {exc!r}")

    def _refilled(self, position: int) -> bool:
        """:meth:`_refill`; a block refused because the run has meanwhile stopped (an underrun, a
        slew fault, the watchdog) says so: the refusal alone would hide why."""
        try:
            return self._refill(position)
        except StageError as refusal:
            if refusal.code < 1:
                raise
            st = self.stage.status()
            if st.running:
                raise
            raise self._stopped(st, refusal) from refusal

    def _refill(self, position: int) -> bool:
        """Send the next half-table if the generator has played the samples its slots held."""
        n = self.n
        if self.written >= n or self.written + self.half > position + self.table:
            return False
        end = min(n, self.written + self.half)
        chunk = self.stage.upload_chunk
        cols = self.v[:, None] if self.columns is None else self.v
        for c in range(self.width):  # channel by channel: a link that selects one, once
            for first in range(self.written, end, chunk):
                self.stage.write_block(first, np.ascontiguousarray(
                    cols[first:min(end, first + chunk), c]), c)
                self._feed()
        self.written = end
        return True

    def _deliver(self, position: int, running: bool) -> bool:
        """Read back recorded samples not yet delivered and hand them to ``on_block``; samples
        already overwritten in the recorder ring are NaN, invalid. While running, at most four read
        requests (or a quarter table) per call, so that refilling the table, which cannot wait,
        comes round again soon (nothing if the link reads back after the run); once stopped,
        everything left."""
        if running and not self.read_along:
            return False
        most = max(1, min(self.half // 2, 4 * self.stage.read_chunk)) if running else position
        end = min(position, self.delivered + most)
        if end <= self.delivered:
            return False
        first, lost = self.delivered, max(self.delivered, position - self.recorder_capacity)
        rec = (self.stage.read_recorder(end - lost, lost, missing_ok=True, channels=self.columns)
               if end > lost else None)
        if rec is not None:
            sl = slice(lost, end)
            self.volt[sl], self.u[sl], self.valid[sl] = (rec.voltage_v, rec.displacement_um,
                                                          rec.valid)
        self._hand_over(first, end)
        return True

    def _hand_over(self, first: int, end: int) -> None:
        """Samples ``first .. end-1`` are final: count them delivered, pass them to on_block.

        A Ctrl-C (SIGINT) that arrives while on_block runs is held until it returns, so a block
        is handed over whole (a run file never ends in half a block) and the interrupt is then
        handled like one anywhere else in the run (the rest handed over by :meth:`abandon`); an
        exception of on_block's own ends the hand-over (``in_callback`` stays set). The samples
        count as delivered, and ``in_callback`` is set, only once Ctrl-C is held: an interrupt
        just before leaves them to :meth:`abandon`, never lost between the two."""
        if self.on_block is None or end <= first:
            self.delivered = max(self.delivered, end)
            return
        sl = slice(first, end)
        with _sigint_held():
            self.delivered = end
            self.in_callback = True
            self.on_block(first, self.volt[sl].copy(), self.u[sl].copy(), self.valid[sl].copy())
            self.in_callback = False

    def abandon(self, cause: BaseException) -> None:
        """After a failed run (the stage already safe): hand every sample not yet delivered to
        on_block, read back if the cause was not the link and the link still answers, else
        missing. Nothing is done if on_block itself raised ``cause``; a failure here becomes a
        note on ``cause``."""
        if self.in_callback:
            return
        try:
            if self.started and not isinstance(cause, StageError | TimeoutError):
                self._deliver(self.stage.status().play_position, running=False)
        except (StageError, TimeoutError) as exc:
            cause.add_note(f"reading back the rest after this failed too: {exc!r}")
        try:
            self._hand_over(self.delivered, self.n)
        except Exception as exc:  # noqa: BLE001 - the original exception is what matters
            cause.add_note(f"handing over the missing samples failed: {exc!r}")


@contextmanager
def _sigint_held() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) until the block ends, then raise KeyboardInterrupt if one came.

    Only the main thread receives Python's signal handlers; elsewhere this does nothing, as it
    does when SIGINT is ignored (a process started in the background, ``nohup``)."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is signal.SIG_IGN):
        yield
        return
    came: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, _frame: came.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if came:
        raise KeyboardInterrupt
