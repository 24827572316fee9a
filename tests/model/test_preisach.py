"""The Preisach grid (afmctl.model.preisach) against analytic limits and an independent relay sum."""

from __future__ import annotations

import numpy as np
import pytest

from afmctl.model import hysteresis as hy
from afmctl.model import inverse as inv
from afmctl.model import preisach as pr
from afmctl.model import rod as rd
from afmctl.model import transducer as tr


def grid(seed: int = 3) -> pr.PreisachGrid:
    """A non-separable, off-centre density: rank > 1, weights favouring negative E_I at low E_c."""
    rng = np.random.default_rng(seed)
    ec = np.linspace(0.0, 0.7, 8)
    ei = np.linspace(-1.4, 0.2, 9)
    w = rng.uniform(0.0, 1.0, (8, 9)) * np.exp(-((ei[None, :] + 0.6 + 0.5 * ec[:, None]) / 0.5) ** 2)
    return pr.PreisachGrid(tuple(ec), tuple(ei), 0.18, tuple(map(tuple, 0.01 * w)), 0.02)


def ramp(*points: float, step: float = 0.01) -> np.ndarray:
    """Piecewise-linear field through ``points`` (MV/m) in steps of at most ``step``."""
    out = [np.array([points[0]])]
    for a, b in zip(points[:-1], points[1:], strict=True):
        n = max(int(np.ceil(abs(b - a) / step)), 1)
        out.append(np.linspace(a, b, n + 1)[1:])
    return np.concatenate(out)


def test_wiping_out() -> None:
    """Exceeding an earlier maximum wipes out every reversal since: the outputs on the last
    branch are those of the history without them (exactly: only the reversals are remembered)."""
    g = grid()
    long = ramp(0.0, 1.0, 0.3, 0.8, 0.5, 1.2, 0.6)
    short = ramp(0.0, 1.2, 0.6)
    p_long, s_long = hy.run(g, long, hy.initial_state(g))
    p_short, s_short = hy.run(g, short, hy.initial_state(g))
    n = ramp(1.2, 0.6).size
    np.testing.assert_allclose(p_long[-n:], p_short[-n:], rtol=0, atol=1e-15)
    np.testing.assert_allclose(s_long.values, s_short.values, rtol=0, atol=1e-15)


def test_congruent_minor_loops() -> None:
    """Minor loops between the same two fields are congruent whatever came before: their
    outputs differ by one constant (the classical Preisach property)."""
    g = grid()
    cycles = [0.5, 1.0, 0.5, 1.0, 0.5]
    a = ramp(0.0, 1.5, 0.2, *cycles)
    b = ramp(0.0, -0.4, 1.2, 0.35, *cycles)
    n = ramp(*cycles[2:]).size  # the second cycle
    pa, _ = hy.run(g, a, hy.initial_state(g))
    pb, _ = hy.run(g, b, hy.initial_state(g))
    diff = pa[-n:] - pb[-n:]
    assert abs(diff[0]) > 1e-4  # the histories left different outputs ...
    np.testing.assert_allclose(diff, diff[0], rtol=0, atol=1e-14)  # ... and congruent loops


def test_rank_one_weights_are_the_normal_kernel() -> None:
    """A single interaction node at 0 with spread sigma_I and weights P_R v_i is (13) with the
    closed-form normal kernel: Algorithm 1's V^T P W as a one-column matrix (to the grid's table
    interpolation, 4.4e-8 of the switched polarization)."""
    pol = hy.Polarization(eta=2.5, p_r=0.3, coercive=hy.Lognormal(0.6, 0.4),
                          interaction=hy.Normal(0.25), n_coercive=32)
    k = hy.build_kernel(pol)
    g = pr.PreisachGrid(tuple(k.ec), (0.0,), 0.25, tuple((0.3 * w,) for w in k.wc), 1 / 2.5)
    e = ramp(0.0, 1.4, -0.3, 0.9, -1.6, 0.4)
    for how in ("depoled", "positive", "negative"):
        p_ref, _ = hy.run(pol, e, hy.initial_state(pol, how))
        p, _ = hy.run(g, e, hy.initial_state(g, how))
        np.testing.assert_allclose(p, p_ref, rtol=0, atol=4.4e-8 * g.hysteretic_range() / 2)


