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
from afmctl.errors import InputError

#: Fewest samples per period of a periodic trajectory (a triangle needs its corners sampled).
MIN_SAMPLES_PER_PERIOD = 20
#: Longest trajectory tracked in one run, s (memory: a few arrays of this many samples).
MAX_DURATION_S = 600.0
#: Largest amplitude or offset accepted before the model judges the reach, um.
MAX_UM = 1000.0
#: ``--offset centre``: the middle of the model's reach on the profile.
CENTRE = "centre"
#: A trajectory this long (s) or longer is planned from a reading of the stage just before
#: each of its runs, long enough to tell the drift rate (:data:`afmctl.model.frame.RATE_READ_S`):
#: over seconds a drift the twin's recordings lag behind moves the whole run.
LONG_RUN_S = 2.0


class Offset(Finite):
    """A finite number (um), or ``centre`` (also ``center``)."""

    name = "um|centre"

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> float | str:
        if isinstance(value, str) and value.strip().lower() in ("centre", "center"):
            return CENTRE
        return super().convert(value, param, ctx)


@main.command("reach")
@click.option("--model", "model_path", type=click.Path(dir_okay=False), required=True,
              help="Model file (identify's or diagnose's).")
@click.option("--profile", "profile_path", type=click.Path(dir_okay=False),
              help="Stage profile, a file or a shipped name: its voltage limits (default: the "
                   "shipped emulated one).")
@click.option("--amplitude", type=Finite(0, open_min=True), default=None,
              help="Peak-to-peak amplitude, um: where a trajectory of it fits.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object on stdout.")
def reach(model_path: str, profile_path: str | None, amplitude: float | None,
          as_json: bool) -> None:
    """Show the displacement range a model reaches on a profile: its quasi-static response
    over the profile's voltage limits (within the model's validity envelope), in the sensor's
    frame. A trajectory must stay inside it (at 27.9 Hz the rod's dynamics take a little more
    near the corners); its centre is what `track --offset centre` uses."""
    from afmctl.experiment import calibration
    from afmctl.files import modelfile
    from afmctl.planning import track as trk
    prof = load_profile_or_exit(profile_path)
    cal = calibration.from_file(model_path)
    env = modelfile.read_envelope(cal.path)
    lim = trk.conditioning_limits(prof.limits, env)
    lo, hi = trk.reach(cal.model, prof.limits, env)
    data: dict[str, Any] = {"model": model_path, "profile": prof.name, "reach_um": [lo, hi],
                            "centre_um": 0.5 * (lo + hi), "span_um": hi - lo,
                            "voltage_V": [lim.v_min, lim.v_max]}
    lines = [f"reach: {lo:.4g} ... {hi:.4g} um (span {hi - lo:.4g} um) on {lim.v_min:.4g} ... "
             f"{lim.v_max:.4g} V, profile {prof.name!r}, model {model_path} (quasi-static)",
             f"centre: {0.5 * (lo + hi):.4g} um (track --offset centre)"]
    if amplitude is not None:
        fits = amplitude < hi - lo
        data["offset_range_um"] = [lo + amplitude / 2, hi - amplitude / 2] if fits else None
        lines.append(f"--amplitude {amplitude:g} fits with --offset {lo + amplitude / 2:.4g} ... "
                     f"{hi - amplitude / 2:.4g} um (keep off the ends at high frequency)" if fits
                     else f"--amplitude {amplitude:g} does not fit: at most {hi - lo:.4g} um "
                          f"peak to peak on this profile")
    if as_json:
        click.echo(json.dumps(data))
        return
    for line in lines:
        click.echo(line)


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
                     default="both", show_default=True,
                     help="Which waveforms to play: the model-based inverse (Algorithm 3), the "
                          "paper's linear baseline (a line through the model's slow response), "
                          "or both, inverse first (the ratio of their errors is printed)."),
        click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
                     help="Output folder (default: ./afmctl-track-<time>)."),
        click.option("--force", is_flag=True,
                     help="Overwrite outputs in --out (never run files: measured data)."),
        click.option("--dry-run", is_flag=True,
                     help="Send nothing; write DIR/waveform_<filter>.csv."),
        click.option("--json", "as_json", is_flag=True, help="Print the summary JSON on stdout."),
        click.option("--axis", "axis", type=click.Choice(["x", "y"]), default=None,
                     help="On a two-axis stage: the axis to drive (its channel, model and "
                          "limits); the other holds its present output, and how far it moved is "
                          "reported (held_axis in summary.json and --json). --model may be a "
                          "two-axis model file."),
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
        click.option("--offset", type=Offset(), default="0", show_default=True,
                     help="Centre of the trajectory, um, in the sensor's frame (what the stage "
                          "reads: the profile's scale * raw + offset_um; on a unipolar stage "
                          "its reach starts above 0), or `centre`: the middle of what the model "
                          "reaches on the profile (`afmctl reach` shows it)."),
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
        if value != CENTRE and abs(value) > MAX_UM:
            raise InputError(f"{name} {value:g} um: beyond any piezo stage (at most "
                             f"{MAX_UM:g} um)")


