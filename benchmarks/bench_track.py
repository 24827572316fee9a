"""Issue 5 figures: the paper's three open-loop experiments on the emulated stage.

The model is identified from sweeps recorded on the emulated stage itself (never its true
parameters); each experiment is planned (Algorithm 3 and the linear filter), played on the stage
through the same driver interface a lab uses, and scored at the samples and, by simulating the
stage's true plant on a grid 8 times finer, between them. Errors are over the steady part (the
first period, the transient of the ramp in, is reported apart), as ``afmctl track`` prints them.

Out-of-family stages (issue 23, ``benchmarks/family_sets.py``, ``--family-only`` for this part
alone): on every unipolar stage, the model identify gives on its three standard triangles
(``--family-cache DIR``: the fits bench_identify kept) plans a 0.279 Hz triangle over 45 % and a
27.9 Hz one over 30 % of the span the fast sweep covered, about its middle, with the inverse
and the linear filter, each planned just before it plays from the model's twin of the stage
(:mod:`afmctl.experiment.twin`: the sweeps, the runs before and the holds between, from each
recording's ``started_s``; row key ``twin``); each is played on the stage and judged by its TRUE
position (the plant re-simulated, no gauge, no noise), first period out. ``family_open_loop_ratio_min`` is the
smallest linear / inverse RMS ratio over both experiments and the Preisach and
Prandtl-Ishlinskii stages, ``bouc_wen_open_loop_ratio_min`` the same over the Bouc-Wen ones
(0 where the planner refused). Each row also gives each run's mean true error and its RMS
with an offset and a slope taken out (``..._true_mean_um``, ``..._true_detrended_rms_um``):
on the creep stages, planned from rest (before the twin), nearly all of the error was the
offset a slow creep leaves.

Run: ``python benchmarks/bench_track.py --json`` (last line: one JSON object).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from afmctl import guard
from afmctl.drivers import open_stage
from afmctl.experiment import calibration
from afmctl.experiment import runner as experiment
from afmctl.files.profile import Profile, default_profile
from afmctl.fit import identify
from afmctl.planning import track

EXPERIMENTS = ((0.279, 40.56), (0.279, 27.04), (27.9, 27.04))  # (Hz, um peak-to-peak), Figs 9-11

if __package__:  # python -m benchmarks.<name>
    from benchmarks import family_sets
else:  # python benchmarks/<name>.py
    import family_sets


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def steady_rms_um(o: experiment.Outcome, desired: track.Desired) -> tuple[float, float]:
    """(RMS, max) error over the steady part, um: from one period after the tracking starts (the
    first period carries the transient of the ramp in), missing samples left out. Computed here
    from the raw arrays, independently of :func:`afmctl.track.score`."""
    err = o.displacement_um[o.waveform.tracking] - desired.u_um
    assert desired.period_s is not None
    steady = err[int(round(desired.period_s / desired.dt_s)):]
    steady = steady[np.isfinite(steady)]
    return float(np.sqrt(np.mean(steady**2))), float(np.abs(steady).max())


def run_experiment(stage: Any, model: Any, prof: Profile, freq: float, amp: float,
                   periods: float, out: Path) -> dict[str, Any]:
    """One experiment (both filters) on ``stage``; the figures of the README's table."""
    desired = track.triangle(freq, amp, 0.0, periods, 1 / prof.sample_rate_hz)
    plans = track.plan(model, desired, prof.limits, stage.voltage())
    runs = experiment.run_all(stage, plans, desired, out, {"bench": out.name},
                              prof.emulator.model)
    assert prof.emulator is not None
    res: dict[str, Any] = {}
    for name, o in runs.items():
        rms, mx = steady_rms_um(o, desired)
        res[f"{name}_rms_um"] = rms
        res[f"{name}_rms_pct"] = 100 * rms / amp
        res[f"{name}_max_um"] = mx
        res[f"{name}_between_rms_um"] = o.score.rms_between_um
        res[f"{name}_transient_rms_um"] = o.score.rms_transient_um
        res[f"{name}_max_slew_V_per_ms"] = o.waveform.max_slew_v_per_ms
        res[f"{name}_complete"] = o.complete
    res["inverse_horizon"] = runs["inverse"].waveform.horizon
    res["inverse_horizons"] = runs["inverse"].waveform.horizon_text()
    res["ratio"] = res["linear_rms_um"] / res["inverse_rms_um"]
    res["ratio_between"] = (runs["linear"].score.rms_between_um
                            / runs["inverse"].score.rms_between_um)
    return res


