"""Log-time creep (afmctl.model.creep): analytic limits, the transducer and its inverse."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from afmctl.model import creep as cr
from afmctl.model import hysteresis as hy
from afmctl.model import inverse as inv
from afmctl.model import rod as rd
from afmctl.model import transducer as tr

TAUS = cr.DEFAULT_TAUS_S  # two per decade, 10 ms ... 1000 s


def test_step_response_is_the_exact_sum_of_exponentials() -> None:
    c = cr.Creep(TAUS, tuple(np.linspace(0.001, 0.01, len(TAUS))))
    dt = 0.003
    k = np.arange(2000)
    p, _ = cr.run(c, np.ones(k.size), dt, cr.rest_state(c, 0.0))
    exact = 1.0 + cr.step_response(c, k * dt)  # z_k = 1 - exp(-k dt / tau): the ZOH is exact
    np.testing.assert_allclose(p, exact, rtol=0, atol=1e-14)


def test_equal_weights_creep_a_straight_line_in_log_time() -> None:
    """Equal weights, two elements per decade: between the first and last time constants the
    step response is a straight line against log t with slope ~ 2 c per decade; one element
    (an exponential, like thermal relaxation) has a knee."""
    c = 0.0075
    creep = cr.Creep(TAUS, (c,) * len(TAUS))
    t = np.logspace(-1, 2, 31)
    y = cr.step_response(creep, t)
    slope, icpt = np.polyfit(np.log10(t), y, 1)
    assert slope == pytest.approx(2 * c, rel=0.1)
    assert np.max(np.abs(y - (slope * np.log10(t) + icpt))) < 0.03 * slope
    one = cr.Creep((1.0,), (3 * 2 * c,))  # the same total change over the 3 decades, at once
    y1 = cr.step_response(one, t)
    s1, i1 = np.polyfit(np.log10(t), y1, 1)
    assert np.max(np.abs(y1 - (s1 * np.log10(t) + i1))) > 0.2 * s1


def model(creep: cr.Creep | None) -> tr.Transducer:
    pol = hy.Polarization(eta=2.5, p_r=0.3, coercive=hy.Lognormal(0.6, 0.4),
                          interaction=hy.Normal(0.25), n_coercive=64)
    return tr.Transducer(pol, rd.Rod(m=0.05, c=60.0, k=2.0e5, a1=3.0e4, a2=1.0e4), 100.0,
                         creep=creep)


def test_a_held_step_creeps_and_the_inverse_holds_it() -> None:
    creep = cr.Creep(TAUS, (0.0075,) * len(TAUS))
    m, dt = model(creep), 2e-3
    cm = tr.compile_model(m, dt)
    st = tr.initial(m)
    n = int(60 / dt)
    v = np.full(n, 100.0)
    u, _, _ = tr.simulate(cm, v, st)
    u_plain = tr.simulate(tr.compile_model(model(None), dt), v, tr.initial(model(None)))[0]
    step = u_plain[-1] - u_plain[0]
    t = np.arange(n) * dt
    late = (t > 0.3) & (t < 30)
    slope = np.polyfit(np.log10(t[late]), u[late] - u_plain[late], 1)[0]
    assert 0.01 * step < slope < 0.03 * step  # ~1.5 % of the step per decade, as set
    # the inverse of "go to the step's first value and stay": the field backs off as it creeps
    target = np.full(n, u[20])
    res = inv.algorithm3(cm, target, st, horizon=1, e_min=0.0, e_max=1.5)
    held = tr.simulate(cm, res.field_mv_m * 100.0, st)[0]
    assert np.max(np.abs(held[200:] - u[20])) < 1e-5  # no drift over the minute
    assert res.field_mv_m[-1] < res.field_mv_m[200] - 0.01  # the creep is compensated


def test_creep_on_the_force_is_creep_on_the_polarization_where_the_force_is_linear() -> None:
    """Analytic limit: with the force linear in ``P`` (``a2 = 0``) driving the creep elements by
    ``P_h`` or by ``F(P_h)`` and adding them there is the same stage; with the paper's ``a2 P^2``
    the two part. Algorithm 3 inverts the creep on the force exactly too."""
    dt = 1e-3
    v = 100.0 * np.abs(np.sin(np.linspace(0.0, 6 * np.pi, 3000))) + 20.0 * np.sin(
        np.linspace(0.0, 40 * np.pi, 3000))
    weights = (0.02,) * len(TAUS)
    out = {}
    for a2 in (0.0, 1.0e4):
        for on in cr.ACTS_ON:
            m = model(cr.Creep(TAUS, weights, acts_on=on))
            m = tr.Transducer(m.polarization, rd.Rod(m=0.05, c=60.0, k=2.0e5, a1=3.0e4, a2=a2),
                              100.0, creep=m.creep)
            out[a2, on] = tr.simulate(tr.compile_model(m, dt), v, tr.initial(m))[0]
    np.testing.assert_allclose(out[0.0, "force"], out[0.0, "polarization"], atol=1e-9)
    assert np.max(np.abs(out[1.0e4, "force"] - out[1.0e4, "polarization"])) > 0.01  # um
    m = model(cr.Creep(TAUS, weights, acts_on="force"))
    cm = tr.compile_model(m, dt)
    st = tr.initial(m)
    u = tr.simulate(cm, v, st)[0]
    res = inv.algorithm3(cm, np.append(u[1:], u[-1]), st, horizon=1, e_min=-1.5, e_max=1.5,
                         tol_um=1e-9)
    back = tr.simulate(cm, res.field_mv_m * 100.0, st)[0]
    assert np.max(np.abs(back[1:] - u[1:])) < 1e-6  # um
    with pytest.raises(ValueError, match="acts on"):
        cr.Creep((1.0,), (0.1,), acts_on="displacement")


def test_rejects_malformed_creep() -> None:
    with pytest.raises(ValueError, match="equally long"):
        cr.Creep((1.0, 2.0), (0.1,))
    with pytest.raises(ValueError, match="> 0"):
        cr.Creep((0.0,), (0.1,))
    with pytest.raises(ValueError, match=">= 0"):
        cr.Creep((1.0,), (-0.1,))


def test_an_element_behind_a_play_keeps_creeping_through_a_small_reversal() -> None:
    """Krejci-Kuhnen elements behind a play of half-width r: a reversal smaller than 2 r does not
    turn them round (a linear element turns at once); a larger one does."""
    dt = 0.01
    hold = np.ones(500)
    p_h = np.concatenate([hold, 0.9 * hold, 0.0 * hold])  # up, a small reversal, a large one
    lin = cr.Creep((1.0,), (0.1,))
    thr = cr.Creep((1.0,), (0.1,), (0.2,))
    part = {}
    for name, c in (("linear", lin), ("play", thr)):
        p, _ = cr.run(c, p_h, dt, cr.rest_state(c, 0.0))
        part[name] = p - p_h
    small = slice(520, 990)
    assert np.all(np.diff(part["linear"][small]) < 0)  # turned with the small reversal
    assert np.all(np.diff(part["play"][small]) > 0)  # still creeping the old way, up
    assert part["play"][1490] < part["play"][990] - 0.05  # a large reversal turns it too


def _lfilter_lag(x: np.ndarray, tau_s: float, dt: float, z0: float) -> np.ndarray:
    """One element's state before every sample by scipy's lfilter: ``z_{k+1} = a z_k + (1 - a)
    x_k``, ``a = exp(-dt / tau)``, from ``z_0 = z0`` (the oracle of :func:`cr.lagged`)."""
    a = math.exp(-dt / tau_s)
    return signal.lfilter([0.0, 1.0 - a], [1.0, -a], x, zi=[z0])[0]


def test_lagged_is_each_elements_lfilter_to_the_last_bit() -> None:
    """:func:`lagged` (one compiled pass over every time constant) equals scipy's lfilter element
    by element exactly, from given states and from rest."""
    rng = np.random.default_rng(7)
    x = np.cumsum(rng.standard_normal(5000))
    tau, z0 = np.asarray(TAUS), rng.standard_normal(len(TAUS))
    got = cr.lagged(x, tau, 1e-4, z0)
    want = np.column_stack([_lfilter_lag(x, t, 1e-4, z) for t, z in zip(tau, z0, strict=True)])
    assert np.array_equal(got, want)
    rest = cr.lagged(x, tau, 1e-3, np.full(tau.size, x[0]))
    assert np.array_equal(rest, np.column_stack([_lfilter_lag(x, t, 1e-3, x[0]) for t in tau]))


def test_lag_columns_of_held_columns_are_the_elements_filters_combined() -> None:
    """:func:`add_lag_columns` on every column of ``x[idx]`` (held where a play last moved)
    equals each element's own filter (:func:`lagged`, scipy's lfilter) weighted and summed,
    added to ``x``."""
    rng = np.random.default_rng(3)
    x = rng.standard_normal((3000, 4))
    q = np.cumsum(rng.standard_normal(3000))
    idx = cr.play_hold(q, 3.0)[1]
    tau, w, dt = np.array([0.02, 0.3, 5.0]), np.array([0.5, 0.3, 0.2]), 1e-3
    out, _ = cr.add_lag_columns(x, [cr.Lags(tau, w, idx)], dt)
    held = x[idx]
    want = x + np.column_stack([cr.lagged(held[:, i], tau, dt, np.full(3, held[0, i])) @ w
                                for i in range(4)])
    np.testing.assert_allclose(out, want, atol=1e-12)
    assert len(set(idx.tolist())) < idx.size  # the play holds: some samples repeat


def test_groups_of_lag_columns_at_once_are_the_groups_one_after_another() -> None:
    """Groups (plays of other widths, one from given start states and holding before its first
    sample) written in one pass equal each group's creep added to ``x`` in turn, stepped here
    sample by sample in NumPy, to the last bit, with the same end states."""
    rng = np.random.default_rng(5)
    x = rng.standard_normal((2000, 6))
    q = np.cumsum(rng.standard_normal(2000))
    dt = 1e-3
    start = (rng.standard_normal((6, 2)), rng.standard_normal(6))
    groups = [cr.Lags(np.array([0.01, 1.0]), np.array([0.4, 0.1]), cr.play_hold(q, 0.0)[1]),
              cr.Lags(np.array([0.1]), np.array([0.3]), cr.play_hold(q, 2.0)[1]),
              cr.Lags(np.array([0.05, 10.0]), np.array([0.2, 0.6]),
                      cr.play_hold(np.concatenate(([q[0] + 1.0], q)), 4.0)[1][1:] - 1, start)]
    assert groups[2].idx[0] == -1  # the play holds what it held before the first sample
    got, ends = cr.add_lag_columns(x, groups, dt)
    want = x.copy()
    for g, (z_end, held_end) in zip(groups, ends, strict=True):
        a = np.exp(-dt / g.tau_s)
        z = (np.repeat(x[g.idx[0]][None, :], a.size, axis=0) if g.start is None
             else g.start[0].T.copy())
        before = np.zeros(x.shape[1]) if g.start is None else g.start[1]
        for t, row in enumerate(g.idx):
            xv = x[row] if row >= 0 else before
            acc = np.zeros(x.shape[1])
            for j in range(a.size):
                acc += g.weights[j] * z[j]
                z[j] = a[j] * z[j] + (1.0 - a[j]) * xv
            want[t] += acc
        assert np.array_equal(z.T, z_end) and np.array_equal(x[g.idx[-1]], held_end)
    assert np.array_equal(got, want)


@pytest.mark.parametrize("seconds", [0.004, 0.3, 4.0, 70.0])
def test_a_hold_is_the_held_voltage_simulated(seconds: float) -> None:
    """:func:`afmctl.model.transducer.held` (doubling steps for a long hold) against
    :func:`simulate` of the held voltage sample by sample, right after a fast move: the creep
    states to round-off, the displacement that follows within a nanometre."""
    m, dt = model(cr.Creep(TAUS, (0.0075,) * len(TAUS))), 1e-4
    cm = tr.compile_model(m, dt)
    move = np.concatenate((np.linspace(0.0, 120.0, 3000), np.linspace(120.0, 20.0, 800)))
    st = tr.simulate(cm, move, tr.initial(m))[2]
    fast = tr.held(cm, 20.0, seconds, st)
    slow = tr.simulate(cm, np.full(int(round(seconds / dt)), 20.0), st)[2]
    np.testing.assert_allclose(fast.creep, slow.creep, rtol=0, atol=1e-10)
    after = [tr.simulate(cm, np.full(5, 20.0), s)[0] for s in (fast, slow)]
    np.testing.assert_allclose(after[0], after[1], rtol=0, atol=1e-3)
    moved = tr.simulate(cm, np.full(5, 20.0), st)[0]
    assert np.max(np.abs(after[1] - moved)) > 0.01  # the hold crept: not a trivial pass
