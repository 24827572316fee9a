"""Learning from repeated scans: play, judge and correct the waveform iteration by iteration.

The law is :mod:`afmctl.planning.ilc` (its docstring states it and its convergence condition). This
module plays it on a stage through the interface of :mod:`drivers` (an object passed in, as
:mod:`afmctl.experiment.runner` does): iteration 0 is the seed filter's waveform (Algorithm 3 through
the model, or the paper's linear filter), every next one the same filter on the corrected
reference, with the same conditioning and inversion horizons. Each waveform passes the guard
before it is sent; one that would not ends learning with the best waveform so far, as do the
noise floor and a diverging error. Every iteration's run file is written as its samples arrive,
and ``summary.json``, ``waveform_learned.csv`` and ``learn.png`` after every iteration.
"""

from __future__ import annotations

import dataclasses as dc
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl import guard
from afmctl.experiment import replay
from afmctl.experiment import runner as experiment
from afmctl.files.modelfile import Envelope
from afmctl.model import effects as fx
from afmctl.model import frame as fr
from afmctl.model import transducer as tr
from afmctl.planning import ilc, track

FloatArray = NDArray[np.float64]
DEFAULT_LAW = ilc.Law()
#: The conditioning's gain and offset are not used when they leave more than this many times the
#: noise of two runs unexplained on it (:func:`offset_checked`).
OFFSET_AGREE = 5.0
#: The run's slow offset is carried along the conditioning's slope to the middle of the tracking
#: part, but no farther past the conditioning than this many times the stretch it was fitted on
#: (a log-time creep is no straight line over seconds; :func:`run_change`).
CARRY_WINDOWS = 1.0


# ----------------------------------------------------------------------------------------------
# planning a reference
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Planner:
    """What stays fixed over the iterations: the model at the sample period, its state after the
    conditioning, the conditioning itself, the seed filter, the inverse's horizons per stretch
    (iteration 0's; a stretch's grows only where a corrected reference would otherwise break
    the guard), the linear filter's voltage range, and the model's validity envelope (every
    iteration's waveform must stay inside it unless ``extrapolate``)."""

    cm: tr.Compiled
    limits: guard.Limits
    start_v: float
    state: tr.StageState
    prefix_v: FloatArray
    seed: str
    horizons: tuple[int, ...]
    v_range: tuple[float, float]
    envelope: Envelope | None = None
    extrapolate: bool = False
    initial: tr.StageState | None = None


def planner(model: tr.Transducer, desired: track.Desired, limits: guard.Limits,
            start_v: float = 0.0, seed: str = "inverse", condition: bool = True,
            envelope: Envelope | None = None, extrapolate: bool = False,
            state: tr.StageState | None = None, frame: fr.Frame = fr.Frame()
            ) -> tuple[Planner, track.Waveform]:
    """The planner and iteration 0's waveform (``seed``: ``inverse``, or the paper's ``linear``
    filter, learning then through the line instead of the model). ``envelope`` bounds the
    conditioning and the waveforms as in :func:`afmctl.planning.track.plan`; ``state`` is the
    model's at the start (default: at rest at ``start_v``; a twin's, to start where a creeping
    stage is) and ``frame`` where the readings will sit from the model (default: its zero)."""
    if seed not in ("inverse", "linear"):
        raise ValueError(f"unknown seed filter {seed!r}")
    plans = track.plan(model, desired, limits, start_v, ("inverse", seed), state=state,
                       condition=condition, envelope=envelope, extrapolate=extrapolate,
                       frame=frame)
    inv = plans["inverse"]
    cm = tr.compile_model(model, desired.dt_s)
    pre = (track.conditioning(track.conditioning_limits(limits, envelope), start_v, desired.dt_s)
           if condition else np.zeros(0))
    st0 = tr.initial(model, voltage_v=start_v) if state is None else state
    _, _, st = tr.simulate(cm, pre, st0)
    v_tr = inv.voltage_v[inv.tracking]
    p = Planner(cm, limits, start_v, st, pre, seed, inv.horizons,
                (float(v_tr.min()), float(v_tr.max())), envelope, extrapolate, st0)
    return p, plans[seed]


