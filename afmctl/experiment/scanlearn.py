"""Learning a raster frame frame by frame, then scanning with what was learned.

The law is ``track --learn``'s (:mod:`afmctl.planning.ilc`), on both axes at once: frame 0 plays
each axis's inverse of its target (the desired trajectory with the coupling fed forward,
:func:`afmctl.planning.raster.targets`); every next frame corrects each axis's **reference**,
``r_{j+1} = r_j + Q[L e_j]``, from that axis's measured error inside the image (the overscan and
its turnarounds learn nothing of their own, so a fast scan does not keep sharpening its corners:
the error there is bridged from the image's edges, :func:`afmctl.planning.ilc.bridged`), and plans
it again through that axis's inverse. The y error includes the y motion x causes that the
feed-forward left: the y reference learns it away with the rest (and likewise x). ``L`` and
``Q`` are tuned per axis on frame 0 (:func:`afmctl.planning.ilc.tune`, the line rate's
harmonics), each axis's reference against its own motion (:func:`_tunings`); each axis's ``Q``
may rise from 600 Hz to 1.2 kHz up to where that axis stops following its model
(:data:`DEFAULT_LAW`, :func:`afmctl.planning.ilc.reach_hz`).

Every frame's waveform passes the guard and the envelope before it is sent; one that would not
ends learning with the best frame so far, as do the noise floor (both axes' image-region RMS
error within :attr:`~afmctl.planning.ilc.Law.floor_factor` of their noise, estimated from the
readings) and a diverging error (worse than :attr:`~afmctl.planning.ilc.Law.diverge_factor`
times the best with an axis at the smallest step). As ``track --learn``
(:class:`afmctl.experiment.learn.Step`), each axis whose error grew past its best sends its next
step from its best frame at half the step, down to :attr:`~afmctl.planning.ilc.Law.min_step`;
the other axis goes on (foreign-xy-4 at 30 lines/s: x 17.3, 4.41, 2.34, 1.80x its noise while y
went 5.27, 2.39, 3.11, 4.60x, chasing the motion x's changing waveform causes in it; with one
whole step for both, learning stopped as diverging at 4.6x). The best frame's waveform is then
what ``--frames`` plays, and is saved (``waveform_learned.csv``, a two-axis waveform file
``afmctl play`` replays).

Frame 0 is played twice: first as a conditioning pass (``run_condition.csv``, kept, not
judged), then as the frame learning starts from. Learning corrects what repeats, and the first
pass of a frame from wherever the stage was is no repetition: an axis without return-point
memory (Bouc-Wen) is still on its way onto the frame's cycle, and the next frames do not make
that way again. On foreign-xy-2's Bouc-Wen y, after the bench's scans, frame 0 was 40x its
noise, of which the conditioning pass takes half; without it the first learned frame was worse
(60x) and five frames reached 17.7x, with it two frames reach the noise floor (19.0, 2.44,
1.10x).
"""

from __future__ import annotations

import dataclasses as dc
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from afmctl import guard
from afmctl.errors import EnvelopeError, InputError
from afmctl.experiment import learn as onelearn
from afmctl.experiment import runner
from afmctl.experiment import scan as xs
from afmctl.files import waveformfile
from afmctl.planning import ilc, raster, track

#: The raster's law: ``track --learn``'s, its cut-off free to rise per axis to 1.2 kHz (a rod's
#: ringing after the fast axis's turnarounds sits near 1 kHz on foreign-xy-3).
DEFAULT_LAW = ilc.Law(cutoff_max_hz=1200.0)