def family_row(case: family_sets.Case, cache: Path | None, periods: float, frame: bool = True
               ) -> dict[str, Any]:
    """Both filters on one out-of-family stage, judged by its true position."""
    with tempfile.TemporaryDirectory() as tmp, family_sets.session(case) as s:
        s.frame = frame
        sweeps = family_sets.record(s, Path(tmp) / "sweeps")
        fit = family_sets.identified(case, sweeps, s.noise_um, cache)
        lo, hi = family_sets.span_of(sweeps)
        row: dict[str, Any] = {"stage": case.name, "family": case.family, "noise_um": s.noise_um,
                               "identify_worst_over_noise": max(fit["rms_over_noise"]),
                               "twin": family_sets.follow(s, fit["model"], sweeps)}
        ratios = []
        for freq, frac in family_sets.TRIANGLES:
            key = f"{freq:g}hz"
            try:
                errors = family_sets.tracked_errors(s, fit["model"], freq, frac, (lo, hi),
                                                    periods)
            except guard.LimitError as exc:
                row[f"{key}_refused"] = str(exc)
                ratios.append(0.0)
                continue
            for name, e in errors.items():
                row[f"{key}_{name}_true_rms_um"] = family_sets.rms(e)
                row[f"{key}_{name}_true_mean_um"] = float(np.mean(e))
                row[f"{key}_{name}_true_detrended_rms_um"] = family_sets.detrended_rms(e)
            ratios.append(row[f"{key}_linear_true_rms_um"] / row[f"{key}_inverse_true_rms_um"])
            row[f"{key}_ratio"] = ratios[-1]
        row["frames"] = s.frames
    row["ratio_min"] = min(ratios)
    log(f"  {case.name:18s}: linear / inverse (true) " + ", ".join(
        f"{row.get(f'{f:g}hz_ratio', 0.0):.1f} at {f:g} Hz" for f, _ in family_sets.TRIANGLES))
    return row


def family(names: str, cache: Path | None, periods: float, design: str = "reversals",
           frame: bool = True) -> dict[str, Any]:
    """The ``family_*`` and ``bouc_wen_*`` keys over the unipolar out-of-family stages
    (``frame``: each run planned in the frame the twin reads; else in the model's)."""
    cases = [c for c in family_sets.cases_named(names, design=design) if not c.bipolar]
    rows = [family_row(c, cache, periods, frame) for c in cases]
    pp = [r["ratio_min"] for r in rows if r["family"] != "bouc-wen"]
    bw = [r["ratio_min"] for r in rows if r["family"] == "bouc-wen"]
    return {"family_open_loop_ratio_min": min(pp) if pp else None,
            "bouc_wen_open_loop_ratio_min": min(bw) if bw else None,
            "family_track_stages": len(rows), "family_track_rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true", help="print the JSON object last")
    ap.add_argument("--periods", type=float, default=3.0,
                    help="periods per experiment (default: track's)")
    ap.add_argument("--model-frame", action="store_true",
                    help="out-of-family runs in the model's own frame, not the one the twin reads "
                         "from the readings (the comparison)")
    family_sets.add_arguments(ap)
    args = ap.parse_args()
    fam = {} if args.family == "none" else family(args.family, args.family_cache, args.periods,
                                                  args.family_design, not args.model_frame)
    if args.family_only:
        print(json.dumps(fam))
        return
    prof = default_profile()
    assert prof.emulator is not None
    out: dict[str, object] = {}
    with tempfile.TemporaryDirectory() as tmp, open_stage(prof) as stage:
        t0 = time.perf_counter()
        recorded = calibration.record_standard(stage, prof, Path(tmp) / "sweeps")
        fit = identify.fit(recorded)
        log(f"identified from {len(recorded)} recorded sweeps in {time.perf_counter() - t0:.1f} s "
            f"(fit {'converged' if fit.success else 'FAILED'})")
        out["identify_success"] = fit.success
        for freq, amp in EXPERIMENTS:
            key = f"{freq:g}hz_{amp:g}um"
            res = run_experiment(stage, fit.model, prof, freq, amp, args.periods, Path(tmp) / key)
            out[key] = res
            log(f"{key:16s} inverse {res['inverse_rms_um']:.4f} um (between "
                f"{res['inverse_between_rms_um']:.4f}; first period "
                f"{res['inverse_transient_rms_um']:.4f}), linear {res['linear_rms_um']:.4f} um, "
                f"ratio {res['ratio']:.1f}; {res['inverse_horizons']}; slew "
                f"{res['inverse_max_slew_V_per_ms']:.1f} / {res['linear_max_slew_V_per_ms']:.1f} V/ms")
    out["ratio_27.9hz"] = out["27.9hz_27.04um"]["ratio"]  # type: ignore[index]
    out["limit_slew_V_per_ms"] = prof.limits.max_rate_v_per_ms
    out["periods"] = args.periods
    out.update(fam)
    if args.json:
        print(json.dumps(out))


if __name__ == "__main__":
    main()
