"""Write sweep sets recorded on random foreign stages (drivers/device/foreign/).

    python benchmarks/foreign_sets.py --out DIR --n N --seed S [--effect CAUSE] [--strength X]
        [--design D] [--start S] [--families default|random]

``--design separating`` records the ``standard`` design and then afmctl's separating sweep
(:func:`afmctl.planning.sweepdesign.separating_sweep`: holds, fast steps, a multisine) at 10 kHz within the
emulated profile's slew limit; ``random`` draws among the lab designs only.

Each stage goes to its own folder ``DIR/stage_XX/``: one sweep CSV per sweep in afmctl's sweep
format, recorded in sequence on one plant (its state carried from sweep to sweep, a random idle
at the next sweep's first voltage in between), and ``truth.json`` with every true parameter, the
hidden effects, the sensor noise (1 sigma), the start state and what was recorded. With a hidden
effect, ``truth.json`` also gives per sweep the RMS of what the effect changed in the noiseless
reading (``effect_rms_um``). The last line on stdout is one JSON object (a summary).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from afmctl.drivers.device.foreign import stage as plant  # noqa: E402
from afmctl.drivers.device.foreign.effects import CAUSES, random_effect  # noqa: E402
from afmctl.drivers.device.foreign.stage import COERCIVE_FAMILIES, INTERACTION_FAMILIES  # noqa: E402
from afmctl.drivers.device.foreign.stages import random_stage  # noqa: E402
from afmctl.drivers.device.foreign.sweeps import DESIGNS, SweepPlan, sweep_set  # noqa: E402
from afmctl.files.profile import default_profile  # noqa: E402
from afmctl.planning import sweepdesign as sd  # noqa: E402

STARTS = ("poled+", "poled-", "depoled", "voltage")
#: Sample rate of the separating sweep, Hz (the emulated profile's: the steps need it).
SEPARATING_RATE_HZ = 10_000.0


def separating_plan(lo: float, hi: float) -> SweepPlan:
    """afmctl's separating sweep over ``max(lo, 0) .. hi`` V within the default profile's usable
    slew rate, as a plan for the foreign plant."""
    rate = default_profile().limits.max_rate_v_per_ms * 1e3
    v, _ = sd.separating_sweep((max(lo, 0.0), hi), SEPARATING_RATE_HZ, rate)
    return SweepPlan(f"sweep_4_{sd.SEPARATING_NAME}", 2 * SEPARATING_RATE_HZ / v.size,
                     SEPARATING_RATE_HZ, v, sd.SEPARATING_NAME)


def plans_for(design: str, lo: float, hi: float, rng: np.random.Generator) -> list[SweepPlan]:
    """The sweeps of ``design``: a lab design of :mod:`afmctl.drivers.device.foreign.sweeps`, or
    ``separating`` (the ``standard`` design, then :func:`separating_plan`)."""
    if design != sd.SEPARATING_NAME:
        return sweep_set(design, lo, hi, rng)
    return sweep_set("standard", lo, hi, rng) + [separating_plan(lo, hi)]


def drive_range(design: str, rng: np.random.Generator) -> tuple[float, float]:
    """A lab's voltage range for a design, V."""
    if design == "semi-bipolar":
        return float(-rng.choice([20.0, 30.0, 40.0])), 150.0
    if design == "offset":
        return 0.0, 120.0
    if design == "nested":
        return (0.0, 150.0) if rng.random() < 0.5 else (-30.0, 150.0)
    if design in ("standard", sd.SEPARATING_NAME):
        return 0.0, 150.0
    return 0.0, float(rng.choice([100.0, 120.0, 150.0]))


def draw_start(kind: str, rng: np.random.Generator, lo: float, hi: float):
    """A start state for :func:`afmctl.drivers.device.foreign.stage.initial_state`."""
    if kind == "random":
        kind = str(rng.choice(STARTS, p=[0.4, 0.1, 0.2, 0.3]))
    return float(rng.uniform(lo, hi)) if kind == "voltage" else kind


def csv_text(plan: SweepPlan, reading_um: np.ndarray, thickness_um: float) -> str:
    """afmctl's sweep format: ``# key: value`` lines, header, one row per sample."""
    t = np.arange(plan.voltage_V.size) / plan.sample_rate_hz
    head = (f"# frequency_hz: {plan.frequency_hz:.6g}\n# sample_rate_hz: {plan.sample_rate_hz:g}\n"
            f"# layer_thickness_um: {thickness_um:.6g}\n# waveform: {plan.waveform}\n"
            f"# source: foreign stage simulator\ntime_s,voltage_V,displacement_um\n")
    rows = np.column_stack([t, plan.voltage_V, reading_um])
    lines = [f"{a:.6f},{b:.5f},{c:.5f}" for a, b, c in rows]
    return head + "\n".join(lines) + "\n"


