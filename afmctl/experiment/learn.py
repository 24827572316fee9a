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
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl import guard
from afmctl.experiment import runner as experiment
from afmctl.files.modelfile import Envelope
from afmctl.model import effects as fx
from afmctl.model import transducer as tr
from afmctl.planning import ilc, track

FloatArray = NDArray[np.float64]
DEFAULT_LAW = ilc.Law()


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
            envelope: Envelope | None = None, extrapolate: bool = False
            ) -> tuple[Planner, track.Waveform]:
    """The planner and iteration 0's waveform (``seed``: ``inverse``, or the paper's ``linear``
    filter, learning then through the line instead of the model). ``envelope`` bounds the
    conditioning and the waveforms as in :func:`afmctl.planning.track.plan`."""
    if seed not in ("inverse", "linear"):
        raise ValueError(f"unknown seed filter {seed!r}")
    plans = track.plan(model, desired, limits, start_v, ("inverse", seed), condition=condition,
                       envelope=envelope, extrapolate=extrapolate)
    inv = plans["inverse"]
    cm = tr.compile_model(model, desired.dt_s)
    pre = (track.conditioning(track.conditioning_limits(limits, envelope), start_v, desired.dt_s)
           if condition else np.zeros(0))
    st0 = tr.initial(model, voltage_v=start_v)
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
    (``error_um`` itself when the gain does not vary), and ``judged_um`` its RMS over the
    learned region (the steady part, or its imaging region)."""

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

    def as_dict(self) -> dict[str, Any]:
        s = self.outcome.score
        return {"iteration": self.index, "rms_um": s.rms_um, "max_um": s.max_um,
                "rms_between_um": s.rms_between_um, "rms_imaging_um": self.rms_imaging_um,
                "rms_imaging_between_um": self.rms_imaging_between_um,
                "rms_steady_um": self.steady_um,
                "max_slew_V_per_ms": self.outcome.waveform.max_slew_v_per_ms,
                "gain_change": self.gain_change, "judged_um": self.judged_um,
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


def run(stage: experiment.PlayingStage, model: tr.Transducer, desired: track.Desired,
        limits: guard.Limits, out: Path, meta: Mapping[str, object], iterations: int,
        law: ilc.Law = DEFAULT_LAW, truth: tr.Transducer | None = None, seed: str = "inverse",
        condition: bool = True, progress: experiment.Progress | None = None,
        on_iteration: OnIteration | None = None, envelope: Envelope | None = None,
        extrapolate: bool = False) -> Result:
    """Play iteration 0 and up to ``iterations`` learning iterations on ``stage``.

    Every iteration's run file goes to ``out`` (``run_<seed>_iterNN.csv``) as it plays;
    ``on_iteration`` is called with the result so far after each finished iteration (write the
    summary there: an interrupt then loses nothing finished). ``truth`` is the plant the stage
    simulates, for judging between the samples (None: not judged there; the model's own
    simulation would only show the model inverting itself). A refused waveform, the noise floor or a
    diverging error end learning early (``Result.stop`` says which).
    """
    out.mkdir(parents=True, exist_ok=True)
    start_v = stage.voltage()
    t0 = time.perf_counter()
    p, wf = planner(model, desired, limits, start_v, seed, condition, envelope, extrapolate)
    ref = desired.u_um.copy()
    done: list[Iteration] = []
    compute: list[float] = []
    noise, best, stop = float("nan"), 0, "iterations done"
    tuning = ilc.Tuning(0, law.cutoff_hz, np.zeros(0), np.zeros(0, complex), np.zeros(0))

    plant = truth
    region = ilc.imaging_mask(desired, first_period=True) if law.region == "imaging" else None
    sigma = 0.0
    for j in range(iterations + 1):
        if j:
            t0 = time.perf_counter()
            ref = ilc.next_reference(ref, done[-1].learned_um, desired, law, tuning, region)
            try:
                wf = plan_reference(p, desired, ref)
            except (guard.LimitError, track.EnvelopeError) as exc:
                stop = f"refused: {exc}"
                break
            if wf.horizons:  # horizons only grow (where a stretch needs it to pass the guard)
                p = dc.replace(p, horizons=wf.horizons)
        wf = dc.replace(wf, filter=f"{seed}_iter{j:02d}")
        t_plan = time.perf_counter() - t0
        path = out / f"run_{wf.filter}.csv"
        measured = experiment.stream(stage, wf, path, meta, progress)
        between = between_error(wf, desired, plant)  # reporting only: not part of the compute
        t1 = time.perf_counter()
        it = judge(wf, desired, j, measured, path, model.effects, between)
        if j == 0:
            noise = ilc.noise_estimate(it.error_um[ilc.steady_part(desired)])
            tuning = ilc.tune(ref, desired.u_um - it.error_um, desired, law, noise)
        if p.prefix_v.size:  # the gain is measured on the conditioning: s is needed
            # s of this waveform: the learned waveforms sit elsewhere on the hysteresis than
            # iteration 0's (its offset alone moved s's mean by ~7 um per unit gain on a stage)
            s_dir = gain_direction(p, wf)
            it = dc.replace(it, gain_direction_um=s_dir[wf.tracking])
            if j:
                it = dc.replace(it, gain_change=gain_change(it, done[0], s_dir, p.prefix_v,
                                                            model.effects))
        done, sigma = at_mean_gain([*done, it], desired, law)
        it = done[-1]
        compute.append(t_plan + time.perf_counter() - t1)
        best = int(np.argmin([x.judged_um for x in done]))
        result = Result(tuple(done), best, stop, noise, tuning, tuple(compute), sigma)
        if on_iteration is not None:
            on_iteration(result)
        floor = ilc.resolution(noise, sigma, ilc.rms(s_dir[wf.tracking][ilc.steady_part(desired)]),
                               len(done))
        if it.judged_um > law.diverge_factor * max(done[best].judged_um, floor):
            stop = (f"diverging: iteration {j} ({it.judged_um:.4g} um) worse than "
                    f"{law.diverge_factor:g} x the best ({done[best].judged_um:.4g} um)")
            break
        if it.judged_um <= law.floor_factor * floor:
            stop = (f"noise floor: {it.judged_um:.4g} um within {law.floor_factor:g} x noise"
                    + ("" if floor == noise else
                       f" and the mean gain's uncertainty ({floor:.4g} um; gain spread "
                       f"{100 * sigma:.2g} %)"))
            break
    return Result(tuple(done), best, stop, noise, tuning, tuple(compute), sigma)


def gain_change(it: Iteration, first: Iteration, s: FloatArray, prefix_v: FloatArray,
                sensor: fx.Effects) -> float:
    """The run's applied-voltage gain relative to iteration 0's (fraction), from the conditioning
    excursion ``prefix_v`` that starts every iteration: the coefficient along ``s`` (with a free
    offset) of the difference of the two runs' readings (corrected for ``sensor``) from its peak
    on, where the same voltages have wiped out what came before, so that nothing but the gain
    and the noise tells the two runs apart. 0 without conditioning. In units of the model's
    ``s``: a stage that moves ``c`` times as far per volt as the model reads ``c`` times its gain
    change, and ``d s`` is the stage's own movement, which is what learning removes."""
    if not prefix_v.size:
        return 0.0
    chain = fx.compile_chain(sensor, it.outcome.waveform.dt_s)
    part = slice(int(np.argmax(prefix_v)), prefix_v.size)
    w = [fx.sensor_correct(chain, x.outcome.displacement_um)[part] for x in (first, it)]
    return ilc.gain_coefficient(w[1] - w[0], s[part])


