"""Run planned waveforms on a stage and keep every measured sample.

This module talks to a stage only through the interface of :mod:`drivers` (an object passed in),
so it imports no device library. Each filter's run streams into its own run file as samples arrive
(:mod:`afmctl.files.runfile`); afterwards the runs are scored, and a combined CSV, ``summary.json`` and a
plot like the paper's Figs. 9-11 are written.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from afmctl.errors import SamplesLostError
from afmctl.experiment.twin import Twin
from afmctl.files import runfile
from afmctl.model import effects as fx
from afmctl.model import frame as fr
from afmctl.model import transducer as tr
from afmctl.planning import raster, track

FloatArray = NDArray[np.float64]
Progress = Callable[[str, int, int], None]

#: Rest before every recorded sweep, s: the stage rings after the last sweep's end, so a sweep
#: started at once began on a transient that depended on how soon the host started it (two
#: recordings of one foreign stage differed by up to 1.3x its noise over the fast sweep's first
#: 50 ms, and diagnose's verdict on it changed between recordings). Half a second is 20 decay
#: times of a rod at 300 Hz with damping 0.02 (2 of one at 100 Hz with 0.005).
SETTLE_S = 0.5


class PlayingStage(Protocol):
    """What an experiment needs of a stage (see ``afmctl.drivers.StageBase``)."""

    def play(self, waveform_v: FloatArray, on_block: Callable[..., None] | None = None,
             **kw: Any) -> Any: ...

    def voltage(self) -> float: ...


@dataclass(frozen=True)
class Outcome:
    """One filter's run: measured displacement (NaN where missing) and its score.

    ``corrected_um`` holds the readings corrected for the sensor effects the model knows (what is
    scored), None when it knows none: the readings are then scored as they are."""

    waveform: track.Waveform
    displacement_um: FloatArray
    voltage_v: FloatArray
    score: track.Score
    complete: bool
    run_file: Path
    corrected_um: FloatArray | None = None

    @property
    def scored_um(self) -> FloatArray:
        """What the score is computed from: the corrected readings if any, else the readings."""
        return self.displacement_um if self.corrected_um is None else self.corrected_um

    def as_dict(self) -> dict[str, Any]:
        missing = int(np.isnan(self.displacement_um).sum())
        return {**self.score.as_dict(), "max_slew_V_per_ms": self.waveform.max_slew_v_per_ms,
                "horizon": self.waveform.horizon, "horizons": list(self.waveform.horizons),
                "samples": int(self.waveform.voltage_v.size),
                "missing_samples": missing, "complete": self.complete,
                "run_file": self.run_file.name}


def stream(stage: PlayingStage, wf: track.Waveform | raster.XYWaveform, path: Path,
           meta: Mapping[str, object], progress: Progress | None = None,
           axes: tuple[str, ...] = raster.AXES) -> tuple[FloatArray, FloatArray, bool]:
    """Play ``wf`` on ``stage``, appending each block to the run file ``path`` as it arrives.

    Returns (displacement_um, voltage_v, complete); samples never received are NaN. Any exception
    (including KeyboardInterrupt) leaves the run file readable and marked interrupted, and is
    re-raised (the stage's ``play`` has already put it in its safe state) with the samples so far
    as its ``partial`` attribute (the same triple).

    A row's ``voltage_V`` is the commanded voltage of a sample the stage played. The samples the
    stage handed over unrecorded are held back until a recorded one follows (they were played,
    only their reading was lost) or the run ends: normally, all played; after a failure, the
    trailing ones were never played (or not known to have been) and are written without a
    voltage, status ``not played``.

    A waveform of several axes (``voltage_v`` of shape (N, C), a raster scan's) plays on ``C``
    channels at once and is written with one column per axis (``axes`` names them).
    """
    n = wf.voltage_v.shape[0]
    u = np.full(wf.voltage_v.shape, np.nan)
    v = np.full(wf.voltage_v.shape, np.nan)
    t = wf.time_s
    held = [n]  # first sample of the unrecorded rows not yet written (n: none)

    def write(writer: runfile.RunWriter, start: int, stop: int, played: bool) -> None:
        sl = slice(start, stop)
        volt = wf.voltage_v[sl] if played else np.full(wf.voltage_v[sl].shape, np.nan)
        writer.write(np.arange(start, stop), t[sl], wf.desired_um[sl], volt, u[sl],
                     None if played else "not played")

    with runfile.RunWriter(path, {**meta, "filter": wf.filter, "samples": n},
                           axes if wf.voltage_v.ndim == 2 else ()) as writer:

        def on_block(first: int, volt: FloatArray, disp: FloatArray, valid: Any) -> None:
            sl = slice(first, first + len(disp))
            u[sl] = np.where(valid, disp, np.nan)
            v[sl] = volt
            recorded = np.flatnonzero(np.isfinite(volt).reshape(len(volt), -1).all(axis=1))
            start = min(held[0], first)
            last = first + int(recorded[-1]) + 1 if recorded.size else start
            if last > start:
                write(writer, start, last, True)
            held[0] = last if last < sl.stop else n
            if progress is not None and np.any(valid):  # an interrupt hands the rest as missing
                progress(wf.filter, sl.stop, n)

        try:
            stage.play(wf.voltage_v, on_block)
        except BaseException as exc:
            if held[0] < n:
                write(writer, held[0], n, False)
            exc.partial = (u, v, False)  # type: ignore[attr-defined]
            raise
        if held[0] < n:
            write(writer, held[0], n, True)
    return u, v, bool(np.isfinite(u).all())


def run_all(stage: PlayingStage, plans: Mapping[str, track.Waveform], desired: track.Desired,
            out: Path, meta: Mapping[str, object], between_model: tr.Transducer | None,
            progress: Progress | None = None, sensor: fx.Effects | None = None,
            done: dict[str, Outcome] | None = None) -> dict[str, Outcome]:
    """Run each plan in turn (inverse first) and score it; run files go to ``out`` (created).

    The readings are scored as the stage's position: corrected for the ``sensor`` effects the
    model knows (delay, gauge; none by default). The run files keep the raw readings.
    ``between_model`` is the plant simulated between the samples (None: not judged there).
    Each finished run is put in ``done`` (if given) as it ends; on an interrupt or a failure the
    run in progress is scored on the samples it got, put there too, and the exception re-raised:
    the caller can still report everything played.
    """
    out.mkdir(parents=True, exist_ok=True)
    outcomes = {} if done is None else done
    for name, wf in plans.items():
        path = out / f"run_{name}.csv"
        try:
            u, v, complete = stream(stage, wf, path, meta, progress)
        except BaseException as exc:
            if getattr(exc, "partial", None) is not None:
                outcomes[name] = scored(wf, desired, exc.partial, path, sensor)  # type: ignore[attr-defined]
            raise
        between = None
        if between_model is not None:
            between = track.between_samples(between_model, wf, desired, tr.initial(between_model))
        outcomes[name] = scored(wf, desired, (u, v, complete), path, sensor, between)
    return outcomes


#: How long after planning a run is taken to start, s, until a start has been seen (then: the
#: last start's delay).
LEAD_S = 0.1
#: A stage that has held its output this long since the twin's last recording (s) is read
#: before a run is planned from the twin (:func:`read_held`) ...
IDLE_S = 10.0
#: ... over this long, s.
READ_S = 0.2
#: The run file of that reading, in the run's output folder.
READ_FILE = "run_read.csv"


def read_held(stage: PlayingStage, tw: Twin, path: Path, meta: Mapping[str, object],
              seconds: float = READ_S) -> Twin:
    """The twin after reading the stage at the output it holds (``tw.held_v``) for
    ``seconds`` (:data:`READ_S`; from :data:`afmctl.model.frame.RATE_READ_S` on the reading
    tells its own drift rate too): a run that moves nothing, streamed to ``path`` like any run, whose readings
    against the model are the twin's ``read`` (:meth:`Twin.planning_frame` anchors the next
    run's frame on it). The sweeps' own observations span a minute and the fit after them
    takes minutes: a frame drifting 2 nm/s (an independent tester's stage) had moved 0.55 um
    unseen when the first run was planned, and that run was off by all of it (0.52 um on a
    27.9 Hz triangle, 7.4x better than the linear filter; the next run, planned with its
    observation, 67x).

    Raises
    ------
    ValueError
        If the stage does not hold ``tw.held_v`` (within 1 mV): reading it there would move it.
    """
    now_v = stage.voltage()
    if abs(now_v - tw.held_v) > 1e-3:
        raise ValueError(f"the stage holds {now_v:.4f} V, not the twin's {tw.held_v:.4f} V")
    n = max(2, int(round(seconds / tw.dt_s)))
    wf = track.Waveform("read", tw.dt_s, np.full(n, tw.held_v), np.full(n, np.nan), slice(0, 0))
    u, _, _ = stream(stage, wf, path, meta)
    return _followed(stage, tw, wf.voltage_v, u, read=True) or tw


def _followed(stage: PlayingStage, tw: Twin, voltage_v: FloatArray, readings_um: FloatArray,
              read: bool = False) -> Twin | None:
    """``tw`` after the run the stage just played (:meth:`Twin.after`, from the stage's start
    time and run counter); None if the stage does not say when the run started."""
    started = getattr(stage, "run_started_s", None)
    if started is None:
        return None
    return tw.after(voltage_v, started, getattr(stage, "run_count", None), readings_um, read)


def run_following(stage: PlayingStage, tw: Twin,
                  plan_for: Callable[[str, tr.StageState, fr.Frame], track.Waveform],
                  names: tuple[str, ...], desired: track.Desired, out: Path,
                  meta: Mapping[str, object], between_model: tr.Transducer | None,
                  progress: Progress | None = None, sensor: fx.Effects | None = None,
                  done: dict[str, Outcome] | None = None,
                  read: Callable[[str, Twin], Twin] | None = None) -> Twin | None:
    """:func:`run_all` with each filter planned just before it plays (``plan_for(name, state,
    frame)``) from the twin's state when it is due to start (the stage's clock now, plus the last
    start's delay) and the frame its readings will be in (:meth:`Twin.planning_frame`), and the
    twin carried through it, readings and all: a creeping stage's run starts where the one
    before left it, not at rest, and a drifting one is followed. ``read(name, twin)``, if
    given, reads the stage before each filter is planned (the twin after it). A plan that took
    longer than the last (the first: :data:`LEAD_S` was all it was given) in a frame that moves
    far enough meanwhile (:data:`REPLAN_UM`) is made again for a start that long after it.
    Returns the twin after the last run (None if the stage does not say when its runs start)."""
    took, delay = 0.0, LEAD_S  # the last plan's duration, and a start's delay after it (s)
    for name in names:
        tw = tw if read is None else read(name, tw)
        wf, took = _planned(stage, tw, plan_for, name, took, delay)
        planned = stage.now_s()  # type: ignore[attr-defined]
        outcome = run_all(stage, {name: wf}, desired, out, meta, between_model, progress,
                          sensor, done)[name]
        followed = _followed(stage, tw, wf.voltage_v, outcome.displacement_um)
        if followed is None:
            return None
        delay = max(0.0, stage.run_started_s - planned)  # type: ignore[attr-defined]
        tw = followed
    return tw


#: A plan is made again (:func:`run_following`) when its frame moves this far (um) over the time
#: by which its planning outlasted the time it was given: a 10.8 s trajectory takes seconds to
#: plan, and at 10 nm/s an independent tester's first run started 0.015 um off.
REPLAN_UM = 0.005


def _planned(stage: PlayingStage, tw: Twin,
             plan_for: Callable[[str, tr.StageState, fr.Frame], track.Waveform], name: str,
             took: float, delay: float) -> tuple[track.Waveform, float]:
    """Filter ``name``'s waveform planned for a start ``took + delay`` s from now (the stage's
    clock), from the twin's state and frame then, and how long the plan kept (s); again for a
    start that much later if this one took longer by more than the frame moves
    :data:`REPLAN_UM` in."""
    def planned_for(ahead: float) -> tuple[track.Waveform, float, float]:
        """The plan for a start ``ahead`` s from now, how long it took (s), its frame's rate."""
        begun = stage.now_s()  # type: ignore[attr-defined]
        frame = tw.planning_frame(begun + ahead)
        wf = plan_for(name, tw.at(begun + ahead), frame)
        return wf, stage.now_s() - begun, frame.um_per_s  # type: ignore[attr-defined]

    wf, spent, rate = planned_for(took + delay)
    if abs(rate * (spent - took)) <= REPLAN_UM:
        return wf, spent
    wf, again, _ = planned_for(spent + delay)
    return wf, again


def scored(wf: track.Waveform, desired: track.Desired, measured: tuple[Any, ...], path: Path,
           sensor: fx.Effects | None, between: FloatArray | None = None) -> Outcome:
    """One run's :class:`Outcome` from :func:`stream`'s (displacement, voltage, complete): the
    readings corrected for ``sensor`` (the model's sensor effects; none: scored as they are) and
    scored, between the samples from ``between`` (:func:`afmctl.planning.track.between_samples`)
    if given."""
    u, v, complete = measured
    sensor = fx.sensor_part(sensor or fx.Effects())
    corrected = (None if sensor == fx.Effects()
                 else fx.sensor_correct(fx.compile_chain(sensor, wf.dt_s), u))
    where = u if corrected is None else corrected
    return Outcome(wf, u, v, track.score(wf, desired, where, between), complete, path, corrected)


@dataclass(frozen=True)
class Reading:
    """The sensor at a held output: mean and standard deviation of ``samples`` readings, um, at
    ``output_v`` V."""

    output_v: float
    mean_um: float
    sd_um: float
    samples: int


def move_and_read(stage: PlayingStage, target_v: float, limits: Any, sample_rate_hz: float,
                  hold_s: float = 0.1, channel: int = 0) -> Reading:
    """Bring the output of ``channel`` to ``target_v`` (V) along a raised-cosine ramp at a
    quarter of the usable slew rate (as track's ramps), hold it ``hold_s`` seconds and read its
    sensor over the hold: one waveform, checked by the guard and played as any run (on a stage of
    several channels the others hold their outputs); the output then stays at ``target_v``. With
    ``target_v`` the present output nothing moves: it only reads."""
    from afmctl import guard
    dt = 1.0 / sample_rate_hz
    held_v = stage.voltages() if channel else None  # type: ignore[attr-defined]
    start = stage.voltage() if held_v is None else float(held_v[channel])
    rate = 0.25 * limits.max_rate_v_per_ms * 1e3
    ramp = (track.raised_cosine(start, target_v, track.ramp_samples(target_v - start, rate, dt))
            if target_v != start else np.zeros(0))
    n_hold = max(2, int(round(hold_s * sample_rate_hz)))
    v = np.concatenate([ramp, np.full(n_hold, float(target_v))])
    guard.check(v, dt, limits, start, "the move")
    if held_v is None:
        rec = stage.play(v)
        disp, valid = rec.displacement_um, rec.valid
    else:
        wave = np.tile(held_v, (v.size, 1))
        wave[:, channel] = v
        rec = stage.play(wave)
        disp, valid = rec.displacement_um[:, channel], rec.valid[:, channel]
    held = disp[ramp.size:][valid[ramp.size:]]
    if held.size == 0:
        return Reading(float(target_v), float("nan"), float("nan"), 0)
    return Reading(float(target_v), float(np.mean(held)), float(np.std(held)), int(held.size))


#: Why a stage's error between samples is not judged (``between_samples_from`` of summary.json).
NO_TRUTH_REAL = ("not judged: a real stage (between its samples there is only the model's own "
                 "simulation, which shows the model inverting itself, not the stage)")
NO_TRUTH_FOREIGN = ("not judged: the emulated device's plant is a foreign stage, not an afmctl "
                    "model ([emulator.model] is not what it does)")


def between_truth(profile: Any) -> tuple[tr.Transducer | None, str]:
    """The plant to judge a run between its samples (:func:`afmctl.planning.track.between_samples`)
    on ``profile``'s stage, and what it is: the emulated device's own model (``emulator truth``),
    or None with the reason when there is no such plant (a real stage, a foreign one)."""
    emu = profile.emulator
    if emu is None:
        return None, NO_TRUTH_REAL
    if emu.plant_model is None:
        return None, NO_TRUTH_FOREIGN
    return emu.plant_model, "emulator truth"


def atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def write_waveform_csv(wf: track.Waveform, path: Path,
                       meta: Mapping[str, object] | None = None) -> None:
    """A waveform file (:mod:`afmctl.files.waveformfile`: ``time_s,voltage_V,desired_um``, the
    desired trajectory empty on the conditioning and the ramps) with ``meta`` (profile, model,
    trajectory, period) in its header, for ``--dry-run``; ``afmctl play`` replays it."""
    from afmctl.files import waveformfile
    atomic_write(path, waveformfile.format_text(wf.time_s, wf.voltage_v, wf.desired_um,
                                                dict(meta or {})))


def write_combined_csv(outcomes: Mapping[str, Outcome], desired: track.Desired,
                       path: Path) -> None:
    """The tracking part of every filter side by side on one time axis (s from tracking start):
    the commanded voltage, the readings and, with a model that corrects them for a sensor
    effect, the corrected readings that are scored (``corrected_displacement_um_<filter>``)."""
    cols = {"time_s": np.arange(desired.u_um.size) * desired.dt_s, "desired_um": desired.u_um}
    for name, o in outcomes.items():
        cols[f"voltage_V_{name}"] = o.waveform.voltage_v[o.waveform.tracking]
        cols[f"displacement_um_{name}"] = o.displacement_um[o.waveform.tracking]
        if o.corrected_um is not None:
            cols[f"corrected_displacement_um_{name}"] = o.corrected_um[o.waveform.tracking]
    lines = [",".join(cols)]
    for row in zip(*cols.values(), strict=True):
        lines.append(",".join("" if np.isnan(x) else f"{x:.7g}" for x in row))
    atomic_write(path, "\n".join(lines) + "\n")


def summary(outcomes: Mapping[str, Outcome], desired: track.Desired,
            meta: Mapping[str, object]) -> dict[str, Any]:
    """The ``--json`` object: per-filter errors and the linear/inverse RMS ratios (both over the
    steady part, like the headline figures; ``_between`` from the errors between samples)."""
    out: dict[str, Any] = {**meta, "trajectory": desired.label,
                           "amplitude_um": desired.amplitude_um,
                           "filters": {k: o.as_dict() for k, o in outcomes.items()}}
    if {"inverse", "linear"} <= outcomes.keys():
        lin, inv = outcomes["linear"].score, outcomes["inverse"].score
        out["ratio_linear_over_inverse"] = lin.rms_um / inv.rms_um
        if lin.rms_between_um is not None and inv.rms_between_um:
            out["ratio_linear_over_inverse_between"] = lin.rms_between_um / inv.rms_between_um
    return out


def json_ready(data: Any) -> Any:
    """``data`` with every non-finite float (a run with no samples scored) as None."""
    if isinstance(data, Mapping):
        return {k: json_ready(v) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [json_ready(v) for v in data]
    if isinstance(data, float) and not np.isfinite(data):
        return None
    return data


def write_summary(data: Mapping[str, Any], path: Path) -> None:
    atomic_write(path, json.dumps(json_ready(data), indent=2, allow_nan=False) + "\n")


def incomplete_path(path: Path) -> Path:
    """Where a sweep bound for ``path`` is streamed while it records: ``<stem>.incomplete.csv``
    (one per sweep: a later attempt replaces an earlier interrupted one once it has received
    samples; the whole sweep removes it)."""
    return path.with_name(f"{path.stem}.incomplete.csv")


def record_sweep(stage: PlayingStage, name: str, frequency_hz: float, voltage_v: FloatArray,
                 sample_rate_hz: float, meta: Mapping[str, str] | None = None,
                 progress: Progress | None = None, path: Path | None = None,
                 settle_s: float = SETTLE_S) -> Any:
    """Play one identification waveform, after ``settle_s`` at rest (:data:`SETTLE_S`), and
    return it as a :class:`afmctl.files.sweepfile.Sweep` (``voltage_v`` of shape (N,)) or a
    two-axis :class:`afmctl.files.xysweepfile.XYSweep` (shape (N, 2), a column per channel).

    The sweep's ``voltage_V`` is the commanded voltage (what a filter controls); a sweep that lost
    samples is refused rather than patched. A one-axis sweep's metadata also says when its first
    sample went out on the stage's clock (``started_s``: the holds between the sweeps of a set,
    which a creeping stage creeps through) and its number on the device's run counter
    (``run_count``), where the stage reports them. With ``path``, the samples are also streamed as they
    arrive (flushed per block) into :func:`incomplete_path`, created with the first samples (a
    start that received none leaves no file, and an earlier interrupted attempt's file stays until
    then); when the sweep completes it is written to ``path`` and the incomplete file removed
    (the whole sweep supersedes it), otherwise (interrupt, lost samples, stage failure) it stays
    as a valid sweep file of the samples received in order (every channel's, for two axes),
    ending ``# end: interrupted (...)``.
    """
    from afmctl.files import sweepfile as sweeps
    from afmctl.files import xysweepfile

    kind = xysweepfile if np.ndim(voltage_v) == 2 else sweeps
    meta = {**(meta or {}), "frequency_hz": f"{frequency_hz:g}"}
    n = len(voltage_v)
    got = np.full(np.shape(voltage_v), np.nan)
    streamed = incomplete_path(path) if path is not None else None
    stream = (sweeps.SweepStream(streamed, meta, sample_rate_hz, kind.COLUMNS)
              if streamed is not None else None)
    done = [0]  # samples received in order so far, on every channel (what the file holds)

    def on_block(first: int, volt: FloatArray, disp: FloatArray, valid: Any) -> None:
        got[first:first + len(disp)] = np.where(valid, disp, np.nan)
        old = prefix = done[0]
        while prefix < n and np.isfinite(got[prefix]).all():
            prefix += 1
        done[0] = prefix
        if stream is not None and prefix > old:  # the first samples replace an earlier attempt's
            stream.append(old, voltage_v[old:prefix], got[old:prefix])
        if progress is not None and np.any(valid):
            progress(name, first + len(disp), n)

    try:
        time.sleep(settle_s)
        rec = stage.play(voltage_v, on_block)
        lost = int((~np.asarray(rec.valid)).sum())
        if lost:
            raise SamplesLostError(f"sweep {name}: {lost} samples were not received; record it again")
        started, count = getattr(rec, "started_s", None), getattr(rec, "run_count", None)
        if kind is sweeps and started is not None:  # the creep's hold between sweeps
            meta = {**meta, "started_s": f"{started:.6f}"}
            if count is not None:  # whether the stage ran anything since (the twin)
                meta = {**meta, "run_count": str(count)}
        sweep = kind.from_arrays(voltage_v, rec.displacement_um, sample_rate_hz, meta, name)
        if path is not None:
            kind.write(sweep, path)
    except BaseException as exc:
        if stream is not None:
            stream.close(interrupted=f"{type(exc).__name__}: {exc}".replace("\n", " "))
        raise
    if stream is not None:
        stream.close()
    if streamed is not None and streamed.exists():
        streamed.unlink()  # superseded by the whole sweep (this attempt's or an earlier one's)
    return sweep
