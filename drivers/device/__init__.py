"""The device side: what a stage controller does, apart from the host.

Modules, by concern:

:mod:`~afmctl.drivers.device.emulator`
    The emulated device's logic (table, generator, recorder, DC output, limits, watchdog, safe
    state), in device time, no I/O: :class:`~afmctl.drivers.device.emulator.Emulator`,
    :class:`~afmctl.drivers.device.emulator.DeviceError`.
:mod:`~afmctl.drivers.device.plant`
    The plant it drives: afmctl's true model with the effects of a real stage
    (:class:`~afmctl.drivers.device.plant.Physics`,
    :func:`~afmctl.drivers.device.plant.expected_readback`), and the hidden effects of
    ``afmctl diagnose``'s catalogue (:func:`~afmctl.drivers.device.plant.hidden_effect`,
    :func:`~afmctl.drivers.device.plant.with_hidden_effect`,
    :func:`~afmctl.drivers.device.plant.hidden_cases`; ``EmulatorConfig`` is re-exported there).
:mod:`~afmctl.drivers.device.ascii_device`, :mod:`~afmctl.drivers.device.register_device`
    The interpreters of the two protocols of ``docs/reference/protocol.md`` (no I/O).
:mod:`~afmctl.drivers.device.serial_server`, :mod:`~afmctl.drivers.device.modbus_server`,
:mod:`~afmctl.drivers.device.wire`
    The wire servers (ASCII on a pty or socket; Modbus TCP and RTU: every pymodbus server call).
:mod:`~afmctl.drivers.device.emulated`
    One emulated device (lock, clock, watchdog ticker) and ``serve_all`` on every wire.
:mod:`~afmctl.drivers.device.faults`
    Fault injection into what the device sends.

:mod:`~afmctl.drivers.conformance`
    The conformance check: exercises any device (this one or a lab's own) against
    ``docs/reference/protocol.md`` clause by clause, through the host's links (``afmctl conformance``).

An independently written foreign plant with hidden effects (``foreign``) lives here too. Host code
(``afmctl`` and the links in :mod:`drivers`) never imports from here except to start an emulated
stage or to run the conformance check.
"""
