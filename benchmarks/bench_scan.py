"""Issue 26 figures: raster scans on two-axis stages, each axis through its own inverse.

Stages: the shipped emulated x/y stage (``emulated-xy``, played in-process through the stage
interface on a device clock 4x real time; its two-axis sweep set, the foreign stages' design on
its ranges, recorded through the same interface), and foreign x/y stages (:func:`afmctl.drivers.device.foreign.xy_stage.xy_stages`: two
hysteretic actuators of other kinds and formulas than afmctl's model, a 3-DOF structure whose
shared mode couples the axes, flexures that move the other axis slightly nonlinearly). On each,
the stage's own two-axis sweep set (:func:`~afmctl.drivers.device.foreign.xy_sweeps.write_sweep_set`)
is identified by ``afmctl identify``'s two-axis fit (:func:`afmctl.fit.xyidentify.fit`: each axis's
model and the coupling both ways); the scan plans with that model, never with the stage's own
parameters. ``--cache DIR`` keeps the identified models (``<stage>-<settings>[-reversals].toml``) for later
runs; ``--identify quick`` (default: the parametric model, one start, no Preisach-grid
alternative) or ``full`` (``afmctl identify``'s defaults, several times slower). ``--design
reversals`` (the default) records each axis's reversal curves after the writer's set
(:func:`reversal_plans`: what ``afmctl sweep --axes x,y --design reversals`` adds; a raster's
fast axis runs minor loops), ``writer`` the writer's set alone.

Frames: 128 pixels x 64 lines, square, centred in the identified reach, 60 x 60 um or the largest
that fits 90 % of the reach and in which the linear filter's waveform passes the guard too (its
line needs more voltage than the inverse near the reach's ends; ``frame_um``), and 10 x 10 um at
10 lines/s (``small``); at 1 line/s 8 lines (the
image's statistics are per line; 64 s frames would only take longer). Played on the plant in
pure simulation (:func:`~afmctl.drivers.device.foreign.xy_stage.run`), the readings with each
axis's gauge noise. Judged on the pixel grid against the **noise-free readings** (the plant's
position in the sensors' frame; on the emulated stage, whose device gives only its readings, the
readings: its 0.02-0.025 um gauge noise is in its figures), except ``learned_over_noise``, which is the readings' own
image-region RMS error over their noise, as learning judges it.

Figures (each with the worst over the stages and every stage's value):

* ``fast_rms_pct_by_rate``: image-region RMS of the fast-axis error, % of the frame width, at 1,
  10, 30 and 100 lines/s, the open-loop inverse and the paper's linear filter beside it;
* ``registration_px``: trace vs retrace (RMS over the image, pixels) at 10 lines/s, inverse;
* ``slow_deviation_px``: RMS slow-axis error in line pitches at 10 lines/s, inverse;
* ``decoupling_db``: the line-synchronous slow motion (the y motion the fast x causes) at
  10 lines/s without and with the coupling's feed-forward (inverse both times), and the reduction
  in dB; ``floor_um`` is twice the y gauge noise over the image's pixels' mean (what the noise-free
  readings cannot go below is 0: the figure is the model's);
* ``learned_over_noise``: after at most 5 learned frames at 30 lines/s
  (:func:`afmctl.experiment.scanlearn.learn`, both axes), the best frame's image-region RMS over
  the noise (the larger axis); per stage (``stages``) the frames, why learning stopped, every
  frame's figure (``over_noise_by_frame``) and each axis's learning cut-off (``cutoff_hz``);
* ``frame_seconds_compute``: host time to plan one 128 x 64 frame at 10 lines/s (both axes, both
  filters, guard included) and make its images.

Run: ``python benchmarks/bench_scan.py --json`` (last line one JSON object); ``--stages N``
for the first N foreign stages (default 4); ``--stage NAME`` for one stage, whose row
``--cache DIR`` keeps (``<stage>-<settings>-row.json``): stages run apart are then collected by a
last run over them all.
"""

from __future__ import annotations

import argparse
import dataclasses as dc
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from afmctl.drivers.device.foreign import xy_stage as xys
from afmctl.drivers.device.foreign import xy_sweeps
from afmctl.experiment import scan as xs
from afmctl.experiment import scanlearn
from afmctl.files import xymodelfile, xysweepfile
from afmctl.fit import identify as idf
from afmctl.fit import xyidentify
from afmctl.guard import Limits, LimitError
from afmctl.planning import raster as rs
from afmctl.planning import sweepdesign as sd
from afmctl.planning import scanimage as si

