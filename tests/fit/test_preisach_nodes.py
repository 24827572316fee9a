"""The grid's coefficient nodes along the coercive field
(:func:`afmctl.fit.preisach_basis.hat_matrix`, ``Settings.coercive_power`` of
:mod:`afmctl.fit.preisach_problem`), against a classical Preisach operator written here from
relays, independently of the fit's kernel."""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

from afmctl.fit import preisach_basis as pb
from afmctl.fit import preisach_problem as pp
from afmctl.model import preisach as pr
from afmctl.planning import sweepdesign as sd


def relays(v: np.ndarray, step_v: float = 0.5) -> np.ndarray:
    """A classical Preisach operator on 0-100 V (relays 0/1, up at alpha, down at beta, on a
    ``step_v`` grid between whole volts), all down at the start; its density a ridge 3 V wide
    by the diagonal that grows along it, and a broad part 30 V wide. Output in um."""
    g = np.arange(step_v / 2, 100.0, step_v)
    a, b = np.meshgrid(g, g, indexing="ij")
    width, mid = a - b, (a + b) / 2
    mu = np.where(width >= 0, np.exp(-0.5 * ((width - 3.0) / 1.5) ** 2) * (0.3 + mid / 50.0)
                  + 0.15 * np.exp(-0.5 * ((width - 30.0) / 12.0) ** 2), 0.0)
    mu *= 60.0 / mu.sum()
    up = np.zeros(a.shape, bool)
    out = np.empty(v.size)
    for k, x in enumerate(v):
        up |= a <= x
        up &= ~(b >= x)
        out[k] = mu[up].sum()
    return out


def reversal_curves() -> np.ndarray:
    """Up to 100 V, then down to a falling sequence of reversals and back up, then loops inside
    the range: 1 V a sample, on whole volts (the relays switch between samples)."""
    nodes = [0.0, 100.0]
    for lo in (80.0, 62.0, 45.0, 30.0, 17.0, 6.0):
        nodes += [lo, 100.0]
    nodes += [20.0, 70.0, 35.0, 60.0, 40.0, 85.0, 50.0]
    return np.concatenate([np.arange(p, q, 1.0 if q > p else -1.0)
                           for p, q in zip(nodes[:-1], nodes[1:])] + [[nodes[-1]]])


def static_misfit(power: float, v: np.ndarray, u: np.ndarray) -> float:
    """RMS (um) of the best non-negative fit of the 16 x 24 coefficients (nodes at ``power``),
    a reversible slope and a free offset to ``u``, after the first visit of 100 V."""
    settings = pp.Settings()
    field = v / 100.0  # MV/m on a 100 um layer
    ec, ei, spread = pp.make_grid([field], settings)
    grid = pb.Grid(ec, ei, spread, pb.hat_matrix(ec.size, 16, power),
                   pb.hat_matrix(ei.size, 24), np.arange(16 * 24))
    cols, _ = pb.basis(field, grid, pr.start_outputs(ec, "negative"))
    judged = np.arange(v.size) >= int(np.argmax(v >= 100.0))
    a = np.column_stack((cols, field, np.ones(v.size), -np.ones(v.size)))[judged]
    x, _ = nnls(a, u[judged], maxiter=20 * a.shape[1])
    return float(np.sqrt(np.mean((a @ x - u[judged]) ** 2)))


def test_nodes_close_at_small_coercive_fields_follow_a_ridge_by_the_diagonal() -> None:
    """The same 16 coercive coefficients, their nodes at ``(k / 15)**1.5`` of the rows instead
    of equally spaced, fit the reversal curves and inner loops of a stage whose density has a
    ridge 3 V wide by the diagonal at least three times closer, without noise, rod or map (the
    equally spaced hats are 3.3 V apart here: the ridge falls inside the first)."""
    v = reversal_curves()
    u = relays(v)
    even, close = static_misfit(1.0, v, u), static_misfit(pp.Settings().coercive_power, v, u)
    assert close < even / 3.0, (even, close)
    assert close < 0.01, close  # um, on a 60 um stroke (0.032 um equally spaced)


def test_the_nodes_of_power_one_are_equally_spaced() -> None:
    m = pb.hat_matrix(64, 16, 1.0)
    peaks = np.argmax(m, axis=0)
    assert set(np.diff(peaks)) <= {4, 5}  # 63 rows / 15 spacings
    np.testing.assert_allclose(m.sum(axis=1), 1.0)
    close = pb.hat_matrix(64, 16, 1.5)
    np.testing.assert_allclose(close.sum(axis=1), 1.0)
    assert (close >= 0).all() and np.all(np.diff(np.argmax(close, axis=0)) >= 1)
    assert np.argmax(close[:, 1]) == 1  # the second node one row from the first


def test_the_reversal_curves_have_the_inner_loops_that_earn_the_close_nodes() -> None:
    """The grid gets the close nodes from a set with :data:`CLOSE_NODES_LOOPS` inner loops
    (:func:`afmctl.fit.preisach.runs`): the reversal curves of ``afmctl sweep --design
    reversals`` have them, the standard set has not, unipolar or bipolar (its nested loops)."""
    for v_range in ((0.0, 150.0), (-150.0, 150.0)):
        standard = [v / 100.0 for _, _, v in sd.standard_set(sample_rate_hz=10_000.0,
                                                              v_range=v_range)]
        curves = sd.reversals_sweep(v_range, 10_000.0, 1_670.0)[2] / 100.0
        assert pp.interior_loops(standard) < pp.CLOSE_NODES_LOOPS
        assert pp.interior_loops(standard + [curves]) >= pp.CLOSE_NODES_LOOPS
