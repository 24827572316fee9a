"""The model's running copy of a stage: its state after everything played on it, and the holds.

A creeping stage is never at rest: its slow creep elements (seconds to 1000 s) still carry every
sweep and run before, and between two runs it keeps creeping while it holds its output. A model
started at rest before each run is then wrong by where those elements are (on the family
plant's creeping Prandtl-Ishlinskii stage, +0.64 um on a 27.9 Hz triangle, 20x the error the
run's shape had). A :class:`Twin` follows the stage instead: the identification sweeps in the
order they were recorded, with the holds between them (each sweep's ``started_s``, the stage's
clock at its first sample, :meth:`afmctl.drivers.stage.StageBase.now_s`), then every waveform
played (:meth:`Twin.after`, from the recording's ``started_s``); :meth:`Twin.at` is its state
at a later time, the output held since (:func:`afmctl.model.transducer.held`). Planning from it
(:func:`afmctl.planning.track.plan`'s ``state``) inverts the creep the stage is in. Where the
readings are given (the sweeps', each run's), the twin also compares them with itself
(:mod:`afmctl.model.frame`): :meth:`Twin.frame` is where a run's readings will sit from the model,
a drifting frame followed (``plan``'s ``frame``).

A twin is saved beside its model file (:mod:`afmctl.files.twinfile`) by identify and by track
after its runs, and loaded by track only while it still follows the stage (:func:`load`). The
twin itself is pure numerics: a frozen record of a model, a state, a time and a held output; no
device I/O.
"""

from __future__ import annotations

import dataclasses as dc
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from afmctl.files import twinfile
from afmctl.files.sweepfile import Sweep, holds_s
from afmctl.model import effects as fx
from afmctl.model import frame as fr
from afmctl.model import hysteresis as hy
from afmctl.model import transducer as tr


@dataclass(frozen=True)
class Twin:
    """The model's state after what a stage last played.

    Parameters
    ----------
    model : transducer.Transducer
    dt_s : float
        Sample period, s.
    state : transducer.StageState
        The model's state after the last sample played.
    ended_s : float
        When that sample ended, s, on the stage's clock.
    held_v : float
        The output the stage has held since, V.
    run_count : int or None
        The device's run counter after that run, if the stage reported it.
    observations : tuple of frame.Observation
        The readings of the recordings followed against the model (oldest first), where given.
    read : frame.Observation or None
        The last reading of the stage where it held its output (:meth:`after` with
        ``read=True``), kept apart from ``observations`` (it anchors the next run's frame, not a
        drift's slope) and not saved.
    """

    model: tr.Transducer
    dt_s: float
    state: tr.StageState
    ended_s: float
    held_v: float
    run_count: int | None = None
    observations: tuple[fr.Observation, ...] = ()
    read: fr.Observation | None = None

    def at(self, when_s: float) -> tr.StageState:
        """The state at ``when_s`` (s, the stage's clock), ``held_v`` held since ``ended_s``
        (none if ``when_s`` is earlier)."""
        hold = max(0.0, when_s - self.ended_s)
        return tr.held(tr.compile_model(self.model, self.dt_s), self.held_v, hold, self.state)

    def after(self, voltage_v: ArrayLike, started_s: float, run_count: int | None = None,
              readings_um: ArrayLike | None = None, read: bool = False) -> Twin:
        """The twin once ``voltage_v`` (V, one value per sample) has played from ``started_s``
        (s, the stage's clock: :attr:`afmctl.drivers.player.Recording.started_s`) as run
        ``run_count`` of the device's counter; ``readings_um`` (um, NaN where missing), the
        sensor's over it, are compared with the model (:func:`afmctl.model.frame.observe`): one
        more of ``observations``, or with ``read`` (a reading at the held output) the new
        ``read``."""
        v = np.asarray(voltage_v, dtype=float)
        u, _, state = tr.simulate(tr.compile_model(self.model, self.dt_s), v, self.at(started_s))
        seen, last = self.observations, self.read
        if readings_um is not None:
            ob = self._observe(u, np.asarray(readings_um, dtype=float), started_s, read)
            if ob is not None and read:
                last = ob
            elif ob is not None:
                seen = (*seen, ob)
        return dc.replace(self, state=state, ended_s=started_s + v.size * self.dt_s,
                          held_v=float(v[-1]), run_count=run_count, observations=seen,
                          read=last)

    def frame(self, when_s: float) -> fr.Frame:
        """Where readings taken from ``when_s`` on (s, the stage's clock) will sit from the
        model (:func:`afmctl.model.frame.estimate`)."""
        return fr.estimate(self.observations, when_s)

    def planning_frame(self, when_s: float) -> fr.Frame:
        """The frame a run starting at ``when_s`` is planned in: from ``read`` if it is the
        latest (:func:`afmctl.model.frame.anchored`), else :meth:`frame` where it drifts
        steadily, else the model's own zero (a last recording's offset alone is not followed:
        on a stage that does not drift it is what the model missed on another trajectory)."""
        if self.read is not None and (not self.observations
                                      or self.read.at_s >= self.observations[-1].at_s):
            return fr.anchored(self.observations, self.read, when_s)
        seen = self.frame(when_s)
        return seen if seen.um_per_s != 0.0 else fr.Frame()

    def _observe(self, rod_um: np.ndarray, readings_um: np.ndarray, started_s: float,
                 read: bool = False) -> fr.Observation | None:
        """Readings against the model's own (its rod and second mode; the readings corrected
        for its sensor effects); a reading at the held output (``read``) long enough with its
        own drift rate (:func:`afmctl.model.frame.tells_rate`, :func:`~afmctl.model.frame.read_line`)."""
        n = min(rod_um.size, readings_um.size)
        chain = fx.compile_chain(self.model.effects, self.dt_s)
        where = fx.sensor_correct(chain, readings_um[:n])
        how = fr.read_line if read and fr.tells_rate(n, self.dt_s) else fr.observe
        return how(started_s + self.dt_s * np.arange(n), where, fx.position(chain, rod_um[:n]))