RATE_HZ = 10000.0
DT = 1.0 / RATE_HZ
RATES = (1.0, 10.0, 30.0, 100.0)
PIXELS, LINES = 128, 64
LINES_AT_1_HZ = 8
MAX_FRAME_UM = 60.0
LEARN_FRAMES = 5
FRAME_SHARE = 0.9
#: The figures of a frame whose waveform no inversion horizon keeps within the limits (refused
#: before anything moves: the stage cannot scan it at that rate).
REFUSED: dict[str, Any] = {"fast_rms_pct": None}
#: Identification settings (``--identify``): ``quick`` fits the parametric model once (no
#: Preisach-grid alternative, one start), ``full`` is ``afmctl identify``'s default.
IDENTIFY = {"quick": idf.Settings(representation="hem", restarts=1), "full": idf.Settings()}
#: Foreign stages' sweep sets (``--design``): the writer's own, or with :func:`reversal_plans`
#: (the default); the cache's file names carry the suffix.
DESIGN_KEY = {"writer": "", "reversals": "-reversals"}


class EmulatedStage:
    """The emulated x/y stage through the stage interface; ``last_clean`` holds the last play's
    readings (the device gives no others)."""

    channels = 2

    def __init__(self, stage: Any) -> None:
        self.stage = stage
        self.last_clean = np.zeros((0, 2))

    def voltages(self) -> np.ndarray:
        return np.asarray(self.stage.voltages(), dtype=float)

    def play(self, v: np.ndarray, on_block: Any = None, **kw: Any) -> np.ndarray:
        rec = self.stage.play(v, on_block, **kw)
        self.last_clean = rec.displacement_um
        return rec


def emulated_sweeps(stage: Any, prof: Any) -> list[Any]:
    """The foreign stages' two-axis design (:mod:`~afmctl.drivers.device.foreign.xy_sweeps`) on the
    emulated stage's ranges, band half its shared mode, recorded through the stage interface."""
    from types import SimpleNamespace

    ranges = [SimpleNamespace(drive_range_V=(lim.v_min, lim.v_max))
              for lim in (prof.axis(n).limits for n in rs.AXES)]
    band = 0.5 * min(c.mode_hz for c in dict(prof.emulator.coupling).values())
    fake = SimpleNamespace(actuators=ranges)
    plans = xy_sweeps._held_files(fake, 0, band) + xy_sweeps._held_files(fake, 1, band)
    out = []
    for plan in plans:
        start = np.asarray(stage.voltages(), dtype=float)
        steps = int(np.ceil(np.max(np.abs(plan.voltage_V[0] - start)) / 2.0)) + 2
        stage.play(np.linspace(start, plan.voltage_V[0], steps))
        rec = stage.play(plan.voltage_V)
        out.append(xysweepfile.from_arrays(plan.voltage_V, rec.displacement_um, RATE_HZ,
                                           {**plan.meta, "sample_rate_hz": f"{RATE_HZ:g}",
                                            "layer_thickness_um": "100.0"}, plan.name))
    return out


def emulated_model(stage: Any, prof: Any, cache: Path | None, how: str) -> tuple[Any, float]:
    """The emulated stage's two-axis model identified from its recorded set (cached)."""
    path = None if cache is None else cache / f"emulated-xy-{how}.toml"
    if path is not None and path.exists():
        return xymodelfile.read(path), 0.0
    t0 = time.perf_counter()
    fit = xyidentify.fit(emulated_sweeps(stage, prof), IDENTIFY[how])
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        xymodelfile.write(fit.model, path, "identified by benchmarks/bench_scan.py")
    return fit.model, time.perf_counter() - t0


class PlantStage:
    """A foreign x/y plant as a stage: ``play`` of (N, 2) voltages block by block, readings with
    each axis's gauge noise; ``last_clean`` keeps the noise-free readings of the last play."""

    channels = 2

    def __init__(self, stage: xys.XYStage, seed: int) -> None:
        self.stage, self.state = stage, xys.initial_state(stage)
        self.rng = np.random.default_rng(seed)
        self.v = np.zeros(2)
        self.last_clean = np.zeros((0, 2))

    def voltages(self) -> np.ndarray:
        return self.v.copy()

    def play(self, v: np.ndarray, on_block: Any = None, **_: Any) -> np.ndarray:
        _, clean, self.state = xys.run(self.stage, v, RATE_HZ, self.state)
        read = clean + xys.noise_um(self.stage) * self.rng.standard_normal(clean.shape)
        if on_block is not None:
            on_block(0, v, read, np.ones(v.shape, dtype=bool))
        self.v, self.last_clean = np.asarray(v[-1], dtype=float), clean
        return read


