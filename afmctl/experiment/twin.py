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
(:func:`afmctl.planning.track.plan`'s ``state``) inverts the creep the stage is in.

Pure numerics: a frozen record of a model, a state, a time and a held output; no device I/O.
"""

from __future__ import annotations

import dataclasses as dc
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from afmctl.files.sweepfile import Sweep, holds_s
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
    """

    model: tr.Transducer
    dt_s: float
    state: tr.StageState
    ended_s: float
    held_v: float

    def at(self, when_s: float) -> tr.StageState:
        """The state at ``when_s`` (s, the stage's clock), ``held_v`` held since ``ended_s``
        (none if ``when_s`` is earlier)."""
        hold = max(0.0, when_s - self.ended_s)
        return tr.held(tr.compile_model(self.model, self.dt_s), self.held_v, hold, self.state)

    def after(self, voltage_v: ArrayLike, started_s: float) -> Twin:
        """The twin once ``voltage_v`` (V, one value per sample) has played from ``started_s``
        (s, the stage's clock: :attr:`afmctl.drivers.player.Recording.started_s`)."""
        v = np.asarray(voltage_v, dtype=float)
        state = tr.simulate(tr.compile_model(self.model, self.dt_s), v, self.at(started_s))[2]
        return dc.replace(self, state=state, ended_s=started_s + v.size * self.dt_s,
                          held_v=float(v[-1]))


def from_sweeps(model: tr.Transducer, sweeps: Sequence[Sweep]) -> Twin | None:
    """The twin after the identification ``sweeps`` (in the order recorded, the first from the
    model's initial state at rest): None unless the set says how long the stage held between
    every two of them (:func:`afmctl.files.sweepfile.holds_s`, the rule the fit's creep chain
    follows too)."""
    holds = holds_s(sweeps)
    if not sweeps or any(not math.isfinite(h) for h in holds[1:]):
        return None
    first = sweeps[0]
    twin = Twin(model, first.dt, tr.initial(model, voltage_v=float(first.voltage_v[0])),
                first.started_s, float(first.voltage_v[0]))
    for s in sweeps:
        twin = twin.after(s.voltage_v, s.started_s)
    return twin
