"""The Modbus register map, version 2: addresses, word encoding and the device-side logic. No I/O.

Holding registers (function codes 3, 6, 16) carry control; input registers (function code 4) carry
status and the recorder. 32-bit values (float32, uint32) take two registers, most significant word
first ("big-endian word order", ``mbpoll -B``). A write must cover whole fields. Upload blocks carry
their own index in the same write (``UPLOAD_BLOCK`` then up to 61 float32 = 123 registers, the
Modbus write limit), so repeating a write is harmless. Recorder readback is paged: write
``RECORDER_PAGE``, then read up to 62 samples (124 registers) per request from the displacement
and voltage windows; recorder indices are global sample indices (the page is 16 bits: 2**29
samples). Version 2 adds streaming: ``HR.STREAM_TOTAL`` then ``Cmd.START_STREAM``; blocks at a 32-bit
global sample index through the stream window (``STREAM_FIRST`` then up to 60 float32 = 122
registers); ``IR.PLAY_POSITION`` and ``IR.RUN_SAMPLES``. See ``docs/reference/protocol.md`` for the table.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from afmctl.drivers.protocol import Status

MAP_VERSION = 2
#: The register map of devices with several channels (``HR.CHANNEL``, ``IR.CHANNELS`` ...).
CHANNELS_MAP_VERSION = 3
#: The versions a host speaks (docs/reference/protocol.md §7: the one the device reports).
MAP_VERSIONS = (MAP_VERSION, CHANNELS_MAP_VERSION)

# Exception codes of the Modbus standard that the device answers with.
ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_BUSY = 2, 3, 6

#: Samples per upload block (1 index register + 2 per sample <= 123).
UPLOAD_BLOCK_SAMPLES = 61
#: Samples per stream block (2 index registers + 2 per sample <= 123).
STREAM_BLOCK_SAMPLES = 60
#: Samples per recorder read (2 registers per sample <= 125).
READ_SAMPLES = 62
#: Samples per recorder page.
PAGE_SAMPLES = 8192


class Cmd:
    """Values written to ``HR.COMMAND``."""

    START = 1   # cycles from HR.CYCLES
    STOP = 2
    SAFE = 3    # stop and ramp to 0 V
    CLEAR_ERROR = 4
    START_STREAM = 5  # N_total from HR.STREAM_TOTAL


class HR:
    """Holding-register addresses."""

    COMMAND = 0            # uint16, see Cmd
    CYCLES = 1             # uint32
    TABLE_LENGTH = 3       # uint32; writing starts a new table
    DC_VOLTAGE = 5         # float32 V; writing applies it, reading gives the output
    HEARTBEAT = 7          # uint16, write anything
    WATCHDOG_S = 8         # float32 s, 0 disarms
    SAMPLE_RATE = 10       # float32 Hz
    RECORDER_PAGE = 12     # uint16
    STREAM_TOTAL = 13      # uint32 samples of the next stream (v2)
    CONTROL_END = 15
    CHANNEL = 15           # uint16: the channel the per-channel fields address (map 3)
    CHANNEL_CONTROL_END = 16
    UPLOAD_BLOCK = 100     # uint16 block index, followed by its samples
    UPLOAD_DATA = 101      # 61 x float32
    STREAM_FIRST = 300     # uint32 global index of the first sample that follows (v2)
    STREAM_DATA = 302      # 60 x float32
    END = STREAM_DATA + 2 * STREAM_BLOCK_SAMPLES


class IR:
    """Input-register addresses."""

    MAP_VERSION = 0        # uint16
    STATUS = 1             # uint16 bits, see StatusBit
    LAST_ERROR = 2         # uint16 (cleared by Cmd.CLEAR_ERROR)
    RECORDER_FILL = 3      # uint32
    OUTPUT_V = 5           # float32
    SAMPLE_RATE = 7        # float32
    V_MIN = 9              # float32
    V_MAX = 11             # float32
    SLEW = 13              # float32 V/ms
    TABLE_LENGTH = 15      # uint32
    RUN_COUNT = 17         # uint32
    RECORDER_CAPACITY = 19  # uint32
    TABLE_CAPACITY = 21    # uint32
    WATCHDOG_S = 23        # float32
    PLAY_POSITION = 25     # uint32 samples clocked out in the current or last run (v2)
    RUN_SAMPLES = 27       # uint32 length of that run (v2)
    STATUS_END = 29
    CHANNELS = 29          # uint16 number of channels (map 3)
    CH_OUTPUT_V = 30       # float32 output of the selected channel (map 3)
    CH_V_MIN = 32          # float32 its limits (map 3)
    CH_V_MAX = 34
    CH_SLEW = 36
    CHANNEL_STATUS_END = 38
    DISPLACEMENT = 0x1000  # float32 raw sensor of sample page * 8192 + i at 0x1000 + 2 i
    VOLTAGE = 0x5000       # float32 V, same indexing
    END = 0x9000


class StatusBit:
    RUNNING = 1
    TABLE_COMPLETE = 2
    WATCHDOG_ARMED = 4
    WATCHDOG_EXPIRED = 8
    READ_ONLY = 16
    RECORDS_COMMAND = 32  # the recorder's voltage is the command, not a measurement (doc v5)


def f32_regs(values: NDArray[np.float32] | list[float]) -> list[int]:
    """float32 values -> registers, big-endian words."""
    raw = np.asarray(values, dtype=">f4").tobytes()
    return np.frombuffer(raw, dtype=">u2").astype(int).tolist()


def regs_f32(regs: list[int]) -> NDArray[np.float32]:
    """Registers (big-endian words) -> float32 values."""
    return np.frombuffer(np.asarray(regs, dtype=">u2").tobytes(), dtype=">f4").astype(np.float32)


def u32_regs(x: int) -> list[int]:
    return [(x >> 16) & 0xFFFF, x & 0xFFFF]


def regs_u32(regs: list[int]) -> int:
    return (regs[0] << 16) | regs[1]


def rtu_bytes_per_sample() -> tuple[float, float]:
    """Bytes on an RTU line per sample (requests and replies) for streaming blocks up and recorder
    reads down: a write of :data:`STREAM_BLOCK_SAMPLES` (9 bytes of header and CRC, 4 of index,
    4 per sample; 8-byte reply) and two reads of :data:`READ_SAMPLES` (8-byte request; 5 bytes of
    header and CRC, 4 per sample)."""
    up = (9 + 4 + 4 * STREAM_BLOCK_SAMPLES + 8) / STREAM_BLOCK_SAMPLES
    down = 2 * (8 + 5 + 4 * READ_SAMPLES) / READ_SAMPLES
    return up, down


def decode_status(regs: list[int]) -> Status:
    """Input registers ``0 .. STATUS_END-1`` -> :class:`~afmctl.drivers.protocol.Status`."""
    if regs[IR.MAP_VERSION] not in MAP_VERSIONS:
        raise ValueError(f"register map version {regs[IR.MAP_VERSION]}, this afmctl speaks "
                         f"{' or '.join(map(str, MAP_VERSIONS))}")
    bits = regs[IR.STATUS]
    f = regs_f32(regs[IR.OUTPUT_V:IR.OUTPUT_V + 4])
    return Status(running=bool(bits & StatusBit.RUNNING),
                  recorder_fill=regs_u32(regs[IR.RECORDER_FILL:IR.RECORDER_FILL + 2]),
                  last_error=regs[IR.LAST_ERROR], output_v=float(f[0]),
                  run_count=regs_u32(regs[IR.RUN_COUNT:IR.RUN_COUNT + 2]),
                  table_length=regs_u32(regs[IR.TABLE_LENGTH:IR.TABLE_LENGTH + 2]),
                  table_complete=bool(bits & StatusBit.TABLE_COMPLETE),
                  watchdog_armed=bool(bits & StatusBit.WATCHDOG_ARMED),
                  watchdog_expired=bool(bits & StatusBit.WATCHDOG_EXPIRED),
                  read_only=bool(bits & StatusBit.READ_ONLY), sample_rate_hz=float(f[1]),
                  play_position=regs_u32(regs[IR.PLAY_POSITION:IR.PLAY_POSITION + 2]),
                  run_samples=regs_u32(regs[IR.RUN_SAMPLES:IR.RUN_SAMPLES + 2]),
                  watchdog_s=float(regs_f32(regs[IR.WATCHDOG_S:IR.WATCHDOG_S + 2])[0]))
