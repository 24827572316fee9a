"""``afmctl score``: score and plot run files that track or play wrote (complete or not)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import click

from afmctl.cli.base import (
    check_output_dir,
    main,
    make_dir,
    say,
    timestamped,
    writing,
)
from afmctl.errors import InputError

OUTPUTS = ("summary.json", "track.png")


def _period(meta: dict[str, str]) -> float | None:
    """The trajectory's period, s: ``period_s``, else from a ``triangle 27.9 Hz, ...`` label."""
    if "period_s" in meta:
        return float(meta["period_s"])
    m = re.match(r"(?:triangle|sine) ([0-9.eE+-]+) Hz", meta.get("trajectory", ""))
    return 1.0 / float(m.group(1)) if m else None


def _run(path: str, model: Any) -> tuple[str, Any, Any]:
    """(filter name, Outcome, Desired) of one run file, scored as track scores it."""
    import numpy as np

    from afmctl.experiment import runner as experiment
    from afmctl.files import runfile
    from afmctl.planning import track
    run = runfile.read(path)
    if run.seq.size < 2:
        raise InputError(f"{path}: fewer than 2 samples")
    dt = float(np.median(np.diff(run.time_s)))
    ok = np.flatnonzero(np.isfinite(run.desired_um))
    if ok.size < 2 or ok.size != ok[-1] - ok[0] + 1:
        raise InputError(f"{path}: no desired trajectory to score against (desired_um must be "
                         f"one contiguous run of values)")
    tracking = slice(int(ok[0]), int(ok[-1]) + 1)
    u = run.desired_um[tracking]
    label = run.meta.get("trajectory", Path(path).stem)
    desired = track.Desired(dt, u, _period(run.meta), float(np.ptp(u)), label)
    name = run.meta.get("filter", Path(path).stem)
    wf = track.Waveform(name, dt, run.voltage_v, run.desired_um, tracking)
    measured = (run.displacement_um, run.voltage_v,
                run.complete and bool(np.isfinite(run.displacement_um).all()))
    outcome = experiment.scored(wf, desired, measured, Path(path),
                                None if model is None else model.effects)
    return name, outcome, desired


@main.command("score")
@click.argument("run_files", nargs=-1, required=True)
@click.option("--model", "model_path", type=click.Path(dir_okay=False),
              help="Model file whose sensor effects correct the readings before scoring (as "
                   "track did with it); default: the readings as they are.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Output folder for summary.json and track.png (default: "
                   "./afmctl-score-<time>).")
@click.option("--force", is_flag=True, help="Overwrite summary.json and track.png in --out.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary JSON on stdout.")
def score(run_files: tuple[str, ...], model_path: str | None, out_dir: str | None, force: bool,
          as_json: bool) -> None:
    """Score and plot RUN_FILES (run_*.csv of track or play, complete or interrupted) against the
    desired trajectory they hold, as track scores them: RMS and maximum error over the steady
    part (one period in), the first period apart; samples never received are left out.

    Several run files of one trajectory (e.g. run_inverse.csv run_linear.csv) are compared."""
    import numpy as np

    from afmctl import plots
    from afmctl.experiment import runner as experiment
    from afmctl.files import modelfile
    from afmctl.model import effects as fx
    model = modelfile.read(model_path) if model_path else None
    runs = [_run(p, model) for p in run_files]
    desired = runs[0][2]
    for p, (_, _, d) in zip(run_files[1:], runs[1:], strict=True):
        if d.u_um.shape != desired.u_um.shape or not (d.u_um == desired.u_um).all():
            raise InputError(f"{p}: another desired trajectory than {run_files[0]}'s")
    outcomes = {}
    for p, (name, o, _) in zip(run_files, runs, strict=True):
        if name in outcomes:
            name = Path(p).stem
        outcomes[name] = o
    out = check_output_dir(Path(out_dir) if out_dir else timestamped("afmctl-score"), "--out",
                           OUTPUTS, force)
    corrected = modelfile.effects_dict(fx.sensor_part(model.effects)) if model else {}
    data = experiment.summary(outcomes, desired, {
        "run_files": list(run_files), "model": model_path, "readings_corrected_for": corrected})
    make_dir(out, "--out")
    with writing(out, "--out"):
        experiment.write_summary(data, out / "summary.json")
        thickness = model.thickness_um if model is not None else 1.0
        plots.save_figure(plots.track_figure(outcomes, desired, thickness, ", ".join(
            k.replace("_", " ") for k in corrected)), out / "track.png")
    if corrected:
        say(f"readings corrected for {', '.join(corrected)} (--model's sensor effects)")
    for name, o in outcomes.items():
        s = o.score
        part = (f"steady part, from {s.steady_from_s:.4g} s" if s.steady else "whole run")
        missing = int(np.isnan(o.scored_um[o.waveform.tracking]).sum())
        gaps = f"; {missing} samples missing" if missing else ""
        say(f"{name:8s} RMS {s.rms_um:.4f} um ({s.rms_pct:.3f} %), max {s.max_um:.4f} um "
            f"({part}){gaps}" + ("" if o.complete else "; incomplete run"))
    if "ratio_linear_over_inverse" in data:
        say(f"ratio linear / inverse RMS: {data['ratio_linear_over_inverse']:.1f} (steady part)")
    say(f"wrote {out}/" + ", ".join(OUTPUTS))
    if as_json:
        click.echo(json.dumps(experiment.json_ready(data), allow_nan=False))
