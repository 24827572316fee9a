"""A two-axis plant for the raster scan's tests, in pure simulation (no wire): each axis an
afmctl transducer of parameters *other* than the model the scan plans with, the sensors reading
each axis's displacement plus the motion the other causes (static gain and a shared mode), plus
Gaussian noise. It plays waveforms of shape (N, 2) block by block as a stage does, and stops on
a KeyboardInterrupt raised from ``on_block`` (the outputs then go to 0 V, as a stage's safe
state)."""

from __future__ import annotations

import dataclasses as dc
from collections.abc import Callable
from typing import Any

import numpy as np

from afmctl.model import coupling as cp
from afmctl.model import transducer as tr
from afmctl.model.transducer import Transducer

BLOCK = 4096


def detuned(model: Transducer, eta: float, a1: float, k: float) -> Transducer:
    """``model`` with its interaction constant, its rod's a1 and its stiffness scaled: another
    stage of the same family (the plant a model planned on the nominal one meets)."""
    pol = dc.replace(model.polarization, eta=model.polarization.eta * eta)
    rod = dc.replace(model.rod, a1=model.rod.a1 * a1, k=model.rod.k * k)
    return dc.replace(model, polarization=pol, rod=rod)


class XYPlant:
    """Plays (N, 2) voltages on two simulated axes coupled both ways."""

    channels = 2

    def __init__(self, plants: dict[str, Transducer], coupling: dict[str, cp.Coupling],
                 dt_s: float, noise_um: float = 0.02, seed: int = 0) -> None:
        self.plants, self.coupling, self.dt_s, self.noise_um = plants, coupling, dt_s, noise_um
        self.rng = np.random.default_rng(seed)
        self.compiled = {n: tr.compile_model(m, dt_s) for n, m in plants.items()}
        self.states = {n: tr.initial(m, voltage_v=0.0) for n, m in plants.items()}
        self.v = np.zeros(2)
        self.safe = False

    def voltages(self) -> np.ndarray:
        return self.v.copy()

    def play(self, v: np.ndarray, on_block: Callable[..., None] | None = None) -> Any:
        v = np.asarray(v, dtype=float)
        u = {}
        for k, n in enumerate(("x", "y")):
            u[n], _, self.states[n] = tr.simulate(self.compiled[n], v[:, k], self.states[n])
        x = u["x"] + cp.caused(self.coupling["xy"], u["y"], self.dt_s)
        y = u["y"] + cp.caused(self.coupling["yx"], u["x"], self.dt_s)
        read = np.column_stack([x, y]) + self.noise_um * self.rng.standard_normal(v.shape)
        ok = np.ones(v.shape, dtype=bool)
        try:
            for first in range(0, v.shape[0], BLOCK):
                sl = slice(first, first + BLOCK)
                if on_block is not None:
                    on_block(first, v[sl], read[sl], ok[sl])
                self.v = v[min(sl.stop, v.shape[0]) - 1].copy()
        except BaseException:
            self.v, self.safe = np.zeros(2), True
            raise
        return read
