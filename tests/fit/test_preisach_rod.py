"""The Preisach grid's rod search (afmctl.fit.preisach_solver.rod_rivals), on the independent
Preisach plant (tests/harness/preisach_plant.py: its rod is at 700 Hz)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmctl.fit import preisach as pf
from afmctl.fit import preisach_solver as ps
from tests.fit.test_preisach_fit import data_of
from tests.harness.preisach_plant import PreisachStage, standard_sweeps

pytestmark = pytest.mark.slow  # a creep fit of the grid: a minute or two

TRUE_HZ = PreisachStage().natural_hz


@pytest.fixture(scope="module")
def fitted() -> pf.Runs:
    """The plant with creep of 1.5 % per decade, its standard set, and the grid fitted with creep
    (on the polarization, one start assignment)."""
    data = data_of(standard_sweeps(PreisachStage(seed=3, creep_per_element=0.0075)))
    runs = pf.runs(data, [("positive",) * 3], (2000.0, 0.3), pf.Settings(), lambda _m: None,
                   on_force=False, creep_above=0.0)
    assert runs.crept is not None
    return runs


def _hz(th: pf.Theta) -> float:
    return math.exp(th.log_fn)


def _with_rod(th: pf.Theta, hz: float, zeta: float) -> pf.Theta:
    out = th.copy()
    out.log_fn, out.log_zeta = math.log(hz), math.log(zeta)
    return out


@pytest.mark.parametrize(("hz", "zeta"), [(8000.0, 0.008), (300.0, 0.1), (3000.0, 0.3)])
def test_a_wrong_rod_under_weights_fitted_with_the_true_one_is_found_and_has_no_rival(
        fitted: pf.Runs, hz: float, zeta: float) -> None:
    """The weights and creep fitted with the rod free (it ends within 2 % of the plant's 700 Hz),
    the rod then set wrong: the coarse search and polish find the plant's rod again, and no rival is
    offered (every other rod misses far more with these weights)."""
    assert fitted.crept is not None
    th = fitted.crept.theta
    assert abs(_hz(th) / TRUE_HZ - 1.0) < 0.02
    found = ps.rod_rivals(fitted.problem, _with_rod(th, hz, zeta))
    assert len(found) == 1
    assert abs(_hz(found[0]) / TRUE_HZ - 1.0) < 0.02


def test_weights_fitted_with_a_wrong_rod_keep_it_and_the_true_one_is_offered_as_rival(
        fitted: pf.Runs) -> None:
    """The weights and creep fitted from nothing with the rod started at 8 kHz: Gauss-Newton keeps
    a rod near 9 kHz, 2x and more the noise on some sweep; with those weights held that rod misses
    less than the plant's, so the search keeps it first, and offers the plant's as the rival;
    fitted again from each, the rival's fit is at the noise and the kept one is not."""
    prob, pen, lam = fitted.problem, fitted.penalty, fitted.smoothing
    assert fitted.crept is not None
    start = _with_rod(fitted.crept.theta, 8000.0, 0.008)
    start.w, start.r = np.zeros_like(start.w), 0.0
    stuck = ps.gauss_newton(prob, start, pen, lam, True, 20, gain_ratio=True)
    assert _hz(stuck.theta) > 5.0 * TRUE_HZ
    assert float(np.max(prob.ratios(stuck.theta))) > 2.0
    kept, *rivals = ps.rod_rivals(prob, stuck.theta)
    assert _hz(kept) > 5.0 * TRUE_HZ
    assert len(rivals) == 1 and abs(_hz(rivals[0]) / TRUE_HZ - 1.0) < 0.05
    again = [ps.gauss_newton(prob, th, pen, lam, True, 20, gain_ratio=True)
             for th in (kept, rivals[0])]
    assert again[1].cost < 0.5 * again[0].cost
    assert float(np.max(prob.ratios(again[1].theta))) < 1.2
    assert abs(_hz(again[1].theta) / TRUE_HZ - 1.0) < 0.02


def test_a_creep_fit_started_on_a_wrong_rod_ends_at_the_plants_rod(fitted: pf.Runs) -> None:
    """``_crept`` (identify's creep fit) warm-started from weights and creep of nothing and the rod
    at 8 kHz: its own steps keep a rod near 9 kHz (the test above); the steps it takes again
    from the search's rival end at the plant's rod, at the noise, and that fit is the one it
    returns."""
    assert fitted.crept is not None
    prob = fitted.problem
    start = _with_rod(fitted.crept.theta, 8000.0, 0.008)
    start.w, start.r, start.c = np.zeros_like(start.w), 0.0, np.zeros_like(start.c)
    run = pf._crept(pf.Fitted(prob, prob), fitted.plain.theta, fitted.penalty, fitted.smoothing,
                    pf.Settings(), warm=start)
    assert abs(_hz(run.theta) / TRUE_HZ - 1.0) < 0.02
    assert float(np.max(prob.ratios(run.theta))) < 1.2
