"""The foreign stage (:mod:`afmctl.drivers.device.foreign.stage`) as the emulated device's plant
(``[emulator.foreign]``), behind the real serial protocol on a pty."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.drivers import open_stage
from afmctl.drivers.device.emulated import EmulatedDevice
from afmctl.drivers.device.foreign import stage as foreign
from afmctl.drivers.device.foreign.physics import foreign_stage
from afmctl.drivers.device.serial_server import SerialServer
from afmctl.files.profile import Profile, SerialTransport, load_profile, shipped_profile
from tests.harness.paths import PROFILES

FOREIGN = PROFILES / "emulated-foreign.toml"


def _quiet(profile: Profile) -> Profile:
    """The shipped foreign stage without sensor noise."""
    em = profile.emulator
    assert em is not None and em.foreign is not None
    spec = replace(em.foreign, overrides=(("noise_um", 0.0),))
    return replace(profile, emulator=replace(em, foreign=spec))


def _play_over_pty(profile: Profile, v: np.ndarray) -> np.ndarray:
    with EmulatedDevice(profile) as dev, SerialServer(dev, "pty") as ser:
        wired = replace(profile, transport=SerialTransport(ser.url))
        with open_stage(wired) as stage:
            rec = stage.play(v)
    assert rec.valid.all()
    return rec.displacement_um


def _waveform() -> np.ndarray:
    t = np.arange(3000) / 10_000.0
    return 75.0 - 70.0 * np.cos(2 * np.pi * 20.0 * t)  # 0.03 .. 0.3 V/sample: within 50 V/ms


def test_readings_over_the_serial_protocol_are_the_foreign_plants() -> None:
    """Readings over the wire equal foreign.run on the same (float32) voltages, from the table's
    start state; with its noise on, they differ from it by the stage's own noise."""
    prof = _quiet(shipped_profile("emulated-foreign"))
    v = _waveform()
    stage = foreign_stage(prof.emulator.foreign, (0.0, 150.0))  # type: ignore[union-attr]
    assert stage.drive_range_V == (0.0, 150.0)
    _, want, _ = foreign.run(stage, v.astype(np.float32).astype(float), 10_000.0,
                             foreign.initial_state(stage, "poled+"), None)
    got = _play_over_pty(prof, v)
    assert np.ptp(want) > 10.0  # the stage moved tens of um
    np.testing.assert_allclose(got, want, atol=1e-4)
    noisy = _play_over_pty(shipped_profile("emulated-foreign"), v)
    assert np.std(noisy - want) == pytest.approx(0.02, rel=0.1)
    again = _play_over_pty(shipped_profile("emulated-foreign"), v)
    np.testing.assert_array_equal(noisy, again)  # reproducible from the seed


def test_run_state_replays_a_run_of_the_thermal_stage() -> None:
    """The state an emulated device keeps for the start of its last run (what the benches'
    truth probes re-simulate a run from) gives that run's readings again: on the quiet foreign
    stage with thermal relaxation (it creeps while the device idles between runs), the second
    run's readings over the pty equal ``foreign.run`` from ``run_state`` at that run's gain."""
    base = _quiet(shipped_profile("emulated-foreign"))
    spec = replace(base.emulator.foreign, effect="thermal-relaxation", strength=1.0)  # type: ignore[union-attr]
    prof = replace(base, emulator=replace(base.emulator, foreign=spec))  # type: ignore[arg-type]
    v = _waveform()
    with EmulatedDevice(prof) as dev, SerialServer(dev, "pty") as ser:
        wired = replace(prof, transport=SerialTransport(ser.url))
        with open_stage(wired) as stage:
            first = stage.play(v).displacement_um
            second = stage.play(v).displacement_um
        emu = dev.emulator
        start = replace(emu.run_state, gain=emu.physics.gain(emu.run_count - 1))
        _, again, _ = foreign.run(emu.physics.stage, v.astype(np.float32).astype(float),  # type: ignore[attr-defined]
                                  10_000.0, start, None)
    assert np.max(np.abs(second - first)) > 0.05  # the runs differ (the creep between them)
    np.testing.assert_allclose(second, again, atol=1e-4)


@pytest.mark.parametrize("line, says", [
    ("colour = 3", "colour: unknown key"),
    ('effect = "gremlins"', "effect: must be one of"),
    ('effect = "backlash"\nstrength = 1.5', "strength: must be in [0, 1]"),
    ("strength = 0.5", "strength: needs an effect"),
    ('start = "sideways"', "start: must be one of"),
    ("resonance_Hz = -5.0", "resonance_Hz"),
])
def test_bad_foreign_keys_exit_2_with_one_line(tmp_path: Path, line: str, says: str) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(FOREIGN.read_text().replace('start = "poled+"', line))
    res = CliRunner().invoke(main, ["emulate", "--profile", str(bad)])
    assert res.exit_code == 2
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("afmctl: error: ")
    assert says in res.stderr and "emulator.foreign" in res.stderr


def test_profile_keys_reach_the_stage(tmp_path: Path) -> None:
    p = tmp_path / "p.toml"
    p.write_text(FOREIGN.read_text().replace(
        'start = "poled+"', 'start = 40.0\nresonance_Hz = 300.0\neffect = "amplifier-lag"\n'
        'strength = 1.0\ncoercive_family = "gamma"'))
    spec = load_profile(p).emulator.foreign  # type: ignore[union-attr]
    assert spec.start == 40.0 and spec.effect == "amplifier-lag" and spec.strength == 1.0
    stage = foreign_stage(spec, (0.0, 150.0))
    assert stage.rod.resonance_hz == pytest.approx(300.0)
    assert stage.material.coercive.family == "gamma"
    assert [foreign.describe(stage)["effects"][0]["cause"]] == ["amplifier-lag"]