def limits(stage: xys.XYStage) -> dict[str, Limits]:
    """Each axis's guard limits: its drive range, the sweeps' 50 V/ms."""
    return {n: Limits(lo, hi, xy_sweeps.SLEW_V_PER_MS, 100.0, 2.0)
            for n, (lo, hi) in zip(rs.AXES, stage.drive_range_V, strict=True)}


def reversal_plans(stage: xys.XYStage) -> list[xy_sweeps.XYPlan]:
    """``afmctl sweep --axes x,y --design reversals``'s extra files on the stage: each axis's
    reversal curves (:func:`afmctl.planning.sweepdesign.reversals_sweep`, at the writer's design
    slew) with the other held mid-range."""
    out = []
    for i, (lo, hi) in enumerate(stage.drive_range_V):
        name, f, v, meta = sd.reversals_sweep(
            (lo, hi), xy_sweeps.RATE_HZ, xy_sweeps.DESIGN_SLEW_V_PER_MS * 1e3)
        both = np.full((v.size, 2), 0.5 * sum(stage.drive_range_V[1 - i]))
        both[:, i] = v
        out.append(xy_sweeps.XYPlan(f"xy_{rs.AXES[i]}_{name}", both, {
            **meta, "frequency_hz": f"{f:g}", "swept_axis": rs.AXES[i],
            "sample_rate_hz": f"{xy_sweeps.RATE_HZ:g}", "layer_thickness_um": "100.0"}))
    return out


def identified(stage: xys.XYStage, cache: Path | None, how: str, design: str
               ) -> tuple[Any, float]:
    """The stage's two-axis model identified from its own sweep set (``design`` "reversals":
    with :func:`reversal_plans` after it; cached), and the seconds."""
    path = None if cache is None else cache / f"{stage.name}-{how}{DESIGN_KEY[design]}.toml"
    if path is not None and path.exists():
        return xymodelfile.read(path), 0.0
    t0 = time.perf_counter()
    extra = reversal_plans(stage) if design == "reversals" else []
    with tempfile.TemporaryDirectory() as d:
        files = xy_sweeps.write_sweep_set(stage, d, np.random.default_rng(11), extra=extra)
        fit = xyidentify.fit(xysweepfile.read_set(files) or [], IDENTIFY[how])
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        xymodelfile.write(fit.model, path, "identified by benchmarks/bench_scan.py")
    return fit.model, time.perf_counter() - t0


def scan(plant: PlantStage, axes: dict[str, rs.AxisPlan], coupling: Any, frame: rs.Frame,
         filters: tuple[str, ...] = ("inverse", "linear")) -> dict[str, Any]:
    """Plan and play one frame per filter; figures of merit on the noise-free readings."""
    t0 = time.perf_counter()
    axes = rs.replace_start(axes, plant.voltages())
    try:
        plans = rs.plan(frame, axes, DT, coupling, filters)
    except LimitError as exc:  # the linear filter's line beyond the limits: the inverse alone
        if "linear" not in filters or "linear" not in str(exc):
            return {"compute_s": None, "refused": str(exc), **{f: REFUSED for f in filters}}
        plans = rs.plan(frame, axes, DT, coupling, ("inverse",))
    grid = rs.pixel_grid(frame, DT)
    compute = time.perf_counter() - t0
    out: dict[str, Any] = {"compute_s": compute, "linear": {"fast_rms_pct": None}}
    for name, wf in plans.items():
        plant.play(wf.voltage_v)
        t1 = time.perf_counter()
        out[name] = si.merit(frame, si.images(frame, grid, plant.last_clean[wf.tracking]))
        out["compute_s"] += time.perf_counter() - t1
    return out


def frame_size(reach: dict[str, tuple[float, float]]) -> float:
    """The largest square frame up to 60 um that fits 90 % of the reach at its centre (whole
    um): the linear filter's line needs more voltage than the inverse near the reach's ends."""
    probe = rs.Frame(MAX_FRAME_UM, MAX_FRAME_UM, PIXELS, LINES, 10.0, centre(reach))
    scale = FRAME_SHARE * rs.largest_scale(probe, reach)
    return float(min(MAX_FRAME_UM, math.floor(MAX_FRAME_UM * scale)))


