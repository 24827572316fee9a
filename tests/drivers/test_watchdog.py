"""The device watchdog on every run over every wire (issue 14, item 4).

``play`` sets the profile's period and arms it (WDT, then HB) before the start, feeds it while the
run plays and disarms it (period 0) when the run is over; a host process killed mid-run (SIGKILL,
a real subprocess) stops feeding it, and the device stops and ramps to 0 V within one period."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import numpy as np
import pytest

from afmctl.drivers.device.emulated import EmulatedDevice
from afmctl.drivers.device.emulator import Emulator
from afmctl.drivers.device.modbus_server import ModbusRtuServer, ModbusTcpServer
from afmctl.drivers.device.serial_server import SerialServer
from afmctl.files.profile import Profile
from tests.harness.emulated import stage_on
from tests.harness.paths import PROFILES

WIRES = ["serial-socket", "serial-pty", "modbus-tcp", "modbus-rtu"]


class Spy:
    """Device time of every heartbeat, watchdog setting and start the device received."""

    def __init__(self, em: Emulator) -> None:
        self.events: list[tuple[str, float, float]] = []
        for name in ("heartbeat", "set_watchdog", "start", "start_stream"):
            real = getattr(em, name)
            setattr(em, name, self._logged(name, real))

    def _logged(self, name: str, real):  # noqa: ANN202
        def call(*args: float) -> None:
            self.events.append((name, args[-1], args[0] if len(args) > 1 else 0.0))
            return real(*args)
        return call


def ramp_and_hold(profile: Profile, target_v: float, hold_s: float) -> np.ndarray:
    step = 0.5 * profile.limits.max_step_v(profile.sample_rate_hz)
    ramp = np.arange(step, target_v, step)
    return np.concatenate([ramp, np.full(int(hold_s * profile.sample_rate_hz), target_v)])


@pytest.mark.parametrize("kind", WIRES)
def test_play_arms_feeds_and_disarms_the_watchdog(kind: str, profile: Profile) -> None:
    period = 0.4
    v = ramp_and_hold(profile, 5.0, 1.5)  # several periods
    with stage_on(kind, profile) as (stage, em):
        spy = Spy(em)
        stage.watchdog_s = period
        rec = stage.play(v)
        st = stage.status()
    assert rec.complete and not st.watchdog_armed and not st.watchdog_expired
    names = [e[0] for e in spy.events]
    starts = names.index("start")
    assert names[:starts] == ["set_watchdog", "heartbeat"]
    assert spy.events[0][2] == pytest.approx(period, rel=1e-6)  # float32 on Modbus
    assert names[-1] == "set_watchdog" and spy.events[-1][2] == 0.0  # disarmed after the run
    beats = np.array([t for name, t, _ in spy.events if name == "heartbeat"])
    t_start = spy.events[starts][1]
    run_s = v.size / profile.sample_rate_hz
    assert beats.size >= run_s / period  # fed all along the run ...
    assert np.diff(np.concatenate([beats, [t_start + run_s]])).max() < period  # ... never starved


CHILD = textwrap.dedent("""
    import sys
    import numpy as np
    from afmctl.files.profile import load_profile
    from afmctl.drivers import open_stage
    prof = load_profile(sys.argv[1])
    step = 0.5 * prof.limits.max_step_v(prof.sample_rate_hz)
    v = np.concatenate([np.arange(step, 30.0, step), np.full(int(60 * prof.sample_rate_hz), 30.0)])
    with open_stage(prof) as stage:
        stage.play(v)