def test_afmctl_emulate_serves_the_foreign_stage() -> None:
    """`afmctl emulate --profile emulated-foreign` serves it; a host plays over the pty."""
    argv = [sys.executable, "-m", "afmctl", "emulate", "--profile", str(FOREIGN),
            "--modbus-port", "0", "--no-rtu"]
    with subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                          text=True) as proc:
        try:
            assert proc.stdout is not None
            url = next((line.split(": ", 1)[1].strip() for line in proc.stdout
                        if line.startswith("serial")), None)
            assert url is not None
            wired = replace(shipped_profile("emulated-foreign"), transport=SerialTransport(url))
            with open_stage(wired) as stage:
                rec = stage.play(_waveform())
            assert rec.valid.all() and np.ptp(rec.displacement_um) > 10.0
        finally:
            proc.terminate()
            proc.wait(timeout=10)


def serial_foreign_profile(tmp_path: Path, url: str) -> Path:
    """The shipped foreign profile reached over the serial protocol at ``url``."""
    path = tmp_path / "foreign-serial.toml"
    path.write_text(FOREIGN.read_text().replace('kind = "emulated"',
                                                f'kind = "serial"\nurl = "{url}"'))
    return path


class _Truth:
    """A driver stage that also keeps the noise-free reading of every run it plays (um),
    re-simulated from the device's state when the run began: on a stage with a linear gauge and
    no latency, the true position in the readings' frame."""

    def __init__(self, stage: object, device: EmulatedDevice) -> None:
        self.stage, self.device = stage, device
        self.clean: list[np.ndarray] = []

    def voltage(self) -> float:
        return self.stage.voltage()  # type: ignore[attr-defined]

    def play(self, waveform_v: np.ndarray, on_block: object = None, **kw: object) -> object:
        rec = self.stage.play(waveform_v, on_block, **kw)  # type: ignore[attr-defined]
        with self.device.lock:
            emu = self.device.emulator
            start = replace(emu.run_state, gain=emu.physics.gain(emu.run_count - 1))
        v = np.asarray(waveform_v, dtype=np.float32).astype(float)
        self.clean.append(foreign.run(emu.physics.stage, v, emu.sample_rate_hz, start,  # type: ignore[attr-defined]
                                      None)[1])
        return rec


@pytest.mark.heavy
def test_sweep_identify_and_learn_over_a_pty_on_the_foreign_stage(tmp_path: Path) -> None:
    """`afmctl sweep` over the serial protocol, then `afmctl identify`: every sweep within 1.5x
    its sensor noise and the rod's resonance where the foreign stage has it (a stage afmctl's
    model was not written for: other code, parameters drawn from seed 7). Then learning (issue
    13) over the same wire from that model: a 27.9 Hz triangle's true error (first period out)
    within 2x the noise, and no worse than iteration 0's (this clean stage starts within the
    noise, 0.011 um, and learning took it to 0.007 um; bench_learn's stages with effects are
    where learning has more to do). Heavy (90 s, ``pytest --heavy``): each part runs in CI
    apart (a calibration over a socket on the independent stage, learning over the serial
    protocol, this stage's readings over the pty)."""
    import json

    from afmctl.experiment import learn
    from afmctl.files import modelfile
    from afmctl.files import sweepfile as sweeps
    from afmctl.planning import ilc, track

    with EmulatedDevice(load_profile(serial_foreign_profile(tmp_path, "/dev/null"))) as dev, \
            SerialServer(dev, "pty") as ser:
        prof = serial_foreign_profile(tmp_path, ser.url)
        res = CliRunner().invoke(main, ["sweep", "--profile", str(prof), "--out",
                                        str(tmp_path / "s")])
        assert res.exit_code == 0, res.output
        truth = dev.emulator.physics.stage  # type: ignore[attr-defined]
        files = sorted(str(p) for p in (tmp_path / "s").glob("*.csv"))
        assert len(files) == 4
        res = CliRunner().invoke(main, ["identify", "--profile", str(prof), "-o",
                                        str(tmp_path / "m.toml"), "--json", *files])
        assert res.exit_code == 0, res.output
        fit = json.loads(res.stdout)
        assert fit["at_noise_floor"]
        assert fit["parameters"]["natural_frequency"]["value"] == pytest.approx(
            truth.rod.resonance_hz, rel=0.05)
        wired = load_profile(prof)
        fast = sweeps.read(tmp_path / "s" / "triangle_27.9hz.csv").displacement_um
        lo, hi = np.percentile(fast[fast.size // 2:], [0, 100])
        desired = track.triangle(27.9, min(27.04, 0.6 * (hi - lo)), 0.5 * (lo + hi), 3,
                                 1 / wired.sample_rate_hz)
        with open_stage(wired) as stage:
            probe = _Truth(stage, dev)
            out = learn.run(probe, modelfile.read(tmp_path / "m.toml"), desired, wired.limits,
                            tmp_path / "learn", {}, 3, ilc.Law(),
                            envelope=modelfile.read_envelope(tmp_path / "m.toml"))
    steady = ilc.steady_part(desired)
    true_rms = [float(np.sqrt(np.mean((c[it.outcome.waveform.tracking] - desired.u_um)[steady]
                                      ** 2)))
                for c, it in zip(probe.clean, out.iterations, strict=True)]
    assert true_rms[out.best] <= 2 * truth.sensor.noise_um, true_rms
    assert true_rms[out.best] <= true_rms[0], true_rms
