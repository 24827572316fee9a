"""The Preisach grid's problem with its slow sweeps in block means (afmctl.fit.preisach_coarse)."""

from __future__ import annotations

import copy
import inspect
import math
from typing import Any

import numpy as np
import pytest

from afmctl.fit import diagnose as dg
from afmctl.fit import gridbase as gb
from afmctl.fit import preisach as pf
from afmctl.fit import preisach_coarse as pc
from afmctl.fit import preisach_solver as ps
from afmctl.fit import rod_response as rr
from afmctl.model import creep as cr
from afmctl.planning import sweepdesign as sd
from tests.fit.test_preisach_fit import data_of
from tests.harness.preisach_plant import PreisachStage, standard_sweeps


def _means(x: np.ndarray, m: int) -> np.ndarray:
    n = (x.size // m) * m
    return x[:n].reshape(-1, m).mean(axis=1)


def test_the_quasi_static_rod_is_the_rods_block_means_on_a_slow_sweep() -> None:
    """A 0.279 Hz triangle at 10 kHz through a 400 Hz rod damped 0.4, averaged over blocks of 89
    samples: the quasi-static limit (half a sample late, through the rod's lag 2 zeta / omega)
    gives those means to within 2 % of the lag it models, away from the triangle's corners; the
    plain block means miss by the whole lag. At a corner the central difference spans the turn
    and misses by about half the lag (0.006 um here, under any stage's sensor noise): what the
    full problem's last steps see."""
    dt, m, fn, zeta = 1e-4, 89, 400.0, 0.4
    x = 40.0 + 30.0 * sd.loop(0.279, -1.0, 1.0, 2, 1.0 / dt)  # um
    want = _means(rr.rod_filter(x, fn, zeta, dt), m)
    got = rr.quasi_static(_means(x, m), fn, zeta, dt, m * dt)
    slope = 2.0 * 60.0 * 0.279  # um/s
    lag = slope * (0.5 * dt + 2.0 * zeta / (2.0 * math.pi * fn))  # um
    t = (np.arange(want.size) + 0.5) * m * dt
    d = (t * 0.279 - 0.25) % 0.5  # turns at a quarter and three quarters of a period
    corner = (np.minimum(d, 0.5 - d) < 0.03) | (t < 0.1) | (t > t[-1] - 0.1)  # 0.1 s about
    assert np.max(np.abs(got - want)[~corner]) < 0.02 * lag
    assert np.max(np.abs(got - want)) < 0.6 * lag
    assert np.median(np.abs(_means(x, m) - want)[~corner]) > 0.9 * lag


def test_only_a_slow_sweep_is_seen_in_blocks() -> None:
    """The standard triangles (0.279, 5.58 and 27.9 Hz over 0-150 V, at 10 kHz): only the slow
    one (1 % of the fast one's field rate), in blocks of 35 samples (its field moves 0.0056 % of
    the range per sample, 0.2 % in 35.8); a creep element of 2 ms would allow 20."""
    fields = [sd.loop(f, 0.0, 150.0, n, 1e4) / 100.0 for f, n in ((0.279, 2), (5.58, 5),
                                                                 (27.9, 10))]
    dts = [1e-4] * 3
    assert pc.blocks(fields, dts, 0.01) == [35, 1, 1]
    assert pc.blocks(fields, dts, 0.002) == [20, 1, 1]
    assert pc.blocks(fields[:1], dts[:1], 0.01) == [1]  # alone, it is the fastest


@pytest.fixture(scope="module")
def creeping() -> tuple[pf.Data, pf.Runs]:
    """The independent plant with creep of 1.5 % per decade, its standard set, and the grid's
    runs on the full problem (creep on the polarization, one start assignment)."""
    data = data_of(standard_sweeps(PreisachStage(seed=3, creep_per_element=0.0075)))
    full = pf.runs(data, [("positive",) * 3], (2000.0, 0.3), pf.Settings(), lambda _m: None,
                   on_force=False, creep_above=0.0)
    assert full.crept is not None
    return data, full


@pytest.fixture(scope="module")
def quick(creeping: tuple[pf.Data, pf.Runs]) -> tuple[pf.Runs, list[str], list[bool]]:
    """The same runs on the problem with the slow sweep at 1 kHz in blocks of 7 samples (0.5 % of
    the range, coarser than the default's 0.2 %, which would make blocks of 2 of this short
    sweep: too few to block), what they said, and the damping rule of each Gauss-Newton run
    (``gain_ratio``)."""
    data, _ = creeping
    said: list[str] = []
    rules: list[bool] = []
    solve = pf.gauss_newton

    def recorded(*args: Any, **kwargs: Any) -> ps.Run:
        rules.append(kwargs.get("gain_ratio", False))
        return solve(*args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(pc, "BLOCK_SHARE", 0.005)
        patch.setattr(pf, "gauss_newton", recorded)
        assert pc.blocks(data.fields, data.dts, 0.01) == [7, 1, 1]
        runs = pf.runs(data, [("positive",) * 3], (2000.0, 0.3), pf.Settings(), said.append,
                       on_force=False, creep_above=0.0, coarse=True)
    return runs, said, rules


def test_a_fit_in_block_means_ends_where_the_full_fit_does(
        creeping: tuple[pf.Data, pf.Runs], quick: tuple[pf.Runs, list[str], list[bool]]) -> None:
    """On the independent Preisach plant with creep of 1.5 % per decade, its slow sweep in blocks
    of 7 samples: the grid and its creep fitted on the problem with the slow sweep in block means
    (``runs`` says so), then a few steps on the full problem, reach the full fit's misfit per
    sweep within 2 %, with the same creep per decade of time (0.1-100 s after a step) within
    10 %."""
    _, full = creeping
    settings = pf.Settings()
    quick_runs, said, _ = quick
    assert any("first fitted with each sweep's rows standing for 7 (means), 1, 1 samples" in m
               for m in said), said
    assert quick_runs.crept is not None and full.crept is not None
    assert quick_runs.problem.blocks == [1, 1, 1]  # the runs come back on the full problem
    last = pf.gauss_newton(quick_runs.problem, quick_runs.crept.theta, quick_runs.penalty,
                           quick_runs.smoothing, True, settings.max_iter,
                           gain_ratio=settings.gain_ratio_damping)
    ref = full.problem.ratios(full.crept.theta)
    got = quick_runs.problem.ratios(last.theta)
    np.testing.assert_allclose(got, ref, rtol=0.02)
    decade = [cr.Creep(tuple(map(float, full.problem.el_tau)), tuple(map(float, r.theta.c))
                       ).per_decade() for r in (full.crept, last)]
    assert abs(decade[1] - decade[0]) < 0.1 * decade[0], decade


def test_the_last_steps_start_nearly_undamped_and_end_where_damped_ones_do(
        quick: tuple[pf.Runs, list[str], list[bool]]) -> None:
    """identify's last steps on the full problem, from the fit in block means, start with the
    damping :data:`afmctl.fit.preisach.POLISH_MU`: they end at the misfit per sweep the usual
    start (:data:`afmctl.fit.preisach_solver.MU_START`) ends at, within 0.2 %, in no more
    steps."""
    runs, _, _ = quick
    assert runs.crept is not None
    prob, settings = runs.problem, pf.Settings()
    ends = {mu0: pf.gauss_newton(prob, runs.crept.theta, runs.penalty, runs.smoothing, True,
                                 settings.max_iter, mu0, gain_ratio=settings.gain_ratio_damping)
            for mu0 in (pf.POLISH_MU, ps.MU_START)}
    polished, usual = ends[pf.POLISH_MU], ends[ps.MU_START]
    np.testing.assert_allclose(prob.ratios(polished.theta), prob.ratios(usual.theta), rtol=2e-3)
    assert polished.iterations <= usual.iterations, (polished.iterations, usual.iterations)
    assert not np.array_equal(polished.theta.w, usual.theta.w)  # mu0 took other steps


def test_the_held_out_error_and_the_uncertainty_take_the_linearization_given(
        monkeypatch: pytest.MonkeyPatch, creeping: tuple[pf.Data, pf.Runs]) -> None:
    """identify linearizes its fit once for its held-out error and its uncertainty: given the
    problem linearized at the fit, neither linearizes it again nor changes it, and both are what
    they are without it (the held-out errors to the last bit)."""
    _, full = creeping
    assert full.crept is not None
    prob, th, pen, lams = full.problem, full.crept.theta, full.penalty, [1e-6, 1e-4]
    given = prob.linearize(th, True)
    kept = copy.deepcopy(given)
    calls: list[object] = []
    linearize = type(prob).linearize
    monkeypatch.setattr(type(prob), "linearize",
                        lambda self, *a: calls.append(a) or linearize(self, *a))
    reused = (pf.heldout(prob, th, pen, lams, True, given),
              pf.scalar_uncertainty(prob, th, True, given))
    assert calls == []
    alone = pf.heldout(prob, th, pen, lams, True), pf.scalar_uncertainty(prob, th, True)
    assert len(calls) == 2
    for lam in lams:
        np.testing.assert_array_equal(reused[0][lam], alone[0][lam])
    assert reused[1] == alone[1]
    for got, want in zip([*given[0], *given[1]], [*kept[0], *kept[1]], strict=True):
        np.testing.assert_array_equal(got, want)  # neither changed it for the other


def test_the_block_problem_holds_the_block_means_of_the_judged_readings_weighed(
        creeping: tuple[pf.Data, pf.Runs]) -> None:
    """``coarse`` on the independent plant's set (slow sweep in blocks of 7): a block is judged
    only if all its samples are (the sweep's first excursion is not judged, and a block straddles
    its end), its reading is their mean, its field the fields' mean, its period 7 samples; the
    cost weighs each block's squared residual by its 7 samples; and it is the full problem's cost
    less about the noise averaged out in the blocks (the models differ by the rod's quasi-static
    limit and the creep's blocks: within 5 % of the noise's sum of squares)."""
    data, full = creeping
    assert full.crept is not None
    m, mask, y = 7, data.masks[0], data.y[0]
    n = (mask.size // m) * m
    share = mask[:n].reshape(-1, m).mean(axis=1)
    assert np.any((share > 0) & (share < 1))  # a block partly judged: left out
    readings = np.full(mask.size, np.nan)
    readings[mask] = y
    want = readings[:n].reshape(-1, m).mean(axis=1)[share == 1]
    blocked = pc.coarse(full.problem, [m, 1, 1])
    np.testing.assert_array_equal(blocked.data.masks[0], share == 1)
    np.testing.assert_allclose(blocked.data.y[0], want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(blocked.data.fields[0], data.fields[0][:n].reshape(-1, m).mean(1))
    assert blocked.data.dts[0] == pytest.approx(m * data.dts[0])
    assert blocked.data.y[1] is data.y[1] and blocked.phi[1] is full.problem.phi[1]
    th, pen = full.crept.theta, full.penalty
    weighed = sum(w * float(np.sum((yy - u) ** 2)) for w, yy, u in
                  zip((m, 1, 1), blocked.data.y, blocked.predict(th), strict=True))
    assert blocked.cost(th, pen, 0.0) == pytest.approx(weighed, rel=1e-12)
    averaged_out = (1 - 1 / m) * y.size * float(data.noise[0]) ** 2
    assert abs(blocked.cost(th, pen, 0.0) - (full.problem.cost(th, pen, 0.0) - averaged_out)
               ) < 0.05 * full.problem.noise_sse


def test_a_sweep_at_its_own_rate_is_judged_on_every_kth_sample_weighed(
        monkeypatch: pytest.MonkeyPatch, creeping: tuple[pf.Data, pf.Runs]) -> None:
    """``coarse`` with the sweeps at their own rate and at most 300 rows each: a sweep with more
    is judged on every k-th of its judged samples (k the least stride leaving at most 300), its
    readings those samples', its rows weighed by k; it is still simulated on every sample (the
    readings the model predicts on those rows are the full problem's, to the last bit), and its
    linearization's rows are the full problem's there times sqrt(k)."""
    monkeypatch.setattr(pc, "THIN_ROWS", 300)
    data, full = creeping
    assert full.crept is not None
    thin = pc.coarse(full.problem, [1] * len(data.fields))
    th, pen = full.crept.theta, full.penalty
    whole, part = full.problem.predict(th, full=True), thin.predict(th)
    for i, (mask, y) in enumerate(zip(data.masks, data.y, strict=True)):
        idx = np.flatnonzero(mask)
        k = max(-(-idx.size // 300), 1)
        assert thin.weights[i] == k and thin.blocks[i] == 1
        np.testing.assert_array_equal(np.flatnonzero(thin.data.masks[i]), idx[::k])
        np.testing.assert_array_equal(thin.data.y[i], y[::k])
        np.testing.assert_array_equal(part[i], whole[i][idx[::k]])
    assert max(thin.weights) > 1
    weighed = sum(k * float(np.sum((y - u) ** 2)) for k, y, u in
                  zip(thin.weights, thin.data.y, part, strict=True))
    assert thin.cost(th, pen, 0.0) == pytest.approx(weighed, rel=1e-12)
    # the linearization (Gauss-Newton's step) weighs the rows alike: sqrt(k) times the full
    # problem's rows there
    (a_thin, b_thin), (a_full, b_full) = thin.linearize(th, True), full.problem.linearize(th, True)
    for k, at, bt, af, bf_ in zip(thin.weights, a_thin, b_thin, a_full, b_full, strict=True):
        np.testing.assert_allclose(at, np.sqrt(k) * af[::k], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(bt, np.sqrt(k) * bf_[::k], rtol=1e-12, atol=1e-12)


def test_nielsens_damping_fits_the_creep_in_fewer_steps_to_the_same_misfit(
        creeping: tuple[pf.Data, pf.Runs]) -> None:
    """identify's damping (:attr:`afmctl.fit.preisach.Settings.gain_ratio_damping`, Nielsen's
    rule) against diagnose's fixed rule, on the independent creeping plant: the creep fitted from
    the fit without it ends at the fixed rule's misfit per sweep within 1 %, in fewer steps."""
    _, full = creeping
    prob = full.problem
    start = full.plain.theta.copy()
    start.c = np.zeros(prob.el_tau.size)
    ends = {rule: pf.gauss_newton(prob, start, full.penalty, full.smoothing, True,
                                  pf.Settings().max_iter, gain_ratio=rule)
            for rule in (False, True)}
    np.testing.assert_allclose(prob.ratios(ends[True].theta), prob.ratios(ends[False].theta),
                               rtol=0.01)
    assert ends[True].iterations < ends[False].iterations, {
        r: e.iterations for r, e in ends.items()}


def test_identifys_grid_is_damped_by_nielsens_rule_and_diagnoses_by_the_fixed_one(
        quick: tuple[pf.Runs, list[str], list[bool]]) -> None:
    """Every Gauss-Newton run of identify's grid (``runs`` with the default settings) is damped by
    Nielsen's rule; diagnose's grid, by default, by the fixed one (its creep verdict follows the
    damping's path: :data:`afmctl.fit.gridbase.GRID_SETTINGS`)."""
    _, _, rules = quick
    assert rules and all(rules), rules
    assert pf.Settings().gain_ratio_damping
    assert gb.GRID_SETTINGS.gain_ratio_damping is False
    assert dg.Settings().grid_fit is gb.GRID_SETTINGS
    assert inspect.signature(gb.judge).parameters["settings"].default is gb.GRID_SETTINGS