def check_duration(seconds: float, what: str) -> None:
    if seconds > MAX_DURATION_S:
        raise InputError(f"{what} lasts {seconds:.3g} s; at most {MAX_DURATION_S:g} s per run")


@track.command("triangle", short_help="Track a triangle wave, as in the paper's Figs 9-11.")
@periodic_options
@track_options
def track_triangle(freq: float, amplitude: float, offset: float | str, periods: float,
                   allow_short: bool, **kw: Any) -> None:
    """Track a triangle wave, as in the paper's Figs 9-11 (27.9 Hz, 27.04 um)."""
    from afmctl.planning import track as trk
    _periodic(trk.triangle, freq, amplitude, offset, periods, allow_short, kw)


@track.command("sine")
@periodic_options
@track_options
def track_sine(freq: float, amplitude: float, offset: float | str, periods: float,
               allow_short: bool, **kw: Any) -> None:
    """Track a sine wave."""
    from afmctl.planning import track as trk
    _periodic(trk.sine, freq, amplitude, offset, periods, allow_short, kw)


def _periodic(shape: Callable[..., Any], freq: float, amplitude: float, offset: float | str,
              periods: float, allow_short: bool, kw: dict[str, Any]) -> None:
    """Track ``shape(freq, amplitude, offset, periods, dt)`` (``--offset centre``: placed once
    the model is known)."""
    off = 0.0 if offset == CENTRE else float(offset)
    _track(lambda dt: shape(freq, amplitude, off, periods, dt),
           lambda rate: check_periodic(freq, amplitude, offset, periods, allow_short, rate),
           centre=offset == CENTRE, **kw)


@track.command("file")
@click.argument("wave", type=click.Path(dir_okay=False))
@track_options
def track_file(wave: str, **kw: Any) -> None:
    """Track any trajectory: a CSV with columns time_s,desired_um (resampled linearly onto the
    stage's sample clock, which is said when the file's own differs)."""
    from afmctl.files import sweepfile as sweeps
    from afmctl.planning import track as trk
    t, u = sweeps.read_trajectory(wave)
    check_duration(float(t[-1] - t[0]), wave)

    def make(dt: float) -> Any:
        import numpy as np
        steps = np.diff(t)
        if steps.size and (abs(float(np.median(steps)) - dt) > 1e-6 * dt
                           or np.ptp(steps) > 1e-3 * dt):
            say(f"{Path(wave).name}: {t.size} samples every {1e3 * float(np.median(steps)):.6g} ms"
                f" (median), resampled linearly onto the stage's clock (every {1e3 * dt:.6g} ms)")
        return trk.from_samples(t, u, dt, f"file {Path(wave).name}")

    _track(make, lambda rate: None, **kw)


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
    from afmctl.drivers import open_stage
    arg = f" --profile {profile_path}" if profile_path else ""
    how = (f"run `afmctl sweep{arg} --out DIR` and `afmctl identify DIR/*.csv{arg} -o "
           f"model.toml`, then track with --model model.toml; or add --calibrate to record, "
           f"identify and track in one go")
    return calibration.for_track(prof, stage, progress_printer(False), calibrate, recalibrate,
                                 open_stage=open_stage, how_to_calibrate=how)