def from_sweeps(model: tr.Transducer, sweeps: Sequence[Sweep]) -> Twin | None:
    """The twin after the identification ``sweeps`` (in the order recorded, the first from the
    model's initial state at rest): None unless the set says how long the stage held between
    every two of them (:func:`afmctl.files.sweepfile.holds_s`, the rule the fit's creep chain
    follows too)."""
    holds = holds_s(sweeps)
    if (not sweeps or any(not math.isfinite(h) for h in holds[1:])
            or not math.isfinite(sweeps[0].started_s)):  # one sweep: its own time says
        return None
    first = sweeps[0]
    twin = Twin(model, first.dt, tr.initial(model, voltage_v=float(first.voltage_v[0])),
                first.started_s, float(first.voltage_v[0]))
    for s in sweeps:
        count = s.meta.get("run_count")
        twin = twin.after(s.voltage_v, s.started_s, None if count is None else int(count),
                          s.displacement_um)
    return twin


def keep_beside(model: tr.Transducer, sweeps: Sequence[Sweep], model_path: str | Path
                ) -> Path | None:
    """:func:`from_sweeps`, saved beside the model file it was identified as (:func:`save`);
    None (nothing written) where the sweeps do not say their holds."""
    tw = from_sweeps(model, sweeps)
    return None if tw is None else save(tw, model_path)


def save(tw: Twin, model_path: str | Path) -> Path:
    """Write ``tw`` beside the model file it follows (:func:`afmctl.files.twinfile.path_for`)."""
    st = tw.state
    rec = twinfile.Record(twinfile.digest(model_path), twinfile.boot_id(), tw.run_count,
                          tw.ended_s, tw.held_v, tw.dt_s, st.polarization.kind,
                          st.polarization.values, np.asarray(st.rod, float),
                          np.asarray(st.creep, float),
                          np.array([(o.at_s, o.offset_um) for o in tw.observations],
                                   float).reshape(-1, 2))
    path = twinfile.path_for(model_path)
    twinfile.write(rec, path)
    return path


def load(model: tr.Transducer, model_path: str | Path, output_v: float,
         run_count: int | None) -> tuple[Twin | None, str]:
    """The twin saved beside ``model_path``, if it still follows the stage, and why not if not:
    it must be of this model file, this boot of the host, the stage must still hold the output it
    left (``output_v``, V, within 1 mV) and its run counter (``run_count``, the device's now)
    must say nothing ran since; otherwise (None, the reason) and the model starts at rest."""
    path = twinfile.path_for(model_path)
    if not path.is_file():
        return None, "no twin file"
    rec = twinfile.read(path)
    checks = ((rec.model_sha256 == twinfile.digest(model_path), "it is of another model file"),
              (rec.boot_id == twinfile.boot_id(), "the host was restarted since"),
              (abs(rec.held_v - output_v) <= 1e-3,
               f"the stage holds {output_v:.3f} V, not the {rec.held_v:.3f} V it left"),
              (rec.run_count is not None and rec.run_count == run_count,
               f"the stage ran something since (run {run_count}, the twin saw {rec.run_count})"))
    for ok, why in checks:
        if not ok:
            return None, f"{path.name} not used: {why}"
    state = tr.StageState(hy.PolarizationState(rec.kind, rec.values), rec.rod, rec.creep,
                          tr.rest_lag(model, rec.held_v / model.thickness_um))
    seen = tuple(fr.Observation(float(t), float(o)) for t, o in rec.observations)
    return (Twin(model, rec.dt_s, state, rec.ended_s, rec.held_v, rec.run_count, seen),
            f"from {path}")
