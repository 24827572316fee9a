"""``afmctl track``: the paper's open-loop experiment."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from afmctl.cli.base import (
    Finite,
    Group,
    check_output_dir,
    load_profile_or_exit,
    main,
    make_dir,
    opened_stage,
    progress_printer,
    say,
    timestamped,
    writing,
)
from afmctl.files.tomlfile import InputError

#: Fewest samples per period of a periodic trajectory (a triangle needs its corners sampled).
MIN_SAMPLES_PER_PERIOD = 20
#: Longest trajectory tracked in one run, s (memory: a few arrays of this many samples).
MAX_DURATION_S = 600.0
#: Largest amplitude or offset accepted before the model judges the reach, um.
MAX_UM = 1000.0


@main.group(cls=Group)
def track() -> None:
    """Open-loop tracking with the model-based inverse filter (and the linear one to compare)."""


def track_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    opts = [
        click.option("--profile", "profile_path", type=click.Path(dir_okay=False),
                     help="Stage profile (default: the embedded emulated stage)."),
        click.option("--model", "model_path", type=click.Path(dir_okay=False),
                     help="Model file (default: the stage's cached calibration; see "
                          "--calibrate)."),
        click.option("--calibrate", is_flag=True,
                     help="If the stage has no calibration yet, record the standard sweeps over "
                          "the profile's voltage range, identify the model, then track (moves "
                          "the stage over its whole range; needed on a real stage)."),
        click.option("--recalibrate", is_flag=True,
                     help="Record and identify a new calibration even if one is cached."),
        click.option("--filter", "filters", type=click.Choice(["inverse", "linear", "both"]),
                     default="both", show_default=True),
        click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
                     help="Output folder (default: ./afmctl-track-<time>)."),
        click.option("--force", is_flag=True,
                     help="Overwrite outputs in --out (never run files: measured data)."),
        click.option("--dry-run", is_flag=True,
                     help="Send nothing; write DIR/waveform_<filter>.csv."),
        click.option("--json", "as_json", is_flag=True, help="Print the summary JSON on stdout."),
        click.option("--condition/--no-condition", default=True, show_default=True,
                     help="Start with one slow excursion to the profile's voltage limits that "
                          "wipes out the stage's hysteresis memory; --no-condition skips it and "
                          "assumes a depoled stage (less accurate)."),
        click.option("--extrapolate", is_flag=True,
                     help="Allow a waveform outside the model's validity envelope (the voltage "
                          "range it was identified on) by more than 5 % of its span."),
        click.option("--learn", "learn", type=click.IntRange(min=0), default=0,
                     help="Learn from repeated scans: after the inverse (or --filter linear) "
                          "waveform, up to N iterations that correct it from the measured error "
                          "(writes every iteration's run file, waveform_learned.csv, learn.png)."),
        click.option("--learn-cutoff", type=click.FloatRange(min=0, min_open=True),
                     default=600.0, show_default=True,
                     help="Cut-off of the learning's zero-phase low-pass filter Q, Hz."),
        click.option("--learn-region", type=click.Choice(["all", "imaging"]), default="all",
                     show_default=True,
                     help="Learn from the error everywhere, or only in the imaging region (the "
                          "central 80 % of every ramp; for fast raster scans)."),
    ]
    for opt in reversed(opts):
        fn = opt(fn)
    return fn


def periodic_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    opts = [
        click.option("--freq", type=Finite(0, open_min=True), required=True,
                     help="Frequency, Hz."),
        click.option("--amplitude", type=Finite(0, open_min=True), required=True,
                     help="Peak-to-peak amplitude, um."),
        click.option("--offset", type=Finite(), default=0.0, show_default=True,
                     help="Centre of the trajectory, um."),
        click.option("--periods", type=Finite(0, open_min=True), default=3.0,
                     show_default=True,
                     help="Periods to track (>= 1; the first is the transient, scored apart)."),
        click.option("--allow-short", is_flag=True,
                     help="Allow --periods below 1 (no steady part to score)."),
    ]
    for opt in reversed(opts):
        fn = opt(fn)
    return fn


def check_periodic(freq: float, amplitude: float, offset: float, periods: float,
                   allow_short: bool, sample_rate_hz: float) -> None:
    """Every number of a periodic trajectory, against the stage, before anything is computed."""
    if periods < 1 and not allow_short:
        raise InputError(f"--periods {periods:g}: at least 1 (the first period is the transient, "
                         f"scored apart); --allow-short tracks less")
    per_period = sample_rate_hz / freq
    if per_period < MIN_SAMPLES_PER_PERIOD:
        raise InputError(f"--freq {freq:g} Hz: {per_period:.3g} samples per period at the "
                         f"stage's {sample_rate_hz:g} Hz; at most "
                         f"{sample_rate_hz / MIN_SAMPLES_PER_PERIOD:g} Hz "
                         f"({MIN_SAMPLES_PER_PERIOD} samples per period)")
    check_duration(periods / freq, f"--freq {freq:g} Hz with --periods {periods:g}")
    if periods * per_period < 2:
        raise InputError(f"--periods {periods:g} at --freq {freq:g} Hz: fewer than 2 samples")
    for name, value in (("--amplitude", amplitude), ("--offset", offset)):
        if abs(value) > MAX_UM:
            raise InputError(f"{name} {value:g} um: beyond any piezo stage (at most "
                             f"{MAX_UM:g} um)")


def check_duration(seconds: float, what: str) -> None:
    if seconds > MAX_DURATION_S:
        raise InputError(f"{what} lasts {seconds:.3g} s; at most {MAX_DURATION_S:g} s per run")


@track.command("triangle")
@periodic_options
@track_options
def track_triangle(freq: float, amplitude: float, offset: float, periods: float,
                   allow_short: bool, **kw: Any) -> None:
    """Track a triangle wave (the paper's Figs. 9-11)."""
    from afmctl.planning import track as trk
    _track(lambda dt: trk.triangle(freq, amplitude, offset, periods, dt),
           lambda rate: check_periodic(freq, amplitude, offset, periods, allow_short, rate), **kw)


@track.command("sine")
@periodic_options
@track_options
def track_sine(freq: float, amplitude: float, offset: float, periods: float, allow_short: bool,
               **kw: Any) -> None:
    """Track a sine wave."""
    from afmctl.planning import track as trk
    _track(lambda dt: trk.sine(freq, amplitude, offset, periods, dt),
           lambda rate: check_periodic(freq, amplitude, offset, periods, allow_short, rate), **kw)


@track.command("file")
@click.argument("wave", type=click.Path(dir_okay=False))
@track_options
def track_file(wave: str, **kw: Any) -> None:
    """Track any trajectory: a CSV with columns time_s,desired_um."""
    from afmctl.files import sweepfile as sweeps
    from afmctl.planning import track as trk
    t, u = sweeps.read_trajectory(wave)
    check_duration(float(t[-1] - t[0]), wave)
    _track(lambda dt: trk.from_samples(t, u, dt, f"file {Path(wave).name}"), lambda rate: None,
           **kw)


def _model(prof: Any, stage: Any | None, model_path: str | None, calibrate: bool,
           recalibrate: bool, profile_path: str | None) -> Any:
    """The calibration (``afmctl.experiment.calibration.Calibration``) track uses."""
    from afmctl.experiment import calibration
    from afmctl.files.profile import EmulatedTransport
    if model_path is not None:
        return calibration.from_file(model_path)
    emulated = isinstance(prof.transport, EmulatedTransport)
    if recalibrate or ((calibrate or emulated) and calibration.find(prof) is None):
        lo, hi = prof.limits.v_min, prof.limits.v_max
        say(f"calibrating: recording {calibration.N_SWEEPS} standard sweeps over [{lo:g}, "
            f"{hi:g}] V, then identifying ...")
    arg = f" --profile {profile_path}" if profile_path else ""
    return calibration.for_track(prof, stage, progress_printer(False), calibrate, recalibrate,
                                 arg)


def _outputs(dry_run: bool, wanted: tuple[str, ...]) -> list[str]:
    if dry_run:
        return [f"waveform_{name}.csv" for name in wanted]
    return ["run.csv", "summary.json", "track.png"]


def _track(make_desired: Callable[[float], Any], check: Callable[[float], None],
           profile_path: str | None, model_path: str | None, calibrate: bool, recalibrate: bool,
           filters: str, out_dir: str | None, force: bool, dry_run: bool, as_json: bool,
           condition: bool, extrapolate: bool, learn: int = 0, learn_cutoff: float = 600.0,
           learn_region: str = "all") -> None:
    if model_path is not None and (calibrate or recalibrate):
        raise InputError("--model and --calibrate/--recalibrate exclude each other")
    if learn and dry_run:
        raise InputError("--learn learns from measurements: it cannot be combined with "
                         "--dry-run")
    prof = load_profile_or_exit(profile_path)
    check(prof.sample_rate_hz)
    if learn:
        from afmctl.cli.play import learn_track
        desired = make_desired(1.0 / prof.sample_rate_hz)
        with opened_stage(prof) as stage:
            cal = _model(prof, stage, model_path, calibrate, recalibrate, profile_path)
            learn_track(desired, prof, cal.model, str(cal.path), stage, learn,
                        {"cutoff_hz": learn_cutoff, "region": learn_region},
                        "linear" if filters == "linear" else "inverse", (condition, extrapolate),
                        out_dir, as_json)
        return
    wanted = ("inverse", "linear") if filters == "both" else (filters,)
    out = check_output_dir(Path(out_dir) if out_dir else timestamped("afmctl-track"), "--out",
                           _outputs(dry_run, wanted), force, measured=("run_*.csv",))
    desired = make_desired(1.0 / prof.sample_rate_hz)
    if dry_run:
        _dry_run(prof, desired, wanted, out, (condition, extrapolate),
                 _model(prof, None, model_path, calibrate, recalibrate, profile_path))
        return
    with opened_stage(prof) as stage:
        cal = _model(prof, stage, model_path, calibrate, recalibrate, profile_path)
        outcomes, meta = _run(prof, stage, cal, desired, wanted, out, (condition, extrapolate))
    _report(prof, cal, outcomes, desired, out, meta, as_json)


def _plan(prof: Any, cal: Any, desired: Any, start_v: float, wanted: tuple[str, ...],
          how: tuple[bool, bool]) -> dict[str, Any]:
    """The waveforms, kept to the model's validity envelope (``how`` = (condition,
    extrapolate))."""
    from afmctl.files import modelfile
    from afmctl.planning import track as trk
    return trk.plan(cal.model, desired, prof.limits, start_v, wanted, condition=how[0],
                    envelope=modelfile.read_envelope(cal.path), extrapolate=how[1])


def _dry_run(prof: Any, desired: Any, wanted: tuple[str, ...], out: Path,
             how: tuple[bool, bool], cal: Any) -> None:
    from afmctl.experiment import runner as experiment
    plans = _plan(prof, cal, desired, 0.0, wanted, how)
    say(cal.describe())
    make_dir(out, "--out")
    for name in wanted:
        path = out / f"waveform_{name}.csv"
        with writing(path, "--out"):
            experiment.write_waveform_csv(plans[name], path)
        say(f"wrote {path}" + (f" ({plans[name].horizon_text()})" if name == "inverse" else ""))


def _run(prof: Any, stage: Any, cal: Any, desired: Any, wanted: tuple[str, ...], out: Path,
         how: tuple[bool, bool]) -> tuple[dict[str, Any], dict[str, Any]]:
    from afmctl.experiment import runner as experiment
    model = cal.model
    start_v = stage.voltage()
    say(f"planning {desired.label} from {start_v:.3f} V ...")
    plans = _plan(prof, cal, desired, start_v, wanted, how)
    say(cal.describe())
    make_dir(out, "--out")
    meta = {"profile": prof.name, "model": str(cal.path), "trajectory": desired.label,
            "sample_rate_Hz": prof.sample_rate_hz}
    truth = prof.emulator.true_model if prof.emulator is not None else model
    outcomes = experiment.run_all(stage, {k: plans[k] for k in wanted}, desired, out, meta,
                                  truth, progress_printer(False), sensor=model.effects,
                                  estimate=prof.emulator is None)
    return outcomes, meta


def _report(prof: Any, cal: Any, outcomes: dict[str, Any], desired: Any, out: Path,
            meta: dict[str, Any], as_json: bool) -> None:
    from afmctl.experiment import runner as experiment
    from afmctl.files import modelfile
    from afmctl.model import effects as fx
    estimate = prof.emulator is None
    data = experiment.summary(outcomes, desired, {
        **meta, "model": cal.as_dict(),
        "between_samples_from": "model estimate" if estimate else "emulator truth",
        "between_samples_misfit": ("the readings at the samples: the model's misfit there "
                                   "interpolated between them") if estimate else None,
        "readings_corrected_for": modelfile.effects_dict(fx.sensor_part(cal.model.effects))})
    written = [o.run_file.name for o in outcomes.values()] + ["run.csv", "summary.json",
                                                                "track.png"]
    with writing(out / "run.csv", "--out"):
        experiment.write_combined_csv(outcomes, desired, out / "run.csv")
        experiment.write_summary(data, out / "summary.json")
        experiment.plot(outcomes, desired, cal.model.thickness_um, out / "track.png")
    for name, o in outcomes.items():
        s = o.score
        part = (f"steady part, from {s.steady_from_s:.4g} s" if s.steady
                else "whole run: no full period after the first")
        first = f"; first period {s.rms_transient_um:.4f} um" if s.rms_transient_um else ""
        horizon = f"; {o.waveform.horizon_text()}" if o.waveform.horizons else ""
        say(f"{name:8s} RMS {s.rms_um:.4f} um ({s.rms_pct:.3f} %), max {s.max_um:.4f} um "
            f"({part}){first}{horizon}; max slew {o.waveform.max_slew_v_per_ms:.1f} V/ms")
        if s.rms_between_um is not None and not estimate:
            say(f"{'':8s} between samples {s.rms_between_um:.4f} um (the emulator's true plant)")
    if "ratio_linear_over_inverse" in data:
        say(f"ratio linear / inverse RMS: {data['ratio_linear_over_inverse']:.1f} (steady part)")
    if estimate:
        for name, o in outcomes.items():
            if o.score.rms_between_um is not None:
                say(f"model estimate, not measured: {name} between samples "
                    f"{o.score.rms_between_um:.4f} um (the model's simulation, moved at every "
                    f"sample onto the reading: its misfit carried between samples)")
    say(f"wrote {out}/" + ", ".join(written))
    if as_json:
        click.echo(json.dumps(data, allow_nan=False))
