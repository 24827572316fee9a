"""``afmctl scan raster``: a raster image on a two-axis stage, both axes through their inverses."""

from __future__ import annotations

import json
from functools import partial
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
    say,
    timestamped,
    writing,
)
from afmctl.errors import InputError

#: Fewest samples per line (a trace and its retrace: the triangle's corners must be sampled).
MIN_SAMPLES_PER_LINE = 20
#: Longest frame, s (memory: a few arrays of this many samples per axis).
MAX_FRAME_S = 600.0
OUTPUTS = ("summary.json", "scan.gwy", "scan.png")


@main.group(cls=Group)
def scan() -> None:
    """Scan images on a two-axis (x/y) stage."""


@scan.command("raster")
@click.option("--size", nargs=2, type=Finite(0, open_min=True), required=True,
              metavar="W H", help="Frame width (fast axis) and height (slow axis), um.")
@click.option("--pixels", type=click.IntRange(min=2), required=True, help="Pixels per line.")
@click.option("--lines", type=click.IntRange(min=1), required=True, help="Lines per frame.")
@click.option("--line-rate", type=Finite(0, open_min=True), required=True, metavar="HZ",
              help="Lines per second (a line: one trace and its retrace).")
@click.option("--centre", "--center", "centre", nargs=2, type=Finite(), default=None,
              metavar="X Y", help="Frame centre, um, in the sensors' frame (default: the "
                                  "middle of each axis's reach).")
@click.option("--angle", type=Finite(), default=0.0, show_default=True, metavar="DEG",
              help="Rotation of the fast axis from x towards y, degrees.")
@click.option("--slow", type=click.Choice(["ramp", "staircase"]), default="ramp",
              show_default=True, help="Slow axis: a continuous ramp, or a step between lines "
                                      "(in the turnaround, outside the image).")
@click.option("--direction", type=click.Choice(["up", "down", "bounce"]), default="up",
              show_default=True, help="Slow axis direction (bounce: up, then down, ...).")
@click.option("--overscan", type=click.FloatRange(0, 1), default=0.1, show_default=True,
              metavar="FRAC", help="Fast-axis travel beyond the image at each side, as a "
                                   "fraction of the width (the turnarounds stay outside).")
@click.option("--frames", type=click.IntRange(min=1), default=1, show_default=True,
              help="Frames to scan (each its own run files).")
@click.option("--learn-frames", type=click.IntRange(min=0), default=0, show_default=True,
              help="Learn the frame from up to N repeated frames first (both axes at once, "
                   "through the inverse), then scan --frames frames with the learned waveform.")
@click.option("--profile", "profile_path", type=click.Path(dir_okay=False),
              help="A two-axis stage profile (e.g. emulated-xy).")
@click.option("--model", "model_path", type=click.Path(dir_okay=False),
              help="Model file: a two-axis model (each axis and the coupling), or a one-axis "
                   "model used for both axes (then no coupling is fed forward).")
@click.option("--calibrate", is_flag=True,
              help="Record the two-axis sweep set (sweep --axes x,y's) on the stage and identify "
                   "both axes and the coupling first, into DIR/calibration/ and "
                   "DIR/model_xy.toml (moves both axes over their whole ranges).")
@click.option("--filter", "filters", type=click.Choice(["inverse", "linear", "both"]),
              default="both", show_default=True,
              help="Each axis's model inverse (Algorithm 3), the paper's linear filter, or both "
                   "(inverse first), compared side by side.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Output folder (default: ./afmctl-scan-<time>).")