def _outputs(dry_run: bool, wanted: tuple[str, ...]) -> list[str]:
    if dry_run:
        return [f"waveform_{name}.csv" for name in wanted]
    return ["run.csv", "summary.json", "track.png"]


def _track(make_desired: Callable[[float], Any], check: Callable[[float], None],
           profile_path: str | None, model_path: str | None, calibrate: bool, recalibrate: bool,
           filters: str, out_dir: str | None, force: bool, dry_run: bool, as_json: bool,
           condition: bool, extrapolate: bool, learn: int = 0, learn_cutoff: float = 600.0,
           learn_region: str = "all", centre: bool = False, axis: str | None = None,
           opened: Any = None) -> None:
    if axis is not None:
        from afmctl.cli.xytrack import on_axis
        on_axis(axis, profile_path, model_path, (calibrate, recalibrate, learn),
                out_dir, force,
                lambda m, o, opened: _track(
                    make_desired, check, profile_path, m, False, False, filters, o, force,
                    dry_run, as_json, condition, extrapolate, centre=centre, opened=opened))
        return
    if model_path is not None and (calibrate or recalibrate):
        raise InputError("--model and --calibrate/--recalibrate exclude each other")
    if learn and dry_run:
        raise InputError("--learn learns from measurements: it cannot be combined with "
                         "--dry-run")
    prof = load_profile_or_exit(profile_path) if opened is None else opened.profile
    check(prof.sample_rate_hz)
    if learn:
        from afmctl.cli.play import learn_track
        desired = make_desired(1.0 / prof.sample_rate_hz)
        with opened_stage(prof) as stage:
            cal = _model(prof, stage, model_path, calibrate, recalibrate, profile_path)
            _warn(cal, learning=True)
            learn_track(_placed(desired, cal, prof, centre), prof, cal.model, str(cal.path),
                        stage, learn, {"cutoff_hz": learn_cutoff, "region": learn_region},
                        "linear" if filters == "linear" else "inverse", (condition, extrapolate),
                        out_dir, as_json, cal)
        return
    wanted = ("inverse", "linear") if filters == "both" else (filters,)
    out = check_output_dir(Path(out_dir) if out_dir else timestamped("afmctl-track"), "--out",
                           _outputs(dry_run, wanted), force, measured=("run_*.csv",))
    desired = make_desired(1.0 / prof.sample_rate_hz)
    if dry_run:
        cal = _model(prof, None, model_path, calibrate, recalibrate, profile_path)
        _warn(cal)
        _dry_run(prof, _placed(desired, cal, prof, centre), wanted, out, (condition, extrapolate),
                 cal)
        return
    outcomes: dict[str, Any] = {}
    with (opened_stage(prof) if opened is None else opened.stage()) as stage:
        cal = _model(prof, stage, model_path, calibrate, recalibrate, profile_path)
        _warn(cal)
        desired = _placed(desired, cal, prof, centre)
        meta = _meta(prof, cal, desired)
        try:
            _run(prof, stage, cal, desired, wanted, out, (condition, extrapolate), meta, outcomes)
        except BaseException as exc:
            if outcomes and not isinstance(exc, SystemExit):  # keep what was played
                _report(prof, cal, outcomes, desired, out, meta, False, interrupted=exc)
            raise
        if opened is not None:
            meta["held_axis"] = opened.report(stage)
    _report(prof, cal, outcomes, desired, out, meta, as_json)


def _warn(cal: Any, learning: bool = False) -> None:
    """The model's flag (identify or diagnose found it missing something) and what it means."""
    text = cal.warning(learning)
    if text:
        say(text)


