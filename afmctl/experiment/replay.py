"""A replay of learning. Resumed (:func:`afmctl.experiment.learn.run`), its iteration 0 plays the
kept voltages and its re-learned waveforms carry them (:class:`Carried`). Played once
(``afmctl play --model``, :func:`moved_replay`), the kept conditioning tells how far the stage
has moved since (creep, drift) and the rest of the waveform is moved for it."""

from __future__ import annotations

import dataclasses as dc
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from afmctl import guard
from afmctl.errors import EnvelopeError
from afmctl.experiment import runner
from afmctl.planning import track

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Carried:
    """What a replay's re-learned waveforms carry (:func:`replayed`): the kept voltages less
    the kept reference's plan now, V (``shift_v``, whose tracking part is ``tracking``)."""

    shift_v: FloatArray
    tracking: slice
    n_prefix: int

    def added(self, wf: track.Waveform) -> FloatArray:
        """``wf``'s voltages with the shift added: as it is if ``wf`` has the kept plan's shape;
        else part by part, on the conditioning (the first ``n_prefix`` samples) and the tracking
        part, the ramps between (which follow the reference's ends, and so can be of other
        lengths) getting a straight line from one part's shift to the next, and the ramp out
        one to the shift of the last sample."""
        v = wf.voltage_v.copy()
        t, n, d = wf.tracking, self.n_prefix, self.shift_v
        if v.size == d.size and t == self.tracking:
            return v + d
        v[:n] += d[:n]
        v[t] += d[self.tracking]
        first, last = d[self.tracking.start], d[self.tracking.stop - 1]
        v[n:t.start] += np.linspace(d[n - 1] if n else first, first, t.start - n + 2)[1:-1]
        v[t.stop:] += np.linspace(last, d[-1], v.size - t.stop + 1)[1:]
        return v


def replayed(wf: track.Waveform, kept_v: FloatArray | None, limits: guard.Limits, start_v: float,
             n_prefix: int) -> tuple[track.Waveform, Carried | None]:
    """A replay's iteration 0: the kept voltages ``kept_v`` (V), and what every re-learned
    waveform carries: their difference from ``wf`` (the kept reference planned now, its
    conditioning the first ``n_prefix`` samples). The kept run was planned from the state learning started in
    (the model's twin, :mod:`afmctl.experiment.twin`), a replay from rest, and the same
    reference then gives other voltages (an independent tester's creeping stage: -0.292 um
    replayed as learned, +0.354 um re-planned). Kept voltages of another shape than ``wf`` (a
    stage that now starts at another voltage) are played, and nothing is carried; without kept
    voltages, ``wf`` as planned.

    Raises
    ------
    guard.LimitError
        If the kept voltages leave the limits from the stage's present output ``start_v``.
    """
    if kept_v is None:
        return wf, None
    kept = np.asarray(kept_v, dtype=float)
    guard.check(kept, wf.dt_s, limits, start_v, "kept waveform")
    played = dc.replace(wf, voltage_v=kept.copy())
    if kept.size != wf.voltage_v.size:
        return played, None
    return played, Carried(kept - wf.voltage_v, wf.tracking, n_prefix)


#: The header key of a learned waveform (``waveform_learned.csv``): the kept run's slow offset less
#: the one its reference was planned for (um), a miss the replay takes out too.
OFFSET_MISS_KEY = "offset_miss_um"
#: The move is read over the conditioning's last this many seconds, just before the trajectory
#: (s). After a minute's hold a creeping stage recovers during the conditioning itself: on the
#: family's creeping PI stage the readings sat -1.05 um from the kept run's on the rise, -0.89
#: on the fall, -0.77 over its last 0.1 s, and the trajectory needed -0.78.
MOVE_WINDOW_S = 0.1


#: The header key of a learned waveform: learning's estimate of the readings' noise (um).
NOISE_KEY = "noise_um"
#: The conditioning tells how far the stage has moved only where its readings differ from the
#: learned run's by an offset and a slow trend (creep recovering) within this many times the
#: noise of two runs (RMS of the rest, from the conditioning's peak on; learning's own rule,
#: :data:`afmctl.experiment.learn.OFFSET_AGREE`): a stage that does not wipe out its past
#: (Bouc-Wen) reads its history there too. On one swung to a rail between learning and the
#: replay, a move read so made the replay 6.9x the noise where as learned it was 1.8x.
AGREE = 5.0
#: The moves (um) the model's plans are made at before a replay, both ways: a move between two is
#: interpolated, one beyond them extrapolated from the last two. Through the hysteresis a move in
#: position is not one in voltage, nor linear in it: scaled from 1 um alone, a 3.4 um move (a
#: drifting stage 180 s later) missed 2.6x the noise, a 5.6 um one 7.4x; from these, 0.57x and
#: 1.3x (2.2x without the plans at 8 um).
MOVES_UM = (1.0, 4.0, 8.0)


