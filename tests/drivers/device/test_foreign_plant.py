"""The foreign stage (drivers/device/foreign/) against analytic limits and slow oracles.

A *linear* stage (coercive fields far above any drive field, a2 = 0) has P = P_sw + chi E exactly,
so its displacement is a linear function of the field and the rod, amplifier and second mass can
be checked against closed forms and scipy's exact LTI simulation.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import signal

from afmctl.drivers.device.foreign import kernel as fk
from afmctl.drivers.device.foreign import stage as fp
from afmctl.drivers.device.foreign.effects import (
    CAUSES,
    Amplifier,
    Backlash,
    GainDrift,
    GaugePolynomial,
    GaugeSaturation,
    Interference,
    SecondMass,
    SensorLatency,
    Thermal,
    mode_frequencies_hz,
    random_effect,
)
from afmctl.drivers.device.foreign.stages import RANGES, random_stage, with_effects
from afmctl.drivers.device.foreign.sweeps import DESIGNS, sweep_set

THICK = 100.0


def linear_stage(resonance_hz=400.0, zeta=0.2, **effects) -> fp.Stage:
    """Coercive fields ~100 MV/m: nothing switches below a few MV/m; a2 = 0."""
    mat = fp.Material(coercive=fp.Coercive("lognormal", 100.0, 0.05),
                      interaction=fp.Interaction("normal", 0.01), remanence_C_m2=0.3,
                      eta_MVm_per_C_m2=10.0, layer_thickness_um=THICK, n_coercive=50)
    m = 0.1
    w = 2 * math.pi * resonance_hz
    rod = fp.Rod(mass_kg=m, damping_N_s_per_m=2 * zeta * m * w, stiffness_N_per_m=m * w * w,
                 a1_N_per_C_m2=50.0)
    return fp.Stage(mat, rod, fp.Sensor(noise_um=0.01), (0.0, 150.0), tuple(effects.values()))


def um_per_volt(stage: fp.Stage) -> float:
    """Static gain of the linear stage: a1 P_R chi / (d k) * 1e6, um/V."""
    mat, rod = stage.material, stage.rod
    return 1e6 * rod.a1_N_per_C_m2 * mat.remanence_C_m2 * mat.chi_per_MVm / (
        mat.layer_thickness_um * rod.stiffness_N_per_m)


@pytest.fixture(scope="module")
def stage():
    return random_stage(np.random.default_rng(11), drive_range_V=(-30.0, 150.0))


# ----------------------------------------------------------------- rod


@pytest.mark.parametrize("zeta", [0.05, 0.3])
def test_rod_step_matches_second_order_closed_form(zeta):
    st = linear_stage(resonance_hz=300.0, zeta=zeta)
    state = fp.initial_state(st, 0.0)
    rate, v = 20_000.0, 10.0
    true_um, _, _ = fp.run(st, np.full(2000, v), rate, state, None)
    wn = 2 * math.pi * 300.0
    wd = wn * math.sqrt(1 - zeta ** 2)
    t = np.arange(2000) / rate
    step = 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta ** 2)
                                         * np.sin(wd * t))
    expect = true_um[0] + um_per_volt(st) * v * step
    assert np.max(np.abs(true_um - expect)) < 1e-4 * um_per_volt(st) * v
    # and the overshoot is the textbook exp(-pi zeta / sqrt(1 - zeta^2))
    over = (true_um.max() - true_um[-1]) / (true_um[-1] - true_um[0])
    assert over == pytest.approx(math.exp(-math.pi * zeta / math.sqrt(1 - zeta ** 2)), rel=2e-3)


def test_rod_static_gain_and_causal_sampling():
    st = linear_stage()
    v = np.concatenate([np.zeros(5), np.full(4000, 40.0)])
    true_um, _, _ = fp.run(st, v, 10_000.0, fp.initial_state(st, 0.0), None)
    assert true_um[5] == true_um[0]  # the sample at the step's instant has not moved yet
    assert true_um[-1] - true_um[0] == pytest.approx(40.0 * um_per_volt(st), rel=1e-6)


# ----------------------------------------------------------------- material


def _loop(ec, vc, interaction, fields, b0):
    b = np.full(ec.size, b0)
    out = []
    for e in fields:
        fk.relay_update(b, ec, e)
        out.append(fk.relay_polarization(b, vc, interaction.code, interaction.std_MVm))
    return np.array(out)


def test_major_loop_symmetric_and_saturating(stage):
    mat = stage.material
    ec, vc = fp.coercive_nodes(mat.coercive, mat.n_coercive)
    top = 50 * mat.coercive.median_MVm + 10 * mat.interaction.std_MVm
    down = np.linspace(top, -top, 4001)
    p_down = _loop(ec, vc, mat.interaction, down, -fk.BIG)
    p_up = _loop(ec, vc, mat.interaction, -down, fk.BIG)
    assert p_down[0] == pytest.approx(1.0, abs=1e-9) and p_down[-1] == pytest.approx(-1.0, abs=1e-9)
    np.testing.assert_allclose(p_up, -p_down, atol=1e-12)  # P_up(E) = -P_down(-E)
    assert np.all(np.diff(p_down) <= 1e-15)  # monotone branches
    assert np.ptp(p_down[1000:3000]) > 0.5  # and it does switch in between


def test_closed_form_interaction_matches_explicit_relays(stage):
    """Slow oracle: every (E_c, E_I) relay (4) on a fine E_I grid, switched explicitly."""
    mat = stage.material
    ec, vc = fp.coercive_nodes(mat.coercive, 60)
    s = mat.interaction.std_MVm
    ei = (np.arange(3000) + 0.5) / 3000 * 14 * s - 7 * s
    wi = np.exp(-0.5 * (ei / s) ** 2)
    wi /= wi.sum()
    up = np.ones((ec.size, ei.size), dtype=bool)  # poled +
    e_max = 150.0 / mat.layer_thickness_um
    fields = np.concatenate([np.linspace(0, e_max, 80), np.linspace(e_max, -0.3 * e_max, 120),
                             np.linspace(-0.3 * e_max, 0.6 * e_max, 90)])
    oracle = []
    for e in fields:
        eff = e + ei[None, :]
        up = np.where(eff >= ec[:, None], True, np.where(eff <= -ec[:, None], False, up))
        oracle.append(vc @ (2.0 * up - 1.0) @ wi)
    fast = _loop(ec, vc, mat.interaction, fields, -fk.BIG)
    assert np.max(np.abs(fast - np.array(oracle))) < 2e-3


def test_wiping_out_and_return_point_memory(stage):
    """A minor loop inside (a, b) that returns to b leaves no trace (Preisach memory)."""
    rate = 2000.0
    ramp = lambda a, b: np.linspace(a, b, int(abs(b - a) * 4) + 2)[1:]  # noqa: E731
    base = np.concatenate([ramp(0, 150), ramp(150, 20), ramp(20, 110)])
    minor = np.concatenate([ramp(110, 60), ramp(60, 100), ramp(100, 70), ramp(70, 110)])
    after = np.concatenate([ramp(110, 135), ramp(135, 10)])
    s0 = fp.initial_state(stage, "poled+")
    _, _, sa = fp.run(stage, base, rate, s0, None)
    _, _, sb = fp.run(stage, minor, rate, sa, None)
    np.testing.assert_array_equal(sb.boundary, sa.boundary)
    # wiping out: going past the old maximum erases the memory of everything below it
    ta, _, _ = fp.run(stage, after, rate, fp.idle(stage, sa, 1.0, 110.0), None)
    tb, _, _ = fp.run(stage, after, rate, fp.idle(stage, sb, 1.0, 110.0), None)
    np.testing.assert_allclose(ta, tb, atol=1e-9)


def test_other_density_families_run_and_differ():
    rng = np.random.default_rng(3)
    outs = []
    for cfam, ifam in [("lognormal", "normal"), ("gamma", "logistic"), ("loglogistic", "laplace")]:
        st = random_stage(np.random.default_rng(3), coercive_family=cfam, interaction_family=ifam)
        ec, vc = fp.coercive_nodes(st.material.coercive, 400)
        assert vc.sum() == pytest.approx(1.0)
        assert np.sum(vc * ec) == pytest.approx(st.material.coercive.distribution().mean(),
                                                rel=1e-3)
        v = np.concatenate([np.linspace(0, 150, 600), np.linspace(150, 0, 600)])
        t, _, _ = fp.run(st, v, 1000.0, fp.initial_state(st), rng)
        outs.append(t)
    assert np.ptp(outs[0] - outs[1]) > 0.1 and np.ptp(outs[0] - outs[2]) > 0.1


# ----------------------------------------------------------------- state handling


def test_chunked_run_equals_one_run(stage):
    rng = np.random.default_rng(0)
    st = with_effects(stage, *(random_effect(c, rng, stage, 0.7) for c in
                               ("amplifier-lag", "sensor-delay", "second-mode", "backlash",
                                "sensor-nonlinearity", "interference")))
    v = sweep_set("standard", 0, 150, rng)[2].voltage_V[:3000]
    s0 = fp.initial_state(st, 40.0)
    t1, r1, e1 = fp.run(st, v, 10_000.0, s0, np.random.default_rng(5))
    rng2 = np.random.default_rng(5)
    ta, ra, sa = fp.run(st, v[:1234], 10_000.0, s0, rng2)
    tb, rb, eb = fp.run(st, v[1234:], 10_000.0, sa, rng2)
    np.testing.assert_allclose(np.concatenate([ta, tb]), t1, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.concatenate([ra, rb]), r1, rtol=0, atol=1e-9)
    assert eb.time_s == pytest.approx(e1.time_s)


def test_idle_decays_ringing_and_holds():
    st = linear_stage(resonance_hz=200.0, zeta=0.05)
    _, _, s = fp.run(st, np.full(20, 100.0), 10_000.0, fp.initial_state(st, 0.0), None)
    assert abs(s.rod[1]) > 1.0  # ringing (um/s)
    s = fp.idle(st, s, 2.0, 100.0)
    true_um, _, _ = fp.run(st, np.full(500, 100.0), 10_000.0, s, None)
    assert np.ptp(true_um) < 1e-9
    assert s.time_s == pytest.approx(20 / 10_000.0 + 2.0)


def test_start_states(stage):
    pos = fp.initial_state(stage, "poled+")
    neg = fp.initial_state(stage, "poled-")
    dep = fp.initial_state(stage, "depoled")
    force = lambda s: s.scalars[fk.S_F]  # noqa: E731
    assert force(pos) > force(dep) > force(neg) or force(pos) < force(dep) < force(neg)
    _, vc = fp.coercive_nodes(stage.material.coercive, stage.material.n_coercive)
    assert fk.relay_polarization(dep.boundary, vc, 0, 1.0) == 0.0
    # left at a voltage after poling: the same as driving there from poled+ at 0 V
    left = fp.initial_state(stage, (150.0, 30.0))
    _, _, driven = fp.run(stage, np.concatenate([np.linspace(0, 150, 300),
                                                 np.linspace(150, 30, 300)]), 1000.0, pos, None)
    np.testing.assert_allclose(left.boundary, driven.boundary, atol=1e-12)
    with pytest.raises(ValueError):
        fp.initial_state(stage, "sideways")


# ----------------------------------------------------------------- thermal kernel


def test_mills_table_matches_the_normal_hazard():
    """The tabulated phi/Phi of the thermal rates (8) against scipy's log-CDF, every regime."""
    from scipy import special

    z = np.concatenate([np.linspace(-45, 45, 90001), np.linspace(-30.01, -29.99, 41),
                        np.linspace(5.99, 6.01, 41)])
    exact = np.exp(-0.5 * z * z - special.log_ndtr(z)) / math.sqrt(2 * math.pi)
    got = np.array([fk.mills(v) for v in z])
    rel = np.abs(got - exact) / np.maximum(exact, 1e-300)
    assert rel[z < 0].max() < 3e-6  # -z - 1/z below -30: 2/z^4
    assert rel[(z > -30) & (z < 0)].max() < 1e-12
    assert rel[(z >= 0) & (exact > 1e-290)].max() < 2e-9  # Phi(z) taken as 1 past z = 6