def plan_reference(p: Planner, desired: track.Desired, reference: FloatArray
                   ) -> track.Waveform:
    """The seed filter's waveform for ``reference`` (um), scored against ``desired``.

    Raises
    ------
    guard.LimitError
        If the waveform would leave the stage's limits or the reference its reach.
    afmctl.planning.track.EnvelopeError
        If it would leave the model's validity envelope (and the planner does not extrapolate).
    """
    ref = dc.replace(desired, u_um=np.asarray(reference, dtype=float))
    if p.seed == "inverse":
        wf = track.plan_inverse(p.cm, ref, p.limits, p.start_v, p.state, p.prefix_v,
                                p.horizons)
    else:
        wf = track.plan_linear(p.cm, ref, p.limits, p.start_v, p.state, p.v_range, p.prefix_v)
    track.check_envelope(wf, p.envelope, p.extrapolate)
    d = wf.desired_um.copy()
    d[wf.tracking] = desired.u_um
    return dc.replace(wf, desired_um=d)


def gain_direction(p: Planner, wf: track.Waveform) -> FloatArray:
    """``s = dy/dg`` (um per unit gain) over the whole of ``wf``: how the model's position (rod,
    amplifier lag and second mode) moves when the stage applies ``g`` times the waveform, as a
    per-run gain does (a central difference at ``g = 1 +- 1 %``, from the state before the
    conditioning)."""
    assert p.initial is not None
    chain = fx.compile_chain(p.cm.model.effects, p.cm.dt)

    def position(g: float) -> FloatArray:
        v_app = fx.lag(chain, g * wf.voltage_v, g * p.start_v)[0]
        return fx.position(chain, tr.simulate(p.cm, v_app, p.initial)[0])

    return (position(1.01) - position(0.99)) / 0.02


# ----------------------------------------------------------------------------------------------
# the iterations on a stage
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Iteration:
    """One played iteration: its outcome (track's scores and run file), the true-position
    error estimate ``error_um`` (desired - corrected readings, tracking part), the imaging-region
    RMS at the samples and (with a plant model) between them, um.

    ``gain_change`` is the run's applied-voltage gain relative to iteration 0's, measured on the
    conditioning excursion (the same voltages every iteration: :func:`gain_change`);
    ``gain_direction_um`` is ``s = dy/dg`` of this iteration's own waveform on the tracking part
    (um per unit gain, :func:`gain_direction`; None without conditioning: no gain is measured
    then); ``learned_um`` is the error learning uses and
    judges, the error the run would have made at the mean gain of the runs so far
    (``error_um`` itself when the gain does not vary) and at the slow offset predicted for it,
    and ``judged_um`` the RMS over the learned region (the steady part, or its imaging region)
    of the error at the mean gain. ``reference_um`` is the reference ``r_j`` the waveform
    inverts (tracking part, um); ``offset_um`` the run's slow offset (creep, drift: um, on the
    conditioning, relative to the first run, or to the kept run of a replay), and
    ``predicted_offset_um`` the offset its reference was shifted for (:func:`at_mean_gain`);
    ``repeatable_um`` the RMS of ``learned_um``: what the waveform itself does, had the slow
    offset been the predicted one (what the step size and the divergence stop look at);
    ``offset_from`` says where the offset was measured (:func:`offset_checked`)."""

    index: int
    outcome: experiment.Outcome
    error_um: FloatArray
    rms_imaging_um: float
    rms_imaging_between_um: float | None
    steady_um: float
    gain_change: float = 0.0
    gain_direction_um: FloatArray | None = None
    learned_um: FloatArray | None = None
    judged_um: float = float("nan")
    reference_um: FloatArray | None = None
    offset_um: float = 0.0
    predicted_offset_um: float = 0.0
    repeatable_um: float = float("nan")
    offset_from: str = "conditioning"
    conditioning_misfit_um: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        s = self.outcome.score
        return {"iteration": self.index, "rms_um": s.rms_um, "max_um": s.max_um,
                "rms_between_um": s.rms_between_um, "rms_imaging_um": self.rms_imaging_um,
                "rms_imaging_between_um": self.rms_imaging_between_um,
                "rms_steady_um": self.steady_um,
                "max_slew_V_per_ms": self.outcome.waveform.max_slew_v_per_ms,
                "gain_change": self.gain_change, "judged_um": self.judged_um,
                "offset_um": self.offset_um, "predicted_offset_um": self.predicted_offset_um,
                "offset_from": self.offset_from,
                "conditioning_misfit_um": self.conditioning_misfit_um,
                "repeatable_um": self.repeatable_um,
                "complete": self.outcome.complete, "run_file": self.outcome.run_file.name}


