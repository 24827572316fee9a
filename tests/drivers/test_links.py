"""Links that keep up (issue 14, items 3 and 5): block reads on ``socket://``, the link capacity
check before a streamed run, and Modbus FC6 echoes checked with a hand-built frame (an independent
client: raw bytes on a TCP socket, no pymodbus)."""

from __future__ import annotations

import socket
import struct
from dataclasses import replace

import numpy as np
import pytest

from afmctl.drivers import register_map as rm
from afmctl.drivers.device.emulated import EmulatedDevice
from afmctl.drivers.device.modbus_server import ModbusTcpServer
from afmctl.drivers.device.serial_server import SerialServer
from afmctl.drivers.serial_link import SerialStage, is_uart
from afmctl.errors import InputError, LinkCapacityError
from afmctl.files.profile import Profile, WireFaults
from tests.harness.emulated import stage_on


def test_socket_replies_are_read_in_blocks(profile: Profile) -> None:
    """pyserial's socket handler says 0 or 1 byte waiting; the host must not read byte by byte."""
    with stage_on("serial-socket", profile) as (stage, _):
        stage.play(np.linspace(0.0, 1.0, 400))
        port = stage._port  # type: ignore[attr-defined]
        calls, sizes = [], []
        real = port.read

        def counted(n: int = 1) -> bytes:
            data = real(n)
            calls.append(n)
            sizes.append(len(data))
            return data

        port.read = counted
        rec = stage.read_recorder(400)
    assert rec.complete
    assert sum(sizes) > 400 * 10  # two float32 values per sample, as text
    assert len(calls) <= 20  # 2 requests of 200 samples: a few blocks each, not ~10,000 bytes


def test_ptys_and_sockets_are_not_uarts(profile: Profile) -> None:
    with stage_on("serial-pty", profile) as (pty, _), stage_on("serial-socket", profile) as (s, _):
        assert not is_uart(pty._port) and not is_uart(s._port)  # type: ignore[attr-defined]
        assert pty.uart_rates() is None and s.uart_rates() is None


def slow_link(profile: Profile, rate_hz: float) -> Profile:
    """A 4,096-sample table, 8,192-sample recorder, clocked at ``rate_hz``."""
    assert profile.emulator is not None
    cfg = replace(profile.emulator, table_capacity=4096, recorder_capacity=8192)
    return replace(profile, emulator=cfg, sample_rate_hz=rate_hz)


#: Every reply 20 ms late: at most 200 samples per 20 ms (10,000 samples/s) each way.
SLOW = WireFaults(delay=1.0, delay_s=0.02)


def _served_slowly(profile: Profile):  # noqa: ANN202
    dev = EmulatedDevice(profile, faults=SLOW)
    srv = SerialServer(dev, "socket://127.0.0.1:0")
    return dev, srv


def test_a_stream_the_link_cannot_carry_is_refused_up_front(profile: Profile) -> None:
    prof = slow_link(profile, 10_000.0)
    dev, srv = _served_slowly(prof)
    handed: list[int] = []
    with dev, srv, SerialStage(prof, srv.url) as stage:
        with pytest.raises(LinkCapacityError) as info:
            stage.play(np.linspace(0.0, 5.0, 4 * 4096), lambda first, *_: handed.append(first))
        st = stage.status()
    msg = str(info.value)
    assert ("needs 10000 samples/s up (refilling the table) and 5000 samples/s down (reading "
            "the recorder)") in msg
    assert "the link carries about" in msg
    assert st.run_count == 0 and not st.running and handed == []  # nothing played, nothing written
    assert isinstance(info.value, InputError)  # exit status 2 at the CLI


def test_a_stream_that_fits_the_recorder_is_read_back_after_the_run(profile: Profile) -> None:
    prof = slow_link(profile, 6_000.0)
    dev, srv = _served_slowly(prof)
    running_at_first_block: list[bool] = []

    def on_block(first: int, *_: object) -> None:
        if first == 0:
            with dev.lock:
                running_at_first_block.append(dev.emulator.status(dev.clock()).running)

    v = np.linspace(0.0, 5.0, 7000)  # longer than the table, shorter than the recorder
    with dev, srv, SerialStage(prof, srv.url) as stage:
        rec = stage.play(v, on_block)
    assert rec.complete and running_at_first_block == [False]
    np.testing.assert_array_equal(rec.voltage_v.astype(np.float32), v.astype(np.float32))


def _fc6(sock: socket.socket, tid: int, address: int, value: int) -> bytes:
    """One Modbus TCP write single register (FC6) request to unit 1, built by hand; its reply."""
    sock.sendall(struct.pack(">HHHBBHH", tid, 0, 6, 1, 6, address, value))
    reply = b""
    while len(reply) < 9 or len(reply) < 6 + struct.unpack(">H", reply[4:6])[0]:
        chunk = sock.recv(256)
        assert chunk, "connection closed"
        reply += chunk
    return reply


