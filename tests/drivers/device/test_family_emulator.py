"""The out-of-family stages (:mod:`afmctl.drivers.device.foreign.family_stage`) as the emulated
device's plant (``[emulator.family]``): the profile's keys, sweeps recorded over the real serial
protocol on a pty and from ``afmctl emulate``, and long holds (creep and drift go on past the
emulator's idle horizon)."""

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
from afmctl.drivers.device.foreign import family_stage as fs
from afmctl.drivers.device.foreign.family_physics import family_stage_of
from afmctl.drivers.device.serial_server import SerialServer
from afmctl.drivers.inprocess import InProcessStage
from afmctl.files.profile import FamilySpec, Profile, SerialTransport, load_profile
from afmctl.planning import sweepdesign as sd
from benchmarks.family_sets import FAMILY_CASES, profile, profile_toml
from benchmarks.family_sets import profile_text as _toml
from tests.harness.paths import PROFILES

FOREIGN = PROFILES / "emulated-foreign.toml"


def _profile(tmp_path: Path, table: str, v_min: float = 0.0) -> Profile:
    path = tmp_path / "family.toml"
    path.write_text(_toml(table, v_min))
    return load_profile(path)


def _triangle(lo: float, hi: float) -> np.ndarray:
    """The standard 27.9 Hz triangle over lo .. hi at 10 kHz (within the profile's slew)."""
    return [v for name, _, v in sd.standard_set(sample_rate_hz=10_000.0, v_range=(lo, hi))
            if name.startswith("triangle_27.9")][0]


def test_profile_keys_reach_the_stage(tmp_path: Path) -> None:
    prof = _profile(tmp_path, 'family = "bouc-wen"\nseed = 9\ncreep = true\ndrift = true\n'
                              'effect = "second-mode"\nresonance_Hz = 800.0\nnoise_um = 0.02\n'
                              'drift_um_per_s = -0.01', v_min=-150.0)
    spec = prof.emulator.family  # type: ignore[union-attr]
    assert spec == FamilySpec("bouc-wen", 9, True, True, "random", "second-mode",
                              (("resonance_hz", 800.0), ("noise_um", 0.02),
                               ("drift_um_per_s", -0.01)))
    stage = family_stage_of(spec, (-150.0, 150.0))
    assert isinstance(stage.operator, fs.BoucWen) and stage.creep is not None
    assert stage.resonance_hz == 800.0 and stage.noise_um == 0.02
    assert stage.drift_um_per_s == -0.01 and stage.drive_range_V == (-150.0, 150.0)
    assert stage.extras.cause == "second-mode"


def test_the_benches_stages_load_as_profile_files(tmp_path: Path) -> None:
    """Every bench stage written as a profile file (for ``afmctl emulate --profile``) reads back
    as the profile the benches build in-process."""
    for case in FAMILY_CASES:
        path = tmp_path / f"{case.name}.toml"
        path.write_text(profile_toml(case))
        prof = load_profile(path)
        assert prof.emulator.family == case.spec  # type: ignore[union-attr]
        assert (prof.limits.v_min, prof.limits.v_max) == case.drive_V
        assert prof.limits == profile(case).limits


@pytest.mark.parametrize("table, says", [
    ('family = "jiles-atherton"', "family: must be one of"),
    ('family = "preisach"\ncolour = 3', "colour: unknown key"),
    ('family = "preisach"\neffect = "backlash"', "effect: must be one of"),
    ('family = "preisach"\nspan_um = -5.0', "span_um"),
    ('seed = 3', "family"),
])
def test_bad_family_keys_exit_2_with_one_line(tmp_path: Path, table: str, says: str) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(_toml(table))
    res = CliRunner().invoke(main, ["emulate", "--profile", str(bad)])
    assert res.exit_code == 2
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("afmctl: error: ")
    assert says in res.stderr and "emulator.family" in res.stderr


def test_a_stage_is_foreign_or_of_a_family_not_both(tmp_path: Path) -> None:
    both = tmp_path / "both.toml"
    both.write_text(FOREIGN.read_text().replace("\n[emulator.foreign]\n",
                                                '\n[emulator.family]\nfamily = "preisach"\n\n'
                                                "[emulator.foreign]\n"))
    res = CliRunner().invoke(main, ["emulate", "--profile", str(both)])
    assert res.exit_code == 2 and "not both" in res.stderr


