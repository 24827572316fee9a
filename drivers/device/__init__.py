"""The device side: what a stage controller does, apart from the host.

Modules, by concern:

:mod:`~drivers.device.emulator`
    The emulated device's logic (table, generator, recorder, DC output, limits, watchdog, safe
    state), in device time, no I/O: :class:`~drivers.device.emulator.Emulator`,
    :class:`~drivers.device.emulator.DeviceError`.
:mod:`~drivers.device.plant`
    The plant it drives: afmctl's true model with the effects of a real stage
    (:class:`~drivers.device.plant.Physics`, :func:`~drivers.device.plant.expected_readback`), and
    the hidden effects of ``afmctl diagnose``'s catalogue (:func:`~drivers.device.plant.
    hidden_effect`, :func:`~drivers.device.plant.with_hidden_effect`, :func:`~drivers.device.plant.
    hidden_cases`; ``EmulatorConfig`` is re-exported there).
:mod:`~drivers.device.ascii_device`, :mod:`~drivers.device.register_device`
    The interpreters of the two protocols of ``docs/protocol.md`` (no I/O).
:mod:`~drivers.device.serial_server`, :mod:`~drivers.device.modbus_server`, :mod:`~drivers.device.wire`
    The wire servers (ASCII on a pty or socket; Modbus TCP and RTU: every pymodbus server call).
:mod:`~drivers.device.emulated`
    One emulated device (lock, clock, watchdog ticker) and ``serve_all`` on every wire.
:mod:`~drivers.device.faults`
    Fault injection into what the device sends.

An independently written foreign plant with hidden effects (``foreign``) and the conformance check
that exercises any device against ``docs/protocol.md`` live here too. Host code (``afmctl`` and the
links in :mod:`drivers`) never imports from here except to start an emulated stage.
"""
