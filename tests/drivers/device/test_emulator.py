"""The emulated device's logic with a hand-stepped clock: physics, persistence, limits, watchdog."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from afmctl.drivers.device import emulator as em
from afmctl.drivers.device import plant
from afmctl.files.profile import Effects, Profile, SecondMode
from afmctl.model import hysteresis as hy

RATE = 10_000.0


def sine(n: int, amplitude_v: float = 100.0, freq_hz: float = 5.0) -> np.ndarray:
    """A sine from 0 V at 10 kHz, inside +-150 V and 50 V/ms for the defaults."""
    return amplitude_v * np.sin(2 * np.pi * freq_hz * np.arange(n) / RATE)


def quiet(profile: Profile, **effects: object) -> Profile:
    """The profile with no sensor noise and the given effects on."""
    assert profile.emulator is not None
    cfg = replace(profile.emulator, noise_um=0.0, effects=replace(Effects(), **effects))
    return replace(profile, emulator=cfg)


def run(emu: em.Emulator, v: np.ndarray, t0: float, cycles: int = 1
        ) -> tuple[np.ndarray, np.ndarray]:
    emu.set_table_length(v.size, t0)
    emu.write_table(0, v, t0)
    emu.start(cycles, t0)
    end = t0 + v.size * cycles / RATE + 1e-3
    assert not emu.status(end).running
    u, va = emu.read_recorder(0, v.size * cycles, end)
    return u.astype(float), va.astype(float)


def test_recorder_is_the_model_run_in_device_time(profile: Profile) -> None:
    emu = em.Emulator(profile)
    v = sine(4000)
    emu.set_table_length(v.size, 0.0)
    emu.write_table(0, v, 0.0)
    emu.start(1, 1.0)
    st = emu.status(1.1)
    assert st.running and st.recorder_fill == 1000
    u, _ = emu.read_recorder(0, 4000, 1.1)
    assert np.isfinite(u[:1000]).all() and np.isnan(u[1000:]).all()
    u, va = emu.read_recorder(0, 4000, 1.5)
    exp_u, exp_v = plant.expected_readback(profile.emulator, RATE, v)  # type: ignore[arg-type]
    np.testing.assert_array_equal(u, exp_u.astype(np.float32))
    np.testing.assert_array_equal(va, exp_v.astype(np.float32))


def test_state_persists_across_runs(profile: Profile) -> None:
    cfg = profile.emulator
    assert cfg is not None
    emu = em.Emulator(profile)
    v = sine(3000)
    run(emu, v, 0.0)
    u2, _ = run(emu, v, 1.0)
    ph = plant.Physics(cfg, RATE)
    _, _, after = ph.respond(v.astype(np.float32).astype(float), ph.initial())  # as on the wire
    held = float(np.float32(v[-1]))
    _, _, after = ph.respond(np.full(7000, held), after)  # idle from 0.3 s to 1.0 s at the output
    exp, _ = plant.expected_readback(cfg, RATE, v, run_index=1, state=after)
    np.testing.assert_array_equal(u2, exp.astype(np.float32))
    first, _ = plant.expected_readback(cfg, RATE, v)
    assert np.max(np.abs(u2 - first)) > 0.1  # hysteresis memory: not a fresh start


def test_refusals_apply_nothing(profile: Profile) -> None:
    emu = em.Emulator(profile)
    with pytest.raises(em.DeviceError) as info:
        emu.set_voltage(-151.0, 0.0)
    assert info.value.code == 3 and emu.last_error == 3
    with pytest.raises(em.DeviceError) as info:
        emu.set_voltage(5.5, 0.0)  # one sample may move 50 V/ms / 10 kHz = 5 V
    assert info.value.code == 4
    emu.set_voltage(5.0, 0.0)
    emu.set_table_length(3, 0.0)
    with pytest.raises(em.DeviceError) as info:
        emu.write_table(0, np.array([0.0, np.nan, 0.0]), 0.0)
    assert info.value.code == 3 and not emu.written[:3].any()
    with pytest.raises(em.DeviceError) as info:
        emu.start(1, 0.0)
    assert info.value.code == 9
    emu.write_table(0, np.array([5.0, 9.0, 13.0]), 0.0)
    with pytest.raises(em.DeviceError) as info:
        emu.start(2, 0.0)  # the wrap 13 V -> 5 V breaks the slew limit
    assert info.value.code == 4
    emu.start(1, 0.0)
    with pytest.raises(em.DeviceError) as info:
        emu.set_voltage(1.0, 0.0)
    assert info.value.code == 5
    log = emu.applied_log(1.0)
    np.testing.assert_array_equal(log, [5.0, 5.0, 9.0, 13.0])
    assert emu.pop_error(1.0) == 5 and emu.pop_error(1.0) == 0


def test_every_applied_sample_is_within_limits(profile: Profile) -> None:
    emu = em.Emulator(profile)
    lim = profile.limits
    run(emu, sine(2000, 140.0, 50.0), 0.0)  # ~44 V/ms peak
    emu.safe_state(1.0)
    for v in (3.0, 8.0, 160.0, 12.0, -4.0):
        try:
            emu.set_voltage(v, 2.0)
        except em.DeviceError:
            pass
    emu.safe_state(3.0)
    log = emu.applied_log(3.0)
    seq = np.concatenate(([0.0], log))
    assert log.min() >= lim.v_min and log.max() <= lim.v_max
    assert np.max(np.abs(np.diff(seq))) <= lim.max_step_v(RATE) * (1 + 1e-6)
    assert log[-1] == 0.0


def test_stop_keeps_what_was_applied(profile: Profile) -> None:
    """docs/reference/protocol.md §2.2(b), (e): stopped at 0.25 s, 2500 samples are played and recorded;
    sample 2500, whose hold began at 0.25 s, stays on the output without counting as played."""
    emu = em.Emulator(profile)
    v = sine(10_000)
    emu.set_table_length(v.size, 0.0)
    emu.write_table(0, v, 0.0)
    emu.start(1, 0.0)
    emu.stop(0.25)
    st = emu.status(5.0)
    assert not st.running and st.recorder_fill == 2500 and st.play_position == 2500
    assert emu.applied_log(5.0).size == 2501 and st.output_v == float(np.float32(v[2500]))


def test_watchdog_expires_and_ramps_to_zero(profile: Profile) -> None:
    emu = em.Emulator(profile)
    v = sine(20_000)
    emu.set_watchdog(0.2, 0.0)
    emu.heartbeat(0.0)
    emu.set_table_length(v.size, 0.0)
    emu.write_table(0, v, 0.0)
    emu.start(1, 0.0)
    emu.heartbeat(0.1)
    st = emu.status(1.0)  # heartbeats stopped at 0.1 s: expires at 0.3 s
    assert st.watchdog_expired and not st.running and st.last_error == 8
    assert st.recorder_fill == 3000 and st.output_v == 0.0
    log = emu.applied_log(1.0)
    assert np.max(np.abs(np.diff(log[2999:]))) <= profile.limits.max_step_v(RATE)


def test_watchdog_needs_a_heartbeat_to_arm(profile: Profile) -> None:
    emu = em.Emulator(profile)
    emu.set_watchdog(0.1, 0.0)
    emu.set_voltage(4.0, 0.0)
    assert not emu.status(10.0).watchdog_expired and emu.output_v == 4.0


def test_read_only_refuses_output_changes(profile: Profile) -> None:
    emu = em.Emulator(profile, read_only=True)
    for call in (lambda: emu.set_voltage(1.0, 0.0), lambda: emu.set_table_length(3, 0.0),
                 lambda: emu.set_sample_rate(5000.0, 0.0)):
        with pytest.raises(em.DeviceError) as info:
            call()
        assert info.value.code == 7
    emu.safe_state(0.0)
    assert emu.applied_log(0.0).size == 0 and emu.status(0.0).read_only


def test_effects_off_by_default(profile: Profile) -> None:
    assert profile.emulator is not None and profile.emulator.effects == Effects()
    assert profile.emulator.model.polarization.thermal is None


def test_sensor_delay_is_pure_latency(profile: Profile) -> None:
    v = sine(1000)
    base, _ = run(em.Emulator(quiet(profile)), v, 0.0)
    late, _ = run(em.Emulator(quiet(profile, sensor_delay_samples=3)), v, 0.0)
    np.testing.assert_array_equal(late[3:], base[:-3])


def test_sensor_nonlinearity_is_quadratic(profile: Profile) -> None:
    v = sine(1000)
    base, _ = run(em.Emulator(quiet(profile)), v, 0.0)
    bent, _ = run(em.Emulator(quiet(profile, sensor_quadratic_per_um=1e-3)), v, 0.0)
    b32 = base.astype(np.float32).astype(float)
    np.testing.assert_allclose(bent, b32 + 1e-3 * b32**2, rtol=1e-6, atol=1e-6)


def test_amplifier_lag_and_gain_drift_act_on_the_applied_voltage(profile: Profile) -> None:
    v = sine(1000)
    _, lag = run(em.Emulator(quiet(profile, amplifier_bandwidth_hz=200.0)), v, 0.0)
    assert 0 < np.max(np.abs(lag - v)) < 10 and np.max(lag) < np.max(v)
    emu = em.Emulator(quiet(profile, voltage_gain_sigma=0.05))
    _, va0 = run(emu, v, 0.0)
    emu.safe_state(1.0)
    _, va1 = run(emu, v, 2.0)
    g0, g1 = va0[250] / v[250], va1[250] / v[250]
    assert abs(g0 - 1) > 1e-4 and abs(g0 - g1) > 1e-4  # a different gain error each run


def test_second_mode_adds_a_ringing_displacement(profile: Profile) -> None:
    v = np.concatenate((np.linspace(0, 4.5, 10), np.full(990, 4.5)))
    base, _ = run(em.Emulator(quiet(profile)), v, 0.0)
    mode = SecondMode(frequency_hz=800.0, damping_ratio=0.02, gain=0.1)
    ring, _ = run(em.Emulator(quiet(profile, second_mode=mode)), v, 0.0)
    extra = ring - base
    assert np.ptp(extra[100:]) > 1e-3
    assert extra[-1] == pytest.approx(0.1 * base[-1], rel=0.05)


def test_thermal_relaxation_creeps_at_constant_voltage(profile: Profile) -> None:
    assert profile.emulator is not None
    model = profile.emulator.model
    pol = replace(model.polarization, thermal=hy.Thermal(0.05, 1000.0), n_coercive=32,
                  n_interaction=16)
    hot = replace(profile, emulator=replace(profile.emulator, noise_um=0.0,
                                            model=replace(model, polarization=pol)))
    v = np.concatenate((np.linspace(0, 100, 400), np.full(1600, 100.0)))
    u, _ = run(em.Emulator(hot), v, 0.0)
    assert u[-1] - u[600] > 1e-3  # still moving long after the rod has settled


def small(profile: Profile) -> Profile:
    assert profile.emulator is not None
    return replace(profile, emulator=replace(profile.emulator, table_capacity=1000,
                                             recorder_capacity=1500))


def test_stream_equals_one_long_run_and_recorder_is_a_ring(profile: Profile) -> None:
    emu = em.Emulator(small(profile))
    v = sine(3000).astype(np.float32)
    emu.set_table_length(1000, 0.0)
    emu.write_table(0, v[:1000], 0.0)
    emu.start_stream(3000, 0.0)
    with pytest.raises(em.DeviceError) as info:
        emu.write_table(1000, v[1000:1600], 0.05)  # slots of samples 500..599 not yet played
    assert info.value.code == 6 and emu.pop_error(0.05) == 6
    emu.write_table(1000, v[1000:1500], 0.05)
    emu.write_table(1000, v[1000:1500], 0.06)  # a repeated block is harmless
    emu.write_table(1500, v[1500:2000], 0.1)
    emu.write_table(2000, v[2000:2500], 0.15)
    emu.write_table(2500, v[2500:], 0.2)
    st = emu.status(0.4)
    assert not st.running and st.play_position == 3000 and st.last_error == 0
    assert st.recorder_fill == 1500
    exp_u, _ = plant.expected_readback(profile.emulator, RATE, v)  # type: ignore[arg-type]
    u, _ = emu.read_recorder(0, 3000, 0.4)
    assert np.isnan(u[:1500]).all()  # overwritten in the ring: missing, never wrong
    np.testing.assert_array_equal(u[1500:], exp_u[1500:].astype(np.float32))
    np.testing.assert_array_equal(emu.applied_log(0.4), v)


def test_stream_underrun_stops_and_ramps_to_zero(profile: Profile) -> None:
    emu = em.Emulator(small(profile))
    v = (100.0 * np.ones(3000)).astype(np.float32)
    v[:40] = np.linspace(0, 100, 40)
    emu.set_table_length(1000, 0.0)
    emu.write_table(0, v[:1000], 0.0)
    emu.start_stream(3000, 0.0)
    st = emu.status(0.15)  # sample 1000 was due at 0.1 s and never written
    assert not st.running and st.last_error == 10 and st.play_position == 1000
    assert st.output_v == 0.0
    log = emu.applied_log(0.15)
    np.testing.assert_array_equal(log[:1000], v[:1000])
    assert np.all(np.abs(np.diff(log[999:])) <= profile.limits.max_step_v(RATE))
    with pytest.raises(em.DeviceError):
        emu.write_table(1000, v[1000:1500], 0.2)  # no stream any more: outside the table
    u, _ = emu.read_recorder(999, 2, 0.2)
    assert np.isfinite(u[0]) and np.isnan(u[1])


def _ramp_then_hold(target_v: float) -> tuple[np.ndarray, np.ndarray]:
    """A ramp at the slew limit to ``target_v`` (ends abruptly: the stage rings), then a hold."""
    ramp = np.linspace(0.0, target_v, int(target_v / 4.5) + 1)[1:]  # 4.5 V per 0.1 ms sample
    return ramp, np.full(2000, target_v)


@pytest.mark.parametrize("effects", [{"second_mode": SecondMode(600.0, 0.02, 0.4)}, {}],
                         ids=["second-mode", "rod"])
def test_idle_time_lets_the_stage_settle_between_runs(profile: Profile,
                                                      effects: dict[str, object]) -> None:
    """A run that starts after an idle pause sees the plant as it evolved while holding the output
    (exactly a continuous hold, by the same model), not frozen at the end of the last run."""
    prof = quiet(profile, **effects)
    cfg = prof.emulator
    assert cfg is not None
    ramp, hold = _ramp_then_hold(90.0)
    emu_now, emu_later = em.Emulator(prof), em.Emulator(prof)
    run(emu_now, ramp, 0.0)
    run(emu_later, ramp, 0.0)
    end = ramp.size / RATE
    back_to_back, _ = run(emu_now, hold, end)
    idle_s = 0.5
    settled, _ = run(emu_later, hold, end + idle_s)
    ph = plant.Physics(cfg, RATE)
    _, _, state = ph.respond(np.concatenate([ramp, np.full(round(idle_s * RATE), 90.0)]),
                             ph.initial())
    exp, _ = plant.expected_readback(cfg, RATE, hold, run_index=1, state=state)
    np.testing.assert_allclose(settled, exp, rtol=0, atol=1e-5)  # float32 recorder
    ringing = np.ptp(back_to_back[:500])
    assert ringing > 0.5  # the abrupt end rings at constant voltage ...
    assert np.ptp(settled[:500]) < 0.02 * ringing  # ... and has decayed after the pause


def test_thermal_relaxation_goes_on_while_idle(profile: Profile) -> None:
    prof = quiet(profile)
    cfg = prof.emulator
    assert cfg is not None
    pol = replace(cfg.model.polarization, n_coercive=48, n_interaction=16,
                  thermal=hy.Thermal(0.05, 30.0))
    cfg = replace(cfg, model=replace(cfg.model, polarization=pol))
    prof = replace(prof, emulator=cfg)
    ramp, hold = _ramp_then_hold(90.0)
    emu = em.Emulator(prof)
    run(emu, ramp, 0.0)
    u, _ = run(emu, hold[:200], ramp.size / RATE + 0.8)
    ph = plant.Physics(cfg, RATE)
    _, _, state = ph.respond(np.concatenate([ramp, np.full(8000, 90.0)]), ph.initial())
    exp, _ = plant.expected_readback(cfg, RATE, hold[:200], run_index=1, state=state)
    np.testing.assert_allclose(u, exp, rtol=0, atol=1e-5)
    _, _, frozen = ph.respond(ramp, ph.initial())
    stale, _ = plant.expected_readback(cfg, RATE, hold[:200], run_index=1, state=frozen)
    assert abs(stale[0] - u[0]) > 0.05  # 0.8 s of creep the frozen stage would have missed, um


def test_a_long_pause_is_simulated_up_to_the_horizon(profile: Profile) -> None:
    """Idle beyond :data:`IDLE_HORIZON_S` costs no more than the horizon (the hold has settled)."""
    prof = quiet(profile, second_mode=SecondMode(600.0, 0.02, 0.4))
    ramp, hold = _ramp_then_hold(90.0)
    runs = []
    for pause_s in (em.IDLE_HORIZON_S, 50.0):
        emu = em.Emulator(prof)
        run(emu, ramp, 0.0)
        runs.append(run(emu, hold[:100], ramp.size / RATE + pause_s)[0])
    np.testing.assert_array_equal(runs[0], runs[1])