@dataclass(frozen=True)
class Learned:
    """The learning frames played (``runs``), the best one's index, why learning stopped, each
    axis's noise estimate (um) and the cut-off of its ``Q`` (Hz; :func:`ilc.reach_hz`)."""

    runs: tuple[xs.FrameRun, ...]
    best: int
    stop: str
    noise_um: dict[str, float]
    cutoffs_hz: dict[str, float]

    @property
    def waveform(self) -> raster.XYWaveform:
        return self.runs[self.best].waveform

    def to_dict(self) -> dict[str, Any]:
        """``summary.json``'s ``learning``: the frames learned (frame 0 not counted), the best
        one (its number and figure), why learning stopped, every frame's figure (both axes'
        image-region RMS error over their noise, the larger), each axis's noise (um) and
        learning cut-off (Hz)."""
        return {"frames_learned": len(self.runs) - 1, "best_frame": self.best,
                "best_over_noise": self.runs[self.best].merit["over_noise"], "stop": self.stop,
                "over_noise_by_frame": [r.merit["over_noise"] for r in self.runs],
                "noise_um": dict(self.noise_um), "cutoff_hz": dict(self.cutoffs_hz)}


def _errors(run: xs.FrameRun, traj: raster.Trajectories) -> dict[str, np.ndarray]:
    """Each axis's error (desired minus readings, um) over the tracking part."""
    return {n: traj.axis(n) - run.scored_um[:, k] for k, n in enumerate(raster.AXES)}


def learn(stage: runner.PlayingStage, setup: xs.Setup, iterations: int, out: Path,
          meta: Mapping[str, object], say: Callable[[str], None] | None = None,
          on_frame: xs.OnFrame | None = None, done: list[xs.FrameRun] | None = None,
          law: ilc.Law = DEFAULT_LAW) -> Learned:
    """Play frame 0 and up to ``iterations`` learning frames (``run_learnNN.csv``); see the
    module docstring."""
    frame, dt = setup.frame, setup.dt_s
    traj = raster.trajectories(frame, dt, 0)
    region = raster.image_mask(frame, dt)
    desired = {n: track.Desired(dt, traj.axis(n), frame.line_s, max(float(np.ptp(traj.axis(n))),
                                                                   frame.pixel_um), n)
               for n in raster.AXES}
    refs = raster.targets(traj, setup.coupling)
    runs = [] if done is None else done
    mine: list[xs.FrameRun] = []
    tunings: dict[str, ilc.Tuning] = {}
    noise: dict[str, float] = {}
    score: list[float] = []
    learned: list[tuple[dict[str, np.ndarray], dict[str, np.ndarray]]] = []  # refs, errors
    steps = {n: onelearn.Step() for n in raster.AXES}
    by_axis: dict[str, list[float]] = {n: [] for n in raster.AXES}
    taken: dict[str, tuple[int, float]] = {}  # each axis's last step: its start, its scale
    stop = "iterations done"
    for j in range(iterations + 1):
        t0 = time.perf_counter()
        if j:
            tunings = _retuned(learned, taken, tunings, traj, desired, setup, law, noise,
                               region)
            refs = {n: _next(learned[steps[n].start], n, desired[n], law, steps[n], tunings[n],
                             region) for n in raster.AXES}
            taken = {n: (steps[n].start, steps[n].scale) for n in raster.AXES}
        try:
            if j == 0:  # the conditioning pass (see the module docstring)
                _play(stage, _planned(stage, setup, refs, "condition"), frame, out,
                      {**meta, "learning_frame": "condition"}, say)
                t0 = time.perf_counter()  # frame 0's own time from here
            wf = _planned(stage, setup, refs, f"learn{j:02d}")
        except (guard.LimitError, EnvelopeError) as exc:
            if not mine:  # frame 0 itself: refused as the scan would be, before anything moves
                raise
            stop = f"refused: {exc}"
            break
        path, measured = _play(stage, wf, frame, out, {**meta, "learning_frame": j}, say)
        run = xs.judge(setup, 0, wf, measured, path, time.perf_counter() - t0)
        runs.append(run)
        mine.append(run)
        errors = _errors(run, traj)
        learned.append((refs, errors))
        if j == 0:
            noise = {n: ilc.noise_estimate(errors[n][region]) for n in raster.AXES}
            tunings = _tunings(refs, traj, errors, desired, setup, law, noise)
        for n in raster.AXES:
            by_axis[n].append(ilc.rms(errors[n][region]) / noise[n])
        score.append(max(by_axis[n][-1] for n in raster.AXES))  # the larger axis's
        run.merit["over_noise"] = score[-1]
        if on_frame is not None:
            on_frame(runs)
        if score[-1] <= law.floor_factor:
            stop = f"noise floor: {score[-1]:.3g} x the noise (both axes, image region)"
            break
        no_step_left = [steps[n].after(by_axis[n], law) for n in raster.AXES]
        if any(no_step_left) and score[-1] > law.diverge_factor * min(score):
            stop = (f"diverging: frame {j} at {score[-1]:.3g} x the noise, best "
                    f"{min(score):.3g}, at the smallest step ({law.min_step:g} rho)")
            break
    return Learned(tuple(mine), int(np.argmin(score)), stop, noise,
                   {n: t.cutoff_hz for n, t in tunings.items()})


