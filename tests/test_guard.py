"""The guard refuses, with a message, every voltage, slew or current violation; it never clips."""

from __future__ import annotations

import numpy as np
import pytest

from afmctl import guard

LIM = guard.Limits(v_min=-150, v_max=150, slew_v_per_ms=80, current_ma=100, capacitance_uf=2)


def test_usable_rate_is_the_smaller_of_slew_and_current_over_capacitance() -> None:
    assert LIM.max_rate_v_per_ms == pytest.approx(50.0)  # 100 mA / 2 uF


@pytest.mark.parametrize(("wave", "start", "match"), [
    (np.array([0.0, 10.0, 151.0]), None, "sample 2 is 151.000 V, above"),
    (np.array([0.0, -150.5]), None, "sample 1 is -150.500 V, below"),
    (np.array([0.0, 5.1]), None, r"step 0 changes at 51.00 V/ms \(stack current 102.0 mA\)"),
    (np.array([5.1, 5.1]), 0.0, "step 0 changes at 51.00 V/ms"),
    (np.array([0.0, np.nan]), None, "sample 1 is not a finite number"),
    (np.array([]), None, "empty"),
])
def test_violations_are_refused(wave: np.ndarray, start: float | None, match: str) -> None:
    with pytest.raises(guard.LimitError, match=match):
        guard.check(wave, 1e-4, LIM, start)


def test_within_limits_passes_and_input_is_untouched() -> None:
    v = np.linspace(-150, 150, 60_001)  # 0.05 V per 0.1 ms = 0.5 V/ms... well inside
    before = v.copy()
    guard.check(v, 1e-4, LIM, start_v=-150.0)
    np.testing.assert_array_equal(v, before)


@pytest.mark.parametrize("bad", [dict(v_min=10, v_max=-10), dict(slew_v_per_ms=0),
                                 dict(current_ma=-1), dict(capacitance_uf=float("inf"))])
def test_inverted_or_nonpositive_limits_are_rejected(bad: dict[str, float]) -> None:
    args = dict(v_min=-150, v_max=150, slew_v_per_ms=50, current_ma=100, capacitance_uf=2)
    args.update(bad)
    with pytest.raises(ValueError):
        guard.Limits(**args)