def _placed(desired: Any, cal: Any, prof: Any, centre: bool) -> Any:
    """``desired`` moved to the middle of the model's reach on the profile (``--offset centre``)."""
    if not centre:
        return desired
    import dataclasses as dc

    from afmctl.files import modelfile
    from afmctl.planning import track as trk
    lo, hi = trk.reach(cal.model, prof.limits, modelfile.read_envelope(cal.path))
    mid = 0.5 * (lo + hi)
    say(f"--offset centre: {mid:.4g} um, the middle of the model's reach {lo:.4g} ... "
        f"{hi:.4g} um on {prof.limits.v_min:g} ... {prof.limits.v_max:g} V")
    return dc.replace(desired, u_um=desired.u_um + mid)


def _meta(prof: Any, cal: Any, desired: Any) -> dict[str, Any]:
    meta: dict[str, Any] = {"profile": prof.name, "model": str(cal.path),
                            "trajectory": desired.label, "sample_rate_Hz": prof.sample_rate_hz}
    if desired.period_s is not None:
        meta["period_s"] = f"{desired.period_s:.9g}"
    return meta


def _plan(prof: Any, cal: Any, desired: Any, start_v: float, wanted: tuple[str, ...],
          how: tuple[bool, bool], state: Any = None, frame: Any = None) -> dict[str, Any]:
    """The waveforms, kept to the model's validity envelope (``how`` = (condition,
    extrapolate)), from the model's ``state`` (default: at rest at ``start_v``), in the readings'
    ``frame`` (default: the model's zero)."""
    from afmctl.files import modelfile
    from afmctl.model import frame as fr
    from afmctl.planning import track as trk
    return trk.plan(cal.model, desired, prof.limits, start_v, wanted, state=state,
                    condition=how[0], envelope=modelfile.read_envelope(cal.path),
                    extrapolate=how[1], frame=fr.Frame() if frame is None else frame)


def _dry_run(prof: Any, desired: Any, wanted: tuple[str, ...], out: Path,
             how: tuple[bool, bool], cal: Any) -> None:
    from afmctl.experiment import runner as experiment
    plans = _plan(prof, cal, desired, 0.0, wanted, how)
    say(cal.describe())
    make_dir(out, "--out")
    meta = _meta(prof, cal, desired)
    for name in wanted:
        path = out / f"waveform_{name}.csv"
        with writing(path, "--out"):
            experiment.write_waveform_csv(plans[name], path, {**meta, "filter": name})
        say(f"wrote {path}" + (f" ({plans[name].horizon_text()})" if name == "inverse" else ""))


def _run(prof: Any, stage: Any, cal: Any, desired: Any, wanted: tuple[str, ...], out: Path,
         how: tuple[bool, bool], meta: dict[str, Any], outcomes: dict[str, Any]) -> None:
    """Plan and play every wanted filter; each outcome goes to ``outcomes`` as it ends (the one
    in progress too, scored on what it got, if the run is interrupted)."""
    from afmctl.experiment import runner as experiment
    from afmctl.experiment import twin
    from afmctl.model import frame as fr
    start_v = stage.voltage()
    # every model: a creeping stage's past, a Bouc-Wen stage's memory (no conditioning wipes
    # it), a drifting frame (read from the readings the twin followed)
    tw, why = twin.load(cal.model, cal.path, start_v, _run_count(stage))
    say(f"planning {desired.label} from {start_v:.3f} V" + (
        f", the stage as the model's twin follows it ({why})" if tw is not None else
        f" ({why}: the model starts at rest)" if why != "no twin file" else "") + " ...")
    truth, _ = experiment.between_truth(prof)
    if tw is None:
        plans = _plan(prof, cal, desired, start_v, wanted, how)
        say(cal.describe())
        make_dir(out, "--out")
        experiment.run_all(stage, {k: plans[k] for k in wanted}, desired, out, meta, truth,
                           progress_printer(False), sensor=cal.model.effects, done=outcomes)
        return
    say(cal.describe())
    make_dir(out, "--out")
    long = desired.u_um.size * desired.dt_s >= LONG_RUN_S
    tw = tw if long else _read_if_idle(stage, tw, out, meta)

    def plan_for(name: str, state: Any, frame: Any) -> Any:
        _say_frame(name, frame)
        return _plan(prof, cal, desired, stage.voltage(), tuple(dict.fromkeys(("inverse", name))),
                     how, state, frame)[name]

    def read(name: str, now: Any) -> Any:
        return _read(stage, now, out, meta, f"run_read_{name}.csv", fr.RATE_READ_S,
                     f"the {name} run lasts {desired.u_um.size * desired.dt_s:.1f} s and the "
                     f"stage holds {now.held_v:g} V")

    after = experiment.run_following(stage, tw, plan_for, wanted, desired, out, meta, truth,
                                     progress_printer(False), sensor=cal.model.effects,
                                     done=outcomes, read=read if long else None)
    if after is not None:
        twin.save(after, cal.path)