@dataclass(frozen=True)
class Moved:
    """A replay played by :func:`moved_replay`: ``waveform`` the part scored as played (the
    part after the conditioning; the whole waveform where it was played as learned in one run),
    ``whole`` the whole waveform as played (conditioning included), ``measured`` ``waveform``'s
    run's (readings um, voltages V, complete), ``move_um`` how far the stage had moved from the
    kept run (None if not read), ``moved`` whether the voltages were moved for it, ``why`` if
    not."""

    waveform: track.Waveform
    whole: track.Waveform
    measured: tuple[FloatArray, FloatArray, bool]
    move_um: float | None
    moved: bool
    why: str = ""


@dataclass(frozen=True)
class Shifts:
    """The voltages (V, rows of the kept waveform's shape) that move the model's position by
    ``-moves_um`` (um, increasing, 0 among them: nothing added)."""

    moves_um: FloatArray
    added_v: FloatArray

    def at(self, move_um: float) -> FloatArray:
        """The voltages for ``move_um`` (um): linear between the two moves about it, and beyond
        the last, along the last two."""
        m = self.moves_um
        hi = int(np.clip(np.searchsorted(m, move_um), 1, m.size - 1))
        w = (move_um - m[hi - 1]) / (m[hi] - m[hi - 1])
        return (1.0 - w) * self.added_v[hi - 1] + w * self.added_v[hi]


def shifts(kept: track.Waveform, reference_um: FloatArray,
           plan: Callable[[FloatArray], track.Waveform], n_prefix: int) -> Shifts | None:
    """The model's plans of the kept reference (um, its tracking part) moved by each of
    :data:`MOVES_UM` both ways, less its plan unmoved, all by ``plan`` (from one state;
    conditioning the first ``n_prefix`` samples), part by part onto ``kept``
    (:meth:`Carried.added`): the voltages each move takes. A move whose plan differs from the
    unmoved one in shape or horizons, or that the model cannot plan (out of reach, the limits,
    its envelope), is left out, beyond the first (None if that one is: the ramp into or out of
    the trajectory changed length; the first's planning errors are raised)."""
    a = plan(reference_um)
    moves, rows = [0.0], [np.zeros(kept.voltage_v.size)]
    for size in MOVES_UM:
        for m in (-size, size):
            try:
                b = plan(reference_um - m)
            except (guard.LimitError, EnvelopeError):
                if size == MOVES_UM[0]:
                    raise
                continue
            if (b.voltage_v.size != a.voltage_v.size or b.tracking != a.tracking
                    or b.horizons != a.horizons):
                if size == MOVES_UM[0]:
                    return None
                continue
            moves.append(m)
            rows.append(Carried(b.voltage_v - a.voltage_v, a.tracking, n_prefix).added(kept)
                        - kept.voltage_v)
    order = np.argsort(moves)
    return Shifts(np.asarray(moves)[order], np.asarray(rows)[order])


def conditioning_move(readings_um: FloatArray, kept_um: FloatArray, n_prefix: int,
                      dt_s: float) -> float:
    """How far the stage reads from the kept run (um): the mean difference of the two runs'
    readings over the conditioning's last :data:`MOVE_WINDOW_S` (the same voltages, the same
    wiped-out state; NaN if no sample of either is there)."""
    part = slice(max(0, n_prefix - int(round(MOVE_WINDOW_S / dt_s))), n_prefix)
    d = readings_um[part] - kept_um[part]
    return float(np.mean(d[np.isfinite(d)])) if np.isfinite(d).any() else float("nan")


def conditioning_misfit(readings_um: FloatArray, kept_um: FloatArray, prefix_v: FloatArray,
                        dt_s: float) -> float:
    """RMS (um) of the two runs' difference of readings over the conditioning ``prefix_v``, from
    its peak on, left by a straight line in time (an offset and creep's slow trend); NaN with
    fewer than three samples read in both."""
    part = slice(int(np.argmax(prefix_v)), prefix_v.size)
    d = readings_um[part] - kept_um[part]
    t = dt_s * np.arange(d.size)
    ok = np.isfinite(d)
    if ok.sum() < 3:
        return float("nan")
    fit = np.polyfit(t[ok], d[ok], 1)
    return float(np.sqrt(np.mean((d[ok] - np.polyval(fit, t[ok])) ** 2)))