def _planned(stage: runner.PlayingStage, setup: xs.Setup, refs: dict[str, np.ndarray],
             name: str) -> raster.XYWaveform:
    """The frame planned to the references ``refs`` from where the stage's outputs are now
    (guarded; raises as :func:`afmctl.planning.raster.plan` does), named ``name``."""
    axes = raster.replace_start(setup.axes, np.asarray(stage.voltages(), dtype=float))
    wf = raster.plan(setup.frame, axes, setup.dt_s, setup.coupling, ("inverse",), 0,
                     setup.extrapolate, aims=refs)["inverse"]
    return dc.replace(wf, filter=name)


def _play(stage: runner.PlayingStage, wf: raster.XYWaveform, frame: raster.Frame, out: Path,
          meta: Mapping[str, object], say: Callable[[str], None] | None
          ) -> tuple[Path, Any]:
    """Stream ``wf`` (a plan of ``frame``) to ``run_<filter>.csv`` in ``out``, with progress:
    the path and the measured streams."""
    path = out / f"run_{wf.filter}.csv"
    show = None if say is None else xs.progress(frame, 1, wf, say, 1 / wf.dt_s, 0)
    return path, runner.stream(stage, wf, path, meta, show)


def _tunings(refs: dict[str, np.ndarray], traj: raster.Trajectories,
             errors: dict[str, np.ndarray], desired: dict[str, track.Desired], setup: xs.Setup,
             law: ilc.Law, noise: dict[str, float]) -> dict[str, ilc.Tuning]:
    """Each axis's ``L`` and ``Q`` (:func:`afmctl.planning.ilc.tune`) from frame 0: its
    reference against its **own** motion, the readings less what the other axis's own motion
    causes through the identified coupling (:func:`afmctl.planning.raster.targets` of the
    readings). Against the readings, y's response at the line's harmonics was mostly what x
    caused and the feed-forward left (foreign-xy-1: ``|G|`` 0.18 at 30 Hz for y's own ~1,
    a learning gain of 2 where 1 was due: y stalled at 9x its noise). A missing reading
    (NaN) is bridged for the coupling's filter, which would carry it to every later sample of
    both axes, and missing again in the own motion."""
    own = _own(traj, errors, setup)
    return {n: ilc.tune(refs[n], own[n], desired[n], law, noise[n]) for n in raster.AXES}


def _own(traj: raster.Trajectories, errors: dict[str, np.ndarray], setup: xs.Setup
         ) -> dict[str, np.ndarray]:
    """Each axis's own motion in a frame (um): its readings less what the other axis's own
    motion causes through the identified coupling (NaN where a reading is missing)."""
    read = {n: traj.axis(n) - errors[n] for n in raster.AXES}
    gap = ~np.isfinite(read["x"]) | ~np.isfinite(read["y"])
    bridged = raster.Trajectories(traj.dt_s, *(ilc.bridged(read[n], np.isfinite(read[n]))
                                                for n in raster.AXES))
    own = raster.targets(bridged, setup.coupling)
    return {n: np.where(gap, np.nan, own[n]) for n in raster.AXES}