@dataclass(frozen=True)
class Result:
    """All finished iterations, the best one (smallest judged error), why learning stopped, the
    noise estimate (um), the tuning of ``L`` and ``Q``, the compute time per iteration (s:
    correction, Algorithm 3, guard and judging at the samples; the simulation of the plant
    between the samples, which only reports, is left out) and the run-to-run spread of the
    applied-voltage gain the conditioning measured (1 sigma of ``gain_change``, fraction)."""

    iterations: tuple[Iteration, ...]
    best: int
    stop: str
    noise_um: float
    tuning: ilc.Tuning
    compute_s: tuple[float, ...]
    gain_sigma: float = 0.0

    @property
    def lead(self) -> int:
        return self.tuning.lead

    @property
    def best_iteration(self) -> Iteration:
        return self.iterations[self.best]


def between_error(wf: track.Waveform, desired: track.Desired,
                  truth: tr.Transducer | None) -> FloatArray | None:
    """Error between the samples (:func:`afmctl.planning.track.between_samples`) of the plant ``truth``,
    or None without one."""
    return None if truth is None else track.between_samples(truth, wf, desired, tr.initial(truth))


def judge(wf: track.Waveform, desired: track.Desired, index: int, measured: tuple[Any, ...],
          path: Path, sensor: fx.Effects, between: FloatArray | None) -> Iteration:
    """Score one played iteration as track does (readings corrected for ``sensor``; between the
    samples from :func:`between_error`, if given), plus the imaging region.

    ``measured`` is :func:`afmctl.experiment.runner.stream`'s (displacement_um, voltage_v, complete).
    """
    img_between = None if between is None else ilc.imaging_rms(desired, between, track.FINE)
    outcome = experiment.scored(wf, desired, measured, path, sensor, between)
    err = desired.u_um - outcome.scored_um[wf.tracking]
    steady = ilc.rms(err[ilc.steady_part(desired)])
    return Iteration(index, outcome, err, ilc.imaging_rms(desired, err), img_between, steady,
                     learned_um=err, judged_um=steady)


OnIteration = Callable[[Result], None]


@dataclass(frozen=True)
class Resume:
    """Where a replay of earlier learning starts: the kept iteration's reference (tracking
    part, um) and inversion horizons, its run's readings (whole run, um: the replay's
    conditioning readings are compared with them to tell how far the stage has moved since,
    creep and drift; None: not told), that learning's tuning of ``L`` and ``Q`` (None:
    measured on the replay, as on a first iteration 0) and the kept waveform's voltages (whole
    run, V; None: re-planned from the reference)."""

    reference_um: FloatArray
    horizons: tuple[int, ...] = ()
    readings_um: FloatArray | None = None
    tuning: ilc.Tuning | None = None
    voltage_v: FloatArray | None = None

    @classmethod
    def kept(cls, result: Result) -> Resume:
        """The replay of ``result``'s best iteration."""
        it = result.best_iteration
        assert it.reference_um is not None
        return cls(it.reference_um, it.outcome.waveform.horizons, it.outcome.displacement_um,
                   result.tuning, it.outcome.waveform.voltage_v)


@dataclass
class Step:
    """The step of the law (a fraction of ``rho``) and where the next step starts: halved, from
    the best iteration, after an iteration worse than the best (never below the law's
    ``min_step``). Shared by the raster's learning (:mod:`afmctl.experiment.scanlearn`)."""

    scale: float = 1.0
    start: int = 0

    def after(self, rep: Sequence[float], law: ilc.Law) -> bool:
        """Update after the last of the iterations whose errors are ``rep`` (any one scale:
        um, or over the noise); True if it was worse than the best at the smallest step
        already (no step left to try)."""
        b, j = int(np.nanargmin(rep)), len(rep) - 1
        if rep[j] <= rep[b] or j == 0:
            self.start = j
            return False
        if self.scale > law.min_step:
            self.scale, self.start = max(self.scale / 2, law.min_step), b
            return False
        self.start = j
        return True


