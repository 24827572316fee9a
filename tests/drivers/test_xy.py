"""A two-axis stage from the wire up (issue 25 items 1-2): the emulated x/y stage plays (N, 2)
waveforms over every wire, its coupling shows on the sensor of the axis not driven, each channel
is guard-checked against its own axis's limits before anything is sent, and a one-axis host
command on it means channel 0."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from afmctl.drivers.device.emulator import Emulator
from afmctl.errors import DeviceError, LimitError, LimitMismatchError
from afmctl.files.profile import Profile, shipped_profile
from tests.harness.emulated import TRANSPORTS, long_waveform, small_buffers, stage_on

XY = shipped_profile("emulated-xy")
RATE = XY.sample_rate_hz


def x_only(n: int, amplitude_v: float = 60.0, freq_hz: float = 20.0) -> np.ndarray:
    """x driven by a slew-safe raised sine from 0 V, y held at 0 V: shape (n, 2)."""
    t = np.arange(n) / RATE
    return np.stack([amplitude_v * np.sin(np.pi * freq_hz * t) ** 2, np.zeros(n)], axis=1)


def coupling_slope(x_um: np.ndarray, y_um: np.ndarray) -> float:
    """Least-squares slope of y on x, um/um."""
    a = np.stack([x_um - x_um.mean(), np.ones_like(x_um)], axis=1)
    return float(np.linalg.lstsq(a, y_um - y_um.mean(), rcond=None)[0][0])


def test_the_shipped_xy_profile_has_two_different_axes_and_both_couplings() -> None:
    x, y = XY.axis("x"), XY.axis("y")
    assert XY.axis_names == ("x", "y") and x.axis_names == ("x",) and y.axis_names == ("y",)
    assert x.emulator is not None and y.emulator is not None
    assert x.emulator.model.rod != y.emulator.model.rod and x.limits != y.limits
    assert x.emulator.seed != y.emulator.seed and y.sensor_offset_um == 1.5
    assert {d for d, _ in XY.emulator.coupling} == {"yx", "xy"}  # type: ignore[union-attr]
    assert x.emulator.coupling == () and y.emulator.coupling == ()


@pytest.mark.parametrize("kind", TRANSPORTS)
def test_a_two_axis_waveform_plays_on_every_wire_and_y_moves_when_only_x_is_driven(
        kind: str) -> None:
    """The coupling travels the wire: y's sensor follows c_yx * x (the profile's 0.012 at 20 Hz,
    where the 420 Hz shared mode adds under 1 %), far beyond its noise; x's own reading is as large
    as a one-axis play of the same voltage makes it."""
    v = x_only(2000, 120.0)
    blocks: list[tuple[int, tuple[int, ...]]] = []
    with stage_on(kind, XY) as (stage, emu):
        assert stage.channels == 2
        rec = stage.play(v, on_block=lambda f, a, u, ok: blocks.append((f, u.shape)))
        assert rec.displacement_um.shape == rec.voltage_v.shape == rec.valid.shape == (2000, 2)
        assert rec.valid.all() and all(shape[1:] == (2,) for _, shape in blocks)
        np.testing.assert_allclose(stage.voltages(), [v[-1, 0], 0.0], rtol=1e-6)
        applied = emu.applied_log(emu.plant_time or 0.0)
    x_um, y_um = rec.displacement_um[:, 0], rec.displacement_um[:, 1]
    y_noise = XY.axis("y").emulator.noise_um  # type: ignore[union-attr]
    assert np.ptp(x_um) > 10.0
    assert abs(coupling_slope(x_um, y_um) - 0.012) < 0.002
    assert np.std(y_um - 0.012 * x_um) < 2 * y_noise < 0.2 * np.ptp(y_um)
    assert np.all(applied[:, 1] == 0.0) and applied.shape[1] == 2  # y was never driven


@pytest.mark.parametrize("kind", TRANSPORTS)
def test_a_sample_beyond_channel_1s_limits_is_refused_before_anything_is_sent(kind: str) -> None:
    """y's amplifier ends at 120 V (x's at 150 V): 121 V on y is refused by the host's guard
    against [axis.y.amplifier], naming the axis; the device saw no table, no run, no sample."""
    v = x_only(400)
    v[200:, 1] = np.linspace(0.0, 121.0, 200)  # within y's slew limit, beyond its range
    with stage_on(kind, XY) as (stage, emu):
        with pytest.raises(LimitError, match=r"axis y \(channel 1\).*above the limit 120"):
            stage.play(v)
        st = stage.status()
        assert (st.run_count, st.table_length) == (0, 0)
        assert emu.applied_log(emu.plant_time or 0.0).size == 0


def test_the_foreign_xy_stage_plays_behind_the_wire_with_its_own_coupling() -> None:
    """``emulated-xy-foreign``: the independently written x/y stage behind socket://; y follows x
    by the stage's own static coupling (its formulas, -35 dB drawn), within 10 % over a sweep."""
    from afmctl.drivers.device.foreign import xy_stage as xs
    prof = shipped_profile("emulated-xy-foreign")
    v = x_only(3000, 120.0, 10.0)
    with stage_on("serial-socket", prof) as (stage, emu):
        rec = stage.play(v)
        truth = xs.describe(emu.physics.stage)["derived"]["yx_static"]  # type: ignore[attr-defined]
    assert rec.valid.all() and abs(xs.db(truth) + 35.0) < 0.01
    slope = coupling_slope(rec.displacement_um[:, 0], rec.displacement_um[:, 1])
    assert abs(slope / truth - 1.0) < 0.1, (slope, truth)