def learning_start(stage: Any, cal: Any, out: Path, meta: dict[str, Any]) -> Any:
    """Where ``track --learn`` starts its iteration 0 (:func:`afmctl.experiment.learn.run`'s
    ``start``): the model's state and the readings' frame from the twin, the stage read first
    (always: iteration 0's frame is where learning starts, and a read takes
    :data:`~afmctl.experiment.runner.READ_S`), or None (from rest, in the model's zero); said
    either way. Without the read the frame is the line through the twin's last recordings, and
    a line through two groups of them hours or minutes apart reads the step between them as a
    drift: an independent tester's creeping stage, its recordings either side of a 193 s hold
    1 um apart, read -4.08 nm/s, and iteration 0 started 0.154 um off (6.3x the noise)."""
    from afmctl.experiment import runner as experiment
    from afmctl.experiment import twin
    tw, why = twin.load(cal.model, cal.path, stage.voltage(), _run_count(stage))
    if tw is None:
        say(f"learning starts from rest in the model's zero ({why}): iteration 0 sits off by any "
            f"creep or drift since the sweeps, and the first iteration takes it out")
        return None
    say(f"learning starts from the stage as the model's twin follows it ({why})")
    tw = _read_if_idle(stage, tw, out, meta, longer_than_s=-1.0)
    when = stage.now_s() + experiment.LEAD_S
    frame = tw.planning_frame(when)
    _say_frame("iteration 0", frame)
    return tw.at(when), frame


def _say_frame(name: str, frame: Any) -> None:
    """Say the frame a run (``name``) is planned in, unless it is the model's own zero."""
    if frame.basis != "none":
        say(f"{name}: readings expected {frame.offset_um:+.4f} um from the model's zero at its "
            f"start ({frame.basis}); planned in that frame")


def _read_if_idle(stage: Any, tw: Any, out: Path, meta: dict[str, Any],
                  longer_than_s: float | None = None) -> Any:
    """The twin, after reading the stage where it holds (:func:`_read`, into ``out``) if it has
    idled more than ``longer_than_s`` (s; None: :data:`~afmctl.experiment.runner.IDLE_S`) since
    the twin's last recording."""
    from afmctl.experiment import runner as experiment
    limit = experiment.IDLE_S if longer_than_s is None else longer_than_s
    idle_s = stage.now_s() - tw.ended_s
    if idle_s <= limit:
        return tw
    return _read(stage, tw, out, meta, experiment.READ_FILE, experiment.READ_S,
                 f"the stage has held {tw.held_v:g} V for {idle_s:.0f} s since the twin's last "
                 f"recording", idle_s)


