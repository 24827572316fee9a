"""Algorithms 2 and 3 round trips, against their literal fixed-step forms, and the linear filter."""

from __future__ import annotations

import dataclasses as dc

import numpy as np
import pytest
from scipy.signal import sawtooth

from afmctl.model import hysteresis as hy
from afmctl.model import inverse as inv
from afmctl.model import rod as rd
from afmctl.model import transducer as tr

DT = 1e-4


def figure5_input(n: int = 3000) -> np.ndarray:
    """Symmetric and biased minor loops in P (C/m^2), like the paper's Fig. 5(c)."""
    t = np.linspace(0, 1, n)
    return 0.55 * np.sin(2 * np.pi * 2 * t) * np.exp(-1.2 * t) + 0.12 * np.sin(2 * np.pi * 11 * t)


@pytest.mark.parametrize("kernel", ["auto", "grid"])
def test_algorithm2_round_trip_error_is_bounded_by_the_step(nominal: tr.Transducer,
                                                            kernel: str) -> None:
    pol = dc.replace(nominal.polarization, kernel=kernel)
    p_in = figure5_input()
    tol = 1e-9
    res = inv.algorithm2(pol, p_in, hy.initial_state(pol), tol=tol)
    p_out, _ = hy.run(pol, res.field_mv_m, hy.initial_state(pol))
    k = hy.build_kernel(pol)
    # the grid's P(E) jumps by 2 P_R w_i w_j when a relay switches: no field lands between
    step = tol if kernel == "auto" else 2 * pol.p_r * k.wc.max() * k.wi.max()
    assert np.max(np.abs(p_in - p_out)) <= step
    np.testing.assert_allclose(np.abs(p_in - p_out), res.error, atol=1e-15)
    np.testing.assert_allclose(p_out, res.predicted, atol=1e-15)


def test_algorithm2_fast_agrees_with_the_literal_march(nominal: tr.Transducer) -> None:
    pol = nominal.polarization
    p_in = figure5_input()[:400]
    s0 = hy.initial_state(pol)
    e_fast = inv.algorithm2(pol, p_in, s0).field_mv_m
    e_step = 1e-3
    e_lit = inv.algorithm2_literal(pol, p_in, s0, e_step=e_step)
    p_lit, _ = hy.run(pol, e_lit, s0)
    # linear interpolation over one step of a kinked curve: error well inside one step
    assert np.max(np.abs(e_lit - e_fast)) < e_step
    assert np.max(np.abs(p_lit - p_in)) < e_step * 1.0  # dP <= (dP/dE)_max * E_step


def triangle(freq: float, amp_um: float, periods: float) -> np.ndarray:
    t = np.arange(1, int(round(periods / freq / DT)) + 1) * DT
    return 0.5 * amp_um * sawtooth(2 * np.pi * freq * t + np.pi / 2, 0.5)


@pytest.mark.parametrize("freq", [0.279, 27.9])
def test_algorithm2_round_trip_on_triangles(nominal: tr.Transducer, freq: float) -> None:
    """P triangles over 80 % of the polarization the stage's +-150 V reach, 2 periods at 10 kHz."""
    pol = nominal.polarization
    p_max, _ = hy.saturation(pol, 150.0 / nominal.thickness_um)
    p_in = triangle(freq, 1.6 * p_max, 2)
    res = inv.algorithm2(pol, p_in, hy.initial_state(pol), tol=1e-9)
    p_out, _ = hy.run(pol, res.field_mv_m, hy.initial_state(pol))
    assert np.max(np.abs(p_in - p_out)) <= 1e-9
    assert np.max(np.abs(res.field_mv_m)) < 1.5  # inside the stage's field range


def tracking_error(model: tr.Transducer, ud: np.ndarray, res: inv.Inversion,
                   skip: int) -> np.ndarray:
    cm = tr.compile_model(model, DT)
    u, _, _ = tr.simulate(cm, res.voltage(model.thickness_um), tr.initial(model))
    np.testing.assert_allclose(u, res.predicted, atol=1e-9)  # the inverse's own prediction
    return (u[1:] - ud[:-1])[skip:]


def test_algorithm3_round_trip_at_0_279_hz_is_exact(nominal: tr.Transducer) -> None:
    ud = triangle(0.279, 40.56, 1.5)
    res = inv.algorithm3(tr.compile_model(nominal, DT), ud, tr.initial(nominal), tol_um=1e-7)
    err = tracking_error(nominal, ud, res, 0)
    assert np.max(np.abs(err)) < 1e-6