def test_thermal_zero_temperature_limit_is_the_relay():
    """E_T -> 0 (any attempt rate): x_+ jumps exactly where the relay (4) switches."""
    ec = np.array([0.3, 0.5, 0.8])
    ei = np.array([-0.4, -0.1, 0.0, 0.2, 0.5])
    w = np.full((3, 5), 1 / 15)
    up = ~(ei[None, :] <= -ec[:, None])  # poled +, at 0 MV/m
    x = up.astype(float)
    fields = np.concatenate([np.linspace(0, -1.2, 50), np.linspace(-1.2, 0.695, 70)])  # no ties
    acc = np.array([fk.thermal_total(x, w)])
    prev = 0.0
    for e in fields:
        p = fk.thermal_update(x, ec, ei, w, e, prev, 1e-3, 1e-6, 1e4, 0.0, acc)
        prev = e
        eff = e + ei[None, :]
        up = np.where(eff >= ec[:, None], True, np.where(eff <= -ec[:, None], False, up))
        np.testing.assert_allclose(x, up.astype(float), atol=1e-12)
        assert p == pytest.approx(np.sum(w * (2.0 * up - 1.0)), abs=1e-12)


def test_thermal_creep_monotone_and_toward_field():
    ec = np.linspace(0.2, 1.0, 9)
    ei = np.linspace(-0.5, 0.5, 11)
    w = np.full((9, 11), 1 / 99)
    x = np.zeros((9, 11))  # poled -
    acc = np.array([fk.thermal_total(x, w)])
    prev = 0.0
    for e in np.linspace(0, 0.6, 60):  # up to a field that switches some, then hold
        fk.thermal_update(x, ec, ei, w, e, prev, 1e-3, 0.03, 1e4, 0.1, acc)
        prev = e
    ps = [fk.thermal_update(x, ec, ei, w, 0.6, 0.6, 1e-3, 0.03, 1e4, 0.1, acc)
          for _ in range(200)]
    assert acc[0] == pytest.approx(fk.thermal_total(x, w), abs=1e-12)
    assert np.all(np.diff(ps) > 0)  # creeps up at constant field, never back
    assert ps[-1] - ps[0] > 1e-4