@click.option("--json", "as_json", is_flag=True, help="Print the summary JSON on stdout.")
def raster(size: tuple[float, float], pixels: int, lines: int, line_rate: float,
           centre: tuple[float, float] | None, angle: float, slow: str, direction: str,
           overscan: float, frames: int, learn_frames: int, profile_path: str | None,
           model_path: str | None, calibrate: bool, filters: str, out_dir: str | None,
           as_json: bool) -> None:
    """Scan a raster frame: the fast axis a triangle (trace and retrace) with overscan, the slow
    axis a ramp or staircase, rotated by the angle; each axis through its own inverse with the
    coupling fed forward. Writes a run file per frame and filter (the raw streams), scan.gwy
    (Gwyddion), scan.png and summary.json; refuses a frame beyond the stage's reach before
    anything moves, naming the largest that fits."""
    from afmctl.experiment import scan as xs
    from afmctl.planning import raster as rs
    if model_path is not None and calibrate:
        raise InputError("--model and --calibrate exclude each other")
    if learn_frames and direction == "bounce":
        raise InputError("--learn-frames learns one frame: scan it --direction up or down")
    prof = load_profile_or_exit(profile_path)
    names = prof.axis_names
    if names != rs.AXES:
        raise InputError(f"profile {prof.name!r} has axes {', '.join(names)}: a raster scan "
                         f"needs a two-axis stage with axes x, y (e.g. --profile emulated-xy)")
    dt = 1.0 / prof.sample_rate_hz
    _check_rate(line_rate, lines, prof.sample_rate_hz)
    out = check_output_dir(Path(out_dir) if out_dir else timestamped("afmctl-scan"), "--out",
                           OUTPUTS, False, measured=("run_*.csv",))
    if calibrate:
        model_path = _calibrated(prof, profile_path, out)
    axes, coupling, about = xs.model_for_scan(prof, model_path)
    frame = rs.Frame(size[0], size[1], pixels, lines, line_rate, (0.0, 0.0), angle, slow,
                     direction, overscan, frames)
    frame = _placed(frame, axes, centre)
    wanted = ("inverse", "linear") if filters == "both" else (filters,)
    setup = xs.Setup(frame, axes, coupling, wanted, dt)
    meta = {"profile": prof.name, "model": model_path, "model_kind": about,
            "frame": frame.label(), "sample_rate_Hz": prof.sample_rate_hz}
    fed = "fed forward" if coupling else "not fed forward (none known)"
    say(f"{frame.label()}, centre {frame.centre_um[0]:.4g}, {frame.centre_um[1]:.4g} um; "
        f"model: {model_path} ({about}); coupling {fed}")
    runs, learning = _scan(prof, setup, learn_frames, out, meta)
    data = _summary(runs, setup, meta, learning)  # as written after the last frame
    _report(data, out)
    if as_json:
        click.echo(json.dumps(data, allow_nan=False))


def _scan(prof: Any, setup: Any, learn_frames: int, out: Path, meta: dict[str, Any]
          ) -> tuple[list[Any], dict[str, Any]]:
    """Play the frames (after learning, with ``learn_frames``); every finished frame's files
    written as it ends, and kept on an interrupt (the stage ends safe). The frames, and what
    learning did (``{"learning": ...}`` once it has ended, in every summary after it)."""
    from afmctl.experiment import scan as xs
    from afmctl.experiment import scanlearn
    runs: list[Any] = []
    learning: dict[str, Any] = {}
    with opened_stage(prof) as stage:
        if getattr(stage, "channels", 1) != 2:
            raise InputError(f"the stage of profile {prof.name!r} reports "
                             f"{getattr(stage, 'channels', 1)} channel(s): a raster scan needs 2")
        make_dir(out, "--out")
        written = partial(_write, setup=setup, out=out, meta=meta, extra=learning)
        try:
            if learn_frames:
                scanlearn.learn_then_scan(
                    stage, setup, learn_frames, out, meta, say, written, runs,
                    lambda got: learning.update(learning=got.to_dict()))
            else:
                xs.run(stage, setup, out, meta, say, written, runs)
        except BaseException as exc:
            if runs and not isinstance(exc, SystemExit):
                say(f"interrupted ({type(exc).__name__}): the finished frames and their files "
                    f"are kept in {out}/")
            raise
    return runs, learning


def _calibrated(prof: Any, profile_path: str | None, out: Path) -> str:
    """``--calibrate``: record ``sweep --axes x,y``'s set on the stage into OUT/calibration/,
    identify it (``identify``'s two-axis fit, the profile's ``[identify]`` settings) and write
    OUT/model_xy.toml; its path."""
    from afmctl.cli.base import fit_settings
    from afmctl.cli.xysweep import first_resonance_hz
    from afmctl.errors import FitError
    from afmctl.experiment import xyrecord
    from afmctl.files import xymodelfile, xysweepfile
    from afmctl.fit import xyidentify
    from afmctl.planning import sweepdesign
    band = first_resonance_hz(prof)
    if band is None:
        raise InputError("--calibrate: the profile does not model its axes (their first "
                         "resonance sets the coupling band): record `afmctl sweep --axes x,y "
                         "--band-hz F`, identify it, and give --model")
    limits = {a: prof.axis(a).limits for a in prof.axis_names}
    design = sweepdesign.xy_design(
        prof.sample_rate_hz, {a: (lim.v_min, lim.v_max) for a, lim in limits.items()},
        {a: lim.max_rate_v_per_ms * 1e3 for a, lim in limits.items()}, 0.5 * band,
        "reversals")  # the fast axis runs minor loops: the curves show them (sweepdesign)
    meta = {"profile": prof.name, "sample_rate_hz": f"{prof.sample_rate_hz:g}",
            **{f"layer_thickness_{a}_um": f"{prof.axis(a).thickness_um:g}" for a in limits}}
    say(f"calibrating: recording {len(design)} two-axis sweeps over each axis's range, then "
        f"identifying both axes and the coupling ...")
    with opened_stage(prof) as stage:
        paths = xyrecord.record(stage, design, prof.sample_rate_hz, limits,
                                make_dir(out / "calibration", "--out"), meta, say)
    result = xyidentify.fit(xysweepfile.read_set(paths) or [], fit_settings(profile_path),
                            progress=say)
    if not result.finite:
        raise FitError("--calibrate: the two-axis fit gave no finite model (the sweeps are "
                       f"kept in {out}/calibration)")
    path = out / "model_xy.toml"
    xymodelfile.write(result.model, path, "afmctl scan raster --calibrate",
                      {a: r.envelope for a, r in result.axes.items()})
    say(f"wrote {path}")
    return str(path)


