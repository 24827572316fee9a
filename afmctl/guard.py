"""The waveform guard: nothing outside the stage's voltage, slew or current limits is ever sent.

A piezo stack is a capacitor: the amplifier must supply ``I = C dV/dt``, so the usable slew rate is
the smaller of the amplifier's slew limit and ``I_max / C``. Violations are refused with a message
that says where and by how much; the guard never clips.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from afmctl.errors import LimitError


@dataclass(frozen=True)
class Limits:
    """Electrical limits of a stage.

    Parameters
    ----------
    v_min, v_max : float
        Output voltage range, V (v_min < v_max).
    slew_v_per_ms : float
        Amplifier slew-rate limit, V/ms (> 0).
    current_ma : float
        Amplifier output-current limit, mA (> 0).
    capacitance_uf : float
        Stack capacitance, uF (> 0).
    """

    v_min: float
    v_max: float
    slew_v_per_ms: float
    current_ma: float
    capacitance_uf: float

    def __post_init__(self) -> None:
        values = (self.v_min, self.v_max, self.slew_v_per_ms, self.current_ma, self.capacitance_uf)
        if not all(np.isfinite(values)):
            raise ValueError("limits must be finite")
        if not self.v_min < self.v_max:
            raise ValueError(f"v_min ({self.v_min} V) must be below v_max ({self.v_max} V)")
        if min(self.slew_v_per_ms, self.current_ma, self.capacitance_uf) <= 0:
            raise ValueError("slew, current and capacitance limits must be > 0")

    def max_step_v(self, sample_rate_hz: float) -> float:
        """Largest change between consecutive samples that the slew limit allows, V."""
        return self.slew_v_per_ms * 1e3 / sample_rate_hz

    @property
    def max_rate_v_per_ms(self) -> float:
        """Usable slew rate: min(slew limit, I_max / C), V/ms (mA / uF = V/ms)."""
        return min(self.slew_v_per_ms, self.current_ma / self.capacitance_uf)


def slew_v_per_ms(voltage_v: NDArray[np.float64], dt_s: float,
                  start_v: float | None = None) -> NDArray[np.float64]:
    """Sample-to-sample rate |dV|/dt, V/ms; with ``start_v`` the first step from it is included."""
    v = np.asarray(voltage_v, dtype=float)
    if start_v is not None:
        v = np.concatenate([[start_v], v])
    return np.abs(np.diff(v)) / (dt_s * 1e3)


def check(voltage_v: NDArray[np.float64], dt_s: float, limits: Limits,
          start_v: float | None = None, what: str = "waveform") -> None:
    """Raise :class:`LimitError` unless every sample and every step is within ``limits``.

    Parameters
    ----------
    voltage_v : ndarray
        Samples to be sent, V, one every ``dt_s`` seconds.
    start_v : float, optional
        The stage's present output; the step from it to the first sample is checked too.
    """
    v = np.asarray(voltage_v, dtype=float)
    if v.size == 0:
        raise LimitError(f"{what}: empty")
    bad = np.flatnonzero(~np.isfinite(v))
    if bad.size:
        raise LimitError(f"{what}: sample {bad[0]} is not a finite number")
    lo, hi = int(np.argmin(v)), int(np.argmax(v))
    if v[lo] < limits.v_min:
        raise LimitError(f"{what}: sample {lo} is {v[lo]:.3f} V, below the limit {limits.v_min} V")
    if v[hi] > limits.v_max:
        raise LimitError(f"{what}: sample {hi} is {v[hi]:.3f} V, above the limit {limits.v_max} V")
    rate = slew_v_per_ms(v, dt_s, start_v)
    k = int(np.argmax(rate))
    if rate[k] > limits.max_rate_v_per_ms * (1 + 1e-12):
        current = rate[k] * limits.capacitance_uf
        raise LimitError(
            f"{what}: step {k} changes at {rate[k]:.2f} V/ms (stack current {current:.1f} mA); "
            f"the limit is {limits.max_rate_v_per_ms:.2f} V/ms (slew {limits.slew_v_per_ms} V/ms, "
            f"{limits.current_ma} mA into {limits.capacitance_uf} uF)")