def test_thermal_stage_creeps_in_idle(stage):
    st = with_effects(stage, Thermal(0.05 * stage.material.coercive.median_MVm, 1e4))
    v = np.linspace(0, 150, 3000)
    _, _, s = fp.run(st, v, 2000.0, fp.initial_state(st), None)
    pos = []
    for _ in range(6):
        s = fp.idle(st, s, 0.5, 150.0)
        pos.append(fp.run(st, np.full(1, 150.0), 2000.0, s, None)[0][0])
    d = np.diff(pos)
    assert np.all(d * np.sign(d[0]) > 0) and abs(pos[-1] - pos[0]) > 0.01


# ----------------------------------------------------------------- hidden effects


def test_effects_at_zero_strength_parameters_change_nothing(stage):
    v = sweep_set("standard", 0, 150, np.random.default_rng(1))[1].voltage_V
    s0 = fp.initial_state(stage)
    plain_t, plain_r, _ = fp.run(stage, v, 5000.0, s0, None)
    null = [GaugePolynomial(50.0, 40.0, 0.0, 0.0), Backlash(0.0), GainDrift(0.0, 0.0),
            Interference(50.0, (0.0,), (0.3,)), SensorLatency(0.0, 0.0),
            GaugeSaturation(50.0, 1e6, 1.0)]
    for eff in null:
        st = with_effects(stage, eff)
        s = fp.start_run(st, fp.initial_state(st), np.random.default_rng(0))
        t, r, _ = fp.run(st, v, 5000.0, s, None)
        np.testing.assert_allclose(t, plain_t, atol=1e-9, err_msg=repr(eff))
        np.testing.assert_allclose(r, plain_r, atol=1e-9, err_msg=repr(eff))


