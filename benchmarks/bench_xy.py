"""Issue 25 figures: the coupling of two-axis stages identified from their sweeps.

Stages: the emulated two-axis stage (profile ``emulated-xy``: its set recorded through the driver
by the design of ``afmctl sweep --axes x,y``, its truth the profile's ``[emulator.coupling]``) and
the foreign x/y stages of ``drivers/device/foreign/xy_stage.py`` (``xy_stages()``: their own
formulas, hysteretic actuators of four kinds, a 3-DOF structure whose shared mode the actuators'
forces drive, a flexure arc; static coupling -45 to -25 dB, shared modes 150 to 800 Hz, unipolar
and bipolar), each with the sweep set its writer designs (``write_sweep_set``: triangles with the
other axis held at 25/60/85 %, a multisine on x and a chirp on y to half the shared mode, one file
with both moving), its truth ``true_coupling``.

Keys (the last stdout line is one JSON object):

``stages``
    Stages identified.
``coupling_static_db_error_max``
    Largest ``|20 log10(identified / true)|`` of the static coupling, both directions, dB.
``coupling_frf_db_error_max``, ``coupling_frf_deg_error_max``
    Largest gain (dB) and phase (deg) error of the identified response against the true one on 25
    log-spaced frequencies from 1 Hz to 0.2 of the shared mode, both directions.
``axis_over_noise_max``
    Largest fit RMS of any sweep of any axis over that axis's true sensor noise (the stages whose
    axes were fitted: ``axis_stages``).
``held_axis_motion_um``
    ``afmctl track --axis x`` on the emulated stage (a 5.58 Hz triangle of 30 um): RMS and peak of
    how far y moved, um.
``identify_seconds``
    Wall time of the two-axis identify on the emulated stage's set (``identify_cpu_seconds``: CPU
    of this process and its workers; the machine may be shared). ``identify_seconds_foreign``: the
    median over the foreign stages whose axes were fitted.
``rows``
    One row per stage.

Run from the repo root: ``python -m benchmarks.bench_xy --json`` (``--axis-stages N``: fit the
axes of the first N foreign stages only, the coupling of all; ``--held`` off skips the track run).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from afmctl.drivers import open_stage
from afmctl.drivers.device.foreign import xy_stage as xst
from afmctl.drivers.device.foreign import xy_sweeps as xsw
from afmctl.errors import StageError
from afmctl.experiment import xyrecord
from afmctl.files import xysweepfile as xs
from afmctl.files.profile import shipped_profile
from afmctl.fit import coupling as fc
from afmctl.fit import xyidentify as xi
from afmctl.model import coupling as cp
from afmctl.planning import sweepdesign as sd

N_FREQ = 25
#: Attempts per emulated file (a stream underrun on a loaded machine stops a run; it is recorded
#: again, as a lab would).
RETRIES = 3
HELD_TRIANGLE = ("5.58", "30")  # --freq Hz, --amplitude um of the track run


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _cpu() -> float:
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def errors(fit: fc.CouplingFit, true_static: float, true_frf: np.ndarray, freq: np.ndarray
           ) -> dict[str, float]:
    """Static (dB) and response (dB, deg) errors of one direction."""
    h = fit.response(freq)[0]
    ratio = h / true_frf
    return {"static": fit.coupling.static, "true_static": true_static,
            "static_db_error": float(abs(20 * np.log10(abs(fit.coupling.static / true_static)))),
            "frf_db_error": float(np.max(np.abs(20 * np.log10(np.abs(ratio))))),
            "frf_deg_error": float(np.max(np.abs(np.degrees(np.angle(ratio))))),
            "mode_hz": fit.coupling.mode_hz}


def judge(name: str, sweeps: list[xs.XYSweep], truth, mode_hz: float,  # noqa: ANN001
          noise: dict[str, float] | None) -> dict:
    """Identify a set (its axes too if ``noise`` is given) and judge it against ``truth(freq)``."""
    freq = np.geomspace(1.0, 0.2 * mode_hz, N_FREQ)
    true = truth(freq)
    t0, c0 = time.perf_counter(), _cpu()
    row: dict = {"stage": name, "mode_hz": mode_hz}
    if noise is not None:
        res = xi.fit(sweeps)
        couplings = res.coupling
        row["identify_seconds"] = time.perf_counter() - t0
        row["identify_cpu_seconds"] = _cpu() - c0
        row["axis_over_noise"] = {a: max(s.rms_um / noise[a] for s in r.sweeps)
                                  for a, r in res.axes.items()}
        row["representation"] = {a: r.representation for a, r in res.axes.items()}
    else:
        couplings = {xi.direction(t, xi._other(t)): fc.identify(xi.coupling_records(sweeps, t))
                     for t in ("x", "y")}
    for d, c in couplings.items():
        row[d] = errors(c, true[f"{d}_static"], true[f"{d}_frf"], freq)
    return row


def emulated(tmp: Path, held: bool) -> tuple[dict, dict]:
    """Record the two-axis design on the emulated stage, identify it, track on x."""
    prof = shipped_profile("emulated-xy")
    em = prof.emulator
    assert em is not None
    truth_c = dict(em.coupling)
    limits = {a: prof.axis(a).limits for a in ("x", "y")}
    rod = {a: prof.axis(a).emulator.model.rod for a in ("x", "y")}  # type: ignore[union-attr]
    first = min(float(np.sqrt(r.k / r.m) / (2 * np.pi)) for r in rod.values())
    design = sd.xy_design(prof.sample_rate_hz, {a: (v.v_min, v.v_max) for a, v in limits.items()},
                          {a: v.max_rate_v_per_ms * 1e3 for a, v in limits.items()}, 0.5 * first)
    out = tmp / "emulated"
    out.mkdir()
    paths = []
    with open_stage(prof) as stage:
        for one in design:
            for attempt in range(RETRIES):
                try:
                    paths += xyrecord.record(stage, [one], prof.sample_rate_hz, limits, out,
                                             {"layer_thickness_x_um": "100",
                                              "layer_thickness_y_um": "100"}, log)
                    break
                except StageError as exc:  # a loaded machine's host may fall behind the stream
                    log(f"{one[0]}: {exc}; again ({attempt + 1} of {RETRIES})")
            else:
                raise RuntimeError(f"{one[0]}: not recorded in {RETRIES} attempts")
    sweeps = [xs.read(p) for p in paths]

    def truth(freq: np.ndarray) -> dict:
        return {**{f"{d}_static": c.static for d, c in truth_c.items()},
                **{f"{d}_frf": cp.frf(c, freq) for d, c in truth_c.items()}}

    noise = {a: prof.axis(a).emulator.noise_um for a in ("x", "y")}  # type: ignore[union-attr]
    mode = truth_c["yx"].mode_hz
    row = judge("emulated-xy", sweeps, truth, mode, noise)
    motion = track_held(tmp, paths) if held else {}
    return row, motion


def track_held(tmp: Path, paths: list[Path]) -> dict:
    """``afmctl track --axis x`` on the emulated stage with the model identified from ``paths``."""
    model = tmp / "xy_model.toml"
    cmd = [sys.executable, "-m", "afmctl", "identify", *map(str, paths), "-o", str(model)]
    subprocess.run(cmd, check=True, capture_output=True)
    cmd = [sys.executable, "-m", "afmctl", "track", "triangle", "--profile", "emulated-xy",
           "--axis", "x", "--model", str(model), "--freq", HELD_TRIANGLE[0], "--amplitude",
           HELD_TRIANGLE[1], "--offset", "centre", "--filter", "inverse", "--out",
           str(tmp / "track"), "--json"]
    done = subprocess.run(cmd, check=True, capture_output=True, text=True)
    doc = json.loads(done.stdout.strip().splitlines()[-1])
    return doc["held_axis"]


def foreign(tmp: Path, axis_stages: int) -> list[dict]:
    rows = []
    for i, stage in enumerate(xst.xy_stages()):
        out = tmp / f"foreign-{i}"
        paths = xsw.write_sweep_set(stage, out, np.random.default_rng(7000 + i))
        sweeps = [xs.read(p) for p in paths]
        mode = xst.mode_hz(stage.structure)
        sig = xst.noise_um(stage)
        noise = {"x": float(sig[0]), "y": float(sig[1])} if i < axis_stages else None
        row = judge(stage.name, sweeps, lambda f, s=stage: xst.true_coupling(s, f), mode, noise)
        log(f"{stage.name}: " + ", ".join(
            f"{d} static {row[d]['static_db_error']:.2f} dB, frf {row[d]['frf_db_error']:.2f} dB "
            f"{row[d]['frf_deg_error']:.1f} deg" for d in ("yx", "xy"))
            + (f"; axes {row['axis_over_noise']}, {row['identify_seconds']:.1f} s"
               if noise else ""))
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--axis-stages", type=int, default=len(xst.BENCH_SPECS),
                    help="fit the axes of this many foreign stages (the coupling of all)")
    ap.add_argument("--no-held", dest="held", action="store_false",
                    help="skip the track --axis x run")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        em_row, motion = emulated(tmp, args.held)
        log(f"emulated-xy: {em_row}")
        rows = [em_row] + foreign(tmp, args.axis_stages)
    dirs = [r[d] for r in rows for d in ("yx", "xy")]
    fitted = [r for r in rows if "axis_over_noise" in r]
    out = {
        "stages": len(rows),
        "coupling_static_db_error_max": max(d["static_db_error"] for d in dirs),
        "coupling_frf_db_error_max": max(d["frf_db_error"] for d in dirs),
        "coupling_frf_deg_error_max": max(d["frf_deg_error"] for d in dirs),
        "axis_over_noise_max": max(max(r["axis_over_noise"].values()) for r in fitted),
        "axis_stages": len(fitted),
        "held_axis_motion_um": motion,
        "identify_seconds": em_row["identify_seconds"],
        "identify_cpu_seconds": em_row["identify_cpu_seconds"],
        "identify_seconds_foreign": (float(np.median([r["identify_seconds"] for r in fitted[1:]]))
                                     if len(fitted) > 1 else None),
        "rows": rows,
    }
    if args.json:
        print(json.dumps(out))


if __name__ == "__main__":
    main()