def next_reference(done: list[Iteration], step: Step, desired: track.Desired, law: ilc.Law,
                   tuning: ilc.Tuning, region: NDArray[np.bool_] | None, pred: float
                   ) -> FloatArray:
    """``r_{j+1}``: the law's step (scaled by ``step``) from ``step.start``'s reference and
    learned error, shifted from the slow offset predicted for that run to ``pred``, the one
    predicted for the next (um, :func:`predicted`)."""
    src = done[step.start]
    assert src.reference_um is not None and src.learned_um is not None
    ref = ilc.next_reference(src.reference_um, src.learned_um, desired,
                             dc.replace(law, gain=law.gain * step.scale), tuning, region)
    return ref - (pred - src.predicted_offset_um)


def predicted(done: list[Iteration], drift_um_per_s: float, since_first_s: float) -> float:
    """The next run's slow offset (um, :func:`afmctl.planning.ilc.predicted_offset`): after the
    first run alone, the frame's drift (um/s, read before it: :class:`afmctl.model.frame.Frame`)
    times ``since_first_s``, the time from that run's start to the next's (s, :func:`_since`).
    A fourth tester's drifting stage (14 nm/s read before learning)
    had moved +0.065 um by iteration 1, planned for no move: 2.9x the noise."""
    return ilc.predicted_offset(np.array([x.offset_um for x in done]),
                                drift_um_per_s * since_first_s)


def _since(stage: experiment.PlayingStage, started_s: float | None) -> float:
    """Seconds from ``started_s`` (the stage's clock) to the next run's start (now, plus the
    delay a start takes: :data:`afmctl.experiment.runner.LEAD_S`); 0 where the stage keeps no
    clock."""
    now = getattr(stage, "now_s", None)
    if started_s is None or now is None:
        return 0.0
    return max(0.0, float(now()) + experiment.LEAD_S - started_s)


def retuned(done: list[Iteration], taken: tuple[int, float] | None, tuning: ilc.Tuning,
            desired: track.Desired, law: ilc.Law, noise: float,
            region: NDArray[np.bool_] | None) -> ilc.Tuning:
    """``tuning`` with ``G^`` re-measured where the last step stalled
    (:func:`afmctl.planning.ilc.retune`): the step ``taken`` (the iteration it started from and
    its scale) that made the last of ``done``; as it was without one."""
    if taken is None:
        return tuning
    a, b = done[taken[0]], done[-1]
    assert a.reference_um is not None and b.reference_um is not None
    assert a.learned_um is not None and b.learned_um is not None
    return ilc.retune(tuning, (a.reference_um, b.reference_um),
                      (desired.u_um - a.learned_um, desired.u_um - b.learned_um),
                      (a.learned_um, b.learned_um), desired,
                      dc.replace(law, gain=law.gain * taken[1]), noise, region)