def _check_rate(line_rate: float, lines: int, sample_rate_hz: float) -> None:
    per_line = sample_rate_hz / line_rate
    if per_line < MIN_SAMPLES_PER_LINE:
        raise InputError(f"--line-rate {line_rate:g}: {per_line:.3g} samples per line at the "
                         f"stage's {sample_rate_hz:g} Hz; at most "
                         f"{sample_rate_hz / MIN_SAMPLES_PER_LINE:g} lines/s")
    if lines / line_rate > MAX_FRAME_S:
        raise InputError(f"--lines {lines} at --line-rate {line_rate:g}: a frame of "
                         f"{lines / line_rate:.4g} s; at most {MAX_FRAME_S:g} s")


def _placed(frame: Any, axes: Any, centre: tuple[float, float] | None) -> Any:
    """The frame at ``centre`` (default: the middle of each axis's reach), refused if beyond the
    reach, naming the largest frame that fits."""
    import dataclasses as dc

    from afmctl.planning import raster as rs
    reach = rs.reach(axes)
    if centre is None:
        centre = tuple(0.5 * (lo + hi) for lo, hi in reach.values())  # type: ignore[assignment]
    frame = dc.replace(frame, centre_um=(float(centre[0]), float(centre[1])))
    rs.check_reach(frame, reach)
    return frame


def _write(runs: list[Any], setup: Any, out: Path, meta: dict[str, Any],
           extra: dict[str, Any]) -> None:
    """summary.json (with ``extra``'s keys), scan.gwy and scan.png of every finished frame
    (replaced after each)."""
    from afmctl import plots
    from afmctl.experiment import runner
    from afmctl.experiment import scan as xs
    from afmctl.files import gwy
    data = _summary(runs, setup, meta, extra)
    fr = setup.frame
    with writing(out / "summary.json", "--out"):
        runner.write_summary(data, out / "summary.json")
        gwy.write(out / "scan.gwy", xs.gwy_channels(runs),
                  (fr.width_um, fr.lines * fr.line_pitch_um),
                  (fr.centre_um[0] - fr.width_um / 2, fr.centre_um[1] - fr.height_um / 2),
                  {"frame": fr.label(), "angle_deg": fr.angle_deg, **meta})
        plots.save_figure(plots.scan_figure(runs), out / "scan.png")


def _summary(runs: list[Any], setup: Any, meta: dict[str, Any], extra: dict[str, Any]
             ) -> dict[str, Any]:
    """``summary.json``'s object (:func:`afmctl.experiment.scan.summary`) with ``extra``'s keys,
    JSON-ready."""
    from afmctl.experiment import runner
    from afmctl.experiment import scan as xs
    return runner.json_ready({**xs.summary(runs, setup, meta), **extra})


def _report(data: dict[str, Any], out: Path) -> None:
    for name, m in data["filters"].items():
        say(f"{name:8s} fast RMS {m['fast_rms_um']:.4f} um ({m['fast_rms_pct']:.3f} % of the "
            f"frame), max {m['fast_max_um']:.4f} um; registration {m['registration_px']:.3f} px;"
            f" slow deviation {m['slow_deviation_px']:.3f} px")
        if m.get("decoupling_db") is not None:
            say(f"{'':8s} y motion caused by x: {m['slow_line_synchronous_um']:.4f} um with the "
                f"feed-forward, {m['slow_line_synchronous_without_feedforward_um']:.4f} um "
                f"without ({m['decoupling_from']}): {m['decoupling_db']:.1f} dB")
    if "ratio_linear_over_inverse_fast_rms" in data:
        say(f"ratio linear / inverse fast RMS: {data['ratio_linear_over_inverse_fast_rms']:.1f}")
    say(f"wrote {out}/ " + ", ".join(OUTPUTS) + " and the run files")
