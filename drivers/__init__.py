"""Device I/O for afmctl: the stage interface, its implementations and the emulator's servers.

This package is the only place that imports pyserial or pymodbus; :mod:`afmctl` never imports it
at import time. The layers, from the application down to the wire and back up to the device:

``Stage`` (this module)
    One small interface for a stage: :meth:`~StageBase.upload` a waveform, :meth:`~StageBase.run`
    it, :meth:`~StageBase.wait` until done, :meth:`~StageBase.read_recorder`, ``set_voltage``,
    ``status``, ``safe_state`` (stop and ramp to 0 V), ``heartbeat``, ``close``.
    :class:`StageBase` composes chunked upload and readback from a few primitives that each
    implementation supplies; :func:`open_stage` picks the implementation from a profile.
Implementations (host side)
    :mod:`drivers.serial_link` speaks the ASCII protocol over any pyserial URL (a port, a pty path,
    ``socket://host:port``); :mod:`drivers.modbus_link` speaks the register map over Modbus TCP or
    RTU (every pymodbus client call lives there); :mod:`drivers.inprocess` calls an emulated device
    directly (the no-hardware default; same interface, no wire).
Protocols (pure, no I/O)
    :mod:`drivers.ascii_protocol` and :mod:`drivers.register_map` define protocol version 1
    (``docs/protocol.md``): the codecs the host uses and the interpreters the emulated device runs.
Device side
    :mod:`afmctl.emulator` is the device's logic (model in device time, limits, watchdog; no I/O).
    :mod:`drivers.servers` serves it over a pty or socket (ASCII), Modbus TCP and Modbus RTU, on
    127.0.0.1 unless told otherwise.

Units on this interface: volts, micrometres (sensor scale and offset from the profile applied),
seconds. Every blocking call has a timeout; none can hang.
"""

from __future__ import annotations

import abc
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from afmctl.emulator import ERRORS, Status
from afmctl.profile import (
    EmulatedTransport,
    ModbusRtuTransport,
    ModbusTcpTransport,
    Profile,
    SerialTransport,
)

__all__ = ["StageError", "Recording", "Status", "Stage", "StageBase", "open_stage"]


class StageError(RuntimeError):
    """The stage refused a command (``code`` from :data:`afmctl.emulator.ERRORS`, or -1 for a
    protocol or transport failure)."""

    def __init__(self, code: int, detail: str = "") -> None:
        what = ERRORS.get(code, "transport or protocol failure")
        super().__init__(f"stage error {code}: {what}" + (f" ({detail})" if detail else ""))
        self.code = code


@dataclass(frozen=True)
class Recording:
    """Recorder contents of one run.

    Attributes
    ----------
    voltage_v : ndarray, shape (N,)
        Voltage on the stack during each sample, V (NaN where missing).
    displacement_um : ndarray, shape (N,)
        Sensor displacement at each sample instant, um (NaN where missing).
    valid : ndarray of bool, shape (N,)
        False for samples the device had not recorded.
    """

    voltage_v: NDArray[np.float64]
    displacement_um: NDArray[np.float64]
    valid: NDArray[np.bool_]

    @property
    def complete(self) -> bool:
        return bool(self.valid.all())


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

    def __init__(self, profile: Profile) -> None:
        self.profile = profile
        self._last_run_samples = 0

    # -- primitives ----------------------------------------------------------------------------
    @abc.abstractmethod
    def identify(self) -> str: ...

    @abc.abstractmethod
    def status(self) -> Status: ...

    @abc.abstractmethod
    def limits(self) -> tuple[float, float, float]:
        """The device's own limits: v_min (V), v_max (V), slew (V/ms)."""

    def voltage(self) -> float:
        """Output voltage now, V."""
        return self.status().output_v

    @abc.abstractmethod
    def set_voltage(self, v: float) -> None:
        """DC output, V (refused outside the limits or beyond one slew-limited step)."""

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
    def _write_chunk(self, first: int, values: NDArray[np.float32]) -> None: ...

    @abc.abstractmethod
    def _start(self, cycles: int) -> None: ...

    @abc.abstractmethod
    def _read_chunk(self, first: int, n: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Raw sensor and voltage of samples ``first .. first+n-1``, float32, NaN if missing."""

    # -- composed operations -------------------------------------------------------------------
    def upload(self, waveform_v: ArrayLike) -> None:
        """Load the waveform table, V, shape (N,) (sent as float32, in chunks)."""
        v = np.asarray(waveform_v, dtype=np.float32).ravel()
        if v.size == 0:
            raise ValueError("empty waveform")
        self._set_table_length(v.size)
        for first in range(0, v.size, self.upload_chunk):
            self._write_chunk(first, v[first:first + self.upload_chunk])

    def run(self, cycles: int = 1) -> None:
        """Start clocking out the table ``cycles`` times, recording every sample."""
        n = self.status().table_length
        self._start(cycles)
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
                raise TimeoutError(f"stage still running after {limit:.3g} s")
            time.sleep(poll_s)
        return st

    def read_recorder(self, n: int | None = None, first: int = 0) -> Recording:
        """Read ``n`` recorder samples from ``first`` (default: all of the last run)."""
        n = self._last_run_samples - first if n is None else n
        raw = np.full(n, np.nan, dtype=np.float32)
        volt = np.full(n, np.nan, dtype=np.float32)
        for off in range(0, n, self.read_chunk):
            m = min(self.read_chunk, n - off)
            raw[off:off + m], volt[off:off + m] = self._read_chunk(first + off, m)
        u = self.profile.sensor_scale_um * raw.astype(float) + self.profile.sensor_offset_um
        v = volt.astype(float)
        return Recording(v, u, np.isfinite(u) & np.isfinite(v))

    def __enter__(self) -> StageBase:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


#: The stage interface (an abstract base class: implementations inherit the composed operations).
Stage = StageBase


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
        from drivers.inprocess import InProcessStage
        return InProcessStage(profile, **options)
    if isinstance(t, SerialTransport):
        from drivers.serial_link import SerialStage
        return SerialStage(profile, **options)
    if isinstance(t, ModbusTcpTransport | ModbusRtuTransport):
        from drivers.modbus_link import ModbusStage
        return ModbusStage(profile, **options)
    raise TypeError(f"unknown transport {t!r}")