def test_dynamic_effects_vanish_in_their_limits(stage):
    """A very fast amplifier, a very light and stiff platform, a very cold material.

    The amplifier is critically damped: an underdamped one overshoots every held step, and the
    material remembers the overshoot at each turning point (real physics, no limit)."""
    v = sweep_set("standard", 0, 150, np.random.default_rng(1))[1].voltage_V
    plain = fp.run(stage, v, 5000.0, fp.initial_state(stage), None)[0]
    span = np.ptp(plain)
    limits = [(Amplifier(2e5, 1.0, 1e9), 1e-4), (SecondMass(1e-4, 30.0, 0.5), 1e-4),
              (Thermal(1e-4 * stage.material.coercive.median_MVm, 1e6), 2e-3)]
    for eff, tol in limits:
        st = with_effects(stage, eff)
        t = fp.run(st, v, 5000.0, fp.initial_state(st), None)[0]
        assert np.max(np.abs(t - plain)) < tol * span, eff


def test_gauge_polynomial_matches_its_formula(stage):
    eff = GaugePolynomial(center_um=sum(stage.static_range_um) / 2, half_range_um=30.0,
                          quadratic=0.01, cubic=-0.02)
    st = with_effects(stage, eff)
    v = np.linspace(0, 150, 2000)
    t, r, _ = fp.run(st, v, 1000.0, fp.initial_state(st), None)
    y = (t + stage.sensor.zero_um - eff.center_um) / eff.half_range_um
    expect = t + eff.half_range_um * (eff.quadratic * y ** 2 + eff.cubic * y ** 3)
    np.testing.assert_allclose(r - stage.sensor.offset_um, expect, atol=1e-9)
    assert np.ptp(r - t) > 0.1