def test_the_kernels_tables_are_each_rows_closed_form() -> None:
    """The compiled kernel reads each row from a table: against the rows' erf sums at the play
    outputs the field leaves (a history that reverses inside and outside the tables), within the
    cubic Hermite bound of :func:`row_tables`, and exact where every cell is switched."""
    g = grid()
    e = ramp(0.0, 1.7, -0.9, 0.8, -0.2, 0.45, 0.1, 4.0, step=0.0007)
    p, _ = hy.run(g, e, hy.initial_state(g))
    y = pr.play(e, np.asarray(g.coercive), pr.start_outputs(np.asarray(g.coercive), "depoled"))
    rows = np.array([pr.row_outputs(g, y[:, i])[0][i] for i in range(g.n_coercive)])
    p_ref = g.reversible * e + rows.sum(axis=0)
    bound = 4.4e-8 * g.hysteretic_range() / 2
    assert np.max(np.abs(p - p_ref)) < bound
    assert abs(p[-1] - (g.reversible * e[-1] + g.hysteretic_range() / 2)) < 1e-12  # all up


def test_equals_an_independent_relay_sum() -> None:
    """Against relays written here: each cell is 4000 literal relays (4) at the normal quantiles
    of its interaction spread, switching up at E >= E_c - E_I and down at E <= -E_c - E_I."""
    g = grid(5)
    q = (np.arange(4000) + 0.5) / 4000
    from scipy import special
    offsets = g.spread * special.ndtri(q)
    e = ramp(0.0, 1.3, 0.1, 0.9, 0.4, 1.1, -0.2)
    w = g.matrix
    p_ref = np.zeros(e.size)
    for i, ec in enumerate(g.coercive):
        for j, eij in enumerate(g.interaction):
            if w[i, j] == 0:
                continue
            e_i = eij + offsets
            state = np.where(e_i > 0, 1.0, -1.0)  # depoled: sgn(E_I) (y = 0)
            for k, ek in enumerate(e):
                state = np.where(ek >= ec - e_i, 1.0, np.where(ek <= -ec - e_i, -1.0, state))
                p_ref[k] += w[i, j] * state.mean()
    p_ref += g.reversible * e
    p, _ = hy.run(g, e, hy.initial_state(g))
    assert np.max(np.abs(p - p_ref)) < 2e-3 * g.hysteretic_range()


def test_algorithm3_through_the_grid_follows_its_target() -> None:
    """It follows its target, and the play outputs it keeps after the first fields are those the
    forward model reaches on them."""
    g = grid()
    model = tr.Transducer(g, rd.Rod(m=0.05, c=60.0, k=2.0e5, a1=3.0e4, a2=1.0e4), 100.0)
    cm = tr.compile_model(model, 1e-4)
    st = tr.initial(model)
    u0 = float(tr.simulate(cm, np.zeros(1), st)[0][0])
    t = np.arange(2000) * 1e-4
    target = u0 + 0.8 * np.sin(np.pi * t / t[-1]) ** 2 * np.sin(2 * np.pi * 10 * t) ** 2
    res = inv.algorithm3(cm, target, st, horizon=2, e_min=0.0, e_max=1.5, keep=1300)
    assert np.max(res.error) < 1e-6
    u = tr.simulate(cm, res.field_mv_m * 100.0, st)[0]
    np.testing.assert_allclose(u[2:], target[1:-1], atol=1e-5)  # horizon 2: u_{k+2} = u*_{k+1}
    want = tr.simulate(cm, res.field_mv_m[:1300] * 100.0, st)[2]
    np.testing.assert_allclose(res.kept.polarization.values, want.polarization.values, atol=1e-12)
    np.testing.assert_allclose(res.kept.rod, want.rod, rtol=1e-9, atol=1e-18)


def test_rejects_malformed_grids() -> None:
    with pytest.raises(ValueError, match="weights must be 2 x 3"):
        pr.PreisachGrid((0.1, 0.2), (0.0, 0.1, 0.2), 0.1, ((1.0, 1.0),), 0.0)
    with pytest.raises(ValueError, match=">= 0"):
        pr.PreisachGrid((0.1,), (0.0,), 0.1, ((-1.0,),), 0.0)
    with pytest.raises(ValueError, match="spread"):
        pr.PreisachGrid((0.1,), (0.0,), 0.0, ((1.0,),), 0.0)
    with pytest.raises(ValueError, match="1/1000 of the interaction nodes' span"):
        pr.PreisachGrid((0.1,), (0.0, 2.0), 1e-3, ((1.0, 1.0),), 0.0)

