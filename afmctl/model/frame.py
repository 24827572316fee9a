"""The readings' frame: where a stage's readings sit from its model, and how that moves.

Identify fits a sensor zero per sweep and the model file keeps one. A stage whose frame drifts
(the frame and mount expanding as they warm: 5-30 nm/s is common for the first hour after
power-on) reads further from that zero the longer it runs, and an open-loop run planned through
the model is off by all of it: on the family plant's drifting Preisach stage, +0.095 um on a
27.9 Hz triangle 40 s after the sweeps, ten times what the run's shape missed. Nothing a model
file holds can know it; the readings can. Each recording the model's twin follows
(:mod:`afmctl.experiment.twin`) is an :class:`Observation`: the mean of readings less the model
over its second half (the first may still carry a start the model got wrong), at its middle.
:func:`estimate` reads the :class:`Frame` a run will be in from the latest ones: their straight
line where it is steady (at least :data:`MIN_POINTS` of them, its slope :data:`SIGNIFICANT`
standard errors from zero over their scatter), else the last one's offset; the line is never
followed further past the last observation than the observations span (a drift does not go on
for ever: beyond, it is held where the line left it). Pure numerics.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: Observations a drift rate is read from: at least this many ...
MIN_POINTS = 4
#: ... the latest this many ...
MAX_POINTS = 12
#: ... and its slope this many standard errors (their scatter about the line) from zero.
SIGNIFICANT = 3.0
#: A reading at the held output this long (s) or longer tells its own drift rate
#: (:func:`read_line`): at 20 nm of noise and 10 kHz, 0.7 nm/s is one standard error.
RATE_READ_S = 1.0


@dataclass(frozen=True)
class Observation:
    """Readings compared with the model over a recording.

    Parameters
    ----------
    at_s : float
        The middle of the readings compared, s (the stage's clock).
    offset_um : float
        Mean of readings less the model over them, um.
    um_per_s : float or None
        A reading's own drift rate over it, um/s (0 where it is not :data:`SIGNIFICANT`
        standard errors from zero; :func:`read_line`); None: not measured (a recording, or a
        reading too short to tell it).
    """

    at_s: float
    offset_um: float
    um_per_s: float | None = None


@dataclass(frozen=True)
class Frame:
    """Where the readings of a run will sit from the model: ``offset_um`` (um) at its first
    sample, moving by ``um_per_s`` (um/s); ``basis`` says how it was found."""

    offset_um: float = 0.0
    um_per_s: float = 0.0
    basis: str = "none"

    def along(self, first: int, n: int, dt_s: float) -> FloatArray:
        """The frame at samples ``first ... first + n - 1`` of the run (um), ``dt_s`` s apart."""
        return self.offset_um + self.um_per_s * dt_s * (first + np.arange(n, dtype=float))

    def as_dict(self) -> dict[str, float | str]:
        return {"offset_um": self.offset_um, "drift_um_per_s": self.um_per_s,
                "basis": self.basis}


def observe(at_s: FloatArray, readings_um: FloatArray, model_um: FloatArray
            ) -> Observation | None:
    """The :class:`Observation` of one recording: readings (um) less the model's (um) at the
    sample times ``at_s`` (s), over the recording's second half, missing samples left out; None
    if none is left."""
    half = slice(at_s.size // 2, None)
    diff, t = (readings_um - model_um)[half], at_s[half]
    ok = np.isfinite(diff)
    if not np.any(ok):
        return None
    return Observation(float(np.mean(t[ok])), float(np.mean(diff[ok])))


def tells_rate(samples: int, dt_s: float) -> bool:
    """Whether a reading of ``samples`` samples ``dt_s`` s apart lasts :data:`RATE_READ_S` (to
    half a sample): long enough to tell its own drift rate (:func:`read_line`)."""
    return (samples + 0.5) * dt_s >= RATE_READ_S


def read_line(at_s: FloatArray, readings_um: FloatArray, model_um: FloatArray
              ) -> Observation | None:
    """A reading at the held output long enough to tell a drift (:func:`tells_rate`) as an
    :class:`Observation` with its own drift rate: the straight line through readings less the
    model (um) at the times ``at_s`` (s), its value at the last sample and its slope, or where
    the slope is not :data:`SIGNIFICANT` standard errors from zero (over the scatter about it)
    the mean and 0; None if fewer than three samples were read."""
    diff = readings_um - model_um
    ok = np.isfinite(diff)
    line = _line(at_s[ok], diff[ok])
    if line is None:
        return None
    rate, last, se = line
    if abs(rate) < SIGNIFICANT * se:  # no rate told: the level is the mean
        return Observation(float(at_s[ok][-1]), float(np.mean(diff[ok])), 0.0)
    return Observation(float(at_s[ok][-1]), last, rate)


def estimate(observations: Sequence[Observation], when_s: float) -> Frame:
    """The frame at ``when_s`` (s, the stage's clock) from ``observations`` (oldest first):
    see the module's text. No observations: the model's own zero."""
    if not observations:
        return Frame()
    t, y = _latest(observations)
    rate = _steady_rate(t, y)
    if rate is None:
        return Frame(float(y[-1]), 0.0, f"offset of the last of {t.size} recordings")
    span = float(t[-1] - t[0])
    t_mean, y_mean = float(np.mean(t)), float(np.mean(y))
    at = min(when_s, float(t[-1]) + span)
    moving = rate if when_s < float(t[-1]) + span else 0.0
    return Frame(y_mean + rate * (at - t_mean), moving,
                 f"drift {1e3 * rate:+.2f} nm/s over {t.size} recordings ({span:.0f} s)")


def anchored(observations: Sequence[Observation], read: Observation, when_s: float) -> Frame:
    """The frame at ``when_s`` (s) from a reading of the stage where it holds its output
    (``read``, taken just before a run) and the ``observations`` before it (oldest first): the
    reading's offset, moved on at the reading's own drift rate where it measured one (a reading
    long enough, :func:`read_line`), else at the steady drift rate of those observations if they
    show one (the module's rule), else held. A short reading sets where the frame is, not how
    fast it moves: minutes after sweeps that span one, its single point would decide the slope
    (on a creeping stage that does not drift, a -0.18 um miss at rest read as -0.84 nm/s). A
    long one measures the rate where the run will be: the line through the recordings lags a
    drift that changes (two independent testers' stages, 8-16 nm/s: read 5.3 and 7.8 nm/s, and
    a 0.279 Hz triangle's 11 s missed 7.5x and 5.7x the noise)."""
    ago = when_s - read.at_s
    basis = f"read at the held output {ago:.1f} s before"
    if read.um_per_s is not None:
        return Frame(read.offset_um + read.um_per_s * ago, read.um_per_s,
                     f"{basis}, drift {1e3 * read.um_per_s:+.2f} nm/s over the reading"
                     if read.um_per_s else f"{basis}, no drift told over the reading")
    t, y = _latest(observations)
    rate = _steady_rate(t, y)
    if rate is None:
        return Frame(read.offset_um, 0.0, basis)
    return Frame(read.offset_um + rate * ago, rate,
                 f"{basis}, drift {1e3 * rate:+.2f} nm/s over {t.size} recordings")


def _latest(observations: Sequence[Observation]) -> tuple[FloatArray, FloatArray]:
    """Times (s) and offsets (um) of the latest :data:`MAX_POINTS` observations."""
    last = observations[-MAX_POINTS:]
    return (np.array([o.at_s for o in last], dtype=float),
            np.array([o.offset_um for o in last], dtype=float))


def _steady_rate(t: FloatArray, y: FloatArray) -> float | None:
    """The slope of ``y`` on ``t`` (um/s) if it is steady (see the module), else None."""
    if t.size < MIN_POINTS:
        return None
    line = _line(t, y)
    if line is None:
        return None
    rate, _, se = line
    return rate if abs(rate) >= SIGNIFICANT * se else None


def _line(t: FloatArray, y: FloatArray) -> tuple[float, float, float] | None:
    """The least-squares line of ``y`` on ``t`` (three points or more): its slope (um/s), its
    value at the last ``t`` (um) and the slope's standard error over the scatter about it; None
    if ``t`` does not vary."""
    tc = t - np.mean(t)
    sxx = float(np.sum(tc**2))
    if sxx <= 0.0 or t.size < 3:
        return None
    rate = float(np.sum(tc * (y - np.mean(y))) / sxx)
    scatter = y - np.mean(y) - rate * tc
    se = float(np.sqrt(np.sum(scatter**2) / (t.size - 2) / sxx))
    return rate, float(np.mean(y) + rate * tc[-1]), se
