"""Sweep designs labs use, to drive a foreign stage (:mod:`afmctl.drivers.device.foreign.stage`).

Each design is a list of :class:`SweepPlan` (voltage samples at one sample rate). Waveforms are
piecewise linear between turning points at a constant slew rate ``2 (v_hi - v_lo) f`` (a
triangle of frequency ``f``), starting at the low end. Sample rates are drawn from ``RATES_HZ``
with at least ``MIN_SAMPLES_PER_PERIOD`` samples per period of the sweep, so they differ between
sweeps of one set.

Designs
-------
``unipolar``      0 .. v_max: slow nested loops, a mid and a fast triangle.
``semi-bipolar``  v_min (< 0) .. v_max, the same three (the fast one may stay above v_min).
``offset``        4 triangles over windows of 0 .. v_max at different offsets and frequencies.
``nested``        slow and mid nested minor loops, a fast triangle.
``standard``      the paper's 0.279 Hz (nested loops), 5.58 Hz and 27.9 Hz, at 1, 5 and 10 kHz.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
RATES_HZ = (1000.0, 2000.0, 2500.0, 5000.0, 10000.0)
MIN_SAMPLES_PER_PERIOD = 300
MAX_SAMPLES_PER_PERIOD = 20000
DESIGNS = ("unipolar", "semi-bipolar", "offset", "nested", "standard")


@dataclass(frozen=True)
class SweepPlan:
    """One sweep to record.

    Parameters
    ----------
    name : str
        File stem, e.g. ``sweep_1_0.279Hz``.
    frequency_hz : float
        Frequency of the triangle the slew rate belongs to, Hz.
    sample_rate_hz : float
        Hz.
    voltage_V : ndarray, shape (N,)
        Commanded voltage per sample, V.
    waveform : str
        ``triangle`` or ``nested``.
    """

    name: str
    frequency_hz: float
    sample_rate_hz: float
    voltage_V: FloatArray
    waveform: str


def ramps(turns: list[float], slew_V_per_s: float, rate_hz: float) -> FloatArray:
    """Piecewise-linear voltage through ``turns`` at a constant slew, sampled at ``rate_hz``.

    The first sample is the first turning point; the last lies at or before the last one.
    """
    turns_arr = np.asarray(turns, dtype=float)
    times = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(turns_arr)) / slew_V_per_s)])
    t = np.arange(int(math.floor(times[-1] * rate_hz)) + 1) / rate_hz
    return np.interp(t, times, turns_arr)


def triangle_turns(lo: float, hi: float, cycles: int) -> list[float]:
    """lo, hi, lo, ... for ``cycles`` full periods."""
    return [lo] + [hi, lo] * cycles


def nested_turns(lo: float, hi: float, levels: int) -> list[float]:
    """A full cycle, then minor loops closing in on the centre: lo, hi, lo, hi_1, lo_1, ..."""
    turns = [lo, hi, lo]
    for i in range(1, levels + 1):
        shrink = 0.5 * (hi - lo) * i / (levels + 1)
        turns += [hi - shrink, lo + shrink]
    return turns


def _rate(rng: np.random.Generator, f: float) -> float:
    ok = [r for r in RATES_HZ if MIN_SAMPLES_PER_PERIOD * f <= r <= MAX_SAMPLES_PER_PERIOD * f]
    return float(rng.choice(ok)) if ok else max(RATES_HZ)


def _plan(index: int, f: float, rate: float, turns: list[float], waveform: str,
          lo: float, hi: float) -> SweepPlan:
    v = ramps(turns, 2.0 * (hi - lo) * f, rate)
    return SweepPlan(f"sweep_{index}_{f:.3g}Hz", f, rate, v, waveform)


def _logu(rng, lo, hi):
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _three(rng, lo, hi, fast_lo, nested_mid=False):
    f1, f2, f3 = _logu(rng, 0.1, 0.5), _logu(rng, 2.0, 8.0), _logu(rng, 15.0, 30.0)
    mid = (nested_turns(lo, hi, int(rng.integers(2, 4))) if nested_mid
           else triangle_turns(lo, hi, int(rng.integers(4, 9))))
    return [
        _plan(1, f1, _rate(rng, f1), nested_turns(lo, hi, int(rng.integers(2, 5))), "nested",
              lo, hi),
        _plan(2, f2, _rate(rng, f2), mid, "nested" if nested_mid else "triangle", lo, hi),
        _plan(3, f3, _rate(rng, f3), triangle_turns(fast_lo, hi, int(rng.integers(6, 16))),
              "triangle", fast_lo, hi),
    ]


def _offset(rng, hi):
    windows = [(0.0, hi), (0.0, 0.6 * hi), (0.4 * hi, hi), (0.2 * hi, 0.8 * hi)]
    freqs = [_logu(rng, 0.1, 0.5), _logu(rng, 1.0, 5.0), _logu(rng, 3.0, 10.0),
             _logu(rng, 10.0, 30.0)]
    plans = []
    for i, ((lo, up), f) in enumerate(zip(windows, freqs, strict=True), 1):
        cycles = 2 if f < 1 else int(rng.integers(4, 12))
        plans.append(_plan(i, f, _rate(rng, f), triangle_turns(lo, up, cycles), "triangle",
                           lo, up))
    return plans


def _standard(lo, hi):
    return [
        _plan(1, 0.279, 1000.0, nested_turns(lo, hi, 2), "nested", lo, hi),
        _plan(2, 5.58, 5000.0, triangle_turns(lo, hi, 4), "triangle", lo, hi),
        _plan(3, 27.9, 10000.0, triangle_turns(lo, hi, 6), "triangle", lo, hi),
    ]


def sweep_set(design: str, v_min: float, v_max: float,
              rng: np.random.Generator) -> list[SweepPlan]:
    """The sweeps of one design, in recording order.

    Parameters
    ----------
    design : str
        One of ``DESIGNS``.
    v_min, v_max : float
        Voltage range, V (``unipolar``, ``offset`` and ``standard`` use 0 .. v_max unless
        ``v_min`` > 0; ``semi-bipolar`` needs ``v_min`` < 0).
    rng : numpy.random.Generator
        Draws frequencies (0.1-30 Hz), cycle counts and sample rates (1-10 kHz).
    """
    if v_max <= max(v_min, 0.0):
        raise ValueError(f"need v_max > max(v_min, 0), got {v_min}, {v_max}")
    lo = max(v_min, 0.0)
    if design == "unipolar":
        return _three(rng, lo, v_max, lo)
    if design == "semi-bipolar":
        if v_min >= 0:
            raise ValueError("semi-bipolar needs v_min < 0")
        fast_lo = v_min if rng.random() < 0.5 else float(rng.uniform(v_min, 0.0))
        return _three(rng, v_min, v_max, fast_lo)
    if design == "offset":
        return _offset(rng, v_max)
    if design == "nested":
        return _three(rng, v_min, v_max, v_min, nested_mid=True)
    if design == "standard":
        return _standard(lo, v_max)
    raise ValueError(f"unknown design {design!r} (one of {', '.join(DESIGNS)})")
