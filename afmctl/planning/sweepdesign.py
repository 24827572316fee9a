"""Sweep set designs: the standard identification set, and one that separates causes.

``standard``: the paper's triangles and nested minor loops (:func:`standard_set`, built from
:func:`voltage_triangle`, :func:`loop` and :func:`nested_loops`). ``separating``: the same set and
one sweep of holds (relaxation and drift move the stage at constant input), fast steps and a
multisine (a lag, a delay and a second mode differ in magnitude and phase against frequency),
repeated so that each held-out half holds every segment. Pure functions: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: The paper's triangle frequencies (Figs. 2 and 7), Hz.
STANDARD_FREQUENCIES_HZ = (0.279, 5.58, 27.9)


def voltage_triangle(frequency_hz: float, amplitude_v: float, cycles: float,
                     sample_rate_hz: float) -> FloatArray:
    """A voltage triangle 0 -> +A -> -A -> 0 per cycle, sampled at ``sample_rate_hz``.

    ``amplitude_v`` is the peak, half the peak-to-peak: a sweep's waveform. The trajectories a stage
    tracks are :func:`afmctl.planning.track.triangle`, whose amplitude is peak to peak (um).

    Parameters
    ----------
    frequency_hz : float
        Hz.
    amplitude_v : float
        Peak voltage, V.
    cycles : float
        Number of periods.
    sample_rate_hz : float
        Hz.

    Returns
    -------
    ndarray, shape (round(cycles * sample_rate_hz / frequency_hz) + 1,)
        Voltage, V.

    Examples
    --------
    >>> v = voltage_triangle(1.0, 2.0, 1, 8.0)
    >>> v.tolist()
    [0.0, 1.0, 2.0, 1.0, 0.0, -1.0, -2.0, -1.0, 0.0]
    """
    n = int(round(cycles * sample_rate_hz / frequency_hz))
    phase = (np.arange(n + 1) * frequency_hz / sample_rate_hz + 0.25) % 1.0
    return amplitude_v * (1.0 - 4.0 * np.abs(phase - 0.5))


def loop(frequency_hz: float, v_lo: float, v_hi: float, cycles: float, sample_rate_hz: float,
         start_v: float = 0.0) -> FloatArray:
    """Triangle cycles ``start -> v_hi -> v_lo -> start`` at one constant rate, any voltage range.

    ``start_v`` (clipped into [v_lo, v_hi]) is where each cycle starts and ends: the stage's safe
    output 0 V, so a sweep starts where the stage is, on a unipolar (0-150 V), semi-bipolar
    (-30-150 V) or bipolar range alike. ``loop(f, -A, A, ...)`` is :func:`voltage_triangle`.

    Returns the voltage, V, ``round(cycles * sample_rate_hz / frequency_hz) + 1`` samples.

    Examples
    --------
    >>> loop(1.0, 0.0, 2.0, 1, 8.0).tolist()
    [0.0, 0.5, 1.0, 1.5, 2.0, 1.5, 1.0, 0.5, 0.0]
    """
    v0 = min(max(start_v, v_lo), v_hi)
    span = v_hi - v_lo
    n = int(round(cycles * sample_rate_hz / frequency_hz))
    phase = (np.arange(n + 1) * frequency_hz / sample_rate_hz) % 1.0
    up = (v_hi - v0) / (2 * span)  # fraction of a cycle spent rising to v_hi
    nodes = [0.0, up, up + 0.5, 1.0]
    v = np.interp(phase, nodes, [v0, v_hi, v_lo, v0])
    if float(cycles).is_integer():  # n samples hold only about ``cycles`` periods: end at the
        v[-1] = v0  # start exactly (27.9 Hz at 10 kHz ended 0.384 V short of 0 V)
    return v


def nested_loops(frequency_hz: float, amplitude_v: float | None, levels: int,
                 sample_rate_hz: float,
                 v_range: tuple[float, float] | None = None) -> FloatArray:
    """Nested minor loops (paper Fig. 1(b)): one loop per level, each from 0 V up, down and back,
    the excursions shrinking linearly from the full range to ``1 / levels`` of it.

    ``v_range`` (V) defaults to ``(-amplitude_v, amplitude_v)``. Returns the voltage, V, sampled
    at ``sample_rate_hz``.
    """
    lo, hi = v_range if v_range is not None else (-float(amplitude_v), float(amplitude_v))
    v0 = min(max(0.0, lo), hi)
    parts = []
    for i in range(levels):
        s = (levels - i) / levels
        parts.append(loop(frequency_hz, v0 + s * (lo - v0), v0 + s * (hi - v0), 1,
                          sample_rate_hz, v0)[:-1])
    return np.concatenate(parts + [np.full(1, v0)])


def standard_set(amplitude_v: float = 150.0, sample_rate_hz: float = 10_000.0,
                 minor_loop_hz: float = 0.1, minor_levels: int = 4,
                 v_range: tuple[float, float] | None = None
                 ) -> list[tuple[str, float, FloatArray]]:
    """The standard identification set as (name, frequency_hz, voltage_v) triples.

    Triangle sweeps at 0.279 Hz (2 cycles), 5.58 Hz (5 cycles) and 27.9 Hz (10 cycles), as in
    Fig. 2 / Fig. 7 of the paper, then the nested minor loops of Fig. 1(b) at ``minor_loop_hz``.
    They cover ``v_range`` = (v_min, v_max) V (default ``(-amplitude_v, amplitude_v)``): a
    unipolar, semi-bipolar or bipolar amplifier's range, every sweep starting and ending at 0 V
    (or the range's end nearest it). The first three are what :func:`afmctl.fit.identify.fit` is
    benchmarked on.

    Examples
    --------
    >>> [name for name, _, _ in standard_set(sample_rate_hz=1000.0)]
    ['triangle_0.279hz', 'triangle_5.58hz', 'triangle_27.9hz', 'minor_loops_0.1hz']
    >>> v = standard_set(v_range=(0.0, 150.0))[2][2]
    >>> float(v[0]), float(v.min()), round(float(v.max()), 1)
    (0.0, 0.0, 150.0)
    """
    lo, hi = v_range if v_range is not None else (-amplitude_v, amplitude_v)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(f"the voltage range must be finite with v_min < v_max, got [{lo}, {hi}]")
    cycles = {0.279: 2, 5.58: 5, 27.9: 10}
    out = [(f"triangle_{f:g}hz", f, loop(f, lo, hi, cycles[f], sample_rate_hz))
           for f in STANDARD_FREQUENCIES_HZ]
    out.append((f"minor_loops_{minor_loop_hz:g}hz", minor_loop_hz,
                nested_loops(minor_loop_hz, None, minor_levels, sample_rate_hz, (lo, hi))))
    return out



#: Sweep set designs: ``standard`` (:func:`standard_set`), ``separating`` (the same set and one
#: sweep of holds, fast steps and a multisine, :func:`separating_sweep`) and ``reversals`` (the same
#: set and first-order reversal curves, :func:`reversal_curves`: a stage off the paper's model
#: family, whose Preisach grid needs reversal points inside the range) and ``full`` (the set, the
#: separating sweep and the reversal curves: a lab's first calibration, which cannot yet know
#: whether its stage is of the paper's family).
DESIGNS = ("standard", "separating", "reversals", "full")
#: Name of the separating design's extra sweep.
SEPARATING_NAME = "separating"
#: Name of the reversals design's extra sweep, and its reversal voltages per kind.
REVERSALS_NAME = "reversals"
REVERSAL_LEVELS = 7
#: The interior loops' centres and first half-amplitudes (shares of the range), and the
#: reversals about each, the half-amplitude shrinking linearly to :data:`INTERIOR_LAST`.
INTERIOR_CENTRES = ((0.5, 0.5), (0.3, 0.3), (0.7, 0.3))
INTERIOR_REVERSALS = 7
INTERIOR_LAST = 0.06
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
    out = v0 + (v1 - v0) * np.arange(1, n + 1) / n
    out[-1] = v1  # exactly, not by round-off
    return out


def _through(nodes: list[float], rate_v_per_s: float, sample_rate_hz: float) -> FloatArray:
    """Ramps at one slew from ``nodes[0]`` through each node in turn (``nodes[0]`` included)."""
    parts = [np.full(1, nodes[0])] + [_ramp(a, b, rate_v_per_s, sample_rate_hz)
                                      for a, b in zip(nodes[:-1], nodes[1:], strict=True) if a != b]
    return np.concatenate(parts)


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


def reversal_curves(v_range: tuple[float, float], sample_rate_hz: float, rate_v_per_s: float,
                    levels: int = REVERSAL_LEVELS) -> FloatArray:
    """First-order reversal curves of both kinds at one constant slew, from and back to the safe
    output ``v0`` (0 V, or the range's end nearest it): from ``v_lo`` up to each of ``levels``
    reversal voltages evenly inside the range and back down, then from ``v_hi`` down to each and
    back up. A Preisach-type stage's density is its second derivative over the (up, down)
    reversal pairs: triangles over the whole range show only the pairs of the major loop, and a
    density fitted to them is the smoothing's guess everywhere inside it (a minor loop of a
    tracking triangle, 50 <-> 117 V on a 0-150 V Preisach stage, was then 0.6 um off a model
    at 1.1x its noise on the triangles).

    Returns the voltage, V, at ``sample_rate_hz``, each step at most ``rate_v_per_s /
    sample_rate_hz``.

    Examples
    --------
    >>> v = reversal_curves((0.0, 150.0), 1000.0, 3000.0, levels=3)
    >>> float(v[0]), float(v[-1]), float(v.min()), float(v.max())
    (0.0, 0.0, 0.0, 150.0)
    """
    lo, hi = v_range
    v0 = min(max(0.0, lo), hi)
    inner = lo + (hi - lo) * np.arange(1, levels + 1) / (levels + 1)
    nodes = [v0, lo]
    for a in inner:
        nodes += [float(a), lo]
    nodes.append(hi)
    for b in inner[::-1]:
        nodes += [float(b), hi]
    nodes.append(v0)
    return _through(nodes, rate_v_per_s, sample_rate_hz)


def interior_loops(v_range: tuple[float, float], sample_rate_hz: float, rate_v_per_s: float
                   ) -> FloatArray:
    """Reversals inside the range, at one constant slew, from and back to the safe output
    ``v0`` (the first of each centre may touch an end of the range): about each of
    :data:`INTERIOR_CENTRES` (shares of the range) an oscillation of :data:`INTERIOR_REVERSALS`
    reversals, above and below the centre in turn, whose half-amplitude shrinks linearly to
    :data:`INTERIOR_LAST` of the range (higher-order reversal curves).

    First-order reversal curves fix a Preisach operator's density, but not a static map after
    it: any family of such curves is some Preisach operator's, so a stage whose force is not
    affine in its hysteretic output (the rod's ``a2``, ``a3``; a modified Prandtl-Ishlinskii
    stage's polynomial map) is fitted as well by a density warped to make up for a wrong map.
    The two differ on loops whose two ends both lie inside the range (the map makes them
    non-congruent): a raster's fast line, a tracking triangle. On the family plant's unipolar
    Prandtl-Ishlinskii stage a 0.279 Hz triangle over 45 % of the span was tracked at 7x the
    noise from the first-order curves alone, 1.6x with these loops and the force's cubic
    (:attr:`afmctl.model.rod.Rod.a3`; either alone 4.5x and 8x: docs/results/track.md).

    Returns the voltage, V, at ``sample_rate_hz``, each step at most ``rate_v_per_s /
    sample_rate_hz``.

    Examples
    --------
    >>> v = interior_loops((0.0, 150.0), 1000.0, 3000.0)
    >>> float(v[0]), float(v[-1]), float(v.min()), float(v.max())
    (0.0, 0.0, 0.0, 150.0)
    """
    lo, hi = v_range
    v0 = min(max(0.0, lo), hi)
    nodes = [v0]
    for centre, first in INTERIOR_CENTRES:
        for a in np.linspace(first, INTERIOR_LAST, INTERIOR_REVERSALS):
            above = len(nodes) % 2 == 1  # every node a turn, also from one centre to the next
            nodes.append(min(max(lo + (hi - lo) * (centre + (a if above else -a)), lo), hi))
    nodes.append(v0)
    return _through(nodes, rate_v_per_s, sample_rate_hz)


def segments_text(segments: tuple[Segment, ...], sample_rate_hz: float) -> str:
    """The ``segments`` metadata value: ``kind start_s-stop_s`` per segment, ``;`` between."""
    return "; ".join(f"{s.kind} {s.start / sample_rate_hz:.4f}-{s.stop / sample_rate_hz:.4f}"
                     for s in segments)


def design_set(design: str, sample_rate_hz: float, max_rate_v_per_s: float,
               v_range: tuple[float, float]) -> list[tuple[str, float, FloatArray, dict[str, str]]]:
    """The sweeps of ``design`` (one of :data:`DESIGNS`) as (name, frequency_hz, voltage_v, meta):
    :func:`standard_set`, for ``separating`` and ``full`` also :func:`separating_sweep` (its
    ``frequency_hz`` the repetition rate), for ``reversals`` and ``full`` also
    :func:`reversals_sweep`, in that order. ``meta`` gives the design and the segment kinds.

    Examples
    --------
    >>> [n for n, _, _, _ in design_set("separating", 1000.0, 5e4, (0.0, 150.0))][-2:]
    ['minor_loops_0.1hz', 'separating']
    >>> [n for n, _, _, _ in design_set("full", 1000.0, 5e4, (0.0, 150.0))][-3:]
    ['minor_loops_0.1hz', 'separating', 'reversals']
    """
    if design not in DESIGNS:
        raise ValueError(f"unknown sweep design {design!r} (one of {', '.join(DESIGNS)})")
    out = [(name, f, v, {"design": design, "segments": "triangle"})
           for name, f, v in standard_set(sample_rate_hz=sample_rate_hz, v_range=v_range)]
    if design in ("separating", "full"):
        v, segs = separating_sweep(v_range, sample_rate_hz, max_rate_v_per_s)
        reps = 2 * sample_rate_hz / v.size
        out.append((SEPARATING_NAME, reps, v,
                    {"design": design, "segments": segments_text(segs, sample_rate_hz)}))
    if design in ("reversals", "full"):
        out.append(reversals_sweep(v_range, sample_rate_hz, max_rate_v_per_s, design))
    return out


def reversals_sweep(v_range: tuple[float, float], sample_rate_hz: float,
                    max_rate_v_per_s: float, design: str = "reversals"
                    ) -> tuple[str, float, FloatArray, dict[str, str]]:
    """The ``reversals`` design's extra sweep as (name, frequency_hz, voltage_v, meta):
    :func:`reversal_curves` then :func:`interior_loops`, at the 5.58 Hz triangle's slew (within
    :data:`SLEW_USE` of ``max_rate_v_per_s``), its ``frequency_hz`` that triangle's."""
    f = STANDARD_FREQUENCIES_HZ[1]
    rate = min(2 * (v_range[1] - v_range[0]) * f, SLEW_USE * max_rate_v_per_s)
    v = np.concatenate((reversal_curves(v_range, sample_rate_hz, rate),
                        interior_loops(v_range, sample_rate_hz, rate)[1:]))
    return (REVERSALS_NAME, f, v, {"design": design,
                                   "segments": "reversal curves; interior loops"})


# ----------------------------------------------------------------------------------------------
# two axes (afmctl sweep --axes x,y)
# ----------------------------------------------------------------------------------------------

#: The coupling's excitation: lines 1 Hz apart (periods of 1 s), this many periods.
XY_PERIODS = 4
#: Its peak excursion about mid-range, as a fraction of the axis's span.
XY_EXCURSION = 0.3


def coupling_multisine(mid_v: float, span_v: float, band_hz: float, max_rate_v_per_s: float,
                       sample_rate_hz: float) -> FloatArray:
    """A Schroeder-phased multisine about ``mid_v``: lines at 1, 2, 3 ... Hz up to ``band_hz``
    (at most 24 of them, log-spaced above 12 Hz), each period 1 s, :data:`XY_PERIODS` periods,
    equal amplitudes scaled so the excursion is at most ``XY_EXCURSION`` of ``span_v`` and the
    slew at most ``SLEW_USE`` of ``max_rate_v_per_s``. Starts and ends at ``mid_v``.

    Examples
    --------
    >>> v = coupling_multisine(0.0, 300.0, 100.0, 5e4, 10_000.0)
    >>> v.size, float(v[0]), float(v[-1]), bool(np.max(np.abs(v)) <= 90.0 + 1e-9)
    (40001, 0.0, 0.0, True)
    """
    lines = np.unique(np.round(np.geomspace(1.0, max(band_hz, 2.0), 24)))
    n = int(round(sample_rate_hz))
    t = np.arange(n) / sample_rate_hz
    k = np.arange(1, lines.size + 1)
    phase = -np.pi * k * (k - 1) / lines.size  # Schroeder: a low crest factor
    shape = np.sum(np.sin(2 * np.pi * lines[:, None] * t + phase[:, None]), axis=0)
    shape -= shape[0]
    rate = np.max(np.abs(np.diff(shape))) * sample_rate_hz
    scale = min(XY_EXCURSION * span_v / np.max(np.abs(shape)),
                SLEW_USE * max_rate_v_per_s / rate)
    v = np.concatenate([np.tile(mid_v + scale * shape, XY_PERIODS), [mid_v]])
    return v


def xy_design(sample_rate_hz: float, v_ranges: dict[str, tuple[float, float]],
              max_rates_v_per_s: dict[str, float], band_hz: float, design: str = "standard"
              ) -> list[tuple[str, float, FloatArray, dict[str, str]]]:
    """A two-axis identification set as (name, frequency_hz, voltage_v (N, 2), meta).

    For each axis in turn (x, then y): the standard triangles (0.279, 5.58, 27.9 Hz over its
    range, :func:`standard_set` without the minor loops) with the other axis held at the middle of
    its range, then :func:`coupling_multisine` up to ``band_hz`` (about half the first resonance)
    about the middle of its range, the other still held: what identifies each axis, and the
    coupling both ways with its dynamics. Each file holds one axis constant; the recorder moves
    the held axis there between files. ``design="reversals"`` adds each axis's
    :func:`reversals_sweep` after its triangles (``<axis>_reversals``): a raster's fast axis runs
    minor loops inside its range, which triangles over the whole range do not show a Preisach-type
    model (foreign-xy-1's 60 um frame: an open-loop error loop of +-1 um about the minor loop).

    Examples
    --------
    >>> d = xy_design(1000.0, {"x": (0.0, 150.0), "y": (-100.0, 100.0)},
    ...               {"x": 5e4, "y": 4e4}, 100.0)
    >>> [n for n, _, _, _ in d]  # doctest: +NORMALIZE_WHITESPACE
    ['x_triangle_0.279hz', 'x_triangle_5.58hz', 'x_triangle_27.9hz', 'x_multisine',
     'y_triangle_0.279hz', 'y_triangle_5.58hz', 'y_triangle_27.9hz', 'y_multisine']
    >>> float(d[0][2][0, 1]), float(d[4][2][0, 0])
    (0.0, 75.0)
    """
    axes, tag = ("x", "y"), "xy" if design == "standard" else f"xy-{design}"
    out = []
    for i, a in enumerate(axes):
        other = axes[1 - i]
        lo, hi = v_ranges[a]
        held = 0.5 * sum(v_ranges[other])
        waves = [(f"{a}_{n}", f, v) for n, f, v in
                 standard_set(sample_rate_hz=sample_rate_hz, v_range=(lo, hi))[:3]]
        if design == "reversals":
            name, f, v, _ = reversals_sweep((lo, hi), sample_rate_hz, max_rates_v_per_s[a])
            waves.append((f"{a}_{name}", f, v))
        waves.append((f"{a}_multisine", 1.0, coupling_multisine(
            0.5 * (lo + hi), hi - lo, band_hz, max_rates_v_per_s[a], sample_rate_hz)))
        for name, f, v in waves:
            both = np.empty((v.size, 2))
            both[:, i], both[:, 1 - i] = v, held
            out.append((name, f, both, {"design": tag, "swept_axis": a,
                                        f"held_voltage_{other}_V": f"{held:g}",
                                        "band_hz": f"{band_hz:g}"}))
    return out