def _read(stage: Any, tw: Any, out: Path, meta: dict[str, Any], file: str, seconds: float,
          why: str, idle_s: float | None = None) -> Any:
    """The twin after reading the stage where it holds for ``seconds``
    (:func:`afmctl.experiment.runner.read_held`, into ``out / file``), ``why`` said first; what
    it read is said and recorded in ``meta`` (the runs' headers, summary.json)."""
    from afmctl.experiment import runner as experiment
    from afmctl.model import frame as fr
    say(f"{why}: reading it there for {seconds:g} s ({file}), to see how far its readings have "
        f"moved from the model (a drifting mount, creep)"
        + (" and how fast" if fr.tells_rate(round(seconds / tw.dt_s), tw.dt_s) else ""))
    tw = experiment.read_held(stage, tw, out / file, meta, seconds)
    if tw.read is not None:
        rate = tw.read.um_per_s
        say(f"read: the readings sit {tw.read.offset_um:+.4f} um from the model's"
            + ("" if rate is None else f", moving {1e3 * rate:+.2f} nm/s"))
        meta.update({"read_offset_um": tw.read.offset_um, "read_file": file,
                     **({} if idle_s is None else {"read_after_idle_s": round(idle_s, 3)}),
                     **({} if rate is None else {"read_drift_um_per_s": rate})})
    return tw


def _run_count(stage: Any) -> int | None:
    """The device's run counter now (None if the stage does not report one)."""
    status = getattr(stage, "status", None)
    return None if status is None else int(status().run_count)


def _report(prof: Any, cal: Any, outcomes: dict[str, Any], desired: Any, out: Path,
            meta: dict[str, Any], as_json: bool, interrupted: BaseException | None = None
            ) -> None:
    """Scores on stderr, run.csv, summary.json and track.png: what was played (all of it, or up
    to an ``interrupted`` run, whose files are then written before the interrupt is reported)."""
    from afmctl import plots
    from afmctl.experiment import runner as experiment
    from afmctl.files import modelfile
    from afmctl.model import effects as fx
    _, between_from = experiment.between_truth(prof)
    corrected = modelfile.effects_dict(fx.sensor_part(cal.model.effects))
    extra: dict[str, Any] = {
        **meta, "model": cal.as_dict(), "between_samples_from": between_from,
        "readings_corrected_for": corrected}
    if interrupted is not None:
        extra["interrupted"] = f"{type(interrupted).__name__}: {interrupted}".strip(": ")
    data = experiment.summary(outcomes, desired, extra)
    written = [o.run_file.name for o in outcomes.values()] + ["run.csv", "summary.json",
                                                                "track.png"]
    with writing(out / "run.csv", "--out"):
        experiment.write_combined_csv(outcomes, desired, out / "run.csv")
        experiment.write_summary(data, out / "summary.json")
        plots.save_figure(plots.track_figure(outcomes, desired, cal.model.thickness_um, ", ".join(
            k.replace("_", " ") for k in corrected)), out / "track.png")
    if interrupted is not None:
        say("interrupted: the scores of what was played so far (a run cut short is scored on "
            "the samples it got)")
    if corrected:
        say(f"readings corrected for {', '.join(corrected)} (the model's sensor effects) before "
            f"scoring: run.csv's corrected_displacement_um_* columns, drawn in track.png")
    for name, o in outcomes.items():
        s = o.score
        if s.steady:
            part = f"steady part, from {s.steady_from_s:.4g} s"
        elif desired.period_s is None:
            part = "whole run"
        else:
            part = "whole run: no full period after the first"
        cut = "" if o.complete else "; cut short" if interrupted is not None else "; incomplete"
        first = f"; first period {s.rms_transient_um:.4f} um" if s.rms_transient_um else ""
        horizon = f"; {o.waveform.horizon_text()}" if o.waveform.horizons else ""
        say(f"{name:8s} RMS {s.rms_um:.4f} um ({s.rms_pct:.3f} %), max {s.max_um:.4f} um "
            f"({part}){first}{horizon}; max slew {o.waveform.max_slew_v_per_ms:.1f} V/ms{cut}")
        if s.rms_between_um is not None:
            say(f"{'':8s} between samples {s.rms_between_um:.4f} um (the emulator's true plant)")
    if "ratio_linear_over_inverse" in data:
        say(f"ratio linear / inverse RMS: {data['ratio_linear_over_inverse']:.1f} (steady part)")
    if between_from != "emulator truth":
        say(f"between samples: {between_from}")
    say(f"wrote {out}/" + ", ".join(written))
    if as_json:
        click.echo(json.dumps(experiment.json_ready(data), allow_nan=False))