def _not_moved(kept: track.Waveform, prefix_v: FloatArray) -> str:
    """Why ``kept`` is played as learned in one run ("" if it is not)."""
    n = prefix_v.size
    if n == 0 or kept.voltage_v.size <= n:
        return "the waveform has no conditioning"
    if not np.allclose(kept.voltage_v[:n], prefix_v, rtol=0.0, atol=1e-5):
        return "its conditioning is not the one planned now (another start voltage or range)"
    return ""


def moved_replay(stage: runner.PlayingStage, kept: track.Waveform, kept_um: FloatArray,
                 reference_um: FloatArray, miss_um: float,
                 plan: Callable[[FloatArray], track.Waveform], prefix_v: FloatArray,
                 limits: guard.Limits, paths: tuple[Path, Path], meta: Mapping[str, object],
                 progress: runner.Progress | None = None, noise_um: float = float("nan")
                 ) -> Moved:
    """Play the learned waveform ``kept`` (its run's readings ``kept_um``, um; its reference, um)
    moved for how far the stage has moved since: its conditioning (``prefix_v``, V: the one
    planned now) to ``paths[0]``; the move read on it (:func:`conditioning_move`) plus the kept
    run's offset miss ``miss_um`` (um); then the rest, to ``paths[1]``, with the move's voltages
    added (:func:`shifts`, planned before the first run so that the second follows it at once;
    as learned where they would leave the limits, or where the conditioning's readings differ
    from the learned run's by more than an offset and a trend, :data:`AGREE` times the noise of
    two runs, ``noise_um`` um: :func:`conditioning_misfit`). Played whole, as learned, to
    ``paths[1]``: a waveform whose first samples are not ``prefix_v`` (to 10 uV: a waveform file
    keeps microvolts)."""
    n = prefix_v.size
    why = _not_moved(kept, prefix_v)
    if why:
        measured = runner.stream(stage, kept, paths[1], meta, progress)
        return Moved(kept, kept, measured, None, False, why)
    try:
        found = shifts(kept, reference_um, plan, n)
        why = "" if found is not None else "the move changes the ramp into or out of the trajectory"
    except (guard.LimitError, EnvelopeError) as exc:
        found, why = None, f"the model cannot plan the move: {exc}"
    head = track.Waveform(kept.filter, kept.dt_s, kept.voltage_v[:n], kept.desired_um[:n],
                          slice(0, 0))
    read = runner.stream(stage, head, paths[0], meta)[0]
    move = conditioning_move(read, kept_um, n, kept.dt_s) + miss_um
    misfit = conditioning_misfit(read, kept_um, prefix_v, kept.dt_s)
    v = kept.voltage_v
    if not np.isfinite(move):
        why = "no readings over the conditioning's last part"
    elif misfit > AGREE * math.sqrt(2.0) * noise_um:
        why = (f"the conditioning read {misfit:.4f} um RMS apart from the learned run's beyond an "
               f"offset and a trend: the stage's past differs (it does not wipe out), and the "
               f"move is not told")
    elif found is not None:
        try:
            v = kept.voltage_v + found.at(move)
            guard.check(v[n:], kept.dt_s, limits, stage.voltage(), "moved replay")
        except guard.LimitError as exc:
            v, why = kept.voltage_v, str(exc)
    t = kept.tracking
    rest = track.Waveform(kept.filter, kept.dt_s, v[n:], kept.desired_um[n:],
                          slice(t.start - n, t.stop - n), kept.horizons)
    measured = runner.stream(stage, rest, paths[1], meta, progress)
    return Moved(rest, dc.replace(kept, voltage_v=v), measured,
                 move if np.isfinite(move) else None, v is not kept.voltage_v, why)


def header_float(meta: Mapping[str, str], key: str, default: float) -> float:
    """A learned waveform's header number ``key`` (:data:`OFFSET_MISS_KEY`, :data:`NOISE_KEY`),
    ``default`` where it does not say (a waveform learned before the key)."""
    try:
        return float(meta.get(key, default))
    except ValueError:
        return default