def test_gauge_saturation_compresses_only_past_the_knee(stage):
    lo, hi = stage.static_range_um
    eff = GaugeSaturation(center_um=(lo + hi) / 2, knee_um=0.3 * (hi - lo), softness_um=2.0)
    st = with_effects(stage, eff)
    t, r, _ = fp.run(st, np.linspace(0, 150, 2000), 1000.0, fp.initial_state(st), None)
    d = t + stage.sensor.zero_um - eff.center_um
    inside = np.abs(d) < eff.knee_um
    err = r - stage.sensor.offset_um - t
    assert np.max(np.abs(err[inside])) < 1e-9
    assert np.all(np.abs(err[~inside]) <= np.abs(d[~inside]) - eff.knee_um + 1e-12)
    assert np.max(np.abs(err)) > 1.0


def test_delay_shifts_the_reading_by_the_set_time(stage):
    """Oracle: the plain stage driven by the same held voltage at 100x the rate, where the
    delay (3.37 samples) is a whole number (337) of fine samples."""
    rate = 1000.0
    v = 75 - 75 * np.cos(2 * math.pi * 0.5 * np.arange(1500) / rate)
    fine = fp.run(stage, np.repeat(v, 100), 100 * rate, fp.initial_state(stage), None)[1]
    st = with_effects(stage, SensorLatency(3.37 / rate, 0.0))
    late = fp.run(st, v, rate, fp.initial_state(st), None)[1]
    expect = np.concatenate([np.full(337, fine[0]), fine])[::100][:1500]
    assert np.max(np.abs(late - expect)) < 1e-4
    assert np.max(np.abs(late - fine[::100])) > 0.1  # and the shift is not nothing


def test_antialias_filter_is_second_order_butterworth():
    st = linear_stage(resonance_hz=2000.0, zeta=0.7)
    f_aa = 300.0
    rate = 20_000.0
    late = with_effects(st, SensorLatency(0.0, f_aa))
    v = np.full(4000, 50.0)
    t_true, r, _ = fp.run(late, v, rate, fp.initial_state(late, 0.0), None)
    b, a = signal.butter(2, 2 * math.pi * f_aa, analog=True)
    _, y, _ = signal.lsim((b, a), t_true - t_true[0], np.arange(4000) / rate)
    np.testing.assert_allclose(r - st.sensor.offset_um - t_true[0], y, atol=2e-3 * np.ptp(y))


def test_amplifier_slew_limit_and_low_pass():
    st = linear_stage(resonance_hz=1000.0, zeta=0.7)
    g = um_per_volt(st)
    rate = 20_000.0
    slow = with_effects(st, Amplifier(bandwidth_hz=20.0, damping=0.6, slew_V_per_s=1e7))
    t_amp, _, _ = fp.run(slow, np.full(2000, 1.0), rate, fp.initial_state(slow, 0.0), None)
    wa, wr = 2 * math.pi * 20.0, 2 * math.pi * 1000.0
    amp_and_rod = signal.lti([wa ** 2 * wr ** 2], np.polymul([1, 2 * 0.6 * wa, wa ** 2],
                                                            [1, 2 * 0.7 * wr, wr ** 2]))
    _, y = signal.step(amp_and_rod, T=np.arange(2000) / rate)
    np.testing.assert_allclose((t_amp - t_amp[0]) / g, y, atol=1e-4)
    limited = with_effects(st, Amplifier(bandwidth_hz=2000.0, damping=0.7, slew_V_per_s=2000.0))
    t_lim, _, _ = fp.run(limited, np.full(2000, 100.0), rate, fp.initial_state(limited, 0.0),
                         None)
    mid = slice(400, 800)  # well inside the 50 ms ramp
    slope = np.polyfit(np.arange(2000)[mid] / rate, t_lim[mid], 1)[0]
    assert slope == pytest.approx(2000.0 * g, rel=0.01)


