"""Raster scans on a two-axis stage: plan each frame, play it, keep its samples, make its images.

Talks to the stage only through the interface of :mod:`drivers` (an object passed in): its
``play`` takes a waveform of shape (N, 2) (channel 0 x, 1 y) and its ``voltages()`` the present
outputs. Every frame is planned from the stage's present outputs (:func:`afmctl.planning.raster.plan`:
each axis through its own inverse, the coupling fed forward, every channel through the guard
and the envelope), then each filter's waveform is played and streamed into its own run file
(``run_frameNNN_<filter>.csv``, NNN the frame's number counted from 1 as everything a user reads
names it: progress, image titles, ``summary.json``; created new: measured data is never
overwritten) as the samples arrive. After every finished frame ``on_frame`` gets everything so
far (write the summary and images there: an interrupt then keeps every finished frame); the
stage's ``play`` puts the stage in its safe state on any error or interrupt, and the run file of
the frame in progress is kept, marked interrupted.

The readings are scored as the stage's position: corrected for each axis model's sensor effects
(delay, gauge), as ``track`` does; the run files keep the raw readings.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl.errors import InputError
from afmctl.experiment import runner
from afmctl.files import modelfile, tomlfile, xymodelfile
from afmctl.model import coupling as cp
from afmctl.model import effects as fx
from afmctl.planning import raster, scanimage

FloatArray = NDArray[np.float64]
#: Progress lines at most this often, s.
PROGRESS_EVERY_S = 0.5


@dataclass(frozen=True)
class Setup:
    """What every frame is planned from: the frame, each axis's model, limits and envelope, the
    coupling fed forward (None: none), the filters to play, the sample period (s)."""

    frame: raster.Frame
    axes: Mapping[str, raster.AxisPlan]
    coupling: Mapping[str, cp.Coupling] | None
    filters: tuple[str, ...]
    dt_s: float
    extrapolate: bool = False


@dataclass(frozen=True)
class FrameRun:
    """One filter's play of one frame: the waveform, the readings (raw, and corrected for the
    models' sensor effects, the tracking part, shape (n, 2)), its images and figures of merit,
    the host's compute time for the frame's plan (s). ``index`` is the planned frame it follows
    (from 0: its slow direction, its pixel grid), ``number`` the frame as a user reads it
    (from 1: run file names, titles, ``summary.json``)."""

    index: int
    number: int
    waveform: raster.XYWaveform
    displacement_um: FloatArray
    scored_um: FloatArray
    images: scanimage.Images
    merit: dict[str, Any]
    complete: bool
    run_file: Path
    compute_s: float
    feedforward_um: FloatArray = field(repr=False, default_factory=lambda: np.zeros((0, 2)))

    @property
    def filter(self) -> str:
        return self.waveform.filter


OnFrame = Callable[[list[FrameRun]], None]


def model_for_scan(profile: Any, model_path: str | None
                   ) -> tuple[dict[str, raster.AxisPlan], dict[str, cp.Coupling] | None, str]:
    """Each axis's model, limits and envelope, the coupling to feed forward (None: none known)
    and a description of where they came from.

    A two-axis model file (each axis's model and the coupling both ways) gives everything; a
    one-axis model file is used for both axes, with no coupling fed forward (said so).
    """
    if model_path is None:
        raise InputError("a raster scan needs a model: --model M (a two-axis model file, from "
                         "`afmctl identify` on two-axis sweeps, or a one-axis one for both "
                         "axes), or --calibrate")
    if modelfile.file_version(tomlfile.load(model_path)) != modelfile.XY_VERSION:
        model, env, _ = xymodelfile.read_axis(model_path, "x")
        axes = {n: raster.AxisPlan(model, profile.axis(n).limits, env) for n in raster.AXES}
        return axes, None, "one-axis model, used for both axes; no coupling"
    both = xymodelfile.read(model_path)
    axes = {n: raster.AxisPlan(both.axes[n], profile.axis(n).limits,
                               xymodelfile.read_axis(model_path, n)[1]) for n in raster.AXES}
    return axes, dict(both.coupling), "two axes and their coupling"


def corrected(setup: Setup, wf: raster.XYWaveform, u: FloatArray) -> FloatArray:
    """The readings of both axes corrected for each axis model's sensor effects (um)."""
    out = np.array(u, dtype=float)
    for k, name in enumerate(raster.AXES):
        sensor = fx.sensor_part(setup.axes[name].model.effects)
        if sensor != fx.Effects():
            out[:, k] = fx.sensor_correct(fx.compile_chain(sensor, wf.dt_s), u[:, k])
    return out


def judge(setup: Setup, index: int, wf: raster.XYWaveform, measured: tuple[Any, ...],
          path: Path, compute_s: float, number: int | None = None) -> FrameRun:
    """A played frame's images and figures of merit, from :func:`runner.stream`'s triple
    (``number``: the frame's number for the user, default ``index + 1``)."""
    u, _, complete = measured
    scored = corrected(setup, wf, u)[wf.tracking]
    frame = setup.frame
    grid = raster.pixel_grid(frame, wf.dt_s, index)
    img = scanimage.images(frame, grid, scored)
    merit = scanimage.merit(frame, img, scored)
    ff = feedforward(setup, index, wf.dt_s)
    if setup.coupling:
        # the slow motion the coupling would have added without the feed-forward: the
        # correction the model fed forward, back on the measured error (a model estimate)
        without = scanimage.images(frame, grid, scored + ff)
        est = scanimage.merit(frame, without)["slow_line_synchronous_um"]
        merit["slow_line_synchronous_without_feedforward_um"] = est
        merit["decoupling_db"] = scanimage.decoupling_db(est, merit["slow_line_synchronous_um"])
        merit["decoupling_from"] = "model estimate (the feed-forward's correction added back)"
    return FrameRun(index, index + 1 if number is None else number, wf, u, scored, img, merit,
                    complete, path, compute_s, ff)


def feedforward(setup: Setup, index: int, dt_s: float) -> FloatArray:
    """The correction the coupling's feed-forward makes (desired minus target, um, (n, 2))."""
    traj = raster.trajectories(setup.frame, dt_s, index)
    aims = raster.targets(traj, setup.coupling)
    return np.column_stack([traj.axis(n) - aims[n] for n in raster.AXES])


def run_path(out: Path, number: int, name: str) -> Path:
    """The run file of frame ``number`` (from 1) played by filter ``name``."""
    return out / f"run_frame{number:03d}_{name}.csv"


def progress(frame: raster.Frame, number: int, wf: raster.XYWaveform, say: Callable[[str], None],
              sample_rate_hz: float, frames_left: int) -> runner.Progress:
    """Progress lines: frame ``number`` of the frames and the line being scanned (both counted
    from 1; before the image, line 1), the filter, and the time left (this run and the frames
    after); a line when the line scanned changes, at most every :data:`PROGRESS_EVERY_S`."""
    last = [0.0, 0]  # when the last line was said, and its line
    per_line = frame.line_s * sample_rate_hz

    def show(name: str, done: int, total: int) -> None:
        now = time.monotonic()
        line = int(np.clip((done - wf.tracking.start) // per_line - raster.LEAD_LINES + 1, 1,
                           frame.lines))
        if line == last[1] or (now - last[0] < PROGRESS_EVERY_S and done < total):
            return
        last[:] = [now, line]
        eta = (total - done) / sample_rate_hz + frames_left * total / sample_rate_hz
        say(f"frame {number}/{frame.frames} {name}: line {line}/{frame.lines}, "
            f"ETA {eta:.0f} s")

    return show


def run(stage: runner.PlayingStage, setup: Setup, out: Path, meta: Mapping[str, object],
        say: Callable[[str], None] | None = None, on_frame: OnFrame | None = None,
        done: list[FrameRun] | None = None) -> list[FrameRun]:
    """Scan ``setup.frame.frames`` frames on ``stage``, every filter of each in turn.

    Each frame's run file goes to ``out`` as it plays; ``on_frame`` is called with every
    :class:`FrameRun` so far after each finished frame (``done``, if given, holds them as they
    finish, for a caller that reports after an interrupt).
    """
    out.mkdir(parents=True, exist_ok=True)
    runs = [] if done is None else done
    rate = 1.0 / setup.dt_s
    frame = setup.frame
    for index in range(frame.frames):
        t0 = time.perf_counter()
        axes = raster.replace_start(setup.axes, np.asarray(stage.voltages(), dtype=float))
        plans = raster.plan(frame, axes, setup.dt_s, setup.coupling, setup.filters, index,
                            setup.extrapolate)
        compute = time.perf_counter() - t0
        for name, wf in plans.items():
            path = run_path(out, index + 1, name)
            show = (None if say is None else
                    progress(frame, index + 1, wf, say, rate,
                             (frame.frames - index - 1) * len(plans)))
            measured = runner.stream(stage, wf, path, {**meta, "frame": index + 1}, show)
            runs.append(judge(setup, index, wf, measured, path, compute))
        if on_frame is not None:
            on_frame(runs)
    return runs


def summary(runs: list[FrameRun], setup: Setup, meta: Mapping[str, object]) -> dict[str, Any]:
    """The ``summary.json`` object: the frame's settings and, per filter, the figures of merit
    of its last frame and of every frame."""
    fr = setup.frame
    data: dict[str, Any] = {
        **meta, "frame": {
            "size_um": [fr.width_um, fr.height_um], "centre_um": list(fr.centre_um),
            "angle_deg": fr.angle_deg, "pixels": fr.pixels, "lines": fr.lines,
            "line_rate_Hz": fr.line_rate_hz, "slow": fr.slow, "direction": fr.direction,
            "overscan": fr.overscan, "frames": fr.frames, "pixel_um": fr.pixel_um,
            "line_pitch_um": fr.line_pitch_um},
        "feedforward": setup.coupling is not None and bool(setup.coupling),
        "filters": {}}
    for name in dict.fromkeys(r.filter for r in runs):
        mine = [r for r in runs if r.filter == name]
        data["filters"][name] = {
            **mine[-1].merit, "frames": [{"frame": r.number, **r.merit, "complete": r.complete,
                                          "run_file": r.run_file.name} for r in mine],
            "compute_s_per_frame": float(np.mean([r.compute_s for r in mine])),
            "horizons": {k: list(v) for k, v in mine[-1].waveform.horizons.items()}}
    filt = data["filters"]
    if {"inverse", "linear"} <= filt.keys():
        data["ratio_linear_over_inverse_fast_rms"] = (filt["linear"]["fast_rms_um"]
                                                      / filt["inverse"]["fast_rms_um"])
    return data


def gwy_channels(runs: list[FrameRun]) -> dict[str, FloatArray]:
    """Every image of every run for ``scan.gwy``, by title (``frame 1 inverse: x trace``, the
    frame counted from 1), um."""
    out = {}
    for r in runs:
        for name, img in r.images.channels().items():
            out[f"frame {r.number} {r.filter}: {name.replace('_', ' ')}"] = img
    return out
