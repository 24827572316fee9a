"""A model's predictions on recorded sweeps, and its error on each (um, against the sweep's noise).

Each sweep is predicted from its start state (``depoled``, ``positive``, ``negative``, or
``previous``: where the sweep before left the hysteresis), with the first voltage applied
quasi-statically and the rod at rest, through the model's effects
(:mod:`afmctl.model.effects`); its error is judged over its window, against its sensor noise
estimated from its own data (:func:`afmctl.fit.noise.sensor_noise_um`). Used by
:mod:`afmctl.fit.identify` and every representation it compares. Pure numerics: no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl.files.sweepfile import Sweep
from afmctl.fit import noise as ns
from afmctl.model import effects as fx
from afmctl.model import hysteresis as hy
from afmctl.model import transducer as td

FloatArray = NDArray[np.float64]
Window = tuple[float, float] | None

__all__ = ["SweepError", "finite_or_none", "start_state", "predict", "predict_set", "judge_set",
           "sweep_error"]


@dataclass(frozen=True)
class SweepError:
    """Error of a model on one sweep (over its judged window), um, against its sensor noise.

    ``noise_um`` is the sweep's sensor noise estimated from its data alone
    (:func:`afmctl.fit.noise.sensor_noise_um`); ``start`` the hysteresis state the sweep was taken
    to start from (one of :data:`afmctl.fit.parametrization.STARTS`) and ``offset_um`` its sensor zero.
    """

    file: str
    rms_um: float
    max_um: float
    range_um: float
    n_samples: int
    noise_um: float = float("nan")
    start: str = "depoled"
    offset_um: float = float("nan")

    @property
    def rms_pct(self) -> float:
        return 100.0 * self.rms_um / self.range_um

    @property
    def max_pct(self) -> float:
        return 100.0 * self.max_um / self.range_um

    @property
    def rms_over_noise(self) -> float:
        return self.rms_um / self.noise_um if self.noise_um > 0 else float("inf")

    def to_dict(self) -> dict[str, Any]:
        return {"file": self.file, "rms_um": self.rms_um, "max_um": self.max_um,
                "range_um": self.range_um, "rms_pct": self.rms_pct, "max_pct": self.max_pct,
                "n_samples": self.n_samples, "noise_um": finite_or_none(self.noise_um),
                "rms_over_noise": finite_or_none(self.rms_over_noise), "start": self.start,
                "offset_um": finite_or_none(self.offset_um)}



def finite_or_none(v: float) -> float | None:
    """JSON has no NaN/inf: non-finite values become null."""
    return float(v) if np.isfinite(v) else None




def start_state(model: td.Transducer, start: str, v0: float,
                 previous: hy.PolarizationState | None) -> td.StageState:
    """Stage state before a sweep's first sample ``v0`` (V): the hysteresis ``start`` (one of
    :data:`afmctl.fit.parametrization.STARTS`), then ``v0`` applied quasi-statically, rod at rest."""
    if start == "previous" and previous is not None:
        p, ps = hy.run(model.polarization, np.array([v0 / model.thickness_um]), previous)
        return td.at_rest(model, ps, float(p[0]), v0 / model.thickness_um)
    return td.initial(model, "depoled" if start == "previous" else start, v0)  # type: ignore[arg-type]


def _reading(model: td.Transducer, voltage_v: FloatArray, dt: float, gain: float, start: str,
             previous: hy.PolarizationState | None) -> tuple[FloatArray, hy.PolarizationState]:
    chain = fx.compile_chain(model.effects, dt)
    v = gain * np.asarray(voltage_v, dtype=float)
    v, _ = fx.lag(chain, v, float(v[0]))
    st = start_state(model, start, float(v[0]), previous)
    u, _, end = td.simulate(td.compile_model(model, dt), v, st)
    return fx.measure(chain, u, *fx.rest(chain, float(u[0])))[0], end.polarization


def predict(model: td.Transducer, voltage_v: FloatArray, dt: float, gain: float = 1.0,
            start: str = "depoled") -> FloatArray:
    """Displacement (um) the model predicts for a voltage history, as the sensor reads it.

    From the hysteresis state ``start`` (default depoled) with the first voltage applied
    quasi-statically, through the model's effects (:mod:`afmctl.model.effects`, none for a model of
    the paper's form) with applied-voltage gain ``gain``.
    """
    return _reading(model, voltage_v, dt, gain, start, None)[0]


def predict_set(model: td.Transducer, sweeps: Sequence[Sweep], starts: Sequence[str],
                offsets_um: Sequence[float] | None = None,
                gains: Sequence[float | FloatArray] | None = None) -> list[FloatArray]:
    """Predicted readings (um) of a set of sweeps recorded in sequence, each from its start
    (``previous``: where the sweep before left the hysteresis), with its own sensor zero
    ``offsets_um`` (default: the model's; it is the rod's zero, so the model's sensor effects see
    it) and applied-voltage gain ``gains`` (default 1; an array: one per sample)."""
    out, prev = [], None
    offs = offsets_um if offsets_um is not None else [model.rod.offset_um] * len(sweeps)
    for s, start, off, g in zip(sweeps, starts, offs, gains or [1.0] * len(sweeps), strict=True):
        zeroed = replace(model, rod=replace(model.rod, offset_um=float(off)))
        u, prev = _reading(zeroed, s.voltage_v, s.dt, g, start, prev)
        out.append(u)
    return out


def _error(name: str, sweep: Sweep, predicted: FloatArray, window_s: Window, start: str,
           offset_um: float) -> SweepError:
    m = sweep.mask(window_s)
    err = (sweep.displacement_um - predicted)[m]
    return SweepError(name, float(np.sqrt(np.mean(err ** 2))), float(np.max(np.abs(err))),
                      float(np.ptp(sweep.displacement_um[m])), int(m.sum()),
                      ns.sensor_noise_um(sweep.displacement_um), start, offset_um)


def judge_set(sweeps: Sequence[Sweep], predicted: Sequence[FloatArray], starts: Sequence[str],
              offsets_um: Sequence[float], window_s: Window = None) -> tuple[SweepError, ...]:
    """Each sweep's error against its prediction (:func:`predict_set`), with the start and the
    sensor zero it was predicted with."""
    return tuple(_error(s.path or s.name, s, u, window_s, start, float(off))
                 for s, u, start, off in zip(sweeps, predicted, starts, offsets_um, strict=True))


def sweep_error(model: td.Transducer, sweep: Sweep, window_s: Window = None,
                start: str = "depoled") -> SweepError:
    """RMS, max and range (um) of ``measured - predicted`` on ``sweep`` (within ``window_s``),
    with the sweep's sensor noise."""
    return _error(sweep.path or sweep.name, sweep, predict(model, sweep.voltage_v, sweep.dt,
                                                           start=start),
                  window_s, start, model.rod.offset_um)
