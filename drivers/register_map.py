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
registers); ``IR.PLAY_POSITION`` and ``IR.RUN_SAMPLES``. See ``docs/protocol.md`` for the table.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from afmctl.emulator import DeviceError, Emulator, Status

MAP_VERSION = 2

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
    DISPLACEMENT = 0x1000  # float32 raw sensor of sample page * 8192 + i at 0x1000 + 2 i
    VOLTAGE = 0x5000       # float32 V, same indexing
    END = 0x9000


class StatusBit:
    RUNNING = 1
    TABLE_COMPLETE = 2
    WATCHDOG_ARMED = 4
    WATCHDOG_EXPIRED = 8
    READ_ONLY = 16


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


@dataclass(frozen=True)
class _Field:
    address: int
    size: int


_HR_FIELDS = [_Field(a, s) for a, s in ((HR.COMMAND, 1), (HR.CYCLES, 2), (HR.TABLE_LENGTH, 2),
                                        (HR.DC_VOLTAGE, 2), (HR.HEARTBEAT, 1),
                                        (HR.WATCHDOG_S, 2), (HR.SAMPLE_RATE, 2),
                                        (HR.RECORDER_PAGE, 1), (HR.STREAM_TOTAL, 2))]


class RegisterDevice:
    """Serve an :class:`~afmctl.emulator.Emulator` as the register map.

    ``read`` and ``write`` return registers or a Modbus exception code (int); a refusal also sets
    the device's last error (``IR.LAST_ERROR``).
    """

    def __init__(self, emulator: Emulator, clock: Callable[[], float]) -> None:
        self.em = emulator
        self.clock = clock
        self.cycles = 1
        self.stream_total = 0
        self.page = 0

    # -- reads ---------------------------------------------------------------------------------
    def read_input(self, address: int, count: int) -> list[int] | int:
        now = self.clock()
        if address + count <= IR.STATUS_END:
            return self._status_regs(now)[address:address + count]
        for base in (IR.DISPLACEMENT, IR.VOLTAGE):
            off = address - base
            if 0 <= off and off + count <= 2 * PAGE_SAMPLES and off % 2 == 0 and count % 2 == 0:
                first = self.page * PAGE_SAMPLES + off // 2
                try:
                    u, v = self.em.read_recorder(first, count // 2, now)
                except DeviceError:
                    return ILLEGAL_ADDRESS
                return f32_regs(u if base == IR.DISPLACEMENT else v)
        return ILLEGAL_ADDRESS

    def _status_regs(self, now: float) -> list[int]:
        s, lim = self.em.status(now), self.em.limits
        bits = (StatusBit.RUNNING * s.running | StatusBit.TABLE_COMPLETE * s.table_complete
                | StatusBit.WATCHDOG_ARMED * s.watchdog_armed
                | StatusBit.WATCHDOG_EXPIRED * s.watchdog_expired
                | StatusBit.READ_ONLY * s.read_only)
        return ([MAP_VERSION, bits, s.last_error] + u32_regs(s.recorder_fill)
                + f32_regs([s.output_v, s.sample_rate_hz, lim.v_min, lim.v_max, lim.slew_v_per_ms])
                + u32_regs(s.table_length) + u32_regs(s.run_count)
                + u32_regs(self.em.rec_u.size) + u32_regs(self.em.table.size)
                + f32_regs([s.watchdog_s]) + u32_regs(s.play_position) + u32_regs(s.run_samples))

    def read_holding(self, address: int, count: int) -> list[int] | int:
        if address + count > HR.CONTROL_END:
            return ILLEGAL_ADDRESS
        s = self.em.status(self.clock())
        regs = ([0] + u32_regs(self.cycles) + u32_regs(s.table_length) + f32_regs([s.output_v])
                + [0] + f32_regs([s.watchdog_s, s.sample_rate_hz]) + [self.page]
                + u32_regs(self.stream_total))
        return regs[address:address + count]

    # -- writes --------------------------------------------------------------------------------
    def write(self, address: int, values: list[int]) -> int | None:
        """Apply a holding-register write; ``None`` on success, else an exception code."""
        if address == HR.UPLOAD_BLOCK:
            return self._upload(values, 1, UPLOAD_BLOCK_SAMPLES)
        if address == HR.STREAM_FIRST:
            return self._upload(values, 2, 1)
        fields = [f for f in _HR_FIELDS if f.address < address + len(values)
                  and address < f.address + f.size]
        if not fields or fields[0].address < address or \
                fields[-1].address + fields[-1].size > address + len(values):
            return ILLEGAL_ADDRESS
        try:
            for f in sorted(fields, key=lambda f: f.address == HR.COMMAND):  # the command last
                self._field(f.address, values[f.address - address:f.address - address + f.size])
        except DeviceError as exc:
            return DEVICE_BUSY if exc.code == 5 else ILLEGAL_VALUE
        return None

    def _field(self, address: int, regs: list[int]) -> None:
        now = self.clock()
        if address == HR.CYCLES:
            self.cycles = regs_u32(regs)
        elif address == HR.COMMAND:
            self._command(regs[0], now)
        elif address == HR.TABLE_LENGTH:
            self.em.set_table_length(regs_u32(regs), now)
        elif address == HR.DC_VOLTAGE:
            self.em.set_voltage(float(regs_f32(regs)[0]), now)
        elif address == HR.HEARTBEAT:
            self.em.heartbeat(now)
        elif address == HR.WATCHDOG_S:
            self.em.set_watchdog(float(regs_f32(regs)[0]), now)
        elif address == HR.SAMPLE_RATE:
            self.em.set_sample_rate(float(regs_f32(regs)[0]), now)
        elif address == HR.RECORDER_PAGE:
            self.page = regs[0]
        elif address == HR.STREAM_TOTAL:
            self.stream_total = regs_u32(regs)

    def _command(self, cmd: int, now: float) -> None:
        if cmd == Cmd.START:
            self.em.start(self.cycles, now)
        elif cmd == Cmd.STOP:
            self.em.stop(now)
        elif cmd == Cmd.SAFE:
            self.em.safe_state(now)
        elif cmd == Cmd.CLEAR_ERROR:
            self.em.pop_error(now)
        elif cmd == Cmd.START_STREAM:
            self.em.start_stream(self.stream_total, now)
        else:
            self.em.last_error = 1
            raise DeviceError(1, f"command {cmd}")

    def _upload(self, values: list[int], index_regs: int, unit: int) -> int | None:
        """A block: ``index_regs`` registers of index (in units of ``unit`` samples), then float32
        samples."""
        if len(values) < index_regs + 2 or (len(values) - index_regs) % 2:
            return ILLEGAL_ADDRESS
        index = values[0] if index_regs == 1 else regs_u32(values[:2])
        try:
            self.em.write_table(index * unit, regs_f32(values[index_regs:]), self.clock())
        except DeviceError as exc:
            return DEVICE_BUSY if exc.code == 5 else ILLEGAL_VALUE
        return None


def decode_status(regs: list[int]) -> Status:
    """Input registers ``0 .. STATUS_END-1`` -> :class:`~afmctl.emulator.Status`."""
    if regs[IR.MAP_VERSION] != MAP_VERSION:
        raise ValueError(f"register map version {regs[IR.MAP_VERSION]}, this afmctl speaks "
                         f"{MAP_VERSION}")
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