def test_second_mass_matches_lti_simulation():
    st = linear_stage(resonance_hz=300.0, zeta=0.1)
    mode = SecondMass(mass_ratio=0.2, frequency_ratio=2.5, damping=0.03)
    two = with_effects(st, mode)
    rate = 40_000.0
    t2, _, _ = fp.run(two, np.full(4000, 10.0), rate, fp.initial_state(two, 0.0), None)
    m1, c1, k1 = st.rod.mass_kg, st.rod.damping_N_s_per_m, st.rod.stiffness_N_per_m
    m2 = 0.2 * m1
    w2 = 2 * math.pi * 2.5 * 300.0
    k2, c2 = m2 * w2 ** 2, 2 * 0.03 * m2 * w2
    a = np.array([[0, 1, 0, 0], [-(k1 + k2) / m1, -(c1 + c2) / m1, k2 / m1, c2 / m1],
                  [0, 0, 0, 1], [k2 / m2, c2 / m2, -k2 / m2, -c2 / m2]])
    sys = signal.StateSpace(a, [[0], [1 / m1], [0], [0]], [[1, 0, 0, 0]], [[0]])  # rod end
    df = 10.0 * um_per_volt(st) * k1  # force step, um N/m
    _, y, _ = signal.lsim(sys, np.full(4000, df), np.arange(4000) / rate)
    np.testing.assert_allclose(t2 - t2[0], y, atol=1e-4 * np.ptp(y))
    lo, hi = mode_frequencies_hz(two, mode)
    assert lo < 300.0 < 2.5 * 300.0 < hi


def test_gain_drift_per_run():
    st = linear_stage()
    drift = GainDrift(sigma=0.02, per_run=0.01)
    two = with_effects(st, drift)
    rng = np.random.default_rng(9)
    s = fp.initial_state(two, 0.0)
    gains = []
    for n in range(1, 401):
        s = fp.start_run(two, s, rng)
        gains.append(s.gain / (1 + 0.01 * n) - 1)
    assert np.std(gains) == pytest.approx(0.02, rel=0.15) and abs(np.mean(gains)) < 0.005
    s = replace(s, gain=1.1)
    t, _, _ = fp.run(two, np.full(3000, 50.0), 10_000.0, s, None)
    assert t[-1] - t[0] == pytest.approx(1.1 * 50.0 * um_per_volt(st), rel=1e-4)
    creeping = with_effects(st, GainDrift(0.0, 0.0, per_second=0.01))
    s = fp.idle(creeping, fp.initial_state(creeping, 0.0), 10.0, 0.0)
    t, _, _ = fp.run(creeping, np.full(3000, 50.0), 10_000.0, s, None)
    assert t[-1] - t[0] == pytest.approx(50.0 * um_per_volt(st) * (1 + 0.01 * 10.3), rel=1e-3)


def test_backlash_is_a_dead_band():
    st = linear_stage(resonance_hz=800.0, zeta=0.7)
    gap = 0.4
    play = with_effects(st, Backlash(gap))
    v = np.concatenate([np.linspace(0, 100, 4000), np.linspace(100, 0, 4000)])
    plain, _, _ = fp.run(st, v, 1000.0, fp.initial_state(st, 0.0), None)
    t, _, _ = fp.run(play, v, 1000.0, fp.initial_state(play, 0.0), None)
    np.testing.assert_allclose((plain - t)[500:3900], gap / 2, atol=1e-3)
    np.testing.assert_allclose((plain - t)[5000:7900], -gap / 2, atol=1e-3)  # gap taken up
    assert np.ptp(t[4000:4100]) < np.ptp(plain[4000:4100])  # stuck while the play is taken up


def test_interference_is_mains_hum_and_spikes(stage):
    eff = Interference(60.0, (0.2, 0.05), (0.0, 1.0))
    st = with_effects(stage, eff)
    v = np.full(10_000, 20.0)
    s = fp.idle(st, fp.initial_state(st, 20.0), 1.0, 20.0)
    _, r, _ = fp.run(st, v, 5000.0, s, None)
    spec = np.abs(np.fft.rfft(r - r.mean())) * 2 / r.size
    f = np.fft.rfftfreq(r.size, 1 / 5000.0)
    assert spec[np.argmin(abs(f - 60))] == pytest.approx(0.2, rel=1e-3)
    assert spec[np.argmin(abs(f - 120))] == pytest.approx(0.05, rel=1e-3)
    spiky = with_effects(stage, Interference(50.0, (0.0,), (0.0,), spike_um=1.0,
                                             spike_period_s=0.1, spike_decay_s=1e-3,
                                             spike_phase_s=1e-4))
    _, r2, _ = fp.run(spiky, v, 5000.0, s, None)
    jumps = np.flatnonzero(np.diff(r2) > 0.5) + 1
    np.testing.assert_allclose(np.diff(jumps), 500)  # one spike every 0.1 s