def both_filters_size(axes: dict[str, rs.AxisPlan], reach: dict[str, tuple[float, float]]
                      ) -> float:
    """:func:`frame_size`, shrunk in 10 % steps until the linear filter's waveform passes the
    guard too (a two-line frame at 10 lines/s is planned to see; at least 10 um)."""
    size = frame_size(reach)
    while size > 10.0:
        probe = rs.Frame(size, size, PIXELS, 2, 10.0, centre(reach))
        try:
            rs.plan(probe, axes, DT, None, ("inverse", "linear"))
            break
        except LimitError:
            size = max(10.0, float(math.floor(0.9 * size)))
    return size


def centre(reach: dict[str, tuple[float, float]]) -> tuple[float, float]:
    return tuple(0.5 * (lo + hi) for lo, hi in reach.values())  # type: ignore[return-value]


def bench_stage(stage: xys.XYStage, cache: Path | None, how: str, design: str, say: Any
                ) -> dict[str, Any]:
    model, fit_s = identified(stage, cache, how, design)
    say(f"{stage.name}: identified ({fit_s:.0f} s)")
    lim = limits(stage)
    axes = {n: rs.AxisPlan(model.axes[n], lim[n]) for n in rs.AXES}
    row = bench_frames(PlantStage(stage, 7), axes, dict(model.coupling), stage.name, say)
    return {**row, "identify_s": round(fit_s, 1),
            "noise_um": [float(x) for x in xys.noise_um(stage)]}


def bench_emulated(cache: Path | None, how: str, say: Any) -> dict[str, Any]:
    from afmctl.drivers.inprocess import InProcessStage, accelerated
    from afmctl.files.profile import load_profile

    prof = load_profile("emulated-xy")
    # the whole of every run in the device's table: a loaded host refilling a stream at 4x real
    # time underran it (the device then stops, as it must)
    big = 1 << 21
    prof = dc.replace(prof, emulator=dc.replace(prof.emulator, table_capacity=big,
                                                recorder_capacity=big))
    with InProcessStage(prof, clock=accelerated(4.0)) as dev:
        model, fit_s = emulated_model(dev, prof, cache, how)
        say(f"emulated-xy: identified ({fit_s:.0f} s)")
        axes = {n: rs.AxisPlan(model.axes[n], prof.axis(n).limits) for n in rs.AXES}
        row = bench_frames(EmulatedStage(dev), axes, dict(model.coupling), "emulated-xy", say)
    return {**row, "identify_s": round(fit_s, 1),
            "noise_um": [prof.axis(n).emulator.noise_um for n in rs.AXES]}


def bench_frames(plant: Any, axes: dict[str, rs.AxisPlan], coupling: dict[str, Any], name: str,
                 say: Any) -> dict[str, Any]:
    """Every figure on one stage (see the module docstring)."""
    reach = rs.reach(axes)
    size = both_filters_size(axes, reach)
    base = rs.Frame(size, size, PIXELS, LINES, 10.0, centre(reach))
    row: dict[str, Any] = {"frame_um": size,
                           "fast_rms_pct_by_rate": {"inverse": {}, "linear": {}}}
    for rate in RATES:
        fr = dc.replace(base, line_rate_hz=rate, lines=LINES_AT_1_HZ if rate == 1 else LINES)
        got = scan(plant, axes, coupling, fr)
        for f in ("inverse", "linear"):
            row["fast_rms_pct_by_rate"][f][f"{rate:g}"] = got[f]["fast_rms_pct"]
        if "refused" in got:
            row.setdefault("refused", {})[f"{rate:g}"] = got["refused"]
        if rate == 10:
            row["registration_px"] = got["inverse"]["registration_px"]
            row["slow_deviation_px"] = got["inverse"]["slow_deviation_px"]
            row["frame_seconds_compute"] = got["compute_s"]
            with_ff = got["inverse"]["slow_line_synchronous_um"]
            without = scan(plant, axes, None, fr, ("inverse",))["inverse"][
                "slow_line_synchronous_um"]
            row["decoupling"] = {"without_um": without, "with_um": with_ff,
                                 "db": si.decoupling_db(without, with_ff)}
        say(f"{name}: {rate:g} lines/s done")
    small = scan(plant, axes, coupling, dc.replace(base, width_um=10.0, height_um=10.0))
    row["small_10um_fast_rms_pct"] = {f: small[f]["fast_rms_pct"] for f in ("inverse", "linear")}
    with tempfile.TemporaryDirectory() as d:
        setup = xs.Setup(dc.replace(base, line_rate_hz=30.0), axes, coupling, ("inverse",), DT)
        got = scanlearn.learn(plant, setup, LEARN_FRAMES, Path(d), {})
    row["learned_over_noise"] = got.runs[got.best].merit["over_noise"]
    row["learning"] = {"frames": len(got.runs) - 1, "stop": got.stop,
                       "over_noise_by_frame": [r.merit["over_noise"] for r in got.runs],
                       "cutoff_hz": got.cutoffs_hz}
    say(f"{name}: {json.dumps(row)}")
    return row


