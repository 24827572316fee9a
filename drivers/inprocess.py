"""The emulated stage in-process: the :class:`~afmctl.drivers.StageBase` interface on an
:class:`~afmctl.drivers.device.emulator.Emulator`, with no wire (tests, and ``afmctl track``
without hardware)."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
from numpy.typing import NDArray

from afmctl.drivers import StageBase
from afmctl.drivers.device.emulator import IDENTITY, IDENTITY_CHANNELS, Emulator
from afmctl.drivers.protocol import Status
from afmctl.errors import DeviceError, StageError
from afmctl.files.profile import Profile


@contextmanager
def _refusals() -> Iterator[None]:
    try:
        yield
    except DeviceError as exc:
        raise StageError(exc.code, str(exc)) from None


class InProcessStage(StageBase):
    """Drive an emulated device by direct calls.

    Parameters
    ----------
    profile : Profile
        With an ``[emulator]`` section.
    emulator : Emulator, optional
        An existing device (e.g. to inspect its applied-sample log); built from the profile if
        omitted.
    clock : callable, optional
        Device time, s; ``time.monotonic`` by default.
    lock : threading.Lock, optional
        Serializes calls into the device; pass the lock of whoever else drives the same emulator
        (e.g. ``EmulatedDevice.lock``, whose ticker advances it).
    """

    upload_chunk = 1 << 20
    read_chunk = 1 << 20

    def __init__(self, profile: Profile, emulator: Emulator | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 lock: threading.Lock | None = None) -> None:
        super().__init__(profile)
        self.emulator = Emulator(profile) if emulator is None else emulator
        self.clock = clock
        self._now = math.nan  # until the first call
        self._lock = threading.Lock() if lock is None else lock
        self._channels = self.emulator.channels

    def _call(self, fn: Callable[..., object], *args: object, **kwargs: object) -> object:
        with self._lock, _refusals():
            self._now = self.clock()
            return fn(*args, self._now, **kwargs)

    def now_s(self) -> float:
        """The device's clock as of the last call into it, s (read without advancing it: a
        clock that steps per reading is not moved by asking)."""
        return self._now

    def _started_at(self, sent_s: float) -> float:
        return self._now  # the device time the start was given

    def identify(self) -> str:
        return f"{IDENTITY_CHANNELS if self.channels > 1 else IDENTITY} (in-process)"

    def status(self) -> Status:
        return self._call(self.emulator.status)  # type: ignore[return-value]

    def limits(self, channel: int = 0) -> tuple[float, float, float]:
        with _refusals():
            lim = self.emulator.channel_limits_of(channel)
        return lim.v_min, lim.v_max, lim.slew_v_per_ms

    def voltage(self, channel: int = 0) -> float:
        return self._call(self.emulator.output, channel=channel)  # type: ignore[return-value]

    def set_voltage(self, v: float, channel: int = 0) -> None:
        self._call(self.emulator.set_voltage, float(v), channel=channel)

    def stop(self) -> None:
        self._call(self.emulator.stop)

    def safe_state(self) -> None:
        self._call(self.emulator.safe_state)

    def heartbeat(self) -> None:
        self._call(self.emulator.heartbeat)

    def set_watchdog(self, period_s: float) -> None:
        self._call(self.emulator.set_watchdog, float(period_s))

    def set_sample_rate(self, hz: float) -> None:
        self._call(self.emulator.set_sample_rate, float(hz))

    def close(self) -> None:
        pass

    def _set_table_length(self, n: int) -> None:
        self._call(self.emulator.set_table_length, n)

    def _write_chunk(self, first: int, values: NDArray[np.float32], channel: int = 0) -> None:
        self._call(self.emulator.write_table, first, values, channel=channel)

    def _start(self, cycles: int) -> None:
        self._call(self.emulator.start, cycles)

    def _read_chunk(self, first: int, n: int, channel: int = 0
                    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        return self._call(self.emulator.read_recorder, first, n,  # type: ignore[return-value]
                          channel=channel)

    def _start_stream(self, n_total: int) -> None:
        self._call(self.emulator.start_stream, n_total)

    def _capacities(self) -> tuple[int, int]:
        return self.emulator.tables.shape[1], self.emulator.rec_global.size


def accelerated(speed: float) -> Callable[[], float]:
    """A device clock that runs ``speed`` times faster than ``time.monotonic`` (tests and
    benchmarks: a 7 s sweep is recorded in 7/speed s through the same stage interface)."""
    t0 = time.monotonic()
    return lambda: t0 + speed * (time.monotonic() - t0)
