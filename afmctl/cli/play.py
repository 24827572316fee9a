"""``afmctl play``: replay a saved waveform; and ``afmctl track ... --learn N``'s body."""

from __future__ import annotations

import json
import shlex
from pathlib import Path
from typing import Any

import click

from afmctl.cli.base import (
    check_output_dir,
    fail,
    load_profile_or_exit,
    main,
    make_dir,
    opened_stage,
    progress_printer,
    timestamped,
)


def _out_dir(out_dir: str | None, prefix: str, force: bool = False) -> Path:
    path = check_output_dir(Path(out_dir) if out_dir else timestamped(prefix), "--out",
                            ("run_*.csv", "summary.json", "waveform_learned.csv", "learn.png", "play.png"),
                            force, measured=("run_*.csv",))
    return make_dir(path, "--out")


def learn_track(desired: Any, prof: Any, model: Any, model_name: str, stage: Any,
                iterations: int, law_args: dict[str, Any], seed: str, how: tuple[bool, bool],
                out_dir: str | None, as_json: bool, cal: Any = None, resume: Any = None) -> None:
    """``afmctl track ... --learn N`` on an open ``stage``: iteration 0 is the ``seed`` filter's
    waveform, then up to N learning iterations (:mod:`afmctl.experiment.learn`); files after every
    iteration. ``how`` = (condition, extrapolate): every iteration keeps to the model's validity
    envelope (read from ``model_name``) unless extrapolate. ``cal`` (the model's calibration) goes
    into summary.json, with the fit's flag if identify or diagnose raised one. With ``resume``
    (``afmctl play --relearn N``) iteration 0 replays a learned waveform and says how far the
    stage has moved since it was learned."""
    from afmctl import plots
    from afmctl.experiment import learn, learnfiles
    from afmctl.experiment import runner as experiment
    from afmctl.files import modelfile
    from afmctl.model import effects as fx
    from afmctl.planning import ilc
    law = ilc.Law(**law_args)
    out = _out_dir(out_dir, "afmctl-track")
    truth, between_from = experiment.between_truth(prof)
    meta = {"profile": prof.name, "model": model_name, "trajectory": desired.label,
            "sample_rate_Hz": prof.sample_rate_hz, "between_samples_from": between_from,
            "readings_corrected_for": modelfile.effects_dict(fx.sensor_part(model.effects))}
    if cal is not None and cal.fit is not None:
        meta["model_fit"] = cal.fit.to_dict()

    def write(result: learn.Result) -> dict[str, Any]:
        data = learnfiles.write_outputs(result, desired, law, meta, out)
        plots.save_figure(plots.learn_figure(result, desired), out / "learn.png", 100)
        return data

    def each(result: learn.Result) -> None:
        it = result.iterations[-1]
        if resume is not None and it.index == 0 and resume.readings_um is not None:
            click.echo(f"replay: the stage has moved {it.offset_um:+.4f} um since the learned "
                       f"run (creep, drift: its conditioning's readings against that run's)",
                       err=True)
        gain = (f", gain {100 * it.gain_change:+.2f} % (at the mean gain {it.judged_um:.4f} um)"
                if abs(it.gain_change) >= 5e-5 else "")
        between = ("" if it.outcome.score.rms_between_um is None else
                   f", between samples {it.outcome.score.rms_between_um:.4f} um (plant)")
        click.echo(f"iteration {it.index}: steady RMS {it.steady_um:.4f} um, imaging "
                   f"{it.rms_imaging_um:.4f} um{between}, max slew "
                   f"{it.outcome.waveform.max_slew_v_per_ms:.1f} V/ms{gain}", err=True)
        write(result)

    start = None
    if resume is None and cal is not None:
        from afmctl.cli.track import learning_start
        start = learning_start(stage, cal, out, meta)
    click.echo(f"learning {desired.label}: up to {iterations} iterations after the "
               + ("replayed" if resume is not None else seed) + " waveform ...", err=True)
    result = learn.run(stage, model, desired, prof.limits, out, meta, iterations, law, truth,
                       seed, how[0], progress_printer(True), each,
                       envelope=modelfile.read_envelope(model_name), extrapolate=how[1],
                       resume=resume, start=start)
    data = write(result)
    if resume is not None and resume.readings_um is not None:
        data["replay_offset_um"] = result.iterations[0].offset_um
        experiment.write_summary(data, out / "summary.json")
    click.echo(f"stopped: {result.stop}; best iteration {result.best} "
               f"({result.best_iteration.judged_um:.4f} um)", err=True)
    if truth is None:
        click.echo(f"between samples: {between_from}", err=True)
    click.echo(f"wrote {out}/run_*_iterNN.csv, summary.json, waveform_learned.csv, learn.png",
               err=True)
    if as_json:
        click.echo(json.dumps(experiment.json_ready(data)))


