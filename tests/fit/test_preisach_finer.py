"""The lighter smoothings tried after the held-out choice (:func:`afmctl.fit.preisach._finer`),
with the fits at each smoothing replaced by a table of held-out errors: which it keeps, where it
stops, what it says."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from afmctl.fit import preisach as pf
from afmctl.fit import preisach_problem as pp

NOISE = np.array([0.02, 0.02])


def walk(held: dict[float, list[float]], lam: float, monkeypatch: pytest.MonkeyPatch,
         loops: int = pp.CLOSE_NODES_LOOPS
         ) -> tuple[float, list[float], list[str], dict[float, float]]:
    """``_finer`` from ``lam`` with each smoothing's held-out RMS / noise per sweep from
    ``held``: the smoothing kept, those refitted in order, what it said, the scores."""
    tried: list[float] = []

    def polished(prob: Any, th: Any, pen: Any, lam_: float, creep: bool, settings: Any
                 ) -> tuple[Any, np.ndarray, Any]:
        tried.append(lam_)
        return SimpleNamespace(theta=lam_), np.asarray(held[lam_]) * NOISE, None

    monkeypatch.setattr(pf, "_polished", polished)
    said: list[str] = []
    prob = SimpleNamespace(data=SimpleNamespace(noise=NOISE), interior_loops=loops)
    run, kept, per, scores, _ = pf._finer(prob, None, None, lam, False,  # type: ignore[arg-type]
                                          pf.Settings(), said.append)
    assert run.theta == kept and np.allclose(per, np.asarray(held[kept]) * NOISE)
    return kept, tried, said, scores


def test_each_lighter_smoothing_is_kept_while_it_is_better_held_out(
        monkeypatch: pytest.MonkeyPatch) -> None:
    held = {1e-4: [1.2, 2.3], 1e-5: [1.1, 1.6], 1e-6: [1.05, 1.4], 1e-7: [1.05, 1.45],
            1e-8: [1.0, 1.0]}
    kept, tried, said, scores = walk(held, 1e-4, monkeypatch)
    # 1e-7 is worse than 1e-6: the walk stops there, and never sees 1e-8's better figure
    assert kept == 1e-6 and tried == [1e-4, 1e-5, 1e-6, 1e-7]
    assert len(said) == 3 and said[-1].endswith("(kept 1e-06)")
    assert scores[1e-6] == pytest.approx(1.05 ** 2 + 1.4 ** 2)


def test_nothing_lighter_is_tried_once_every_sweep_is_within_the_floor(
        monkeypatch: pytest.MonkeyPatch) -> None:
    held = {1e-5: [1.02, 1.09], 1e-6: [1.0, 1.0]}
    kept, tried, said, _ = walk(held, 1e-5, monkeypatch)
    assert kept == 1e-5 and tried == [1e-5] and said == []


def test_a_gain_under_one_percent_keeps_the_heavier_smoothing(
        monkeypatch: pytest.MonkeyPatch) -> None:
    held = {1e-6: [1.0, 1.5], 1e-7: [1.0, 1.497]}
    kept, tried, _, _ = walk(held, 1e-6, monkeypatch)
    assert kept == 1e-6 and tried == [1e-6, 1e-7]


def test_the_walk_goes_down_to_the_finest(monkeypatch: pytest.MonkeyPatch) -> None:
    held = {1e-6: [1.3, 2.0], 1e-7: [1.2, 1.8], 1e-8: [1.1, 1.6]}
    kept, tried, _, _ = walk(held, 1e-6, monkeypatch)
    assert kept == 1e-8 and tried == [1e-6, 1e-7, 1e-8]
    assert min(pf.Settings().finer_smoothing) == 1e-8


def test_a_set_without_the_reversal_curves_keeps_the_chosen_smoothing(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Measured only with the curves: on three triangles the chosen fit is kept as it was."""
    held = {1e-5: [1.3, 2.0], 1e-6: [1.0, 1.0]}
    kept, tried, said, _ = walk(held, 1e-5, monkeypatch, loops=pp.CLOSE_NODES_LOOPS - 1)
    assert kept == 1e-5 and tried == [1e-5] and said == []
