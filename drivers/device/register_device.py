"""The device's side of the Modbus register map: register reads and writes -> an
:class:`~afmctl.drivers.device.emulator.Emulator`. No I/O
(:mod:`afmctl.drivers.device.modbus_server` serves it).
Addresses and encoding: :mod:`afmctl.drivers.register_map`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from afmctl.drivers.device.emulator import Emulator
from afmctl.drivers.register_map import (
    CHANNELS_MAP_VERSION,
    DEVICE_BUSY,
    HR,
    ILLEGAL_ADDRESS,
    ILLEGAL_VALUE,
    IR,
    MAP_VERSION,
    PAGE_SAMPLES,
    UPLOAD_BLOCK_SAMPLES,
    Cmd,
    StatusBit,
    f32_regs,
    regs_f32,
    regs_u32,
    u32_regs,
)
from afmctl.errors import DeviceError


@dataclass(frozen=True)
class _Field:
    address: int
    size: int


_HR_FIELDS = [_Field(a, s) for a, s in ((HR.COMMAND, 1), (HR.CYCLES, 2), (HR.TABLE_LENGTH, 2),
                                        (HR.DC_VOLTAGE, 2), (HR.HEARTBEAT, 1),
                                        (HR.WATCHDOG_S, 2), (HR.SAMPLE_RATE, 2),
                                        (HR.RECORDER_PAGE, 1), (HR.STREAM_TOTAL, 2))]
_CHANNEL_FIELDS = [*_HR_FIELDS, _Field(HR.CHANNEL, 1)]


class RegisterDevice:
    """Serve an :class:`~afmctl.drivers.device.emulator.Emulator` as the register map.

    ``read`` and ``write`` return registers or a Modbus exception code (int); a refusal also sets
    the device's last error (``IR.LAST_ERROR``). A device of several channels serves map 3: the
    per-channel fields address the channel selected in ``HR.CHANNEL`` (docs/reference/protocol.md
    §4.4); one of a single channel serves map 2, as before.
    """

    def __init__(self, emulator: Emulator, clock: Callable[[], float]) -> None:
        self.em = emulator
        self.clock = clock
        several = emulator.channels > 1
        self.version = CHANNELS_MAP_VERSION if several else MAP_VERSION
        self.status_end = IR.CHANNEL_STATUS_END if several else IR.STATUS_END
        self.control_end = HR.CHANNEL_CONTROL_END if several else HR.CONTROL_END
        self.fields = _CHANNEL_FIELDS if several else _HR_FIELDS
        self.channel = 0
        self.cycles = 1
        self.stream_total = 0
        self.page = 0
        #: Last values accepted in ``HR.COMMAND`` and ``HR.HEARTBEAT``: what these registers read
        #: back, so that a write single register (FC6) echoes the value written (protocol v4).
        self.command = self.heartbeat = 0

    # -- reads ---------------------------------------------------------------------------------
    def read_input(self, address: int, count: int) -> list[int] | int:
        now = self.clock()
        if address + count <= self.status_end:
            return self._status_regs(now)[address:address + count]
        for base in (IR.DISPLACEMENT, IR.VOLTAGE):
            off = address - base
            if 0 <= off and off + count <= 2 * PAGE_SAMPLES and off % 2 == 0 and count % 2 == 0:
                first = self.page * PAGE_SAMPLES + off // 2
                try:
                    u, v = self.em.read_recorder(first, count // 2, now, self.channel)
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
        regs = ([self.version, bits, s.last_error] + u32_regs(s.recorder_fill)
                + f32_regs([s.output_v, s.sample_rate_hz, lim.v_min, lim.v_max, lim.slew_v_per_ms])
                + u32_regs(s.table_length) + u32_regs(s.run_count)
                + u32_regs(self.em.rec_global.size) + u32_regs(self.em.tables.shape[1])
                + f32_regs([s.watchdog_s]) + u32_regs(s.play_position) + u32_regs(s.run_samples))
        if self.version == MAP_VERSION:
            return regs
        c = self.channel
        mine = self.em.channel_limits[c]
        return regs + [self.em.channels] + f32_regs([self.em.outputs[c], mine.v_min, mine.v_max,
                                                     mine.slew_v_per_ms])

    def read_holding(self, address: int, count: int) -> list[int] | int:
        if address + count > self.control_end:
            return ILLEGAL_ADDRESS
        now = self.clock()
        s = self.em.status(now)
        regs = ([self.command] + u32_regs(self.cycles) + u32_regs(s.table_length)
                + f32_regs([self.em.output(now, self.channel)]) + [self.heartbeat]
                + f32_regs([s.watchdog_s, s.sample_rate_hz]) + [self.page]
                + u32_regs(self.stream_total) + [self.channel])
        return regs[address:address + count]

    # -- writes --------------------------------------------------------------------------------
    def write(self, address: int, values: list[int]) -> int | None:
        """Apply a holding-register write; ``None`` on success, else an exception code."""
        if address == HR.UPLOAD_BLOCK:
            return self._upload(values, 1, UPLOAD_BLOCK_SAMPLES)
        if address == HR.STREAM_FIRST:
            return self._upload(values, 2, 1)
        fields = [f for f in self.fields if f.address < address + len(values)
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
            self.command = regs[0]
        elif address == HR.TABLE_LENGTH:
            self.em.set_table_length(regs_u32(regs), now)
        elif address == HR.DC_VOLTAGE:
            self.em.set_voltage(float(regs_f32(regs)[0]), now, self.channel)
        elif address == HR.HEARTBEAT:
            self.em.heartbeat(now)
            self.heartbeat = regs[0]
        elif address == HR.WATCHDOG_S:
            self.em.set_watchdog(float(regs_f32(regs)[0]), now)
        elif address == HR.SAMPLE_RATE:
            self.em.set_sample_rate(float(regs_f32(regs)[0]), now)
        elif address == HR.RECORDER_PAGE:
            self.page = regs[0]
        elif address == HR.STREAM_TOTAL:
            self.stream_total = regs_u32(regs)
        elif address == HR.CHANNEL:
            self.em.output(now, regs[0])  # error 6 unless the device has that channel
            self.channel = regs[0]

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
            self.em.write_table(index * unit, regs_f32(values[index_regs:]), self.clock(),
                                self.channel)
        except DeviceError as exc:
            return DEVICE_BUSY if exc.code == 5 else ILLEGAL_VALUE
        return None


