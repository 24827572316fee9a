"""The stage over every real wire, against the model's own simulation; protocol details; safety."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np
import pytest

from afmctl.drivers import open_stage
from afmctl.drivers import register_map as rm
from afmctl.drivers.device import emulator as em
from afmctl.drivers.device import plant
from afmctl.drivers.device.ascii_device import AsciiDevice
from afmctl.drivers.device.emulated import EmulatedDevice
from afmctl.drivers.device.modbus_server import ModbusTcpServer
from afmctl.drivers.device.register_device import RegisterDevice
from afmctl.drivers.device.wire import open_pty
from afmctl.drivers.inprocess import InProcessStage
from afmctl.drivers.modbus_link import ModbusStage
from afmctl.drivers.serial_link import SerialStage
from afmctl.errors import StageError
from afmctl.files.profile import Profile
from tests.harness.emulated import TRANSPORTS, ScriptedPort, long_waveform, small_buffers, stage_on


@pytest.mark.parametrize("kind", TRANSPORTS)
def test_readback_equals_model_over_each_transport(kind: str, profile: Profile,
                                                   waveform: np.ndarray) -> None:
    assert profile.emulator is not None
    u_exp, v_exp = plant.expected_readback(profile.emulator, profile.sample_rate_hz, waveform)
    with stage_on(kind, profile) as (stage, _):
        stage.upload(waveform)
        stage.run(1)
        status = stage.wait()
        rec = stage.read_recorder()
        stage.safe_state()
        assert stage.status().output_v == 0.0
    assert status.recorder_fill == waveform.size and not status.running
    assert rec.complete and rec.displacement_um.size == waveform.size
    np.testing.assert_array_equal(rec.displacement_um.astype(np.float32), u_exp.astype(np.float32))
    np.testing.assert_array_equal(rec.voltage_v.astype(np.float32), v_exp.astype(np.float32))
    assert np.ptp(rec.displacement_um) > 10.0  # a real response, not zeros


@pytest.mark.parametrize("kind", ["modbus-tcp", "serial-pty"])
def test_refusals_carry_device_codes_and_apply_nothing(kind: str, profile: Profile) -> None:
    with stage_on(kind, profile) as (stage, emu):
        with pytest.raises(StageError) as info:
            stage.set_voltage(200.0)
        assert info.value.code == 3
        with pytest.raises(StageError) as info:
            stage.set_voltage(20.0)  # in range, but a 20 V step in one sample: 200 V/ms
        assert info.value.code == 4
        with pytest.raises(StageError) as info:
            stage.upload(np.full(10, 151.0))
        assert info.value.code == 3
        with pytest.raises(StageError) as info:
            stage.upload(np.array([0.0, 20.0, 0.0]))  # 20 V steps at 10 kHz: 200 V/ms
        assert info.value.code == 4
        stage.upload(np.full(10, 20.0))  # smooth, but the step in from 0 V is 20 V
        with pytest.raises(StageError) as info:
            stage.run(1)
        assert info.value.code == 4
        assert emu.applied_log(0.0).size == 0 and stage.status().run_count == 0


@pytest.mark.parametrize("kind", ["modbus-tcp", "serial-pty"])
def test_read_only_device_refuses_output_changes(kind: str, profile: Profile) -> None:
    with stage_on(kind, profile, read_only=True) as (stage, emu):
        assert stage.status().read_only
        for action in (lambda: stage.set_voltage(1.0), lambda: stage.upload(np.zeros(5))):
            with pytest.raises(StageError) as info:
                action()
            assert info.value.code == 7
        assert emu.applied_log(0.0).size == 0


def test_watchdog_over_modbus_ramps_to_zero(profile: Profile) -> None:
    import time
    with stage_on("modbus-tcp", profile) as (stage, emu):
        stage.set_voltage(4.0)
        stage.set_watchdog(0.1)
        stage.heartbeat()
        assert stage.status().watchdog_armed
        time.sleep(0.3)
        st = stage.status()
    assert st.watchdog_expired and st.output_v == 0.0 and st.last_error == 8
    assert emu.applied_log(0.0)[-1] == 0.0


def test_repeated_upload_block_is_harmless(profile: Profile) -> None:
    with stage_on("modbus-tcp", profile) as (stage, emu):
        assert isinstance(stage, ModbusStage)
        v = np.linspace(0, 10, 100).astype(np.float32)
        stage.upload(v)
        stage._write_chunk(61, v[61:])  # the same block again
        assert stage.status().table_complete
        np.testing.assert_array_equal(emu.table[:100], v)


def test_register_map_rejects_partial_fields(profile: Profile) -> None:
    emu = em.Emulator(profile)
    dev = RegisterDevice(emu, lambda: 0.0)
    assert dev.write(rm.HR.DC_VOLTAGE, [0x4020]) == rm.ILLEGAL_ADDRESS  # half a float32
    assert dev.write(rm.HR.DC_VOLTAGE + 1, [0, 0]) == rm.ILLEGAL_ADDRESS
    assert dev.read_input(rm.IR.DISPLACEMENT + 1, 2) == rm.ILLEGAL_ADDRESS
    assert dev.write(rm.HR.DC_VOLTAGE, rm.f32_regs([2.5])) is None and emu.output_v == 2.5
    assert rm.decode_status(dev.read_input(0, rm.IR.STATUS_END)).output_v == 2.5


def test_serial_codec_against_a_script(profile: Profile) -> None:
    status = ("running=0 fill=3 error=0 out=5 runs=1 len=3 complete=1 wd=0 expired=0 ro=0 rate=10000 "
              "pos=3 total=3 wdt=0")
    script = [
        ("VER?", "3"),
        ("WTL 3", "OK"),
        ("WAV 0 3 0 2.5 5", "OK"),
        ("STA?", status.replace("fill=3", "fill=0").replace("runs=1", "runs=0").replace("pos=3", "pos=0")),
        ("STA?", status.replace("fill=3", "fill=0").replace("runs=1", "runs=0").replace("pos=3", "pos=0")),
        ("WGO 1", "OK"),
        ("STA?", status),
        ("DRR? 0 3", "0 3 0 0 0.125 2.5 0.25 5"),
        ("SVA 20", "ERR 4 slew limit exceeded"),
        ("SAFE", "OK"),
    ]
    port = ScriptedPort(script)
    stage = SerialStage(profile, port=port, timeout_s=0.1)
    stage.upload([0.0, 2.5, 5.0])
    stage.run(1)
    assert not stage.wait(poll_s=0).running
    rec = stage.read_recorder()
    np.testing.assert_array_equal(rec.displacement_um, [0.0, 0.125, 0.25])
    np.testing.assert_array_equal(rec.voltage_v, [0.0, 2.5, 5.0])
    with pytest.raises(StageError, match="slew"):
        stage.set_voltage(20.0)
    stage.safe_state()
    assert port.script == []


def test_serial_host_times_out_instead_of_hanging(profile: Profile) -> None:
    import os
    master, _slave, path = open_pty()
    try:
        with pytest.raises(StageError, match="no complete reply"):
            SerialStage(profile, path, timeout_s=0.2)
    finally:
        os.close(master)
        os.close(_slave)


def test_ascii_device_reports_unknown_and_malformed_commands(profile: Profile) -> None:
    dev = AsciiDevice(em.Emulator(profile), lambda: 0.0)
    assert dev.handle("FOO").startswith("ERR 1")
    assert dev.handle("WAV 0 2 1.0").startswith("ERR 2")
    assert dev.handle("SVA x").startswith("ERR 2")
    assert dev.handle("ERR?") == "2" and dev.handle("ERR?") == "0"


def test_open_stage_defaults_to_the_in_process_emulator(profile: Profile) -> None:
    with open_stage(profile) as stage:
        assert isinstance(stage, InProcessStage)
        stage.set_voltage(3.0)
        assert stage.status().output_v == 3.0


def test_afmctl_imports_no_device_library() -> None:
    code = ("import sys, afmctl, afmctl.files.profile, afmctl.cli\n"
            "bad = [m for m in sys.modules\n"
            "       if m.split('.')[0] in ('serial', 'pymodbus', 'drivers')]\n"
            "assert not bad, bad\n")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_device_logic_imports_no_device_library() -> None:
    """The emulated device's logic and plant (used in-process, e.g. by diagnose's tests) and the
    stage interface import neither pyserial nor pymodbus: only the links and servers do."""
    code = ("import sys, afmctl.drivers, afmctl.drivers.device.emulator, afmctl.drivers.device.plant, "
            "afmctl.drivers.inprocess\n"
            "bad = [m for m in sys.modules if m.split('.')[0] in ('serial', 'pymodbus')]\n"
            "assert not bad, bad\n")
    subprocess.run([sys.executable, "-c", code], check=True)


def _mbpoll(*args: str) -> str:
    out = subprocess.run(["mbpoll", "-1", "-0", *args], capture_output=True, text=True,
                         timeout=20)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def _mbpoll_values(text: str) -> list[str]:
    """The values of mbpoll's ``[address]: value`` lines."""
    return [line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith("[")]


