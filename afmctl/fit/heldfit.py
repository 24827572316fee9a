"""Fits with a model's hysteresis held: the rod and an effect by variable projection.

An identified model's hysteresis gives each sweep's static displacement ``g`` (um: the rod's
force (16) over its stiffness, :func:`static_um`). Holding it, what acts after the hysteresis
(the rod's dynamics, a second mode, a sensor's latency or gauge error) is fitted to the readings
by variable projection: a few nonlinear parameters ``z`` (the rod's log frequency and damping,
the effect's own) give each sweep's design columns, and the gains and each sweep's sensor zero are
solved for linearly (:class:`Problem`). What acts before it (an amplifier's lag, an applied
voltage's gain) re-runs the hysteresis on the effect's field (:func:`static_um` with the effect
in the model, or per-sweep gains). Used by :mod:`afmctl.fit.modes` (an axis's second mode) and
:mod:`afmctl.fit.heldbase` (diagnose's causes on identify's model). Pure numerics: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from scipy import optimize

from afmctl.files.sweepfile import Sweep
from afmctl.fit import identify as idf
from afmctl.model import effects as fx
from afmctl.model import transducer as td
from afmctl.model.rod import UM_PER_M

FloatArray = NDArray[np.float64]
#: ``design(z)``: per sweep, its design columns (N x k, every sample) and the readings they
#: are fitted to (N, um; the recorded readings, or a transform of them the effect asks for).
#: Gains of a physical second mode (:class:`afmctl.model.effects.SecondMode`): ``gain`` within
#: these (a mode that carries as much of the stroke as the rod is not a second mode of it).
GAIN_BOUNDS = (-0.5, 1.0)
Design = Callable[[FloatArray], list[tuple[FloatArray, FloatArray]]]


def static_um(model: td.Transducer, sweeps: Sequence[Sweep], starts: Sequence[str],
              gains: Sequence[float | FloatArray] | None = None) -> list[FloatArray]:
    """Per sweep (recorded in sequence, each from its start): the rod's static displacement
    ``f / k`` (um) for the force (16) the model's hysteresis (and creep) gives, with the model's
    amplifier between the command and the stage and applied-voltage ``gains`` (default 1), as
    :func:`afmctl.fit.identify.predict_set` runs them."""
    out, prev = [], None
    for s, start, gain in zip(sweeps, starts, gains or [1.0] * len(sweeps), strict=True):
        chain = fx.compile_chain(model.effects, s.dt)
        v = gain * np.asarray(s.voltage_v, dtype=float)
        v, _ = fx.lag(chain, v, float(v[0]))
        st = idf.start_state(model, start, float(v[0]), prev)
        f, _, end = td.driving_force(td.compile_model(model, s.dt), v, st)
        out.append(f / model.rod.k * UM_PER_M)
        prev = end.polarization
    return out


def mode_parts(u: FloatArray, f_hz: float, zeta: float, dt: float) -> tuple[FloatArray,
                                                                             FloatArray]:
    """``M1[u]`` and ``M2[u]``: a second mode's displacement per unit gain and per unit rate gain
    (:class:`afmctl.model.effects.SecondMode`)."""
    parts = []
    for gain, rate in ((1.0, 0.0), (0.0, 1.0)):
        chain = fx.compile_chain(fx.Effects(second_mode=fx.SecondMode(f_hz, zeta, gain, rate)), dt)
        parts.append(fx.position(chain, u) - u)
    return parts[0], parts[1]


def with_rod(model: td.Transducer, natural_hz: float, damping_ratio: float, scale: float,
             offset_um: float) -> td.Transducer:
    """``model`` with its rod at a new resonance (Hz) and damping ratio (its stiffness and
    damping set for them, its mass kept: a convention of the fit), the force scaled so that the
    static displacement is ``scale`` times the old, and the sensor zero ``offset_um`` (um)."""
    r = model.rod
    k = r.m * (2 * math.pi * natural_hz) ** 2
    f = scale * k / r.k
    return replace(model, rod=replace(r, k=k, c=2 * damping_ratio * math.sqrt(k * r.m),
                                      a1=f * r.a1, a2=f * r.a2, a3=f * r.a3,
                                      offset_um=offset_um))


class Problem:
    """Variable projection on the rows ``masks`` selects (each sweep weighs the same, in units
    of its ``noise``, um): the gains of ``design``'s columns and one sensor zero per sweep are
    solved for linearly at every ``z``."""

    def __init__(self, design: Design, masks: Sequence[NDArray[np.bool_]],
                 noise: FloatArray) -> None:
        self.design, self.masks = design, list(masks)
        n = np.array([m.sum() for m in self.masks], dtype=float)
        self.noise = np.asarray(noise, dtype=float)
        self.w = np.sqrt(n.mean() / n) / self.noise

    def solve(self, z: FloatArray) -> tuple[FloatArray, FloatArray, list[FloatArray]]:
        """The linear parameters (the columns' gains, then the sensor zeros), the weighted
        residual and each sweep's unweighted residual on its rows."""
        parts = [(c[m], y[m]) for (c, y), m in zip(self.design(z), self.masks, strict=True)]
        n_s, k = len(parts), parts[0][0].shape[1]
        rows = []
        for s, (c, _) in enumerate(parts):
            ind = np.zeros((c.shape[0], n_s))
            ind[:, s] = 1.0
            rows.append(self.w[s] * np.hstack((c, ind)))
        a = np.vstack(rows)
        b = np.concatenate([w * y for w, (_, y) in zip(self.w, parts, strict=True)])
        beta = np.linalg.lstsq(a, b, rcond=None)[0]
        per = [y - c @ beta[:k] - beta[k + s] for s, (c, y) in enumerate(parts)]
        return beta, b - a @ beta, per

    def cost(self, z: FloatArray) -> float:
        """Sum of squares of the weighted residual at ``z``."""
        return float(np.sum(self.solve(z)[1] ** 2))

    def polish(self, z0: Sequence[FloatArray], lo: FloatArray, hi: FloatArray,
               max_nfev: int) -> optimize.OptimizeResult:
        """The best of least-squares runs from each of ``z0`` within the bounds."""
        runs = [optimize.least_squares(lambda z: self.solve(z)[1], np.clip(z, lo, hi),
                                       bounds=(lo, hi), diff_step=1e-5, max_nfev=max_nfev)
                for z in z0]
        return min(runs, key=lambda r: float(r.cost))

    def ratios(self, per: Sequence[FloatArray]) -> tuple[float, ...]:
        """Each sweep's RMS residual over its noise."""
        return tuple(float(np.sqrt(np.mean(r ** 2)) / n) for r, n in zip(per, self.noise,
                                                                          strict=True))