def at_mean_gain(done: list[Iteration], desired: track.Desired, law: ilc.Law
                 ) -> tuple[list[Iteration], float]:
    """Every iteration judged at the mean gain of the runs so far, and the gain's spread (1 sigma).

    A run whose gain was ``d_i - mean(d)`` above the mean moved the stage by that times its own
    waveform's ``s`` (``gain_direction_um``) on the trajectory: added back to its error, it
    leaves the error its waveform makes at the mean gain (``learned_um``, what learning learns
    from; ``judged_um`` its RMS over the learned region). All iterations are compared at the
    same gain, so a run's own draw neither makes its waveform look best nor ends learning as a
    divergence.
    """
    d = np.array([x.gain_change for x in done])
    out = []
    for x in done:
        s = x.gain_direction_um if x.gain_direction_um is not None else 0.0
        learned = x.error_um + (x.gain_change - float(d.mean())) * s
        judged = (ilc.imaging_rms(desired, learned) if law.region == "imaging"
                  else ilc.rms(learned[ilc.steady_part(desired)]))
        out.append(dc.replace(x, learned_um=learned, judged_um=judged))
    return out, float(np.std(d, ddof=1)) if d.size > 1 else 0.0


# ----------------------------------------------------------------------------------------------
# outputs
# ----------------------------------------------------------------------------------------------


def summary(result: Result, desired: track.Desired, law: ilc.Law,
            meta: Mapping[str, object]) -> dict[str, Any]:
    """The ``--json`` object: track's per-run figures for iteration 0 and the best iteration, and
    one row per iteration (``iterations``)."""
    first, best = result.iterations[0], result.best_iteration
    outs = {"iteration_0": first.outcome, "learned": best.outcome}
    data = experiment.summary(outs, desired, meta)
    data.update({
        "iterations": [it.as_dict() for it in result.iterations],
        "best_iteration": best.index, "stop": result.stop,
        "noise_estimate_um": result.noise_um, "gain_sigma_estimate": result.gain_sigma,
        "law": {"max_cutoff_Hz": law.cutoff_hz, "cutoff_Hz": result.tuning.cutoff_hz,
                "gain": law.gain, "lead_samples": result.lead,
                "per_harmonic": result.tuning.harmonic,
                "measured_harmonics_Hz": [round(float(f), 3) for f in result.tuning.freqs_hz],
                "floor_factor": law.floor_factor, "diverge_factor": law.diverge_factor, "region": law.region},
        "seconds_per_iteration_compute": float(np.mean(result.compute_s)),
    })
    return data


def waveform_text(it: Iteration, desired: track.Desired, meta: Mapping[str, object]) -> str:
    """``waveform_learned.csv``: the iteration's whole waveform (conditioning and ramps
    included) with the desired trajectory on its tracking part, for ``afmctl play``."""
    from afmctl.files import waveformfile

    wf = it.outcome.waveform
    info = {**meta, "trajectory": desired.label, "iteration": it.index,
            "rms_steady_um": f"{it.steady_um:.6g}"}
    if desired.period_s is not None:
        info["period_s"] = f"{desired.period_s:.9g}"
    return waveformfile.format_text(wf.time_s, wf.voltage_v, wf.desired_um, info)


def write_outputs(result: Result, desired: track.Desired, law: ilc.Law,
                  meta: Mapping[str, object], out: Path) -> dict[str, Any]:
    """``summary.json`` and ``waveform_learned.csv`` (the best iteration), each replaced
    atomically: called after every iteration, so an interrupt keeps what finished (the CLI draws
    ``learn.png`` beside them: :func:`afmctl.plots.learn_figure`)."""
    data = summary(result, desired, law, meta)
    experiment.write_summary(data, out / "summary.json")
    experiment.atomic_write(out / "waveform_learned.csv",
                            waveform_text(result.best_iteration, desired, meta))
    return data