def run(stage: experiment.PlayingStage, model: tr.Transducer, desired: track.Desired,
        limits: guard.Limits, out: Path, meta: Mapping[str, object], iterations: int,
        law: ilc.Law = DEFAULT_LAW, truth: tr.Transducer | None = None, seed: str = "inverse",
        condition: bool = True, progress: experiment.Progress | None = None,
        on_iteration: OnIteration | None = None, envelope: Envelope | None = None,
        extrapolate: bool = False, resume: Resume | None = None,
        start: tuple[tr.StageState, fr.Frame] | None = None) -> Result:
    """Play iteration 0 and up to ``iterations`` learning iterations on ``stage``.

    Every iteration's run file goes to ``out`` (``run_<seed>_iterNN.csv``) as it plays;
    ``on_iteration`` is called with the result so far after each finished iteration (write the
    summary there: an interrupt then loses nothing finished). ``truth`` is the plant the stage
    simulates, for judging between the samples (None: not judged there; the model's own
    simulation would only show the model inverting itself). A refused waveform, the noise floor
    or a diverging error end learning early (``Result.stop`` says which). With ``resume``,
    iteration 0 replays its kept waveform (its voltages, if ``resume`` has them, else re-planned
    from its reference) and the next ones re-learn from there with its tuning, each planned
    from its reference with the kept voltages' difference from their own plan added
    (:class:`afmctl.experiment.replay.Carried`), guard-checked from the stage's output then;
    the replay's ``offset_um`` is how far the stage has moved since the kept run. ``start``
    (the model's state when the stage starts, and the frame its readings will be in: a twin's,
    :meth:`Twin.planning_frame`)
    plans iteration 0 as ``afmctl track`` does, its reference the trajectory less the frame;
    without it, from rest in the model's zero.

    Raises
    ------
    guard.LimitError, afmctl.planning.track.EnvelopeError
        If iteration 0's waveform would leave the limits or the envelope (nothing is sent).
    """
    out.mkdir(parents=True, exist_ok=True)
    start_v = stage.voltage()
    t0 = time.perf_counter()
    state, frame = start if start is not None else (None, fr.Frame())
    if resume is not None:  # the replay's reference is the kept one
        frame = fr.Frame()
    p, wf = planner(model, desired, limits, start_v, seed, condition, envelope, extrapolate,
                    state, frame)
    ref = desired.u_um - frame.along(wf.tracking.start, desired.u_um.size, desired.dt_s)
    tuning = ilc.Tuning(0, law.cutoff_hz, np.zeros(0), np.zeros(0, complex))
    if resume is not None:
        ref, tuning = resume.reference_um.copy(), resume.tuning or tuning
        if resume.horizons:  # the kept run's (grown) horizons
            p = dc.replace(p, horizons=resume.horizons)
        wf = plan_reference(p, desired, ref)
    wf, carried = replay.replayed(wf, None if resume is None else resume.voltage_v, limits,
                                  start_v, p.prefix_v.size)
    done: list[Iteration] = []
    compute: list[float] = []
    noise, best, stop, sigma, step = float("nan"), 0, "iterations done", 0.0, Step()
    region = ilc.imaging_mask(desired, first_period=True) if law.region == "imaging" else None
    taken: tuple[int, float] | None = None  # the last step: where it started, its scale
    started: float | None = None  # when the first run started (s, the stage's clock)
    pred = 0.0  # the slow offset the run is planned for (um)
    for j in range(iterations + 1):
        if j:
            t0 = time.perf_counter()
            tuning = retuned(done, taken, tuning, desired, law, noise, region)
            pred = predicted(done, frame.um_per_s, _since(stage, started))
            ref = next_reference(done, step, desired, law, tuning, region, pred)
            taken = (step.start, step.scale)
            try:
                wf = plan_reference(p, desired, ref)
                if carried is not None:
                    wf = dc.replace(wf, voltage_v=carried.added(wf))
                    guard.check(wf.voltage_v, wf.dt_s, limits, stage.voltage(),
                                "re-learned waveform")
            except (guard.LimitError, track.EnvelopeError) as exc:
                stop = f"refused: {exc}"
                break
            if wf.horizons:  # horizons only grow (where a stretch needs it to pass the guard)
                p = dc.replace(p, horizons=wf.horizons)
        wf = dc.replace(wf, filter=f"{seed}_iter{j:02d}")
        t_plan = time.perf_counter() - t0
        path = out / f"run_{wf.filter}.csv"
        measured = experiment.stream(stage, wf, path, meta, progress)
        started = started if j else getattr(stage, "run_started_s", None)
        between = between_error(wf, desired, truth)  # reporting only: not part of the compute
        t1 = time.perf_counter()
        it = judge(wf, desired, j, measured, path, model.effects, between)
        if j == 0:
            noise = ilc.noise_estimate(it.error_um[ilc.steady_part(desired)])
            if resume is None or resume.tuning is None:
                tuning = ilc.tune(ref, desired.u_um - it.error_um, desired, law, noise)
        it = dc.replace(it, reference_um=ref, predicted_offset_um=pred)
        first = (resume.readings_um if resume is not None and resume.readings_um is not None
                 else done[0].outcome.displacement_um if done else None)
        it = measure_change(p, it, first, model.effects)
        if done and resume is None:
            it = offset_checked(it, done[0], desired, noise)
        if j == 0 and resume is not None:  # the replay's offset could not be predicted: its
            it = dc.replace(it, predicted_offset_um=it.offset_um)  # error is its waveform's now
        done, sigma = at_mean_gain([*done, it], desired, law)
        it = done[-1]
        compute.append(t_plan + time.perf_counter() - t1)
        best = int(np.argmin([x.judged_um for x in done]))
        if on_iteration is not None:
            on_iteration(Result(tuple(done), best, stop, noise, tuning, tuple(compute), sigma))
        s_rms = (0.0 if it.gain_direction_um is None
                 else ilc.rms(it.gain_direction_um[ilc.steady_part(desired)]))
        floor = ilc.resolution(noise, sigma, s_rms, len(done))
        stop = stop_rule(done, step.after([x.repeatable_um for x in done], law), floor, noise,
                         law, sigma) or stop
        if stop != "iterations done":
            break
    return Result(tuple(done), best, stop, noise, tuning, tuple(compute), sigma)


