"""Sensor-side causes and their actuator-side twins: do the sweeps separate them, and which would.

A sensor-side cause (a gauge nonlinearity, a sensor delay) changes what afmctl believes the true
position is: ``track`` corrects the readings with it. Its actuator-side twin is the same effect
before the rod's dynamics (:data:`afmctl.fit.candidates.TWINS`): a cubic in ``Q`` driving the
rod instead of a cubic of the rod's displacement in the gauge; an amplifier's lag instead of a
late reading. The twin moves the stage and leaves the readings true. Quasi-statically the two give
the same readings (after the rod's dynamics the nonlinearity acts on the filtered displacement,
before them on the quasi-static one, and slow sweeps do not tell these apart; a rate-independent
hysteresis and an LTI rod commute with a delay), so a sensor cause is named only when its twin
misses the held-out data clearly more (:func:`afmctl.fit.verdict.separated`).

When they are not separated, :func:`separating_sweep` predicts, with both fitted models, the
readings of fast triangles over the recorded voltage range (2, 4, 8, ... times the fastest
recorded frequency, up to a twentieth of the fastest sample rate) and of a step, and names the
first that puts the two predictions :data:`SEPARATES` times the noise floor apart (RMS): the
sweep to record. Given the stage's slew limit, every proposal keeps to :data:`SLEW_SHARE` of it
(as the separating design's steps do): a fast triangle narrows about the range's middle, the
step becomes a ramp. Pure numerics: no I/O.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl.files.sweepfile import Sweep, from_arrays
from afmctl.fit import verdict as vd
from afmctl.fit.candidates import TWINS

FloatArray = NDArray[np.float64]
#: A proposed sweep separates the twins when their predicted readings differ by this RMS, in
#: multiples of the noise floor (held-out data then show the difference well above the 1.1 bar).
SEPARATES = 3.0
#: Fast triangles tried: the fastest recorded frequency times 2, 4, ... (at most this many).
DOUBLINGS = 8
#: Cycles of a proposed triangle; its first is the memory (not compared).
CYCLES = 4
#: A proposed step: held at the low end, at the high end and at the low end again, s.
STEP_HOLDS_S = (0.01, 0.04, 0.04)
#: Share of the stage's slew limit a proposed sweep may use.
SLEW_SHARE = 0.5
#: A triangle narrowed by the slew limit to under this share of the range is not proposed.
NARROWEST = 0.1


def pairs(scored: Sequence[vd.Scored], rule: vd.Rule = vd.Rule()) -> list[dict[str, Any]]:
    """Every fitted sensor-side cause with its twin: held-out RMS of both (um), the twin's over
    the sensor cause's (held out, and on the halves both were fitted on: None if not known), the
    bar and whether the sweeps separate them (the twin misses more on both) or refute the sensor
    cause (the twin explains them clearly better)."""
    by_name = {s.name: s for s in scored}
    out = []
    for sensor, twin in TWINS.items():
        s, t = by_name.get(sensor), by_name.get(twin)
        if s is None or t is None:
            continue
        out.append({"sensor": sensor, "actuator": twin, "sensor_heldout_rms_um": s.heldout_rms_um,
                    "actuator_heldout_rms_um": t.heldout_rms_um,
                    "actuator_over_sensor": vd.ratio(t.heldout_rms_um, s.heldout_rms_um),
                    "actuator_over_sensor_fitted": vd.fitted_ratio(s, t),
                    "needed": rule.separated, "separated": vd.separated(s, t, rule),
                    "refuted": vd.refuted(s, by_name, rule)})
    return out


def _triangle(hz: float, lo: float, hi: float, fs: float) -> FloatArray:
    """:data:`CYCLES` cycles ``lo -> hi -> lo`` at ``hz``, sampled at ``fs`` (V)."""
    t = np.arange(int(round(CYCLES * fs / hz)) + 1) / fs
    return np.interp((t * hz) % 1.0, [0.0, 0.5, 1.0], [lo, hi, lo])


def _step(lo: float, hi: float, fs: float, slew: float) -> FloatArray:
    """Held at ``lo``, ``hi`` and ``lo`` (:data:`STEP_HOLDS_S`), moving between them at ``slew``
    (V/s; within one sample if faster)."""
    up = np.linspace(lo, hi, max(int(np.ceil((hi - lo) / slew * fs)), 1) + 1)[1:]
    held = [np.full(max(int(round(h * fs)), 1), v)
            for h, v in zip(STEP_HOLDS_S, (lo, hi, lo), strict=True)]
    return np.concatenate([held[0], up, held[1], up[::-1], held[2]])


def proposals(sweeps: Sequence[Sweep], max_slew_v_per_s: float | None = None
              ) -> list[tuple[dict[str, Any], Sweep]]:
    """The sweeps :func:`separating_sweep` tries, each with its description: fast triangles over
    the recorded voltage range at the fastest recorded sample rate, slowest first, then a step;
    within :data:`SLEW_SHARE` of ``max_slew_v_per_s`` (V/s; None: no limit)."""
    fs = max(1.0 / s.dt for s in sweeps)
    lo = min(float(np.min(s.voltage_v)) for s in sweeps)
    hi = max(float(np.max(s.voltage_v)) for s in sweeps)
    f0 = max((s.frequency_hz or 0.0 for s in sweeps), default=0.0) or fs / 1000
    slew = SLEW_SHARE * max_slew_v_per_s if max_slew_v_per_s else np.inf
    out = []
    for k in range(1, DOUBLINGS + 1):
        hz = f0 * 2 ** k
        half = 0.5 * min(hi - lo, slew / (2 * hz))  # the slew limit narrows a fast triangle
        if hz > fs / 20 or 2 * half < NARROWEST * (hi - lo):
            break
        a, b = 0.5 * (lo + hi) - half, 0.5 * (lo + hi) + half
        what = {"kind": "triangle", "frequency_hz": hz, "v_range_V": [a, b],
                "sample_rate_hz": fs, "slew_V_per_s": 2 * (b - a) * hz}
        v = _triangle(hz, a, b, fs)
        out.append((what, from_arrays(v, np.zeros_like(v), fs, {"frequency_hz": f"{hz:g}"},
                                      f"triangle_{hz:.4g}hz")))
    v = _step(lo, hi, fs, slew)
    step = {"kind": "step", "frequency_hz": None, "v_range_V": [lo, hi], "sample_rate_hz": fs,
            "slew_V_per_s": min((hi - lo) * fs, slew)}
    return out + [(step, from_arrays(v, np.zeros_like(v), fs, {}, "step"))]


def separating_sweep(readings: Callable[[str, Sweep], FloatArray], sensor: str,
                     sweeps: Sequence[Sweep], floor_um: float,
                     max_slew_v_per_s: float | None = None) -> dict[str, Any]:
    """The first of :func:`proposals` on which the fitted sensor cause and its fitted twin
    predict readings at least :data:`SEPARATES` times ``floor_um`` apart (RMS after the first
    cycle), or the proposal that puts them furthest apart if none does.

    Parameters
    ----------
    readings : callable
        ``readings(candidate, sweep)``: what the fitted candidate reads on a sweep (um).
    sensor : str
        The sensor-side cause (a key of :data:`afmctl.fit.candidates.TWINS`).
    sweeps : sequence of Sweep
        The recorded sweeps (their voltage range, fastest frequency and sample rate).
    floor_um : float
        The noise floor, um.
    max_slew_v_per_s : float, optional
        The stage's slew limit, V/s (:func:`proposals`).

    Returns
    -------
    dict
        The sweep (``kind``, ``frequency_hz``, ``v_range_V``, ``sample_rate_hz``,
        ``slew_V_per_s``), ``difference_um``, ``difference_over_noise``, ``separates``, every
        proposal tried (``tried``) and one sentence (``text``).
    """
    twin, tried, found = TWINS[sensor], [], None
    for what, sweep in proposals(sweeps, max_slew_v_per_s):
        hz = what["frequency_hz"]
        judged = sweep.time_s >= (1.0 / hz if hz else 0.0)
        diff = readings(sensor, sweep) - readings(twin, sweep)
        rms = float(np.sqrt(np.mean(diff[judged] ** 2)))
        row = {**what, "difference_um": rms, "difference_over_noise": rms / floor_um}
        tried.append(row)
        if rms >= SEPARATES * floor_um:
            found = row
            break
    best = found or max(tried, key=lambda r: r["difference_over_noise"])
    return {**best, "separates": found is not None, "tried": tried,
            "text": _text(sensor, twin, best, found is not None)}


def _text(sensor: str, twin: str, row: dict[str, Any], separates: bool) -> str:
    lo, hi = row["v_range_V"]
    what = (f"a triangle at {row['frequency_hz']:.4g} Hz" if row["kind"] == "triangle"
            else "a step") + (f" over {lo:.4g} .. {hi:.4g} V at {row['sample_rate_hz']:g} "
                              f"samples/s (slew {row['slew_V_per_s']:.3g} V/s)")
    apart = (f"{sensor} and {twin}, as fitted, predict readings "
             f"{row['difference_over_noise']:.1f}x the noise apart there")
    if separates:
        return f"record {what}: {apart}"
    return (f"no fast triangle or step tells them apart by {SEPARATES:g}x the noise (at most "
            f"{row['difference_over_noise']:.2f}x, with {what}); an independent reference "
            f"(a calibrated gauge, an interferometer) does")

