"""Host side of the Modbus register map (``afmctl.drivers.register_map``) on pymodbus (TCP and RTU).

Every pymodbus client call of afmctl lives in this module (the emulated device's servers:
``afmctl.drivers.device.modbus_server``). One
request is in flight at a time; the client has a timeout; a refused request (Modbus exception
response) is turned into :class:`~afmctl.drivers.StageError` carrying the device's own error code, read
from ``IR.LAST_ERROR``; a transport failure (no reply, a bad CRC on RTU, a stale transaction id on
TCP, a dropped connection) becomes ``StageError(-1)``. pymodbus's own retries are off: afmctl
retries idempotent requests itself (see :mod:`drivers`), after a resync that closes and reopens
the connection, so that nothing of a failed exchange can be taken for a later reply.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from afmctl.drivers import StageBase
from afmctl.drivers import register_map as rm
from afmctl.drivers.protocol import Status
from afmctl.drivers.register_map import HR, IR
from afmctl.drivers.serial_link import is_uart
from afmctl.errors import StageError
from afmctl.files.profile import ModbusRtuTransport, ModbusTcpTransport, Profile


def make_client(transport: ModbusTcpTransport | ModbusRtuTransport) -> Any:
    """A pymodbus sync client for the transport (not yet connected)."""
    if isinstance(transport, ModbusTcpTransport):
        return ModbusTcpClient(transport.host, port=transport.port, timeout=transport.timeout_s,
                               retries=0)
    return ModbusSerialClient(transport.port, framer=FramerType.RTU, baudrate=transport.baudrate,
                              timeout=transport.timeout_s, retries=0)


class ModbusStage(StageBase):
    """A stage on the register map.

    Parameters
    ----------
    profile : Profile
        Transport ``modbus-tcp`` or ``modbus-rtu``.
    transport : ModbusTcpTransport or ModbusRtuTransport, optional
        Overrides the profile's transport (e.g. a server on an ephemeral port).
    """

    upload_chunk = rm.STREAM_BLOCK_SAMPLES
    read_chunk = rm.READ_SAMPLES

    def __init__(self, profile: Profile,
                 transport: ModbusTcpTransport | ModbusRtuTransport | None = None) -> None:
        super().__init__(profile)
        t = transport or profile.transport
        if not isinstance(t, ModbusTcpTransport | ModbusRtuTransport):
            raise TypeError(f"not a Modbus transport: {t!r}")
        self.unit = t.unit
        self.timeout_s = t.timeout_s
        self.watchdog_s = t.watchdog_s
        self._transport = t
        self._client = make_client(t)
        self._lock = threading.Lock()  # sync pymodbus clients are not thread-safe
        self._page = -1
        if not self._client.connect():
            self._client.close()
            raise StageError(-1, f"cannot connect to {t}")
        try:
            version = self._request("read_input_registers", IR.MAP_VERSION, count=1)[0]
        except StageError:
            self.close()  # nothing answers: leave no socket open behind the error
            raise
        if version not in rm.MAP_VERSIONS:
            self.close()
            raise StageError(-1, f"register map version {version}, afmctl speaks "
                                 f"{' or '.join(map(str, rm.MAP_VERSIONS))}")
        #: The register map version the device reports, which this link speaks.
        self.version = version
        #: The channel selected in ``HR.CHANNEL`` as far as this link knows (-1: not known).
        self._channel = -1
        if version >= rm.CHANNELS_MAP_VERSION:
            self._channels = self._request("read_input_registers", IR.CHANNELS, count=1)[0]

    def _request(self, name: str, *args: Any, idempotent: bool = True, **kwargs: Any
                 ) -> list[int]:
        """One client call (retried on transport failure if ``idempotent``) -> its registers."""
        res = self._retrying(lambda: self._call(name, *args, **kwargs), idempotent)
        if res.isError():
            code = self._retrying(self._device_error)
            raise StageError(code, f"{name} at {args[0]}: Modbus exception "
                                   f"{getattr(res, 'exception_code', '?')}")
        return list(getattr(res, "registers", []) or [])

    def _call(self, name: str, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            try:
                return getattr(self._client, name)(*args, device_id=self.unit, **kwargs)
            except (ModbusException, OSError) as exc:
                raise StageError(-1, f"{name}: {self._said(exc)}") from None

    def _said(self, exc: BaseException) -> str:
        """A failed exchange in afmctl's words (pymodbus's speak of its own retries, which
        afmctl turns off: it retries itself)."""
        if isinstance(exc, ConnectionException):
            return f"connection to {self._transport} failed or was lost"
        if isinstance(exc, ModbusIOException) or "No response" in str(exc):
            return f"no reply within {self.timeout_s:g} s"
        return str(exc)

    def _device_error(self) -> int:
        """The device's own code for the refusal just answered (``IR.LAST_ERROR``)."""
        res = self._call("read_input_registers", IR.LAST_ERROR, count=1)
        return -1 if res.isError() else int(res.registers[0])

    def _resync(self) -> None:
        with self._lock:
            self._client.close()
            time.sleep(min(0.05, self.timeout_s))
            if not self._client.connect():
                raise StageError(-1, "cannot reconnect")

    def _write(self, address: int, regs: list[int], idempotent: bool = True) -> None:
        self._request("write_registers", address, regs, idempotent=idempotent)

    def uart_rates(self) -> tuple[float, float] | None:
        """Modbus RTU on a real UART: what its baud rate carries (10 bits per byte) with the
        register map's blocks (:func:`~afmctl.drivers.register_map.rtu_bytes_per_sample`). None for TCP,
        a socket or a pty."""
        t = self._transport
        if not isinstance(t, ModbusRtuTransport) or not is_uart(getattr(self._client, "socket", None)):
            return None
        up, down = rm.rtu_bytes_per_sample()
        return t.baudrate / 10 / up, t.baudrate / 10 / down

    # -- diagnostics (the conformance check) ---------------------------------------------------
    def echo(self, address: int, value: int) -> int:
        """Write single register (FC6) ``value`` at ``address``; the value the device echoed.
        StageError (the device's code) if refused."""
        res = self._retrying(lambda: self._call("write_register", address, value))
        if res.isError():
            raise StageError(self._retrying(self._device_error), f"FC6 at {address}")
        return int(res.registers[0])

    def write_exception(self, address: int, regs: list[int]) -> int:
        """The Modbus exception code a raw FC16 write of ``regs`` at ``address`` gets (0:
        accepted)."""
        res = self._call("write_registers", address, regs)
        return int(getattr(res, "exception_code", -1)) if res.isError() else 0

    def select_channel(self, channel: int) -> None:
        """Select ``channel`` in ``HR.CHANNEL`` (map 3), whatever this link thought was
        selected (e.g. after raw writes to it)."""
        self._write(HR.CHANNEL, [channel])
        self._channel = channel

    def _use(self, channel: int) -> None:
        """Address ``channel`` with the per-channel fields: select it if it is not (map 3);
        on map 2 every field is channel 0's."""
        if self.version >= rm.CHANNELS_MAP_VERSION and channel != self._channel:
            self.select_channel(channel)

    def clear_error(self) -> None:
        """Clear the device's last error (command 4)."""
        self._write(HR.COMMAND, [rm.Cmd.CLEAR_ERROR])

    # -- Stage primitives ----------------------------------------------------------------------
    def identify(self) -> str:
        return f"afmctl register map {self.version}, unit {self.unit}"

    def status(self) -> Status:
        return rm.decode_status(self._request("read_input_registers", 0, count=IR.STATUS_END))

    def limits(self, channel: int = 0) -> tuple[float, float, float]:
        """Device limits of ``channel``: v_min (V), v_max (V), slew (V/ms)."""
        address = IR.V_MIN
        if channel:
            self._use(channel)
            address = IR.CH_V_MIN
        a, b, c = rm.regs_f32(self._request("read_input_registers", address, count=6))
        return float(a), float(b), float(c)

    def voltage(self, channel: int = 0) -> float:
        if not channel:
            return self.status().output_v
        self._use(channel)
        return float(rm.regs_f32(self._request("read_input_registers", IR.CH_OUTPUT_V,
                                               count=2))[0])

    def set_voltage(self, v: float, channel: int = 0) -> None:
        self._use(channel)
        self._write(HR.DC_VOLTAGE, rm.f32_regs([v]))

    def stop(self) -> None:
        self._write(HR.COMMAND, [rm.Cmd.STOP])

    def safe_state(self) -> None:
        self._write(HR.COMMAND, [rm.Cmd.SAFE])

    def heartbeat(self) -> None:
        self._write(HR.HEARTBEAT, [1])

    def set_watchdog(self, period_s: float) -> None:
        self._write(HR.WATCHDOG_S, rm.f32_regs([period_s]))

    def set_sample_rate(self, hz: float) -> None:
        self._write(HR.SAMPLE_RATE, rm.f32_regs([hz]))

    def close(self) -> None:
        self._client.close()

    def _set_table_length(self, n: int) -> None:
        self._write(HR.TABLE_LENGTH, rm.u32_regs(n))

    def _write_chunk(self, first: int, values: NDArray[np.float32], channel: int = 0) -> None:
        self._use(channel)
        self._write(HR.STREAM_FIRST, rm.u32_regs(first) + rm.f32_regs(values))

    def _start(self, cycles: int) -> None:
        self._write(HR.COMMAND, [rm.Cmd.START] + rm.u32_regs(cycles), idempotent=False)

    def _read_chunk(self, first: int, n: int, channel: int = 0
                    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        self._use(channel)
        out_u = np.empty(n, dtype=np.float32)
        out_v = np.empty(n, dtype=np.float32)
        done = 0
        while done < n:
            page, off = divmod(first + done, rm.PAGE_SAMPLES)
            m = min(n - done, rm.PAGE_SAMPLES - off)
            if page != self._page:
                self._write(HR.RECORDER_PAGE, [page])
                self._page = page
            for base, out in ((IR.DISPLACEMENT, out_u), (IR.VOLTAGE, out_v)):
                regs = self._request("read_input_registers", base + 2 * off, count=2 * m)
                out[done:done + m] = rm.regs_f32(regs)
            done += m
        return out_u, out_v

    def _start_stream(self, n_total: int) -> None:
        self._write(HR.STREAM_TOTAL, rm.u32_regs(n_total))
        self._write(HR.COMMAND, [rm.Cmd.START_STREAM], idempotent=False)

    def _capacities(self) -> tuple[int, int]:
        regs = self._request("read_input_registers", IR.RECORDER_CAPACITY, count=4)
        return rm.regs_u32(regs[2:]), rm.regs_u32(regs[:2])
