"""The register map served on Modbus TCP and Modbus RTU (every pymodbus server call lives here).

With wire faults configured, the TCP server sits behind a :class:`~afmctl.drivers.device.faults.
FaultyTcpProxy`; the RTU server always talks through a :class:`~afmctl.drivers.device.faults.PtyBridge`
(a null-modem pair of ptys: pymodbus opens one end, the host the other), faulty if configured.
"""

from __future__ import annotations

import asyncio
import threading
from typing import TYPE_CHECKING, Any

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer
from pymodbus.server import ModbusTcpServer as _PymodbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from afmctl.drivers import register_map as rm
from afmctl.drivers.device.faults import FaultyTcpProxy, PtyBridge
from afmctl.drivers.device.wire import LOOPBACK

if TYPE_CHECKING:
    from afmctl.drivers.device.emulated import EmulatedDevice


def sim_device(device: EmulatedDevice, unit: int = 1) -> SimDevice:
    """A pymodbus SimDevice whose every access is answered by the device's register map."""

    async def action(function_code: int, start_address: int, address: int, count: int,
                     registers: list[int], set_values: list[int] | list[bool] | None
                     ) -> ExcCodes | None:
        with device.lock:
            if set_values is not None:
                res = device.registers.write(address, [int(x) for x in set_values])
                return None if res is None else ExcCodes(res)
            regs = (device.registers.read_input(address, count) if function_code == 4
                    else device.registers.read_holding(address, count))
        if isinstance(regs, int):
            return ExcCodes(regs)
        registers[address - start_address:address - start_address + count] = regs
        return None

    bits = [SimData(0, count=16, values=False, datatype=DataType.BITS)]
    holding = [SimData(0, count=rm.HR.END, values=0, datatype=DataType.REGISTERS)]
    inputs = [SimData(0, count=rm.IR.END, values=0, datatype=DataType.REGISTERS)]
    return SimDevice(unit, simdata=(bits, list(bits), holding, inputs), action=action)


class _LoopThread:
    """An asyncio loop in a background thread, for pymodbus servers."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="modbus-loop",
                                        daemon=True)
        self._thread.start()

    def run(self, coro: Any, timeout_s: float = 10.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout_s)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join()
        self.loop.close()


class _ModbusServerBase:
    def __init__(self) -> None:
        self._loop: _LoopThread | None = None
        self._server: Any = None

    def _make(self) -> Any:
        raise NotImplementedError

    def __enter__(self) -> Any:
        self._loop = _LoopThread()

        async def start() -> Any:
            server = self._make()
            await server.serve_forever(background=True)
            return server

        try:
            self._server = self._loop.run(start())
        except RuntimeError as exc:  # pymodbus's "Could not start listen" names no address
            self._loop.close()
            raise OSError(f"Modbus server cannot listen on {self._address()}: {exc} (in use?)"
                          ) from None
        return self

    def _address(self) -> str:
        raise NotImplementedError

    def __exit__(self, *exc: object) -> None:
        assert self._loop is not None
        self._loop.run(self._shutdown())
        self._loop.close()

    async def _shutdown(self) -> None:
        await self._server.shutdown()
        await asyncio.sleep(0)
        pending = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for t in pending:
            t.cancel()
        await asyncio.gather(*pending, return_exceptions=True)


class ModbusTcpServer(_ModbusServerBase):
    """The register map on Modbus TCP at ``host:port`` (port 0: a free one, see ``.port``).

    With wire faults configured, ``host:port`` is a :class:`FaultyTcpProxy` and pymodbus listens
    on a free loopback port behind it.
    """

    def __init__(self, device: EmulatedDevice, host: str = LOOPBACK, port: int = 0,
                 unit: int = 1) -> None:
        super().__init__()
        self.device, self.host, self.port, self.unit = device, host, port, unit
        self._proxy: FaultyTcpProxy | None = None

    def _make(self) -> Any:
        where = (LOOPBACK, 0) if self.device.faults.active else (self.host, self.port)
        return _PymodbusTcpServer(sim_device(self.device, self.unit), address=where)

    def _address(self) -> str:
        return f"{self.host}:{self.port}"

    def __enter__(self) -> ModbusTcpServer:
        super().__enter__()
        backend = self._server.transport.sockets[0].getsockname()[1]
        if self.device.faults.active:
            self._proxy = FaultyTcpProxy(backend, self.device.faults, self.host, self.port)
            self._proxy.__enter__()
            backend = self._proxy.port
        self.port = backend
        return self

    def __exit__(self, *exc: object) -> None:
        if self._proxy is not None:
            self._proxy.__exit__(*exc)
        super().__exit__(*exc)


class ModbusRtuServer(_ModbusServerBase):
    """The register map with RTU framing on a pty pair; the host opens ``url``."""

    def __init__(self, device: EmulatedDevice, unit: int = 1, baudrate: int = 115200) -> None:
        super().__init__()
        self.device, self.unit, self.baudrate = device, unit, baudrate
        self._bridge = PtyBridge(device.faults if device.faults.active else None)
        self.url = self._bridge.host_path

    def _make(self) -> Any:
        return ModbusSerialServer(sim_device(self.device, self.unit), framer=FramerType.RTU,
                                  port=self._bridge.device_path, baudrate=self.baudrate)

    def _address(self) -> str:
        return self.url

    def __enter__(self) -> ModbusRtuServer:
        self._bridge.__enter__()
        super().__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        super().__exit__(*exc)
        self._bridge.__exit__(*exc)

