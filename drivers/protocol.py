"""What both wire protocols share: the device's error codes and its status record. No I/O.

The host's links (:mod:`afmctl.drivers.serial_link`, :mod:`afmctl.drivers.modbus_link`) decode a
device's replies into these; the emulated device (:mod:`afmctl.drivers.device`) produces them.
``docs/reference/protocol.md`` is the normative text.
"""

from __future__ import annotations

from dataclasses import dataclass

from afmctl.errors import DEVICE_ERRORS

#: Error codes shared by both wire protocols (sticky until queried or cleared); the table lives
#: in :mod:`afmctl.errors`, whose stage errors carry these codes.
ERRORS = DEVICE_ERRORS


@dataclass(frozen=True)
class Status:
    """What the device reports about itself.

    ``recorder_fill`` is the number of samples the recorder holds (at most its capacity);
    ``play_position`` the number of samples the generator has clocked out in the current or last run
    (global index of the next one); ``run_samples`` that run's length (``N_total`` of a stream).
    """

    running: bool
    recorder_fill: int
    last_error: int
    output_v: float
    run_count: int
    table_length: int
    table_complete: bool
    watchdog_armed: bool
    watchdog_expired: bool
    read_only: bool
    sample_rate_hz: float
    play_position: int
    run_samples: int
    watchdog_s: float