def record(stage, plans, start, rng):
    """Record the sweeps in sequence; return readings, true positions and what happened."""
    state = plant.initial_state(stage, start)
    clean = replace(stage, effects=())
    shadow = plant.initial_state(clean, start) if stage.effects else None
    out, log = [], []
    for plan in plans:
        wait = float(rng.uniform(0.5, 5.0))
        state = plant.start_run(stage, state, rng)
        state = plant.idle(stage, state, wait, float(plan.voltage_V[0]))
        pre = state
        true_um, reading, state = plant.run(stage, plan.voltage_V, plan.sample_rate_hz, pre, rng)
        entry = {"name": plan.name, "frequency_hz": plan.frequency_hz,
                 "sample_rate_hz": plan.sample_rate_hz, "samples": int(plan.voltage_V.size),
                 "idle_before_s": wait, "voltage_gain": state.gain,
                 "true_range_um": [float(true_um.min()), float(true_um.max())]}
        if shadow is not None:
            shadow = plant.idle(clean, shadow, wait, float(plan.voltage_V[0]))
            _, base, shadow = plant.run(clean, plan.voltage_V, plan.sample_rate_hz, shadow, None)
            _, noiseless, _ = plant.run(stage, plan.voltage_V, plan.sample_rate_hz, pre, None)
            diff = noiseless - base
            entry["effect_rms_um"] = float(np.sqrt(np.mean((diff - diff.mean()) ** 2)))
        out.append((plan, reading, true_um))
        log.append(entry)
    return out, log


def one_stage(folder: Path, seed: int, index: int, args) -> dict:
    rng = np.random.default_rng([seed, index])
    design = args.design if args.design != "random" else str(rng.choice(DESIGNS))
    lo, hi = drive_range(design, rng)
    families = {}
    if args.families == "random":
        families = {"coercive_family": str(rng.choice(COERCIVE_FAMILIES)),
                    "interaction_family": str(rng.choice(INTERACTION_FAMILIES))}
    stage = random_stage(rng, drive_range_V=(lo, hi), **families)
    strength = None
    if args.effect != "none":
        strength = float(rng.uniform(0, 1)) if args.strength is None else args.strength
        stage = replace(stage, effects=(random_effect(args.effect, rng, stage, strength),))
    start = draw_start(args.start, rng, lo, hi)
    plans = plans_for(design, lo, hi, rng)
    recorded, log = record(stage, plans, start, rng)
    folder.mkdir(parents=True, exist_ok=False)
    for plan, reading, _ in recorded:
        (folder / f"{plan.name}.csv").write_text(
            csv_text(plan, reading, stage.material.layer_thickness_um), encoding="utf-8")
    truth = {"seed": [seed, index], "design": design, "drive_range_V": [lo, hi],
             "start": start, "noise_um": stage.sensor.noise_um, "cause": args.effect,
             "strength": strength, "stage": plant.describe(stage), "sweeps": log}
    (folder / "truth.json").write_text(json.dumps(truth, indent=1), encoding="utf-8")
    return truth


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--n", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--effect", default="none", choices=["none", *CAUSES])
    ap.add_argument("--strength", type=float, default=None, help="0 (barely) .. 1 (strong)")
    ap.add_argument("--design", default="random",
                    choices=["random", *DESIGNS, sd.SEPARATING_NAME])
    ap.add_argument("--start", default="random", choices=["random", *STARTS])
    ap.add_argument("--families", default="default", choices=["default", "random"],
                    help="density families: lognormal/normal, or drawn from all three each")
    args = ap.parse_args(argv)
    if args.out.exists() and any(args.out.iterdir()):
        print(f"foreign_sets: error: {args.out} exists and is not empty", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    truths = []
    for i in range(args.n):
        truths.append(one_stage(args.out / f"stage_{i:02d}", args.seed, i, args))
        print(f"stage {i + 1}/{args.n}: {truths[-1]['design']}", file=sys.stderr)
    summary = {"stages": args.n, "out": str(args.out), "effect": args.effect,
               "designs": [t["design"] for t in truths],
               "seconds": round(time.perf_counter() - t0, 2)}
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