@pytest.mark.skipif(shutil.which("mbpoll") is None,
                    reason="mbpoll (Debian package) could not be installed")
def test_mbpoll_reads_map_and_writes_dc_voltage(profile: Profile, device: EmulatedDevice
                                                ) -> None:
    with ModbusTcpServer(device) as srv:
        base = ["-m", "tcp", "-p", str(srv.port), "-a", "1"]
        version = _mbpoll(*base, "-t", "3", "-r", str(rm.IR.MAP_VERSION), "-c", "1", "127.0.0.1")
        assert _mbpoll_values(version) == [str(rm.MAP_VERSION)]
        status = _mbpoll(*base, "-t", "3", "-r", str(rm.IR.STATUS), "-c", "2", "127.0.0.1")
        assert _mbpoll_values(status) == ["0", "0"]  # idle, table empty; no error
        _mbpoll(*base, "-t", "4:float", "-B", "-r", str(rm.HR.DC_VOLTAGE), "127.0.0.1", "2.5")
        out = _mbpoll(*base, "-t", "3:float", "-B", "-r", str(rm.IR.OUTPUT_V), "-c", "1",
                      "127.0.0.1")
        assert float(_mbpoll_values(out)[0]) == 2.5
    assert device.emulator.output_v == 2.5
    assert device.emulator.applied_log(0.0).tolist() == [2.5]