""")


def _profile_text(transport: str, rate_hz: float) -> str:
    shipped = PROFILES / "emulated.toml"
    text = shipped.read_text()
    head, _, rest = text.partition("[transport]")
    rest = rest.split("\n", 2)[2]  # drop the emulated transport's kind line
    head = head.replace("sample_rate_Hz = 10000.0", f"sample_rate_Hz = {rate_hz}")
    return head + "[transport]\n" + transport + "\n" + rest.split("[emulator]")[0]


@contextmanager
def served(kind: str, profile: Profile) -> Iterator[tuple[EmulatedDevice, str]]:
    """A device on ``kind`` and the [transport] table a host needs to reach it."""
    with ExitStack() as stack:
        dev = stack.enter_context(EmulatedDevice(profile))
        keys = "timeout_s = 0.2\nwatchdog_s = 0.5\n"
        if kind == "modbus-tcp":
            port = stack.enter_context(ModbusTcpServer(dev)).port
            where = f'kind = "modbus-tcp"\nhost = "127.0.0.1"\nport = {port}\n'
        elif kind == "modbus-rtu":
            url = stack.enter_context(ModbusRtuServer(dev)).url
            where = f'kind = "modbus-rtu"\nport = "{url}"\n'
        else:
            url = stack.enter_context(SerialServer(
                dev, "pty" if kind == "serial-pty" else "socket://127.0.0.1:0")).url
            where = f'kind = "serial"\nurl = "{url}"\n'
        yield dev, where + keys


def _device_status(dev: EmulatedDevice):  # noqa: ANN202
    with dev.lock:
        return dev.emulator.status(dev.clock())


@pytest.mark.parametrize("kind", WIRES)
def test_killed_host_leaves_the_stage_at_zero(kind: str, profile: Profile,
                                              tmp_path: Path) -> None:
    rate = 2000.0  # the child's 60 s run plays from the table (no streaming needed to prove this)
    with served(kind, profile) as (dev, transport):
        path = tmp_path / "stage.toml"
        path.write_text(_profile_text(transport, rate))
        child = subprocess.Popen([sys.executable, "-c", CHILD, str(path)],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:
            deadline = time.monotonic() + 60.0
            while not ((st := _device_status(dev)).running and st.output_v >= 30.0):
                assert child.poll() is None, child.communicate()[1].decode()[-2000:]
                assert time.monotonic() < deadline, "the host never reached 30 V"
                time.sleep(0.02)
            assert st.watchdog_armed and st.watchdog_s == 0.5
            os.kill(child.pid, signal.SIGKILL)
            killed = dev.clock()
            child.wait(10)
            while (st := _device_status(dev)).running or st.output_v != 0.0:
                assert dev.clock() - killed < 5.0, f"still at {st.output_v} V, running={st.running}"
                time.sleep(0.005)
            zero_at = dev.clock()
        finally:
            if child.poll() is None:
                child.kill()
                child.wait(10)
            child.stdout.close()  # type: ignore[union-attr]
            child.stderr.close()  # type: ignore[union-attr]
        log = dev.emulator.applied_log(dev.clock())
    assert st.watchdog_expired and st.last_error == 8
    assert st.play_position < st.run_samples  # stopped by the watchdog, not by the run's end
    ramp_s = 30.0 / (0.9 * profile.limits.slew_v_per_ms * 1000.0)
    assert zero_at - killed <= 0.5 + ramp_s + 0.1  # one period after the last heartbeat, at most
    assert log[-1] == 0.0
    steps = np.abs(np.diff(log))
    assert steps.max() <= profile.limits.max_step_v(rate) * (1 + 1e-6)  # the ramp within the slew


@pytest.mark.parametrize("kind", ["serial-socket", "modbus-tcp"])
def test_an_interrupted_play_disarms_the_watchdog(kind: str, profile: Profile) -> None:
    """Ctrl-C mid-run: the stage is made safe and the watchdog disarmed, so it does not expire a
    period later on the idle device and leave error 8 (watchdog expired) for `afmctl status`."""
    v = ramp_and_hold(profile, 5.0, 1.5)

    def interrupt(first: int, *_: object) -> None:
        raise KeyboardInterrupt

    with stage_on(kind, profile) as (stage, _):
        stage.watchdog_s = 0.3
        with pytest.raises(KeyboardInterrupt):
            stage.play(v, interrupt)
        time.sleep(0.5)
        st = stage.status()
    assert not st.running and st.output_v == 0.0
    assert not st.watchdog_armed and not st.watchdog_expired and st.last_error == 0


def test_an_ignored_sigint_stays_ignored_while_a_block_is_handed_over() -> None:
    """A process that ignores SIGINT (started in the background) is not interrupted by one that
    lands while a block is written (it once became a KeyboardInterrupt only there)."""
    from afmctl.drivers.player import _sigint_held
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        try:
            with _sigint_held():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)
        except KeyboardInterrupt:  # caught here: it would end the whole pytest session
            pytest.fail("an ignored SIGINT became a KeyboardInterrupt")
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)
