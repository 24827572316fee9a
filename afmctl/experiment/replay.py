"""A replay of learning (:func:`afmctl.experiment.learn.run` resumed): its iteration 0 plays the
kept voltages, and what its re-learned waveforms carry from them."""

from __future__ import annotations

import dataclasses as dc
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from afmctl import guard
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