@pytest.mark.parametrize("kind", ["modbus-tcp", "serial-pty", "inprocess"])
def test_every_stage_reports_the_same_limits(kind: str, profile: Profile) -> None:
    with stage_on(kind, profile) as (stage, _):
        assert stage.limits() == (-150.0, 150.0, 50.0)
        assert stage.voltage() == 0.0


# -- streaming (protocol v2) ----------------------------------------------------------------------
STREAM_KINDS = ["inprocess", "modbus-tcp", "modbus-rtu", "serial-pty"]


class Blocks:
    """An ``on_block`` that keeps every block (a stand-in for writing each to disk)."""

    def __init__(self, sleep_s: float = 0.0) -> None:
        self.blocks: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
        self.sleep_s = sleep_s

    def __call__(self, first: int, v: np.ndarray, u: np.ndarray, ok: np.ndarray) -> None:
        self.blocks.append((first, v, u, ok))
        time.sleep(self.sleep_s)

    def joined(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        starts = [b[0] for b in self.blocks]
        ends = np.cumsum([b[1].size for b in self.blocks])
        assert starts == [0, *ends[:-1].tolist()]  # in order and contiguous
        return tuple(np.concatenate([b[i] for b in self.blocks]) for i in (1, 2, 3))  # type: ignore


@pytest.mark.parametrize("kind", STREAM_KINDS)
def test_play_streams_three_tables_and_matches_the_model(kind: str, profile: Profile) -> None:
    small = small_buffers(profile)
    if kind == "modbus-rtu":  # pymodbus RTU on a pty reads back ~8,600 samples/s on an idle
        # machine, and under half that beside a busy test worker (CI lost readbacks at 5 kHz)
        small = replace(small, sample_rate_hz=2000.0)
    v = long_waveform(3 * 4096)
    assert small.emulator is not None
    u_exp, v_exp = plant.expected_readback(small.emulator, small.sample_rate_hz, v)
    blocks = Blocks()
    with stage_on(kind, small) as (stage, emu):
        rec = stage.play(v, blocks)
        st = stage.status()
        log = emu.applied_log(0.0)
    assert not st.running and st.play_position == v.size and st.last_error == 0
    assert len(blocks.blocks) > 3  # delivered progressively, not at the end
    volt, disp, ok = blocks.joined()
    assert ok.all() and disp.size == v.size and rec.complete
    np.testing.assert_array_equal(disp.astype(np.float32), u_exp.astype(np.float32))
    np.testing.assert_array_equal(volt.astype(np.float32), v_exp.astype(np.float32))
    np.testing.assert_array_equal(rec.displacement_um, disp)
    np.testing.assert_array_equal(log, v.astype(np.float32))  # every sample played, once, in order


def test_play_of_a_short_waveform_is_a_normal_run(profile: Profile, waveform: np.ndarray) -> None:
    blocks = Blocks()
    with stage_on("inprocess", profile) as (stage, _):
        rec = stage.play(waveform[:3000], blocks)
        assert stage.status().run_samples == 3000 and stage.status().table_length == 3000
    assert rec.complete and blocks.joined()[2].all()


@pytest.mark.parametrize("kind", ["inprocess", "serial-pty", "modbus-tcp"])
def test_play_clocks_the_device_at_the_profile_rate(kind: str, profile: Profile,
                                                    waveform: np.ndarray) -> None:
    """A device left at another sample rate is set back to the profile's before anything plays
    (timestamps, the model and the slew check all assume the profile's rate)."""
    with stage_on(kind, profile) as (stage, emu):
        stage.set_sample_rate(5000.0)
        assert stage.status().sample_rate_hz == 5000.0
        stage.play(waveform[:1000])
        assert stage.status().sample_rate_hz == profile.sample_rate_hz
        assert emu.sample_rate_hz == profile.sample_rate_hz


@pytest.mark.parametrize("kind", ["inprocess", "modbus-tcp"])
def test_slow_host_underruns_safely(kind: str, profile: Profile) -> None:
    small = small_buffers(profile)
    v = long_waveform(3 * 4096)
    blocks = Blocks(sleep_s=0.6)  # the table holds 0.41 s: the host falls behind
    with stage_on(kind, small) as (stage, emu):
        with pytest.raises(StageError) as info:
            stage.play(v, blocks)
        st = stage.status()
        log = emu.applied_log(0.0)
    assert info.value.code == 10 and "stopped after" in str(info.value)
    assert not st.running and st.output_v == 0.0 and 4096 <= st.play_position < v.size
    played, ramp = log[:st.play_position], log[st.play_position:]
    np.testing.assert_array_equal(played, v[:st.play_position].astype(np.float32))  # nothing stale
    assert ramp[-1] == 0.0 and np.all(np.diff(np.abs(ramp)) <= 0)
    volt, disp, ok = blocks.joined()
    assert volt.size == v.size  # every sample handed over: what was played measured, then the error
    assert ok[:st.play_position].all() and not ok[st.play_position:].any()
    assert np.isnan(disp[st.play_position:]).all()  # the rest flagged missing, never invented


@pytest.mark.parametrize("kind", ["inprocess", "serial-pty"])
def test_interrupt_in_on_block_leaves_the_stage_safe(kind: str, profile: Profile) -> None:
    small = small_buffers(profile)
    v = long_waveform(3 * 4096)

    def interrupt(first: int, *_: object) -> None:
        if first > 2000:
            raise KeyboardInterrupt

    with stage_on(kind, small) as (stage, emu):
        with pytest.raises(KeyboardInterrupt):
            stage.play(v, interrupt)
        st = stage.status()
        log = emu.applied_log(0.0)
    assert not st.running and st.output_v == 0.0 and st.play_position < v.size
    assert log[-1] == 0.0


def test_play_never_hangs(profile: Profile) -> None:
    with stage_on("inprocess", small_buffers(profile)) as (stage, emu):
        with pytest.raises(TimeoutError):
            stage.play(long_waveform(3 * 4096), timeout_s=0.2)
        assert not stage.status().running and emu.output_v == 0.0


def test_register_map_streams_at_global_indices(profile: Profile) -> None:
    emu = em.Emulator(small_buffers(profile))
    dev = RegisterDevice(emu, lambda: 0.0)
    v = np.linspace(0.0, 1.0, 60).astype(np.float32)
    assert dev.write(rm.HR.TABLE_LENGTH, rm.u32_regs(100)) is None
    assert dev.write(rm.HR.STREAM_FIRST, rm.u32_regs(40) + rm.f32_regs(v)) is None
    assert dev.write(rm.HR.STREAM_FIRST, rm.u32_regs(41) + rm.f32_regs(v)) == rm.ILLEGAL_VALUE
    assert dev.write(rm.HR.STREAM_TOTAL, rm.u32_regs(10_000)) is None
    assert dev.write(rm.HR.COMMAND, [rm.Cmd.START_STREAM]) == rm.ILLEGAL_VALUE  # 0..39 missing
    assert emu.last_error == 9
    st = rm.decode_status(dev.read_input(0, rm.IR.STATUS_END))
    assert st.play_position == 0 and st.run_samples == 0 and not st.running