def test_a_one_axis_play_on_the_xy_device_drives_channel_0_and_holds_channel_1() -> None:
    """Old forms mean channel 0 (docs/reference/protocol.md §2.14): a (N,) waveform plays x while y
    holds its DC set point through the run."""
    with stage_on("serial-pty", XY) as (stage, emu):
        stage.set_voltage(3.0, channel=1)
        rec = stage.play(x_only(500)[:, 0])
        assert rec.displacement_um.shape == (500,)
        log = emu.applied_log(emu.plant_time or 0.0)
    assert np.all(log[-500:, 1] == 3.0) and np.array_equal(log[-500:, 0],
                                                          x_only(500)[:, 0].astype(np.float32))


def test_a_streamed_two_axis_run_longer_than_the_table_records_both_channels() -> None:
    """Streaming per channel through a 4,096-sample table: every sample of both channels played
    as written and read back (at 5 kHz: a loaded CI machine keeps up with two channels)."""
    n = 6_000
    wave = np.stack([long_waveform(n), 0.5 * long_waveform(n)], axis=1)
    with stage_on("modbus-tcp", replace(small_buffers(XY), sample_rate_hz=5000.0)) as (stage, emu):
        rec = stage.play(wave)
        log = emu.applied_log(emu.plant_time or 0.0)
    assert rec.valid.all() and rec.displacement_um.shape == (n, 2)
    np.testing.assert_array_equal(log[-n:], wave.astype(np.float32))


def test_safe_state_ramps_every_output_to_zero_each_within_its_own_slew() -> None:
    emu = Emulator(XY)
    for k in range(1, 11):  # x to 40 V in 4 V steps, y to -30 V in 3 V steps (y: 4 V/sample)
        emu.set_voltage(4.0 * k, 0.0, channel=0)
        emu.set_voltage(-3.0 * k, 0.0, channel=1)
    before = emu.applied_log(0.0).shape[0]
    emu.safe_state(0.0)
    ramp = emu.applied_log(0.0)[before:]
    assert np.array_equal(emu.outputs, [0.0, 0.0]) and np.all(ramp[-1] == 0.0)
    steps = np.abs(np.diff(np.vstack([[40.0, -30.0], ramp]), axis=0))
    assert steps[:, 0].max() <= 0.9 * 5.0 + 1e-9 and steps[:, 1].max() <= 0.9 * 4.0 + 1e-9
    assert np.count_nonzero(ramp[:, 0]) == 8 and np.count_nonzero(ramp[:, 1]) == 8