def _tracking(desired_um: Any) -> slice:
    import numpy as np
    ok = np.flatnonzero(np.isfinite(desired_um))
    if ok.size == 0:
        return slice(0, 0)
    if ok.size != ok[-1] - ok[0] + 1:
        fail("desired_um must be one contiguous run of values (empty only before and after it)")
    return slice(int(ok[0]), int(ok[-1]) + 1)


@main.command("play")
@click.argument("wave", type=click.Path(dir_okay=False))
@click.option("--profile", "profile_path", type=click.Path(dir_okay=False),
              help="Stage profile (default: the embedded emulated stage).")
@click.option("--model", "model_path", type=click.Path(dir_okay=False),
              help="Model file whose sensor effects correct the readings before scoring (the "
                   "one the waveform was made with, named in its header).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Output folder (default: ./afmctl-play-<time>).")
@click.option("--json", "as_json", is_flag=True, help="Print the summary JSON on stdout.")
@click.option("--relearn", type=click.IntRange(min=0), default=0,
              help="Re-learn: after the replay, up to N learning iterations from the waveform's "
                   "learned reference (a stage that has moved on since: creep, drift), through "
                   "--model; says how far the stage has moved (needs a waveform_learned.csv "
                   "with its reference_um column).")
@click.option("--as-learned", is_flag=True,
              help="Play a learned waveform's voltages as they were learned, in one run (by "
                   "default, with --model, its conditioning first tells how far the stage has "
                   "moved since, and the rest is moved for it).")
