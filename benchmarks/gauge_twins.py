"""How far a gauge's gap law and its actuator-side twin part, sweep design by sweep design (issue 23,
item 4, on the other-form ``sensor-nonlinearity`` stages of :mod:`benchmarks.family_sets`).

A sensor-side cause is named only when the sweeps separate it from its twin, the same
nonlinearity before the rod's dynamics instead of after it
(:func:`afmctl.fit.verdict.separated`). This asks the stage itself how far apart the two are,
noise-free and with the stage's own gap law, before any fit:

- the stage's gauge: ``f(x)``, ``x`` the platform's position
  (:mod:`afmctl.drivers.device.foreign.family_stage`, run without its gauge);
- the twin: ``L[f(g)]``, ``g`` the position of the same stage with a rod 200 kHz fast (its
  static output) and ``L`` the stage's rod (:func:`afmctl.fit.rod_response.rod_filter`);
  ``check_over_noise`` is the largest ``|x - L[g]|`` (0: the rod and the conventions agree);
- ``rms_over_noise`` and ``max_over_noise``: the two apart, after the best affine map of the
  twin onto the gauge, in units of the stage's noise. A fit of the twin may move its density
  and polynomial too, so these are what the best twin fit can at most be told apart by.

The designs run back to back from power-on: the three standard triangles, the separating sweep
(``afmctl sweep --design separating``) and eight full-range up-and-down ramps with 15 ms holds at
:data:`afmctl.planning.sweepdesign.SLEW_USE` and at 1.0 of the usable slew.

Run from the repo root: ``python -m benchmarks.gauge_twins --json`` (last line: one JSON object).
"""

from __future__ import annotations

import argparse
import dataclasses as dc
import json
from typing import Any

import numpy as np

from afmctl.drivers.device.foreign import family_physics as fp
from afmctl.drivers.device.foreign import family_stage as fst
from afmctl.fit.rod_response import rod_filter
from afmctl.planning import sweepdesign as sd
from benchmarks import family_sets

STAGES = "other-sensor-nonlinearity-0,other-sensor-nonlinearity-1"
#: The static output's rod: fast enough to follow every sample, Hz.
FAST_ROD_HZ = 2e5
#: Full-range ramps of the step design, and the hold after each, s.
STEP_PAIRS, STEP_HOLD_S = 8, 0.015


def steps(v_range: tuple[float, float], rate_v_per_s: float, rate_hz: float) -> np.ndarray:
    """Full-range up-and-down ramps at ``rate_v_per_s`` from and back to the safe output."""
    lo, hi = v_range
    v0, hold = min(max(0.0, lo), hi), int(STEP_HOLD_S * rate_hz)
    nodes = [v0, lo] + [hi, lo] * STEP_PAIRS + [v0]
    parts = [np.full(1, v0)]
    for a, b in zip(nodes[:-1], nodes[1:], strict=True):
        if a != b:
            parts += [sd._ramp(a, b, rate_v_per_s, rate_hz), np.full(hold, b)]
    return np.concatenate(parts)


def designs(case: family_sets.Case) -> list[tuple[str, np.ndarray]]:
    """The sweeps, in the order they run: name and voltage (V)."""
    prof = family_sets.profile(case)
    lim, rate_hz = prof.limits, prof.sample_rate_hz
    span, slew = (lim.v_min, lim.v_max), lim.max_rate_v_per_ms * 1e3
    out = [(name, v) for name, _, v in sd.standard_set(sample_rate_hz=rate_hz, v_range=span)[:3]]
    out.append(("separating", sd.separating_sweep(span, rate_hz, slew)[0]))
    for use in (sd.SLEW_USE, 1.0):
        out.append((f"steps_{use:g}_slew", steps(span, use * slew, rate_hz)))
    return out


def row(name: str) -> dict[str, Any]:
    """One stage: its gap law and, per design, how far the gauge and its twin part."""
    case = family_sets.cases_named(name, family_sets.OTHER_FORM_CASES)[0]
    prof = family_sets.profile(case)
    assert prof.emulator is not None and prof.emulator.family is not None
    stage = fp.family_stage_of(prof.emulator.family, (prof.limits.v_min, prof.limits.v_max))
    gap, mid, noise = stage.extras.gauge_gap_um, stage.extras.gauge_mid_um, stage.noise_um
    plain = dc.replace(stage, extras=fst.Extras())
    rigid = dc.replace(plain, resonance_hz=FAST_ROD_HZ)
    parts = designs(case)
    v = np.concatenate([p for _, p in parts])
    rate_hz = prof.sample_rate_hz
    x = fst.run(plain, v, rate_hz, fst.initial_state(plain))[0]
    g = fst.run(rigid, v, rate_hz, fst.initial_state(rigid))[0]
    g = np.r_[g[1:], g[-1]]  # the rigid rod's position at a sample's start is the sample before

    def law(q: np.ndarray) -> np.ndarray:
        return mid + gap * (q - mid) / (gap - (q - mid))

    rod = (stage.resonance_hz, stage.damping, 1.0 / rate_hz)
    lg, twin, gauge = rod_filter(g, *rod), rod_filter(law(g), *rod), law(x)
    half = 0.5 * stage.loop.span_um
    out: dict[str, Any] = {"stage": name, "noise_um": noise, "gap_um": gap,
                           "error_at_range_end_over_noise": half * half / abs(gap) / noise,
                           "rod_Hz": stage.resonance_hz, "rod_damping_ratio": stage.damping,
                           "designs": {}}
    start = 0
    for design, p in parts:
        sl = slice(start, start + p.size)
        start += p.size
        a = np.column_stack((twin[sl], np.ones(p.size)))
        apart = gauge[sl] - a @ np.linalg.lstsq(a, gauge[sl], rcond=None)[0]
        out["designs"][design] = {
            "samples": p.size, "rms_over_noise": float(np.sqrt(np.mean(apart ** 2)) / noise),
            "max_over_noise": float(np.max(np.abs(apart)) / noise),
            "rod_lag_max_um": float(np.max(np.abs(x[sl] - g[sl]))),
            "check_over_noise": float(np.max(np.abs(x[sl] - lg[sl])) / noise)}
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stages", default=STAGES, help="comma-separated other-form stages")
    ap.add_argument("--json", action="store_true", help="end with one JSON line")
    args = ap.parse_args(argv)
    rows = [row(n) for n in args.stages.split(",")]
    for r in rows:
        print(f"{r['stage']}: gap law {r['error_at_range_end_over_noise']:.0f}x the noise at the "
              f"range's end, rod {r['rod_Hz']:.0f} Hz")
        for d, f in r["designs"].items():
            print(f"  {d:20s} gauge vs twin {f['rms_over_noise']:6.3f}x noise RMS, "
                  f"{f['max_over_noise']:6.2f}x at most (rod lag up to {f['rod_lag_max_um']:.2f} um; "
                  f"check {f['check_over_noise']:.1e})")
    if args.json:
        print(json.dumps({"gauge_twin_rows": rows}))


if __name__ == "__main__":
    main()
