"""The Preisach grid's problem (afmctl.fit.preisach_problem): its linearization against the exact
model, with the creep on the polarization and on the force."""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmctl.fit import preisach_basis as pb
from afmctl.fit import preisach_problem as pp
from afmctl.model import creep as cr


def problem(on_force: bool, gap_s: float = math.nan) -> pp.Problem:
    """Two sweeps (a triangle, then minor loops inside the range) on a coarse grid, the creep
    elements behind a play of 0 and of 0.3 um; the second sweep's creep from the first's after a
    hold of ``gap_s`` (default NaN: from rest)."""
    rng = np.random.default_rng(3)
    e1 = np.interp(np.arange(800), [0, 200, 400, 600, 799], [0.0, 1.5, 0.0, 1.5, 0.0])
    e2 = np.interp(np.arange(600), [0, 100, 200, 300, 400, 500, 599],
                   [0.0, 1.2, 0.4, 1.0, 0.6, 0.9, 0.7])
    fields = [e1, e2]
    data = pp.Data(fields, [np.ones(e.size, bool) for e in fields],
                   [rng.normal(size=e.size) for e in fields], [1e-3, 1e-3], np.array([0.02, 0.02]),
                   gaps_s=[math.nan, gap_s])
    settings = pp.Settings(n_coercive=8, n_interaction=12, coef_coercive=4, coef_interaction=6)
    ec, ei, spread = pp.make_grid(fields, settings)
    mi, mj = pb.hat_matrix(ec.size, 4), pb.hat_matrix(ei.size, 6)
    grid = pb.Grid(ec, ei, spread, mi, mj, np.arange(24))
    prob = pp.Problem(data, grid, ("positive", "previous"), (0.01, 0.1, 1.0))
    prob.set_thresholds((0.0, 0.3))
    prob.creep_on_force = on_force
    return prob


@pytest.mark.parametrize("first_off", [False, True])
@pytest.mark.parametrize("gap_s", [math.nan, 0.0, 0.05])
@pytest.mark.parametrize("on_force", [False, True])
def test_the_design_is_the_models_derivative_and_b0_its_rest(on_force: bool, gap_s: float,
                                                            first_off: bool) -> None:
    """``y - rhs = b0`` and ``A x + b0`` is the model to first order: a step ``h`` in every
    parameter but the rod's moves the exact prediction by ``A h`` up to O(h^2) (halving ``h``
    quarters the miss); at the point itself ``A x0 + b0`` is the prediction. Also where the
    second sweep's creep goes on from the first's (``gap_s`` >= 0): the design then carries the
    first sweep's columns into the second's creep, each play width's from its own (``first_off``:
    the first width's elements all at 0, so the second's are the only ones carried)."""
    prob = problem(on_force, gap_s)
    prob.cubic = True
    rng = np.random.default_rng(5)
    th = pp.Theta(rng.uniform(0.5, 2.0, 24), 0.7, rng.uniform(0.0, 0.02, 6), 0.004, 2e-5,
                  np.log(60.0), np.log(0.3), np.array([0.5, -0.2]))
    if first_off:
        th.c[:3] = 0.0
    designs, rhs = prob.linearize(th, True)
    k, nc = th.w.size, th.c.size

    def at(t: pp.Theta) -> np.ndarray:
        return np.concatenate((t.w, [t.r], t.c, [t.s, t.t], [0.0, 0.0], t.offsets))

    a = np.vstack(designs)
    b0 = np.concatenate([y - r for y, r in zip(prob.data.y, rhs, strict=True)])
    exact = np.concatenate(prob.predict(th))
    np.testing.assert_allclose(a @ at(th) + b0, exact, atol=1e-9)
    step = np.concatenate((rng.normal(0, 0.05, k), [0.02], rng.uniform(0, 0.002, nc),
                           [2e-4, 1e-6], [0.0, 0.0], [0.01, 0.01]))
    misses = []
    for h in (1.0, 0.5):
        moved = th.copy()
        x = at(th) + h * step
        moved.w, moved.r, moved.c = x[:k], float(x[k]), x[k + 1:k + 1 + nc]
        moved.s, moved.t = float(x[k + 1 + nc]), float(x[k + 2 + nc])
        moved.offsets = x[-2:]
        misses.append(float(np.max(np.abs(np.concatenate(prob.predict(moved)) - exact
                                          - h * (a @ step)))))
    assert misses[1] < 0.3 * misses[0], misses  # second order: a quarter, with slack
    assert misses[0] < 0.05 * float(np.max(np.abs(a @ step)))


def test_creep_on_the_force_and_on_the_polarization_differ_where_the_map_bends() -> None:
    """The same point, creep on ``Q`` or on ``g(Q)``: equal with a straight map (``s = t = 0``),
    apart with a bent one."""
    rng = np.random.default_rng(6)
    th = pp.Theta(rng.uniform(0.5, 2.0, 24), 0.7, rng.uniform(0.0, 0.02, 6), 0.0, 0.0,
                  np.log(60.0), np.log(0.3), np.array([0.5, -0.2]))
    pol, force = problem(False), problem(True)
    np.testing.assert_allclose(np.concatenate(pol.forces(th)), np.concatenate(force.forces(th)),
                               atol=1e-12)
    th.s = 0.01
    assert np.max(np.abs(np.concatenate(pol.forces(th)) - np.concatenate(force.forces(th)))) > 1e-3