def play(wave: str, profile_path: str | None, model_path: str | None, out_dir: str | None,
         as_json: bool, relearn: int, as_learned: bool) -> None:
    """Replay a saved waveform (time_s,voltage_V[,desired_um] CSV, e.g. a learned one; or a
    two-axis one, time_s,voltage_x_V,voltage_y_V[,desired_x_um,desired_y_um], on a two-axis
    stage).

    The waveform passes the same guard as track's (nothing is sent otherwise); its run file,
    summary.json, play.png and scores (against desired_um, if the file has it) are track's. A
    waveform whose header names another profile or model is played with a warning. With
    --relearn N the replay is iteration 0 of learning resumed from the waveform's reference
    (the outputs of ``track --learn``). A learned waveform played with --model (its run file
    beside it) is played in two runs: its conditioning (run_play_conditioning.csv), whose last
    0.1 s against the learned run's tell how far the stage has moved since (creep, drift), then
    the rest (run_play.csv) with the voltages that move the model by as much added
    (--as-learned: one run, as it was learned).
    """
    import numpy as np

    from afmctl import plots
    from afmctl.errors import FileFormatError
    from afmctl.experiment import learn
    from afmctl.experiment import runner as experiment
    from afmctl.files import modelfile, waveformfile
    from afmctl.model import effects as fx
    from afmctl.planning import ilc, track
    prof = load_profile_or_exit(profile_path)
    try:
        w = waveformfile.read(wave)
    except FileFormatError as exc:
        fail(str(exc))
    dt = 1.0 / prof.sample_rate_hz
    if abs(w.dt_s - dt) > 1e-6 * dt + 1e-9:
        fail(f"the waveform is sampled every {w.dt_s * 1e3:.6g} ms; profile {prof.name!r} "
             f"plays every {dt * 1e3:.6g} ms")
    for line in header_warnings(w.meta, prof.name, model_path, Path(wave).name):
        click.echo(line, err=True)
    if w.voltage_v.ndim == 2:
        _play_xy(w, prof, Path(wave).name, out_dir, as_json)
        return
    model = modelfile.read(model_path) if model_path else None
    if relearn and as_learned:
        fail("--as-learned plays the waveform as it was learned, --relearn learns it again: "
             "give one of them")
    if relearn:
        _relearn(w, Path(wave), prof, model, model_path, relearn, out_dir, as_json)
        return
    sensor = model.effects if model is not None else fx.Effects()
    tracking = _tracking(w.desired_um)
    wf = track.Waveform("play", dt, w.voltage_v, w.desired_um, tracking)
    desired = None
    if tracking.stop > tracking.start:
        period = float(w.meta["period_s"]) if "period_s" in w.meta else None
        u = w.desired_um[tracking]
        desired = track.Desired(dt, u, period, float(np.ptp(u)), w.meta.get("trajectory", "none"))
    kept_um = (None if as_learned or model is None or desired is None
               else _kept_readings(w, Path(wave)))
    moved_um: float | None = None
    with opened_stage(prof) as stage:
        stage.check_waveform(w.voltage_v)  # refused before the folder is made, nothing sent
        out = _out_dir(out_dir, "afmctl-play")
        meta = {"profile": prof.name, "waveform": Path(wave).name,
                "trajectory": w.meta.get("trajectory", "none"),
                "sample_rate_Hz": prof.sample_rate_hz}
        got = (_moved(w, wf, kept_um, desired, model, model_path, prof, stage, out, meta)
               if kept_um is not None and model_path is not None and desired is not None
               else None)
        if got is not None:
            wf, whole, measured, moved_um = got.waveform, got.whole, got.measured, got.move_um
        else:
            whole = wf
            measured = experiment.stream(stage, wf, out / "run_play.csv", meta,
                                         progress_printer(True))
    data: dict[str, Any] = {**meta, "samples": int(wf.voltage_v.size),
                            "complete": measured[2],
                            "max_slew_V_per_ms": wf.max_slew_v_per_ms}
    if moved_um is not None:
        data["replay_moved_um"] = moved_um
    written = [*(["run_play_conditioning.csv"] if whole is not wf else []), "run_play.csv",
               "summary.json"]
    if desired is not None:
        truth, between_from = experiment.between_truth(prof)
        it = learn.judge(wf, desired, 0, measured, out / "run_play.csv", sensor,
                         learn.between_error(whole, desired, truth))
        data.update({k: v for k, v in it.as_dict().items()
                     if k not in ("iteration", "gain_change", "judged_um")})
        data["between_samples_from"] = between_from
        data.update(_moved_on(w.meta, model_path, data["rms_steady_um"],
                              -it.error_um[ilc.steady_part(desired)]))
        s = it.outcome.score
        part = f"steady part, from {s.steady_from_s:.4g} s" if s.steady else "whole run"
        between = ("" if s.rms_between_um is None
                   else f"; between samples {s.rms_between_um:.4f} um (the emulator's plant)")
        click.echo(f"play: RMS {s.rms_um:.4f} um ({s.rms_pct:.3f} %), max {s.max_um:.4f} um "
                   f"({part}); imaging region {it.rms_imaging_um:.4f} um{between}", err=True)
        thickness = model.thickness_um if model is not None else prof.thickness_um
        corrected = modelfile.effects_dict(fx.sensor_part(sensor))
        plots.save_figure(plots.track_figure({"play": it.outcome}, desired, thickness, ", ".join(
            k.replace("_", " ") for k in corrected)), out / "play.png")
        written.append("play.png")
    experiment.write_summary(data, out / "summary.json")
    click.echo(f"wrote {out}/" + ", ".join(written), err=True)
    if data.get("moved_on"):
        again = shlex.join(["afmctl", "play", wave, *(["--profile", profile_path]
                                                      if profile_path else []),
                            "--model", model_path or w.meta.get("model", "MODEL"),
                            "--relearn", "2"])
        click.echo(f"warning: the replay misses by {data['rms_steady_um']:.4f} um RMS, "
                   f"{data['rms_steady_um'] / data['learned_rms_steady_um']:.1f}x what the "
                   f"waveform did when it was learned ({data['learned_rms_steady_um']:.4f} um), "
                   f"its mean error (readings less desired) {data['mean_error_um']:+.4f} um: the "
                   f"stage has moved on since (creep, drift); `{again}` learns it again where "
                   f"the stage is now and says how far it moved", err=True)
    if as_json:
        click.echo(json.dumps(experiment.json_ready(data)))


