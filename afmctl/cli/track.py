"""``afmctl track``: the paper's open-loop experiment."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from afmctl.cli.base import Group, fail, load_profile_or_exit, main, progress_printer


@main.group(cls=Group)
def track() -> None:
    """Open-loop tracking with the model-based inverse filter (and the linear one to compare)."""


def track_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    opts = [
        click.option("--profile", "profile_path", type=click.Path(dir_okay=False),
                     help="Stage profile (default: the embedded emulated stage)."),
        click.option("--model", "model_path", type=click.Path(dir_okay=False),
                     help="Model file (default: identified from the stage's own sweeps, cached)."),
        click.option("--filter", "filters", type=click.Choice(["inverse", "linear", "both"]),
                     default="both", show_default=True),
        click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
                     help="Output folder (default: ./afmctl-track-<time>)."),
        click.option("--dry-run", is_flag=True,
                     help="Send nothing; write DIR/waveform_<filter>.csv."),
        click.option("--json", "as_json", is_flag=True, help="Print the summary JSON on stdout."),
        click.option("--condition/--no-condition", default=True, show_default=True,
                     help="Start with one slow full-range excursion (to the profile's voltage "
                          "limits) that wipes out the stage's hysteresis memory; --no-condition "
                          "skips it and assumes a depoled stage (less accurate)."),
        click.option("--extrapolate", is_flag=True,
                     help="Allow a waveform outside the model's validity envelope (the voltage "
                          "range it was identified on) by more than 5 % of its span."),
    ]
    for opt in reversed(opts):
        fn = opt(fn)
    return fn


def periodic_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    opts = [
        click.option("--freq", type=click.FloatRange(min=0, min_open=True), required=True,
                     help="Frequency, Hz."),
        click.option("--amplitude", type=click.FloatRange(min=0, min_open=True), required=True,
                     help="Peak-to-peak amplitude, um."),
        click.option("--offset", type=float, default=0.0, show_default=True,
                     help="Centre of the trajectory, um."),
        click.option("--periods", type=click.FloatRange(min=0, min_open=True), default=3.0,
                     show_default=True),
    ]
    for opt in reversed(opts):
        fn = opt(fn)
    return fn


@track.command("triangle")
@periodic_options
@track_options
def track_triangle(freq: float, amplitude: float, offset: float, periods: float,
                   **kw: Any) -> None:
    """Track a triangle wave (the paper's Figs. 9-11)."""
    from afmctl import track as trk
    _track(lambda dt: trk.triangle(freq, amplitude, offset, periods, dt), **kw)


@track.command("sine")
@periodic_options
@track_options
def track_sine(freq: float, amplitude: float, offset: float, periods: float, **kw: Any) -> None:
    """Track a sine wave."""
    from afmctl import track as trk
    _track(lambda dt: trk.sine(freq, amplitude, offset, periods, dt), **kw)


@track.command("file")
@click.argument("wave", type=click.Path(dir_okay=False))
@track_options
def track_file(wave: str, **kw: Any) -> None:
    """Track any trajectory: a CSV with columns time_s,desired_um."""
    from afmctl import sweeps
    from afmctl import track as trk
    t, u = sweeps.read_trajectory(wave)
    _track(lambda dt: trk.from_samples(t, u, dt, f"file {Path(wave).name}"), **kw)


def _out_dir(out_dir: str | None) -> Path:
    path = Path(out_dir) if out_dir else Path(f"afmctl-track-{time.strftime('%Y%m%d-%H%M%S')}")
    if path.exists() and any(path.glob("run_*.csv")):
        fail(f"{path} already holds run data; choose another --out (measured data is never "
             f"overwritten)")
    path.mkdir(parents=True, exist_ok=True)
    return path


def _envelope(prof: Any, model_path: str | None) -> Any:
    """The validity envelope of the model in use (None for a model file without one)."""
    from afmctl import calibration, modelfile
    return modelfile.read_envelope(model_path or calibration.cache_dir(prof) / "model.toml")


def _track(make_desired: Callable[[float], Any], profile_path: str | None,
           model_path: str | None, filters: str, out_dir: str | None, dry_run: bool,
           as_json: bool, condition: bool, extrapolate: bool) -> None:
    from afmctl import calibration, experiment, modelfile
    from afmctl import effects as fx
    from afmctl import track as trk
    prof = load_profile_or_exit(profile_path)
    desired = make_desired(1.0 / prof.sample_rate_hz)
    wanted = ("inverse", "linear") if filters == "both" else (filters,)
    say = progress_printer(False)
    if dry_run:
        model = (modelfile.read(model_path) if model_path
                 else calibration.cached_model(prof, None, say))
        plans = trk.plan(model, desired, prof.limits, 0.0, wanted, condition=condition,
                         envelope=_envelope(prof, model_path), extrapolate=extrapolate)
        out = _out_dir(out_dir)
        for name in wanted:
            experiment.write_waveform_csv(plans[name], out / f"waveform_{name}.csv")
            click.echo(f"wrote {out / f'waveform_{name}.csv'}", err=True)
        return
    from drivers import open_stage
    with open_stage(prof) as stage:
        model = (modelfile.read(model_path) if model_path
                 else calibration.cached_model(prof, stage, say))
        start_v = stage.voltage()
        click.echo(f"planning {desired.label} from {start_v:.3f} V ...", err=True)
        plans = trk.plan(model, desired, prof.limits, start_v, wanted, condition=condition,
                         envelope=_envelope(prof, model_path), extrapolate=extrapolate)
        out = _out_dir(out_dir)
        meta = {"profile": prof.name, "model": model_path or "identified (cached)",
                "trajectory": desired.label, "sample_rate_Hz": prof.sample_rate_hz}
        truth = prof.emulator.true_model if prof.emulator is not None else model
        outcomes = experiment.run_all(stage, {k: plans[k] for k in wanted}, desired, out, meta,
                                      truth, say, sensor=model.effects)
    data = experiment.summary(outcomes, desired, {
        **meta, "between_samples_model": "emulator truth" if prof.emulator else "model estimate",
        "readings_corrected_for": modelfile.effects_dict(fx.sensor_part(model.effects))})
    experiment.write_combined_csv(outcomes, desired, out / "run.csv")
    experiment.write_summary(data, out / "summary.json")
    experiment.plot(outcomes, desired, model.thickness_um, out / "track.png")
    for name, o in outcomes.items():
        click.echo(f"{name:8s} RMS {o.score.rms_um:.4f} um ({o.score.rms_pct:.3f} %), max "
                   f"{o.score.max_um:.4f} um; between samples {o.score.rms_between_um:.4f} um; "
                   f"max slew {o.waveform.max_slew_v_per_ms:.1f} V/ms", err=True)
    click.echo(f"wrote {out}/run.csv, summary.json, track.png", err=True)
    if as_json:
        click.echo(json.dumps(data))