def test_a_plays_coefficient_is_its_rows_line_in_the_models_kernel() -> None:
    """The grid with plays: the fit's columns times any coefficients (smooth ones and one play
    per row, some left out) are the polarization the model's own kernel
    (:func:`afmctl.model.hysteresis.run` on the :class:`PreisachGrid` of ``Grid.weights``) gives,
    through minor loops, to the kernel's table interpolation (4.4e-8 of the switched
    polarization, :func:`afmctl.model.preisach.row_tables`); and the penalty smooths the plays
    along the coercive field only."""
    from afmctl.fit import preisach as pf
    from afmctl.model import hysteresis as hy
    from afmctl.model import preisach as pr

    rng = np.random.default_rng(1)
    e = np.interp(np.arange(900), [0, 200, 400, 600, 700, 800, 899],
                  [0.0, 1.5, 0.0, 1.2, 0.5, 1.0, 0.7])
    settings = pp.Settings(n_coercive=8, n_interaction=12, coef_coercive=4, coef_interaction=6)
    ec, ei, spread = pp.make_grid([e], settings)
    active = np.flatnonzero(rng.random(24 + 8) < 0.8)
    grid = pb.Grid(ec, ei, spread, pb.hat_matrix(ec.size, 4), pb.hat_matrix(ei.size, 6), active,
                   plays=True)
    coef = rng.uniform(0.0, 0.02, active.size)
    cols, _ = pb.basis(e, grid, pr.start_outputs(ec, "depoled"))
    model = pr.PreisachGrid(tuple(ec), tuple(ei), spread, tuple(map(tuple, grid.weights(coef))),
                            0.0)
    p, _ = hy.run(model, e, hy.initial_state(model))
    np.testing.assert_allclose(cols @ coef, p, atol=4.4e-8 * model.hysteretic_range() / 2)
    lines = active >= 24
    pen = pf.grid_penalty(grid)
    assert not np.any(pen[:, lines] * pen[:, ~lines].any(axis=1, keepdims=True))  # apart
    x = np.where(lines, 1.0, 0.0)  # plays equal, smooth part zero: no penalty
    np.testing.assert_allclose(pen @ x, 0.0, atol=1e-12)
    bump = np.zeros(active.size)
    bump[np.flatnonzero(lines)[2]] = 1.0  # one play alone: its neighbours' differences see it
    assert np.count_nonzero(pen @ bump) >= 2


@pytest.mark.parametrize("periods", range(2, 11))
def test_every_phase_held_out_in_one_period_is_trained_on_in_another(periods: int) -> None:
    """On a sweep of whole periods, the samples a fold holds out at one phase of the loop are in
    another fold one period or more away: no fold is judged on an arc the others never saw.
    Each fold holds a quarter of the samples."""
    n = 2520 * periods  # samples divisible by the blocks and the periods
    data = pp.Data([np.zeros(n)], [np.ones(n, bool)], [np.zeros(n)], [1e-3], np.array([0.01]))
    fold = data.folds[0].reshape(periods, -1)  # one row per period
    assert not (fold == fold[0]).all(axis=0).any()
    assert np.bincount(data.folds[0], minlength=pp.FOLDS).tolist() == [n // pp.FOLDS] * pp.FOLDS


def test_a_sweeps_creep_goes_on_from_the_one_before_across_the_hold() -> None:
    """Chained, the second sweep's creep elements are those of one record: the first sweep, the
    hold at its last drive for ``gap_s``, the second sweep, run through each play and element
    from rest (:func:`afmctl.model.creep.play_hold`, :func:`afmctl.model.creep.lagged`); with
    the hold unknown (NaN) the second starts at rest, and with the chain off too."""
    gap_s, dt = 0.05, 1e-3
    prob = problem(False, gap_s)
    rng = np.random.default_rng(8)
    drives = [np.cumsum(rng.normal(0, 0.05, e.size)) for e in prob.data.fields]
    hold = np.full(int(round(gap_s / dt)), drives[0][-1])
    whole = np.concatenate((drives[0], hold, drives[1]))
    oracle = np.hstack([cr.lagged(cr.play_hold(whole, r)[0], prob.taus, dt,
                                  np.full(prob.taus.size, whole[0]))
                        for r in prob.thresholds])
    states = prob.creep_states(drives)
    np.testing.assert_allclose(states[0], oracle[:drives[0].size], atol=1e-12)
    np.testing.assert_allclose(states[1], oracle[-drives[1].size:], atol=1e-12)
    for unchained in (problem(False), problem(False, gap_s)):
        unchained.chained = unchained.data.gaps_s[1] != gap_s
        rest = np.hstack([cr.lagged(cr.play_hold(drives[1], r)[0], prob.taus, dt,
                                    np.full(prob.taus.size, drives[1][0]))
                          for r in prob.thresholds])
        np.testing.assert_allclose(unchained.creep_states(drives)[1], rest, atol=1e-12)
    assert np.max(np.abs(states[1] - rest)) > 1e-3  # the chain matters here