def _kept_readings(w: Any, wave: Path) -> Any:
    """The learned run's readings (um; its run file beside the waveform, named in its header, of
    the waveform's length), or None (a waveform not learned, or its run not beside it)."""
    from afmctl.errors import FileFormatError
    from afmctl.files import runfile
    kept = wave.parent / w.meta.get("run_file", "")
    if w.reference_um is None or not w.meta.get("run_file") or not kept.is_file():
        return None
    try:
        run = runfile.read(kept)
    except FileFormatError as exc:
        click.echo(f"replay: played as learned (the learned run {kept.name} is not readable: "
                   f"{exc})", err=True)
        return None
    return run.displacement_um if run.displacement_um.size == w.voltage_v.size else None


def _moved(w: Any, wf: Any, kept_um: Any, desired: Any, model: Any, model_path: str, prof: Any,
           stage: Any, out: Path, meta: dict[str, Any]) -> Any:
    """A learned waveform played moved for how far the stage has moved since it was learned
    (:func:`afmctl.experiment.replay.moved_replay`: its :class:`~afmctl.experiment.replay.Moved`),
    said either way; None, nothing played, if the model cannot plan the trajectory now."""
    from afmctl.experiment import learn, replay
    from afmctl.files import modelfile
    from afmctl.guard import LimitError
    seed = w.meta.get("filter", "inverse")
    try:
        p, _ = learn.planner(model, desired, prof.limits, stage.voltage(),
                             "linear" if seed == "linear" else "inverse",
                             envelope=modelfile.read_envelope(model_path))
    except LimitError as exc:
        click.echo(f"replay: played as learned (the model cannot plan the trajectory now: {exc})",
                   err=True)
        return None
    got = replay.moved_replay(stage, wf, kept_um, w.reference_um[wf.tracking],
                              replay.header_float(w.meta, replay.OFFSET_MISS_KEY, 0.0),
                              lambda r: learn.plan_reference(p, desired, r), p.prefix_v,
                              prof.limits, (out / "run_play_conditioning.csv", out / "run_play.csv"),
                              meta, progress_printer(True),
                              noise_um=replay.header_float(w.meta, replay.NOISE_KEY, float("nan")))
    if got.move_um is not None:
        click.echo(f"replay: the stage has moved {got.move_um:+.4f} um since the learned run "
                   f"(the conditioning's last {replay.MOVE_WINDOW_S:g} s against that run's); "
                   + ("the rest of the waveform moved for it (--as-learned: as it was)"
                      if got.moved else f"the rest played as learned ({got.why})"), err=True)
    else:
        click.echo(f"replay: played as learned ({got.why})", err=True)
    return got


#: A replay this many times the RMS its waveform had when learned: the stage has moved on.
MOVED_ON = 2.0


def _moved_on(meta: dict[str, str], model_path: str | None, rms_um: float, error_um: Any
              ) -> dict[str, Any]:
    """Whether a replay (steady RMS ``rms_um``, um; its steady part's readings less desired,
    ``error_um``, um) misses by :data:`MOVED_ON` times what its waveform did when learned (the
    header's ``rms_steady_um``, written by ``track --learn``). No keys for a waveform that does
    not say, nor for one learned with readings corrected for a sensor effect and replayed
    without ``--model`` (the two would not be scored alike)."""
    import numpy as np
    try:
        learned = float(meta["rms_steady_um"])
    except (KeyError, ValueError):
        return {}
    if model_path is None and meta.get("readings_corrected_for", "{}") not in ("{}", ""):
        return {}
    return {"learned_rms_steady_um": learned, "mean_error_um": float(np.nanmean(error_um)),
            "moved_on": bool(rms_um > MOVED_ON * learned)}