def test_algorithm3_inverts_a_cubic_force(nominal: tr.Transducer) -> None:
    """With a cubic term of the force (``a3``, not in (16); the Preisach grid's fit has it) the
    round trip at 0.279 Hz is still exact (inside the play's quiet band the closed form solves
    the cubic); and the cubic matters: the same fields on the model without it land most of a
    micrometre away."""
    p_max, _ = hy.saturation(nominal.polarization, 150.0 / nominal.thickness_um)
    a3 = 0.5 * nominal.rod.a1 / (3 * p_max ** 2)  # the slope a1 + 3 a3 P^2 up to 1.5 a1
    cubic = dc.replace(nominal, rod=dc.replace(nominal.rod, a3=a3))
    ud = triangle(0.279, 40.56, 1.5)
    res = inv.algorithm3(tr.compile_model(cubic, DT), ud, tr.initial(cubic), tol_um=1e-7)
    assert np.max(np.abs(tracking_error(cubic, ud, res, 0))) < 1e-6
    u, _, _ = tr.simulate(tr.compile_model(nominal, DT), res.voltage(nominal.thickness_um),
                          tr.initial(nominal))
    assert np.max(np.abs(u[1:] - ud[:-1])) > 0.5


def test_algorithm3_at_27_9_hz_with_smooth_horizon(nominal: tr.Transducer) -> None:
    cm = tr.compile_model(nominal, DT)
    d = rd.smooth_horizon(cm.disc)
    ud = triangle(27.9, 27.04, 4)
    res = inv.algorithm3(cm, ud, tr.initial(nominal), horizon=d, e_max=1.5)
    period = int(1 / 27.9 / DT)
    err = tracking_error(nominal, ud, res, period)
    assert np.sqrt(np.mean(err**2)) / 27.04 < 0.005  # < 0.5 % of amplitude
    v = res.voltage(nominal.thickness_um)[period:]
    # no chatter: the field does not alternate sign of its increments sample after sample
    flips = np.mean(np.diff(np.sign(np.diff(v))) != 0)
    assert flips < 0.2


def test_literal_one_step_algorithm3_chatters_at_27_9_hz(nominal: tr.Transducer) -> None:
    """The failure the horizon fixes: as printed, the inverse alternates between samples."""
    cm = tr.compile_model(nominal, DT)
    ud = triangle(27.9, 27.04, 1.2)
    v = inv.algorithm3(cm, ud, tr.initial(nominal), horizon=1, e_max=1.5).voltage(100.0)
    assert np.mean(np.diff(np.sign(np.diff(v))) != 0) > 0.5


def test_algorithm3_fast_agrees_with_the_literal_algorithm(nominal: tr.Transducer) -> None:
    cm = tr.compile_model(nominal, DT)
    ud = triangle(0.279, 40.56, 0.02)[:300] * 50  # a fast ramp within 300 samples
    s0 = tr.initial(nominal)
    e_fast = inv.algorithm3(cm, ud, s0).field_mv_m
    e_lit = inv.algorithm3_literal(cm, ud, s0, e_step=1e-4)
    np.testing.assert_allclose(e_lit, e_fast, atol=1e-5)


def test_inequalities_19_on_the_ascending_branch(nominal: tr.Transducer) -> None:
    """u_{k+1} >= u~_{k+1} while E rises (c_L) and <= while it falls (c_U)."""
    cm = tr.compile_model(nominal, DT)
    e = 1.2 * np.sin(2 * np.pi * 27.9 * np.arange(2000) * DT)
    disc, rod = cm.disc, nominal.rod
    p, _ = hy.run(cm.kernel, e, hy.initial_state(nominal.polarization), DT)
    f = rod.force(p)
    u, _ = rd.simulate(rod, disc, f)
    x = np.zeros(2)
    for k in range(1, e.size - 1):
        x = disc.phi @ x + disc.gamma * f[k - 1]
        u_true = disc.phi[0] @ x + disc.gamma[0] * f[k]
        u_held = disc.phi[0] @ x + disc.gamma[0] * f[k - 1]
        assert np.sign(e[k] - e[k - 1]) * (u_true - u_held) >= -1e-18


def test_linear_filter_recovers_a_line() -> None:
    v = np.linspace(-100, 100, 50)
    lin = inv.fit_linear(v, 0.3 * v + 2.0)
    assert lin.gain_um_per_v == pytest.approx(0.3)
    np.testing.assert_allclose(lin.voltage(0.3 * v + 2.0), v, atol=1e-10)