def test_a_sweep_over_the_serial_protocol_is_the_family_stages(tmp_path: Path) -> None:
    """A bipolar Preisach stage with creep, its fast standard triangle recorded over a pty: the
    readings are the plant's own (``family_stage.run`` on the float32 voltages from power-on) plus
    the stage's noise, nothing else."""
    prof = _profile(tmp_path, 'family = "preisach"\nseed = 11\ncreep = true', v_min=-150.0)
    v = _triangle(-150.0, 150.0)
    with EmulatedDevice(prof) as dev, SerialServer(dev, "pty") as ser:
        with open_stage(replace(prof, transport=SerialTransport(ser.url))) as stage:
            rec = stage.play(v)
        truth = dev.emulator.physics.stage  # type: ignore[attr-defined]
    assert rec.valid.all()
    want = fs.run(truth, v.astype(np.float32).astype(float), 10_000.0,
                  fs.initial_state(truth))[1]
    assert np.ptp(want) > 50.0  # the stage moved its stroke
    diff = rec.displacement_um - want
    assert np.std(diff) == pytest.approx(truth.noise_um, rel=0.1)
    assert abs(np.mean(diff)) < 4 * truth.noise_um / np.sqrt(diff.size)


def test_afmctl_emulate_serves_a_family_stage(tmp_path: Path) -> None:
    """`afmctl emulate --profile FILE` with ``[emulator.family]``: a host records the fast
    triangle over its serial port; the readings are the modified PI stage's, within its noise."""
    path = tmp_path / "pi.toml"
    path.write_text(_toml('family = "prandtl-ishlinskii"\nseed = 4'))
    argv = [sys.executable, "-m", "afmctl", "emulate", "--profile", str(path),
            "--modbus-port", "0", "--no-rtu"]
    v = _triangle(0.0, 150.0)
    with subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                          text=True) as proc:
        try:
            assert proc.stdout is not None
            url = next((line.split(": ", 1)[1].strip() for line in proc.stdout
                        if line.startswith("serial")), None)
            assert url is not None
            wired = replace(load_profile(path), transport=SerialTransport(url))
            with open_stage(wired) as stage:
                rec = stage.play(v)
        finally:
            proc.terminate()
            proc.wait(timeout=10)
    truth = family_stage_of(load_profile(path).emulator.family, (0.0, 150.0))  # type: ignore[union-attr, arg-type]
    want = fs.run(truth, v.astype(np.float32).astype(float), 10_000.0, fs.initial_state(truth))[1]
    assert rec.valid.all()
    assert np.std(rec.displacement_um - want) == pytest.approx(truth.noise_um, rel=0.15)


def test_creep_and_drift_go_on_through_a_long_hold(tmp_path: Path) -> None:
    """Two plays 300 s apart (device time) on a creeping, drifting stage: the second's readings
    are the plant's after the hold (``family_stage.idle``), not after the emulator's 1 s
    horizon: the drift alone moved the stage by 300 s x its rate."""
    prof = _profile(tmp_path, 'family = "preisach"\nseed = 12\ncreep = true\ndrift = true\n'
                              "drift_um_per_s = 0.02")
    now = [0.0]

    def clock() -> float:
        now[0] += 0.01
        return now[0]

    v = _triangle(0.0, 150.0)
    with InProcessStage(prof, clock=clock) as stage:
        first = stage.play(v).displacement_um
        dev = stage.emulator
        end_first = dev.state
        now[0] += 300.0
        second = stage.play(v).displacement_um
        start_second = dev.run_state
    truth = dev.physics.stage  # type: ignore[attr-defined]
    held = dev.run_state.scalars[0] - end_first.scalars[0]  # device time between the runs, s
    assert 300.0 < held < 301.0
    want = fs.run(truth, v.astype(np.float32).astype(float), 10_000.0,
                  fs.idle(truth, end_first, held, float(np.float32(v[-1]))))[1]
    assert np.std(second - want) == pytest.approx(truth.noise_um, rel=0.15)
    assert start_second.scalars[0] == pytest.approx(end_first.scalars[0] + held)
    assert np.mean(second - first) == pytest.approx(0.02 * held, rel=0.1)