def test_fc6_echoes_the_written_value(profile: Profile) -> None:
    with EmulatedDevice(profile) as dev, ModbusTcpServer(dev) as srv, \
            socket.create_connection(("127.0.0.1", srv.port), timeout=5.0) as sock:
        for tid, (address, value) in enumerate([(rm.HR.HEARTBEAT, 0x1234),
                                                (rm.HR.COMMAND, rm.Cmd.STOP),
                                                (rm.HR.COMMAND, rm.Cmd.SAFE),
                                                (rm.HR.RECORDER_PAGE, 7)], start=1):
            request = struct.pack(">HHHBBHH", tid, 0, 6, 1, 6, address, value)
            assert _fc6(sock, tid, address, value) == request  # the echo is the request itself
        refused = _fc6(sock, 9, rm.HR.COMMAND, 99)  # no such command
        assert refused[7:] == bytes([0x86, rm.ILLEGAL_VALUE])
        with dev.lock:
            assert dev.emulator.last_error == 1


def test_a_local_serial_device_is_a_uart_and_a_pty_is_not() -> None:
    import os

    import serial
    port = serial.Serial()  # not opened: only its path is looked at
    port.port = "/dev/ttyUSB0"
    assert is_uart(port)
    master, slave = os.openpty()
    try:
        port.port = os.ttyname(slave)
        assert not is_uart(port)
    finally:
        os.close(master)
        os.close(slave)


def test_uart_byte_counts_cover_real_lines(profile: Profile) -> None:
    """The bytes per sample a UART's capacity is computed from are what the lines really take."""
    from afmctl.drivers import ascii_protocol as ap
    rng = np.random.default_rng(3)
    v = rng.uniform(-150, 150, 200).astype(np.float32)
    line = ap.frame(ap.wav_line(0, v), 99999) + "\n"
    assert 0.85 * ap.UPLOAD_BYTES_PER_SAMPLE <= len(line) / v.size <= ap.UPLOAD_BYTES_PER_SAMPLE
    with stage_on("serial-pty", profile) as (stage, _):
        stage.play(100.0 * np.sin(np.linspace(0, 6, 2000)) * np.linspace(0, 1, 2000))
        reply = stage.query("DRR? 1000 200")
    per_sample = (len(ap.frame(reply, 99999)) + 1) / 200
    assert 0.7 * ap.READBACK_BYTES_PER_SAMPLE <= per_sample <= ap.READBACK_BYTES_PER_SAMPLE
    up, down = rm.rtu_bytes_per_sample()
    assert up == pytest.approx(4 + 21 / 60) and down == pytest.approx(8 + 26 / 62)


def test_ctrl_c_inside_on_block_is_held_until_the_block_is_handed_over(profile: Profile) -> None:
    """A SIGINT that lands while on_block writes a block (an fsync, say) does not cut the block:
    it is raised after it, the stage is made safe and every later sample is still handed over."""
    import os
    import signal
    import time

    v = np.concatenate([np.linspace(0.0, 20.0, 50), np.full(12_000, 20.0)])
    seen: list[tuple[int, int]] = []

    def on_block(first: int, volt: np.ndarray, *_: object) -> None:
        if first == 0:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # the signal arrives while the block is being written
        seen.append((first, volt.size))

    with stage_on("serial-pty", profile) as (stage, _):
        with pytest.raises(KeyboardInterrupt):
            stage.play(v, on_block)
        st = stage.status()
    assert seen[0][0] == 0 and len(seen) >= 2  # the first block whole, then the rest
    assert [f for f, _ in seen] == list(np.cumsum([0] + [m for _, m in seen[:-1]]))
    assert sum(m for _, m in seen) == v.size
    assert not st.running and st.output_v == 0.0


def test_ctrl_c_just_before_a_hand_over_loses_no_block(profile: Profile,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A SIGINT that lands just before the hold of the second hand-over (before on_block is
    entered): that block is not counted delivered, and the abandon hands it over with the rest,
    every sample exactly once and in order."""
    from contextlib import contextmanager

    from afmctl.drivers import player

    held = player._sigint_held
    calls = [0]

    @contextmanager
    def interrupted_on_second():  # type: ignore[no-untyped-def]
        calls[0] += 1
        if calls[0] == 2:
            raise KeyboardInterrupt
        with held():
            yield

    monkeypatch.setattr(player, "_sigint_held", interrupted_on_second)
    v = np.concatenate([np.linspace(0.0, 20.0, 50), np.full(12_000, 20.0)])
    seen: list[tuple[int, int]] = []
    with stage_on("serial-pty", profile) as (stage, _):
        with pytest.raises(KeyboardInterrupt):
            stage.play(v, lambda first, volt, *_: seen.append((first, volt.size)))
        st = stage.status()
    assert calls[0] >= 3 and len(seen) >= 2
    assert [f for f, _ in seen] == list(np.cumsum([0] + [m for _, m in seen[:-1]]))
    assert sum(m for _, m in seen) == v.size
    assert not st.running and st.output_v == 0.0


def test_a_refill_refused_after_the_run_stopped_says_the_run_stopped(profile: Profile) -> None:
    """The device underruns between the host's status poll and its refill (a device clock that
    jumps 0.3 s per call): the error names the stopped run, not only the refused block."""
    from afmctl.drivers.inprocess import InProcessStage
    from afmctl.errors import StageError
    t = [0.0]

    def jumpy() -> float:
        t[0] += 0.3
        return t[0]

    prof = slow_link(profile, 10_000.0)
    stage = InProcessStage(prof, clock=jumpy)
    with pytest.raises(StageError) as info:
        stage.play(np.linspace(0.0, 5.0, 3 * 4096))
    assert info.value.code == 10 and "the run stopped after 4096 of 12288 samples" in str(info.value)
    assert "the host fell behind refilling the table" in str(info.value)  # an underrun, named
    assert stage.status().output_v == 0.0