@pytest.mark.parametrize("creeps", [None, "polarization", "force"])
def test_algorithm3_keeps_the_state_simulate_reaches(nominal: tr.Transducer,
                                                     creeps: str | None) -> None:
    """``keep``: the model state after the first fields is the one the forward model reaches on
    their voltages (what the planner goes on from), up to round-off: hysteresis memory, rod and
    creep (on the polarization or on the force)."""
    from afmctl.model import creep as cr

    model = (dc.replace(nominal, creep=cr.Creep((0.01, 1.0, 100.0), (0.01, 0.01, 0.01),
                                                acts_on=creeps))
             if creeps else nominal)
    cm = tr.compile_model(model, DT)
    ud = triangle(27.9, 27.04, 1.5)
    keep = 400  # past the first corner (of 537 samples)
    st0 = tr.initial(model)
    res = inv.algorithm3(cm, ud, st0, horizon=2, e_max=1.5, keep=keep)
    _, _, want = tr.simulate(cm, res.voltage(model.thickness_um)[:keep], st0)
    got = res.kept
    np.testing.assert_allclose(got.polarization.values, want.polarization.values, atol=1e-12)
    np.testing.assert_allclose(got.rod, want.rod, rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(got.creep, want.creep, atol=1e-12)
    assert got.creep.size == (6 if creeps else 0)
    assert not np.allclose(got.rod, res.state.rod)  # not the state after the last sample
    assert inv.algorithm3(cm, ud, st0, horizon=2, e_max=1.5).kept is None


def test_a_first_order_stage_is_inverted_at_a_short_horizon(nominal: tr.Transducer) -> None:
    """A heavily damped rod (a stage that acts as a first-order lag, here 700 Hz like an
    independent tester's) has a zero eigenvalue in the horizon inverse's state map that
    round-off puts just below zero. It is no alternating mode: the smooth horizon stays short,
    and the corners of a 27.9 Hz triangle are turned when they come, not ``d`` samples early."""
    k = nominal.rod.k  # the static gain kept; a light rod (7 kHz) damped to a 700 Hz lag
    m, c = k / (2 * np.pi * 7000.0) ** 2, k / (2 * np.pi * 700.0)
    lagging = dc.replace(nominal, rod=dc.replace(nominal.rod, m=m, c=c))
    assert lagging.rod.damping_ratio > 4.9
    cm = tr.compile_model(lagging, DT)
    d = rd.smooth_horizon(cm.disc)
    assert d <= 2
    ud = triangle(27.9, 27.04, 3)
    period = int(1 / 27.9 / DT)
    worst = {h: np.max(np.abs(tracking_error(lagging, ud, inv.algorithm3(
        cm, ud, tr.initial(lagging), horizon=h, e_max=1.5), period))) for h in (d, 8)}
    assert worst[d] < 0.25 * worst[8] and worst[d] < 0.2, worst


def test_a_rod_resonating_above_a_quarter_of_the_sample_rate_gets_a_horizon_that_tracks(
        nominal: tr.Transducer) -> None:
    """A rod at 3.5 kHz damped 0.04, sampled at 10 kHz (a third tester's Bouc-Wen stage): its own
    discrete poles have negative real parts, so no horizon's inverse has only positive ones, and
    the longest (64) turned every corner of a 27.9 Hz triangle 63 samples early. The horizon
    given is one whose inverse is stable, and it tracks the triangle through the model several
    times better than horizon 64."""
    k = nominal.rod.k  # the static gain kept
    w = 2 * np.pi * 3500.0
    m = k / w ** 2
    fast = dc.replace(nominal, rod=dc.replace(nominal.rod, m=m, c=2 * 0.04 * m * w))
    cm = tr.compile_model(fast, DT)
    assert np.all(np.linalg.eigvals(cm.disc.phi).real < 0)
    d = rd.smooth_horizon(cm.disc)
    row, gain = cm.disc.horizon(d)
    assert d < 64
    assert np.max(np.abs(np.linalg.eigvals(cm.disc.phi - np.outer(cm.disc.gamma, row) / gain))) < 1
    ud = triangle(27.9, 27.04, 3)
    period = int(1 / 27.9 / DT)
    rms = {h: float(np.sqrt(np.mean(tracking_error(fast, ud, inv.algorithm3(
        cm, ud, tr.initial(fast), horizon=h, e_max=1.5), period) ** 2))) for h in (d, 64)}
    assert rms[d] < 0.2 * rms[64], rms
