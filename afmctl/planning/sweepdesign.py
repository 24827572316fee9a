"""Sweep set designs: the standard identification set, and one that separates causes (issue 12, point 5).

``standard``: the triangles of :func:`afmctl.files.sweepfile.standard_set`. ``separating``: the same set and
one sweep of holds (relaxation and drift move the stage at constant input), fast steps and a
multisine (a lag, a delay and a second mode differ in magnitude and phase against frequency),
repeated so that each held-out half holds every segment. Pure functions: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from afmctl.files.sweepfile import standard_set

FloatArray = NDArray[np.float64]


#: Sweep set designs: ``standard`` (:func:`standard_set`) and ``separating`` (the same set and one
#: sweep of holds, fast steps and a multisine, :func:`separating_sweep`).
DESIGNS = ("standard", "separating")
#: Name of the separating design's extra sweep.
SEPARATING_NAME = "separating"
#: Fraction of the usable slew rate the fast steps and the multisine may use (the guard's margin).
SLEW_USE = 0.5
#: The multisine's highest tone, as a fraction of the sample rate.
MULTISINE_TOP = 1 / 20


@dataclass(frozen=True)
class Segment:
    """One part of a designed sweep: ``kind`` (ramp, hold, step, multisine, triangle) over the
    samples ``[start, stop)``."""

    kind: str
    start: int
    stop: int


def _ramp(v0: float, v1: float, rate_v_per_s: float, sample_rate_hz: float) -> FloatArray:
    """Samples after ``v0`` up to and ending at ``v1``, each step at most ``rate / sample_rate``."""
    n = max(1, math.ceil(abs(v1 - v0) * sample_rate_hz / rate_v_per_s))
    return v0 + (v1 - v0) * np.arange(1, n + 1) / n


def multisine(bias_v: float, amplitude_v: float, max_rate_v_per_s: float, duration_s: float,
              sample_rate_hz: float, tones: int = 4) -> FloatArray:
    """Sines at ``tones`` frequencies spaced by 3x up to ``MULTISINE_TOP`` of the sample rate, each an
    integer number of cycles in ``duration_s`` (so it starts and ends at ``bias_v``), all with the
    same velocity amplitude (a lag, a delay or a mode's rate term shows equally in each), scaled so
    that the peak excursion is at most ``amplitude_v`` and the slew at most ``max_rate_v_per_s``.

    Returns the voltage, V, ``round(duration_s * sample_rate_hz)`` samples after the start.

    Examples
    --------
    >>> v = multisine(50.0, 10.0, 1e4, 0.2, 10_000.0)
    >>> v.size, bool(abs(v[-1] - 50.0) < 1e-9), bool(np.max(np.abs(v - 50.0)) <= 10.0)
    (2000, True, True)
    """
    n = int(round(duration_s * sample_rate_hz))
    step = 1.0 / duration_s
    f = np.array([max(1, round(sample_rate_hz * MULTISINE_TOP / 3 ** k / step)) * step
                  for k in range(tones)])
    t = np.arange(1, n + 1) / sample_rate_hz
    shape = np.sum(np.sin(2 * np.pi * f[:, None] * t) / f[:, None], axis=0)
    velocity = min(amplitude_v / np.max(np.abs(shape)), max_rate_v_per_s / (2 * np.pi * f.size))
    v = bias_v + velocity * shape
    v[-1] = bias_v
    return v


def separating_sweep(v_range: tuple[float, float], sample_rate_hz: float,
                     max_rate_v_per_s: float, repeats: int = 2
                     ) -> tuple[FloatArray, tuple[Segment, ...]]:
    """A sweep whose segments separate causes that triangles confuse, repeated ``repeats`` times
    (each half of the sweep holds every segment: diagnose fits the first and judges the second).

    One repetition, from the safe output ``v0`` (0 V, or the range's end nearest it):

    * ramp to ``v_hi`` at the 5.58 Hz triangle's slew, **hold** (creep and thermal relaxation move
      the stage at constant voltage; a gain drift does not);
    * fast **steps** (at ``SLEW_USE`` of the usable slew) to 1/2, 3/4 and 1/4 of the range, each
      held: their ringing and the approach to rest separate an amplifier's lag (rounded corner), a
      reading's delay (a shift) and a second mode (a ring at its own frequency), and the holds on
      both branches are minor-loop turning points at three biases;
    * a **multisine** about mid-range (:func:`multisine`, up to ``sample_rate / 20``): gain and phase
      against frequency;
    * ramp to ``v_lo`` and hold (then back to ``v0`` if that is not ``v_lo``).

    Parameters
    ----------
    v_range : (float, float)
        (v_min, v_max), V.
    sample_rate_hz : float
        Hz.
    max_rate_v_per_s : float
        The stage's usable slew rate, V/s (:attr:`afmctl.guard.Limits.max_rate_v_per_ms` x 1000).
    repeats : int

    Returns
    -------
    voltage_v : ndarray
        V, one sample per ``1 / sample_rate_hz``, within ``v_range`` and the slew limit.
    segments : tuple of Segment
    """
    lo, hi = v_range
    span, v0 = hi - lo, min(max(0.0, lo), hi)
    fast = SLEW_USE * max_rate_v_per_s
    slow = min(2 * span * 5.58, fast)
    hold = {"long": 0.1, "short": 0.04}
    plan: list[tuple[str, FloatArray]] = []
    v = v0
    for _ in range(repeats):
        for kind, target, rate, rest in (("ramp", hi, slow, "long"),
                                         ("step", lo + 0.5 * span, fast, "short"),
                                         ("step", lo + 0.75 * span, fast, "short"),
                                         ("step", lo + 0.25 * span, fast, "short"),
                                         ("step", lo + 0.5 * span, fast, "short")):
            plan += [(kind, _ramp(v, target, rate, sample_rate_hz)),
                     ("hold", np.full(int(hold[rest] * sample_rate_hz), target))]
            v = target
        plan.append(("multisine", multisine(v, 0.25 * span, fast, 0.2, sample_rate_hz)))
        plan += [("ramp", _ramp(v, lo, slow, sample_rate_hz)),
                 ("hold", np.full(int(hold["long"] * sample_rate_hz), lo))]
        if v0 != lo:  # a bipolar range: back to the safe output
            plan.append(("ramp", _ramp(lo, v0, slow, sample_rate_hz)))
        v = v0
    parts, segments, k = [np.full(1, v0)], [], 1
    for kind, samples in plan:
        segments.append(Segment(kind, k, k + samples.size))
        parts.append(samples)
        k += samples.size
    return np.concatenate(parts), tuple(segments)


def segments_text(segments: tuple[Segment, ...], sample_rate_hz: float) -> str:
    """The ``segments`` metadata value: ``kind start_s-stop_s`` per segment, ``;`` between."""
    return "; ".join(f"{s.kind} {s.start / sample_rate_hz:.4f}-{s.stop / sample_rate_hz:.4f}"
                     for s in segments)


def design_set(design: str, sample_rate_hz: float, max_rate_v_per_s: float,
               v_range: tuple[float, float]) -> list[tuple[str, float, FloatArray, dict[str, str]]]:
    """The sweeps of ``design`` (one of :data:`DESIGNS`) as (name, frequency_hz, voltage_v, meta):
    :func:`standard_set`, and for ``separating`` also :func:`separating_sweep` (its
    ``frequency_hz`` the repetition rate). ``meta`` gives the design and the segment kinds.

    Examples
    --------
    >>> [n for n, _, _, _ in design_set("separating", 1000.0, 5e4, (0.0, 150.0))][-2:]
    ['minor_loops_0.1hz', 'separating']
    """
    if design not in DESIGNS:
        raise ValueError(f"unknown sweep design {design!r} (one of {', '.join(DESIGNS)})")
    out = [(name, f, v, {"design": design, "segments": "triangle"})
           for name, f, v in standard_set(sample_rate_hz=sample_rate_hz, v_range=v_range)]
    if design == "separating":
        v, segs = separating_sweep(v_range, sample_rate_hz, max_rate_v_per_s)
        reps = 2 * sample_rate_hz / v.size
        out.append((SEPARATING_NAME, reps, v,
                    {"design": design, "segments": segments_text(segs, sample_rate_hz)}))
    return out