def collect(rows: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The JSON object: each figure's worst over the stages and every stage's value."""
    def worst(get: Any, pick: Any = max) -> float | None:
        vals = [v for v in (get(r) for r in rows.values()) if v is not None]
        return float(pick(vals)) if vals else None

    by_rate = {f: {f"{r:g}": worst(lambda x, f=f, r=r: x["fast_rms_pct_by_rate"][f][f"{r:g}"])
                   for r in RATES} for f in ("inverse", "linear")}
    return {
        "fast_rms_pct_by_rate": {**by_rate, "frame_um": {k: r["frame_um"] for k, r in rows.items()},
                                 "small_10um": {k: r["small_10um_fast_rms_pct"]
                                                for k, r in rows.items()},
                                 "stages": {k: r["fast_rms_pct_by_rate"] for k, r in rows.items()}},
        "registration_px": {"worst": worst(lambda r: r["registration_px"]),
                            "stages": {k: r["registration_px"] for k, r in rows.items()}},
        "slow_deviation_px": {"worst": worst(lambda r: r["slow_deviation_px"]),
                              "stages": {k: r["slow_deviation_px"] for k, r in rows.items()}},
        "decoupling_db": {"worst": worst(lambda r: r["decoupling"]["db"], min),
                          "stages": {k: r["decoupling"] for k, r in rows.items()}},
        "learned_over_noise": {"worst": worst(lambda r: r["learned_over_noise"]),
                               "stages": {k: r["learning"] for k, r in rows.items()}},
        "frame_seconds_compute": {"max": worst(lambda r: r["frame_seconds_compute"]),
                                  "stages": {k: r["frame_seconds_compute"]
                                             for k, r in rows.items()}},
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="last line: one JSON object")
    ap.add_argument("--stages", type=int, default=4, help="the first N foreign stages")
    ap.add_argument("--cache", type=Path, default=None, help="keep identified models here")
    ap.add_argument("--no-emulated", action="store_true", help="foreign stages only")
    ap.add_argument("--stage", action="append", default=None,
                    help="only this stage (emulated-xy or foreign-xy-N; repeatable); with "
                         "--cache each stage's row is kept and reused")
    ap.add_argument("--identify", choices=sorted(IDENTIFY), default="quick",
                    help="identification settings (quick: the parametric model, one start)")
    ap.add_argument("--design", choices=sorted(DESIGN_KEY), default="reversals",
                    help="foreign stages' sweep sets: the writer's alone, or with each axis's "
                         "reversal curves (afmctl sweep --axes x,y --design reversals)")
    args = ap.parse_args(argv)

    def say(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    names = ([] if args.no_emulated else ["emulated-xy"]) + [
        st.name for st in xys.xy_stages()[:args.stages]]
    stages = {st.name: st for st in xys.xy_stages()}
    rows = {}
    for name in args.stage or names:
        key = f"{args.identify}{'' if name == 'emulated-xy' else DESIGN_KEY[args.design]}"
        row_path = None if args.cache is None else args.cache / f"{name}-{key}-row.json"
        if row_path is not None and row_path.exists():
            rows[name] = json.loads(row_path.read_text())
            continue
        rows[name] = (bench_emulated(args.cache, args.identify, say) if name == "emulated-xy"
                      else bench_stage(stages[name], args.cache, args.identify, args.design, say))
        if row_path is not None:
            row_path.write_text(json.dumps(rows[name]))
    data = collect(rows)
    if args.json:
        print(json.dumps(data, allow_nan=True))
    else:
        print(json.dumps(data, indent=2))
    return data


if __name__ == "__main__":
    main()