def _relearn(w: Any, wave: Path, prof: Any, model: Any, model_path: str | None,
             iterations: int, out_dir: str | None, as_json: bool) -> None:
    """``afmctl play WAVE --relearn N``: learning resumed from the waveform's reference
    (:class:`afmctl.experiment.learn.Resume`), the learned run's readings (its run file beside
    the waveform, named in the header) telling how far the stage has moved."""
    import numpy as np

    from afmctl.experiment import learn
    from afmctl.files import runfile
    from afmctl.planning import track
    if model is None or model_path is None:
        fail("--relearn learns through the model: give --model (the one the waveform was "
             "learned with)")
    if w.reference_um is None or "period_s" not in w.meta:
        fail(f"{wave.name} has no reference_um column or no period_s (written by afmctl track "
             f"--learn): it cannot be re-learned; play it without --relearn")
    tracking = _tracking(w.desired_um)
    u = w.desired_um[tracking]
    desired = track.Desired(w.dt_s, u, float(w.meta["period_s"]), float(np.ptp(u)),
                            w.meta.get("trajectory", "none"))
    readings = None
    kept = wave.parent / w.meta.get("run_file", "")
    if kept.is_file() and kept.name:
        run = runfile.read(kept)
        if run.displacement_um.size == w.voltage_v.size:
            readings = run.displacement_um
    if readings is None:
        click.echo(f"warning: the learned run ({w.meta.get('run_file', 'not named')}) is not "
                   f"beside {wave.name}: how far the stage has moved is not told", err=True)
    horizons = tuple(int(h) for h in w.meta.get("horizons", "").split(",") if h.strip())
    resume = learn.Resume(w.reference_um[tracking], horizons, readings,
                          voltage_v=w.voltage_v)
    seed = w.meta.get("filter", "inverse")
    with opened_stage(prof) as stage:
        learn_track(desired, prof, model, model_path, stage, iterations, {},
                    seed if seed in ("inverse", "linear") else "inverse", (True, False),
                    out_dir, as_json, resume=resume)


def _play_xy(w: Any, prof: Any, name: str, out_dir: str | None, as_json: bool) -> None:
    """Replay a two-axis waveform (``scan raster --learn-frames``'s) on a two-axis stage: every
    channel through its axis's guard, one two-axis run file, each axis's error against its
    desired column where the file has one (:func:`afmctl.planning.scanimage.axis_errors`)."""
    import numpy as np

    from afmctl.experiment import runner as experiment
    from afmctl.planning import raster, scanimage
    names = prof.axis_names
    if names != raster.AXES:
        fail(f"{name} is a two-axis waveform; profile {prof.name!r} has axes "
             f"{', '.join(names)} (e.g. --profile emulated-xy)")
    dt = 1.0 / prof.sample_rate_hz
    rows = np.flatnonzero(np.isfinite(w.desired_um).all(axis=1))
    tracking = slice(int(rows[0]), int(rows[-1]) + 1) if rows.size else slice(0, 0)
    wf = raster.XYWaveform("play", dt, w.voltage_v, w.desired_um, tracking, {}, False)
    with opened_stage(prof) as stage:
        stage.check_waveform(w.voltage_v)  # refused before the folder is made, nothing sent
        out = _out_dir(out_dir, "afmctl-play")
        meta = {"profile": prof.name, "waveform": name, "sample_rate_Hz": prof.sample_rate_hz}
        u, _, complete = experiment.stream(stage, wf, out / "run_play.csv", meta,
                                           progress_printer(True))
    axes = scanimage.axis_errors(u[tracking], w.desired_um[tracking])
    data = {**meta, "samples": int(w.voltage_v.shape[0]), "complete": complete, "axes": axes}
    for a, m in axes.items():
        if np.isfinite(m["rms_um"]):
            click.echo(f"play axis {a}: RMS {m['rms_um']:.4f} um, max {m['max_um']:.4f} um "
                       f"(against the file's desired_{a}_um)", err=True)
    experiment.write_summary(data, out / "summary.json")
    click.echo(f"wrote {out}/run_play.csv, summary.json", err=True)
    if as_json:
        click.echo(json.dumps(experiment.json_ready(data)))


def header_warnings(meta: dict[str, str], profile: str, model_path: str | None,
                    name: str) -> list[str]:
    """Warnings for a waveform whose header names another profile or model than this replay's
    (its voltages were planned for that stage and model)."""
    out = []
    made_for = meta.get("profile")
    if made_for and made_for != profile:
        out.append(f"warning: {name} was made for profile {made_for!r} (its header) and plays on "
                   f"profile {profile!r}: its voltages were planned for that stage")
    made_with = meta.get("model")
    if made_with and (model_path is None or
                      Path(made_with).resolve() != Path(model_path).resolve()):
        given = f"--model {model_path}" if model_path else "no --model"
        out.append(f"warning: {name} was made with model {made_with} (its header), and this "
                   f"replay has {given}: the readings are corrected for that model's sensor "
                   f"effects only when it is given")
    return out