def replayed_moved(stage: experiment.PlayingStage, model: tr.Transducer, desired: track.Desired,
                   limits: guard.Limits, result: Result, paths: tuple[Path, Path]
                   ) -> replay.Moved:
    """``result``'s kept waveform played as ``afmctl play --model`` plays a learned one
    (:func:`afmctl.experiment.replay.moved_replay`), planned through ``model`` from the stage's
    present output, in process (its run's readings, reference, offset miss and noise from
    ``result``; run files ``paths``)."""
    kept = result.best_iteration
    assert kept.reference_um is not None
    p, _ = planner(model, desired, limits, stage.voltage())
    return replay.moved_replay(stage, kept.outcome.waveform, kept.outcome.displacement_um,
                               kept.reference_um, kept.offset_um - kept.predicted_offset_um,
                               lambda r: plan_reference(p, desired, r), p.prefix_v, limits,
                               paths, {}, noise_um=result.noise_um)


def stop_rule(done: list[Iteration], no_step_left: bool, floor: float, noise: float,
              law: ilc.Law, sigma: float) -> str:
    """Why learning stops after the last of ``done`` ("" to go on): its error at the mean gain
    within ``law.floor_factor`` x the resolution ``floor`` (um), or its repeatable error (the
    slow offset's miss removed: drift is not a divergence) worse than ``law.diverge_factor``
    x the best's with no smaller step left to try."""
    it, rep = done[-1], min(x.repeatable_um for x in done)
    if no_step_left and it.repeatable_um > law.diverge_factor * max(rep, floor):
        return (f"diverging: iteration {it.index} ({it.repeatable_um:.4g} um) worse than "
                f"{law.diverge_factor:g} x the best ({rep:.4g} um) at the smallest step "
                f"({law.min_step:g} rho)")
    if it.judged_um <= law.floor_factor * floor:
        return (f"noise floor: {it.judged_um:.4g} um within {law.floor_factor:g} x noise"
                + ("" if floor == noise else
                   f" and the mean gain's uncertainty ({floor:.4g} um; gain spread "
                   f"{100 * sigma:.2g} %)"))
    return ""


def measure_change(p: Planner, it: Iteration, first: FloatArray | None,
                   sensor: fx.Effects) -> Iteration:
    """``it`` with its waveform's gain direction ``s`` and, against the readings ``first`` of
    the run it is compared with (um; None: there is none), its gain change and slow offset
    (:func:`run_change`). Without conditioning nothing is measured."""
    if not p.prefix_v.size:
        return it
    # s of this waveform: the learned waveforms sit elsewhere on the hysteresis than
    # iteration 0's (its offset alone moved s's mean by ~7 um per unit gain on a stage)
    s_dir = gain_direction(p, it.outcome.waveform)
    it = dc.replace(it, gain_direction_um=s_dir[it.outcome.waveform.tracking])
    if first is None:
        return it
    d, o, misfit = run_change(it, first, s_dir, p.prefix_v, sensor)
    return dc.replace(it, gain_change=d, offset_um=o, conditioning_misfit_um=misfit)


def offset_checked(it: Iteration, first: Iteration, desired: track.Desired, noise: float
                   ) -> Iteration:
    """``it`` with its slow offset measured on the tracking part where the conditioning does
    not describe the run.

    The conditioning tells two runs apart only by their gain and offset if its peak wipes out
    what came before; then the two runs' readings after it differ by ``d s + o`` and the noise
    of two runs. A stage without return-point memory (Bouc-Wen) does not forget: on bw-b the
    excursion read -1.21 um between two runs whose tracking parts were 0.03 um apart, the next
    run was shifted for a -1.8 um drift, and learning went from 0.029 to 1.89 um. Where the
    difference leaves more than :data:`OFFSET_AGREE` times the noise of two runs unexplained,
    the gain change is dropped and the offset is the tracking part's mean change less the
    reference's (the model's DC response through its own inverse taken as 1;
    ``offset_from = "tracking"``)."""
    steady = ilc.steady_part(desired)
    if (it.reference_um is None or first.reference_um is None or not np.isfinite(noise)
            or it.conditioning_misfit_um <= OFFSET_AGREE * math.sqrt(2.0) * noise):
        return it
    diff = (first.error_um - it.error_um)[steady]  # y = u - e
    if not np.isfinite(diff).any():
        return it
    moved = float(np.nanmean(diff))
    shift = float(np.mean((it.reference_um - first.reference_um)[steady]))
    return dc.replace(it, offset_um=moved - shift, gain_change=0.0, offset_from="tracking")


