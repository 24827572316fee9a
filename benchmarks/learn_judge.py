"""Learning judged under run-to-run gain variation (issue 13, point 7), for any plant.

Shared by :mod:`bench_learn` (afmctl's emulated stage, gain ``1 + sigma N(0, 1)`` per run) and
:mod:`foreign_learn` (the foreign plant's :class:`~afmctl.drivers.device.foreign.effects.GainDrift`,
a random gain per run on a systematic drift). The plant enters as ``respond(voltage_V, gain)``:
its true position (um, in the frame learning is judged in) at every sample of a run from rest at
the given applied-voltage gain.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from afmctl.experiment import learn
from afmctl.planning import ilc, track

#: Settled: expected error within this factor of the gain variation's floor.
SETTLE_FACTOR = 1.5
#: Iterations on a stage with run-to-run gain variation (to show it settles, not diverges).
GAIN_ITERATIONS = 8

Respond = Callable[[np.ndarray, float], np.ndarray]
Spread = Callable[[learn.Result], tuple[float, list[float]]]


def true_rms(position: np.ndarray, it: learn.Iteration, desired: track.Desired) -> float:
    """RMS true error of one iteration at the samples, first period excluded (um)."""
    err = position[it.outcome.waveform.tracking] - desired.u_um
    return float(np.sqrt(np.mean(err[ilc.steady_part(desired)] ** 2)))


def gain_spread(respond: Respond, desired: track.Desired, center: float, sigma: float,
                res: learn.Result) -> tuple[float, list[float]]:
    """The gain variation's floor and each iteration's expected error under it (um).

    Floor: the true RMS error a perfect waveform (one that puts the stage on the trajectory at
    the gain ``center``) still makes when a run's gain is ``center (1 +- sigma)``: the
    difference of the stage's true positions at those gains and at ``center``, on the kept
    waveform (it hardly depends on which). Expected error of a waveform: its true RMS error at
    ``center (1 +- sigma)`` (the two-point rule: exact for the mean square to second order in
    the gain), what it makes on average over runs drawn from that spread.
    """
    steady = ilc.steady_part(desired)
    gains = (center, center * (1 + sigma), center * (1 - sigma))

    def positions(wf: track.Waveform) -> dict[float, np.ndarray]:
        return {g: respond(wf.voltage_v, g)[wf.tracking][steady] for g in gains}

    pos = positions(res.best_iteration.outcome.waveform)
    floor = np.concatenate([pos[g] - pos[center] for g in gains[1:]])
    expected = []
    for it in res.iterations:
        p = positions(it.outcome.waveform)
        err = np.concatenate([p[g] - desired.u_um[steady] for g in gains[1:]])
        expected.append(float(np.sqrt(np.mean(err**2))))
    return float(np.sqrt(np.mean(floor**2))), expected


def variation_row(spread: Spread, res: learn.Result, continued: Spread, c_res: learn.Result,
                  trend: bool = False) -> dict[str, Any]:
    """The row keys of a stage with run-to-run gain variation and its verdict ``ok``.

    ``res`` is learning as shipped, ``c_res`` learning continued past the floor (its floor stop
    off) for :data:`GAIN_ITERATIONS`; ``spread`` and ``continued`` give each one's floor and expected
    errors (:func:`gain_spread`). Settled: the kept and the last iteration's expected error
    within ``SETTLE_FACTOR`` x the floor; no divergence: no iteration's expected error above
    1.2 x the best before it and neither run ended as diverging or refused. Continued past the
    floor, a gain that varies at random about a fixed mean must keep every iteration from 1 on
    within ``SETTLE_FACTOR`` x the floor (``trend`` False); one with a systematic trend
    (``trend`` True) starts the continued run from the model again, at a gain the trend has
    moved since the sweeps, and must come down to ``SETTLE_FACTOR`` x its own runs' floor by
    the last iteration without an iteration above 1.2 x the best before it.
    """
    floor, expected = spread(res)
    c_floor, c_expected = continued(c_res)
    if not trend:
        c_floor = floor
    ok = (len(expected) > 1 and len(c_expected) > 1
          and max(expected[res.best], expected[-1]) <= SETTLE_FACTOR * floor
          and not_diverging(expected)
          and not res.stop.startswith(("diverging", "refused"))
          and not c_res.stop.startswith(("diverging", "refused"))
          and (not_diverging(c_expected) and c_expected[-1] <= SETTLE_FACTOR * c_floor
               if trend else max(c_expected[1:]) <= SETTLE_FACTOR * floor))
    continued_target = (
        f"comes down to {SETTLE_FACTOR:g} x its own runs' floor by the last iteration, no "
        "iteration above 1.2 x the best before it (the gain's trend moved it since the sweeps)"
        if trend else f"every iteration from 1 on within {SETTLE_FACTOR:g} x the floor")
    return {
        "variation_floor_um": floor, "expected_rms_um_by_iteration": expected,
        "expected_over_floor_by_iteration": [x / floor for x in expected],
        "continued_variation_floor_um": c_floor,
        "continued_expected_over_floor_by_iteration": [x / c_floor for x in c_expected],
        "continued_stop": c_res.stop,
        "target": (f"settles: the expected RMS (over the gain spread) of the kept and of the "
                   f"last iteration within {SETTLE_FACTOR:g} x variation_floor_um; no "
                   "divergence: no iteration's expected RMS above 1.2 x the best before it, "
                   "learning not ended as diverging or refused, and continued past the floor "
                   f"({GAIN_ITERATIONS} iterations, floor stop off, not ended as diverging): "
                   + continued_target),
        "ok": bool(ok)}


def not_diverging(expected: list[float]) -> bool:
    """No iteration's error above 1.2 x the best before it (learning's own divergence rule)."""
    return all(x <= 1.2 * min(expected[:i]) for i, x in enumerate(expected) if i)
