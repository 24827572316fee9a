"""Issue 6 figures: afmctl diagnose on a seeded batch of emulated stages with hidden effects.

Each case is the shipped emulated stage carrying one catalogue effect (or none) at a random
strength (:func:`drivers.device.plant.hidden_effect`); the three standard triangles are recorded on it
through the driver interface (device clock 4x real time), and ``diagnose`` must name the effect.
Then, for every case whose effect track can invert or correct for, the 27.9 Hz / 27.04 um triangle
is tracked on that stage with the base and with the extended model that diagnose wrote, and judged
by the stage's true position (``track_*_rms_um``: the emulator's plant simulated between samples)
and by the readings as each model corrects them (``track_*_readings_rms_um``).

Run: ``python benchmarks/bench_diagnose.py --json`` (last line: one JSON object with ``cases``,
``correct``, ``min_gain_with_effect``, ``false_alarms``, per-case rows and the track figures).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from afmctl import calibration, experiment, extension, track
from afmctl import diagnose as dg
from afmctl import effects as fx
from afmctl.profile import Profile, default_profile
from afmctl.transducer import Transducer
from drivers.device import plant
from drivers.inprocess import InProcessStage, accelerated

SPEED = 4.0
#: Effects track inverts (a per-run gain cannot be known before the run).
TRACKABLE = {"thermal-relaxation", "amplifier-lag", "sensor-delay", "sensor-nonlinearity",
             "second-mode"}


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def track_rms(profile: Profile, models: dict[str, Transducer], out: Path
              ) -> dict[str, tuple[float, float]]:
    """Per model: RMS error (um) of the 27.9 Hz / 27.04 um triangle on ``profile``'s stage, of
    the stage's true position (the emulator's plant simulated between samples) and of the
    readings as the model corrects them."""
    assert profile.emulator is not None
    desired = track.triangle(27.9, 27.04, 0.0, 3, 1 / profile.sample_rate_hz)
    rms = {}
    with InProcessStage(profile, clock=accelerated(SPEED)) as stage:
        for name, model in models.items():
            plans = track.plan(model, desired, profile.limits, stage.voltage(), ("inverse",))
            runs = experiment.run_all(stage, plans, desired, out / name, {},
                                      profile.emulator.true_model, sensor=model.effects)
            score = runs["inverse"].score
            assert score.rms_between_um is not None
            rms[name] = (score.rms_between_um, score.rms_um)
    return rms


def run_case(cause: str, index: int, tmp: Path) -> dict[str, Any]:
    prof = plant.with_hidden_effect(default_profile(), cause, index)
    with InProcessStage(prof, clock=accelerated(SPEED)) as stage:
        recorded = calibration.record_standard(stage, prof, tmp / "sweeps")
    d = dg.diagnose(recorded)
    cfg = prof.emulator
    assert cfg is not None
    hidden = (cfg.model.polarization.thermal if cause == "thermal-relaxation"
              else fx.Effects() if cause == "none" else cfg.effects)
    row: dict[str, Any] = {"truth": cause, "index": index, "hidden": repr(hidden),
                           "named": d.cause,
                           "gain": d.gain, "base_rms_um": d.base_rms_um,
                           "extended_rms_um": d.extended_rms_um,
                           "fitted": d.table[d.cause].fitted.parameters,
                           "seconds": round(d.seconds, 1)}
    if cause in TRACKABLE and d.cause == cause:
        rms = track_rms(prof, {"base": d.base_model, "extended": d.extended_model}, tmp / "track")
        row["track_base_rms_um"], row["track_base_readings_rms_um"] = rms["base"]
        row["track_extended_rms_um"], row["track_extended_readings_rms_um"] = rms["extended"]
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true", help="print the JSON object last")
    ap.add_argument("--per-cause", type=int, default=2, help="cases per cause (default 2)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    rows = []
    for cause, index in plant.hidden_cases(extension.NAMES, args.per_cause):
        with tempfile.TemporaryDirectory() as tmp:
            row = run_case(cause, index, Path(tmp))
        rows.append(row)
        extra = (f"; track {row['track_base_rms_um']:.4f} -> {row['track_extended_rms_um']:.4f} um"
                 if "track_base_rms_um" in row else "")
        log(f"{cause:20s} #{index:2d}: named {row['named']:20s} gain {row['gain']:6.2f} "
            f"({row['base_rms_um']:.4f} -> {row['extended_rms_um']:.4f} um, {row['seconds']} s)"
            + extra)
    effect = [r for r in rows if r["truth"] != "none"]
    out = {"cases": len(rows), "correct": sum(r["named"] == r["truth"] for r in rows),
           "min_gain_with_effect": min(r["gain"] for r in effect),
           "false_alarms": sum(r["named"] != "none" for r in rows if r["truth"] == "none"),
           "track_extended_beats_base": sum(r["track_extended_rms_um"] < r["track_base_rms_um"]
                                            for r in rows if "track_base_rms_um" in r),
           "track_cases": sum("track_base_rms_um" in r for r in rows),
           "seconds": round(time.perf_counter() - t0, 1), "rows": rows}
    log(f"{out['correct']}/{out['cases']} named correctly, min gain with an effect "
        f"{out['min_gain_with_effect']:.2f}, false alarms {out['false_alarms']}")
    if args.json:
        print(json.dumps(out))


if __name__ == "__main__":
    main()
