"""Device I/O for afmctl: the stage interface, the links that implement it, and the device side.

This package is the only place that imports pyserial or pymodbus; :mod:`afmctl` never imports it
at import time. The layers, from the application down to the wire and back up to the device:

Stage interface (:mod:`afmctl.drivers.stage`, re-exported here)
    :class:`StageBase`: ``upload``, ``run``, ``wait``, ``read_recorder``, ``set_voltage``,
    ``status``, ``safe_state`` (stop and ramp to 0 V), ``heartbeat``, ``close``, and ``play``,
    which does all of it for a waveform of any length (streamed through the device's table,
    read back progressively, left in the safe state on any error or interrupt);
    :func:`open_stage` picks the implementation from a profile; :class:`StageError`,
    :class:`LinkCapacityError`. :mod:`afmctl.drivers.player` is one ``play``: link capacity check,
    watchdog, double-buffered refill, progressive readback.
Links (host side)
    :mod:`afmctl.drivers.serial_link` speaks the ASCII protocol over any pyserial URL (a port, a pty path,
    ``socket://host:port``); :mod:`afmctl.drivers.modbus_link` speaks the register map over Modbus TCP or
    RTU (every pymodbus client call lives there); :mod:`afmctl.drivers.inprocess` calls an emulated device
    directly (the no-hardware default; same interface, no wire).
Protocols (pure, no I/O)
    :mod:`afmctl.drivers.protocol` (error codes, status record), :mod:`afmctl.drivers.ascii_protocol`
    and :mod:`afmctl.drivers.register_map`: the codecs of ``docs/reference/protocol.md``, shared by
    host and device.
Device side (:mod:`afmctl.drivers.device`)
    The emulated device: its logic (:mod:`~afmctl.drivers.device.emulator`), plant and hidden effects
    (:mod:`~afmctl.drivers.device.plant`), protocol interpreters (:mod:`~afmctl.drivers.device.ascii_device`,
    :mod:`~afmctl.drivers.device.register_device`), wire servers
    (:mod:`~afmctl.drivers.device.serial_server`, :mod:`~afmctl.drivers.device.modbus_server`, every
    pymodbus server call; :mod:`~afmctl.drivers.device.emulated` serves one device on every wire),
    fault injection (:mod:`~afmctl.drivers.device.faults`), and the
    conformance check that exercises any device against ``docs/reference/protocol.md``. Host code imports
    from it only to start an emulated stage.

Test and benchmark harnesses (the safety campaign) live outside the shipped packages
(``benchmarks/campaign.py``).
"""

from afmctl.drivers.protocol import Status
from afmctl.drivers.stage import BlockCallback, Recording, StageBase, open_stage
from afmctl.errors import LimitMismatchError, LinkCapacityError, StageError, StoppedError

__all__ = ["StageError", "StoppedError", "LinkCapacityError", "LimitMismatchError", "Recording",
           "Status", "StageBase", "BlockCallback", "open_stage"]