def test_noise_std_as_set(stage):
    v = np.full(40_000, 30.0)
    s = fp.idle(stage, fp.initial_state(stage, 30.0), 1.0, 30.0)
    t, r, _ = fp.run(stage, v, 10_000.0, s, np.random.default_rng(4))
    resid = r - t - stage.sensor.offset_um
    assert np.std(resid) == pytest.approx(stage.sensor.noise_um, rel=0.03)
    assert abs(np.mean(resid)) < 4 * stage.sensor.noise_um / math.sqrt(v.size)


@pytest.mark.parametrize("cause", sorted(CAUSES))
def test_every_cause_changes_the_reading_more_when_stronger(stage, cause):
    v = sweep_set("standard", 0, 150, np.random.default_rng(2))[2].voltage_V
    plain = fp.run(stage, v, 10_000.0, fp.initial_state(stage), None)[1]
    change = []
    for strength in (0.0, 1.0):
        eff = random_effect(cause, np.random.default_rng(7), stage, strength)
        st = with_effects(stage, eff)
        s = fp.start_run(st, fp.initial_state(st), np.random.default_rng(8))
        d = fp.run(st, v, 10_000.0, s, None)[1] - plain
        change.append(np.sqrt(np.mean((d - d.mean()) ** 2)))
    assert change[1] > 2 * change[0] > 0


# ----------------------------------------------------------------- generator and sweeps


def test_random_stages_cover_the_stated_ranges():
    rng = np.random.default_rng(21)
    stages = [random_stage(rng) for _ in range(12)]
    for st in stages:
        lo, hi = st.static_range_um
        assert 40 - 1e-6 <= hi - lo <= 120 + 1e-6
        assert 100 <= st.rod.resonance_hz <= 1000 and 0.05 <= st.rod.damping_ratio <= 0.5
        assert 0.005 <= st.sensor.noise_um <= 0.05
    a2 = [st.rod.a2_N_per_C2_m4 for st in stages]
    assert min(a2) < 0 < max(a2)
    for name, (lo, hi, kind) in RANGES.items():
        if kind == "log":
            assert hi / lo >= 2.5, name


@pytest.mark.parametrize("design", DESIGNS)
def test_sweep_designs(design):
    rng = np.random.default_rng(4)
    lo = -40.0 if design in ("semi-bipolar", "nested") else 0.0
    plans = sweep_set(design, lo, 150.0 if design != "offset" else 120.0, rng)
    assert len(plans) >= 3
    for p in plans:
        assert 0.1 <= p.frequency_hz <= 30 and 1000 <= p.sample_rate_hz <= 10_000
        assert p.sample_rate_hz / p.frequency_hz >= 300
        assert lo - 1e-9 <= p.voltage_V.min() and p.voltage_V.max() <= 150 + 1e-9
        slope = np.max(np.abs(np.diff(p.voltage_V))) * p.sample_rate_hz
        assert slope <= 2 * np.ptp(p.voltage_V) * p.frequency_hz * 1.001
    if design == "semi-bipolar":
        assert min(p.voltage_V.min() for p in plans) < 0


def test_foreign_sets_writes_sweeps_afmctl_reads(tmp_path):
    from afmctl.files import sweepfile as sw
    from benchmarks import foreign_sets

    out = tmp_path / "sets"
    assert foreign_sets.main(["--out", str(out), "--n", "2", "--seed", "3",
                              "--effect", "sensor-delay", "--design", "semi-bipolar"]) == 0
    for folder in sorted(out.iterdir()):
        truth = json.loads((folder / "truth.json").read_text())
        assert truth["stage"]["effects"][0]["cause"] == "sensor-delay"
        files = sorted(folder.glob("sweep_*.csv"))
        assert len(files) == len(truth["sweeps"]) == 3
        for f, rec in zip(files, truth["sweeps"], strict=True):
            s = sw.read(f)
            assert 1 / s.dt == pytest.approx(rec["sample_rate_hz"])
            assert s.thickness_um == pytest.approx(truth["stage"]["material"]
                                                   ["layer_thickness_um"], rel=1e-5)
            assert s.time_s.size == rec["samples"] and rec["effect_rms_um"] > 0