def _retuned(learned: list[tuple[dict[str, np.ndarray], dict[str, np.ndarray]]],
             taken: dict[str, tuple[int, float]], tunings: dict[str, ilc.Tuning],
             traj: raster.Trajectories, desired: dict[str, track.Desired], setup: xs.Setup,
             law: ilc.Law, noise: dict[str, float], region: np.ndarray) -> dict[str, ilc.Tuning]:
    """Each axis's ``G^`` re-measured where its last step (``taken``: the frame it started
    from, its scale) stalled (:func:`afmctl.planning.ilc.retune`, on the axes' own motions as
    :func:`_tunings`)."""
    if not taken:
        return tunings
    last = len(learned) - 1
    own = {k: _own(traj, learned[k][1], setup) for k in {last, *(s for s, _ in taken.values())}}
    (r1, e1), y1 = learned[last], own[last]
    out = {}
    for n, (start, scale) in taken.items():
        (r0, e0), y0 = learned[start], own[start]
        out[n] = ilc.retune(tunings[n], (r0[n], r1[n]), (y0[n], y1[n]), (e0[n], e1[n]),
                            desired[n], dc.replace(law, gain=law.gain * scale), noise[n],
                            region)
    return out


def _next(start: tuple[dict[str, np.ndarray], dict[str, np.ndarray]], axis: str,
          desired: track.Desired, law: ilc.Law, step: onelearn.Step, tuning: ilc.Tuning,
          region: np.ndarray) -> np.ndarray:
    """Axis ``axis``'s next reference: the law's step (scaled by ``step``) from the frame
    ``start`` (its references and errors)."""
    refs, errors = start
    return ilc.next_reference(refs[axis], errors[axis], desired,
                              dc.replace(law, gain=law.gain * step.scale), tuning, region)


def waveform_text(wf: raster.XYWaveform, meta: Mapping[str, object]) -> str:
    """``waveform_learned.csv``: the whole two-axis waveform with its desired tracking part."""
    return waveformfile.format_text(wf.time_s, wf.voltage_v, wf.desired_um, dict(meta))


def learn_then_scan(stage: runner.PlayingStage, setup: xs.Setup, iterations: int, out: Path,
                    meta: Mapping[str, object], say: Callable[[str], None] | None = None,
                    on_frame: xs.OnFrame | None = None, done: list[xs.FrameRun] | None = None,
                    on_learned: Callable[[Learned], None] | None = None) -> Learned:
    """Learn the frame (:func:`learn`), tell ``on_learned``, save its waveform, then play it
    ``setup.frame.frames`` times (``run_frameNNN_learned.csv``, NNN from 1; the same frame
    every time)."""
    if setup.frame.direction == "bounce":
        raise InputError("--learn-frames learns one frame: scan it --direction up or down")
    runs = [] if done is None else done
    got = learn(stage, setup, iterations, out, meta, say, on_frame, runs)
    if say is not None:
        say(f"learning: {len(got.runs)} frames, best frame {got.best} "
            f"({got.runs[got.best].merit['over_noise']:.3g} x the noise); stopped: {got.stop}; "
            + ", ".join(f"{n} learned up to {f:.0f} Hz" for n, f in got.cutoffs_hz.items()))
    if on_learned is not None:
        on_learned(got)
    wf = dc.replace(got.waveform, filter="learned")
    runner.atomic_write(out / "waveform_learned.csv",
                        waveform_text(wf, {**meta, "learning_frame": got.best}))
    for number in range(1, setup.frame.frames + 1):
        path = xs.run_path(out, number, wf.filter)
        show = None if say is None else xs.progress(setup.frame, number, wf, say, 1 / setup.dt_s,
                                                    setup.frame.frames - number)
        measured = runner.stream(stage, wf, path, {**meta, "frame": number}, show)
        runs.append(xs.judge(setup, 0, wf, measured, path, 0.0, number))
        if on_frame is not None:
            on_frame(runs)
    return got