def run_change(it: Iteration, first: FloatArray, s: FloatArray, prefix_v: FloatArray,
               sensor: fx.Effects) -> tuple[float, float, float]:
    """The run's applied-voltage gain relative to that of the run whose readings are ``first``
    (um) (fraction) and its slow offset
    (um: creep, drift), from the conditioning excursion ``prefix_v`` that starts every
    iteration: the coefficient along ``s``, the free offset and a free slope of the difference
    of the two runs' readings (corrected for ``sensor``) from its peak on, where the same
    voltages have wiped out what came before, so that nothing but the gain, the slow offset and
    the noise tells the two runs apart. In units of the model's ``s``: a stage that moves ``c``
    times as far per volt as the model reads ``c`` times its gain change, and ``d s`` is the
    stage's own movement, which is what learning removes.

    The offset is the line's value at the middle of the tracking part (at most
    :data:`CARRY_WINDOWS` fitted stretches past the conditioning): a run that follows the one
    before it closely sees that run's creep relax faster than one after a rest, and the offset
    on the conditioning missed what the tester's creeping, drifting stage did on the tracking
    part by 0.012-0.018 um (its learning ended as "diverging" on that); the slope's value there
    came within 0.002 um. Also returns the RMS the fit left unexplained (um: the noise of two
    runs if the excursion wiped out what came before)."""
    wf = it.outcome.waveform
    chain = fx.compile_chain(sensor, wf.dt_s)
    peak = int(np.argmax(prefix_v))
    part = slice(peak, prefix_v.size)
    middle = (wf.tracking.start + wf.tracking.stop - 1) / 2
    at = min(middle, prefix_v.size + CARRY_WINDOWS * (prefix_v.size - peak))
    ramp = (np.arange(peak, prefix_v.size) - at) * wf.dt_s
    w = [fx.sensor_correct(chain, x)[part] for x in (first, it.outcome.displacement_um)]
    return ilc.gain_and_offset(w[1] - w[0], s[part], ramp)


def at_mean_gain(done: list[Iteration], desired: track.Desired, law: ilc.Law
                 ) -> tuple[list[Iteration], float]:
    """Every iteration judged at the mean gain of the runs so far, and the gain's spread (1 sigma).

    A run whose gain was ``d_i - mean(d)`` above the mean moved the stage by that times its own
    waveform's ``s`` (``gain_direction_um``) on the trajectory: added back to its error, it
    leaves the error its waveform makes at the mean gain (``judged_um`` its RMS over the
    learned region). All iterations are compared at the same gain, so a run's own draw neither
    makes its waveform look best nor ends learning as a divergence. Likewise a run whose slow
    offset was ``o_i`` where ``o^_i`` was predicted moved by the difference: added back, that
    leaves the error its waveform makes at the predicted offset (``learned_um``, what learning
    learns from; ``repeatable_um`` its RMS), so learning neither chases the drift's
    unpredictable part nor takes it for a divergence.
    """
    d = np.array([x.gain_change for x in done])
    out = []
    for x in done:
        s = x.gain_direction_um if x.gain_direction_um is not None else 0.0
        at_gain = x.error_um + (x.gain_change - float(d.mean())) * s
        learned = at_gain + (x.offset_um - x.predicted_offset_um)
        out.append(dc.replace(x, learned_um=learned, judged_um=_region_rms(desired, at_gain, law),
                              repeatable_um=_region_rms(desired, learned, law)))
    return out, float(np.std(d, ddof=1)) if d.size > 1 else 0.0


def _region_rms(desired: track.Desired, error: FloatArray, law: ilc.Law) -> float:
    """RMS (um) over the learned region: the imaging region, or the steady part."""
    return (ilc.imaging_rms(desired, error) if law.region == "imaging"
            else ilc.rms(error[ilc.steady_part(desired)]))