def test_the_device_refuses_what_the_document_refuses_per_channel() -> None:
    """Channel index (6), y's own range (3) and slew (4), the table complete only when every
    channel written holds its samples (9), held channels, and read-only (7) before the index."""
    emu = Emulator(XY)
    emu.set_table_length(2, 0.0)
    codes = []
    for call in (lambda: emu.set_voltage(1.0, 0.0, channel=2),
                 lambda: emu.write_table(0, np.array([121.0]), 0.0, channel=1),
                 lambda: emu.set_voltage(4.5, 0.0, channel=1)):
        with pytest.raises(DeviceError) as err:
            call()
        codes.append(err.value.code)
    assert codes == [6, 3, 4]
    emu.write_table(0, np.array([0.0, 1.0]), 0.0, channel=0)
    emu.write_table(0, np.array([0.0]), 0.0, channel=1)
    assert not emu.status(0.0).table_complete
    with pytest.raises(DeviceError) as err:
        emu.start(1, 0.0)
    assert err.value.code == 9
    emu.write_table(1, np.array([2.0]), 0.0, channel=1)
    assert emu.status(0.0).table_complete
    emu.start(1, 0.0)
    assert emu.status(1.0).play_position == 2
    read_only = Emulator(XY, read_only=True)
    with pytest.raises(DeviceError) as err:
        read_only.set_voltage(1.0, 0.0, channel=5)
    assert err.value.code == 7


def test_a_two_axis_profile_on_a_one_channel_device_is_refused_naming_both(
        profile: Profile) -> None:
    from afmctl.drivers.inprocess import InProcessStage
    with InProcessStage(XY, emulator=Emulator(profile)) as stage:
        assert stage.channels == 1
        with pytest.raises(LimitMismatchError, match="2 axes .* 1 channel"):
            stage.play(np.zeros(10))


def test_a_y_amplifier_beyond_the_devices_channel_1_is_named() -> None:
    wide = replace(XY, other_axes=(replace(XY.axis("y"), limits=replace(
        XY.axis("y").limits, v_max=140.0)),))
    from afmctl.drivers.inprocess import InProcessStage
    with InProcessStage(wide, emulator=Emulator(XY)) as stage:
        with pytest.raises(LimitMismatchError, match=r"\[axis\.y\.amplifier\].*of channel 1"):
            stage.check_limits()


def test_the_xy_plant_adds_the_coupling_of_afmctl_model_coupling_in_pieces_as_in_one() -> None:
    """The plant's y reading is y's own plant plus ``caused(c_yx, x)`` (afmctl.model.coupling's
    response from rest), also when the run is played in two pieces (the mode's state carried)."""
    from afmctl.drivers.device.emulator import plant
    from afmctl.model.coupling import caused
    physics = plant(XY, RATE)
    v = x_only(3000, 120.0, 20.0)
    v[:, 1] = 10.0 * np.sin(2 * np.pi * 7.0 * np.arange(3000) / RATE)
    whole, _, _ = physics.respond(v, physics.initial())
    first, _, state = physics.respond(v[:1234], physics.initial())
    rest, _, _ = physics.respond(v[1234:], state)
    np.testing.assert_allclose(np.vstack([first, rest]), whole, atol=1e-9)
    own = [p.respond(v[:, c], p.initial())[0] for c, p in enumerate(physics.plants)]
    coupling = dict(XY.emulator.coupling)  # type: ignore[union-attr]
    np.testing.assert_allclose(whole[:, 1] - own[1], caused(coupling["yx"], own[0], 1 / RATE),
                               atol=1e-6)
    np.testing.assert_allclose(whole[:, 0] - own[0], caused(coupling["xy"], own[1], 1 / RATE),
                               atol=1e-6)
