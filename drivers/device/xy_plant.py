"""The emulated two-axis (x/y) stage's plant: one plant per channel, coupled both ways.

Each channel is afmctl's own emulated plant (:class:`~afmctl.drivers.device.plant.Physics`, or the
foreign or out-of-family one its axis profile names: :func:`~afmctl.drivers.device.emulator.plant`)
with its axis's own parameters. The coupling (:class:`afmctl.model.coupling.Coupling`, the profile's
``[emulator.coupling.yx]`` and ``.xy``) adds to the target channel's reading the motion the source
channel's displacement causes: a static gain plus one shared mode that vanishes at DC,
discretized exactly for a source taken piecewise linear between samples (first-order hold, as
:func:`afmctl.model.coupling.caused`), with its filter state carried from call to call so that a
run played in pieces reads what one long run reads. The source is each channel's noise-free
reading; sensor noise is added after the coupling.

Conventions as in :mod:`~afmctl.drivers.device.plant`: arrays are ``(n, C)``, channel ``c`` in
column ``c``; channel ``c``'s noise and gain draws are those of its own plant (its axis profile's
``[emulator] seed``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from afmctl.model.coupling import Coupling

FloatArray = NDArray[np.float64]

#: Channel of each axis name.
CHANNEL = {"x": 0, "y": 1}


@dataclass(frozen=True)
class XYState:
    """The channels' plant states and each coupling direction's filter state."""

    channels: tuple[Any, ...]
    filters: tuple[FloatArray, ...]


class _Direction:
    """One coupling direction, discretized at ``dt`` (first-order hold)."""

    def __init__(self, name: str, c: Coupling, dt: float) -> None:
        self.target, self.source = CHANNEL[name[0]], CHANNEL[name[1]]
        self.coupling = c
        num, den = c.transfer()
        if c.mode_hz == 0:
            self.b, self.a = np.array([c.static]), np.array([1.0])
        else:
            bd, ad, _ = signal.cont2discrete((num, den), dt, method="foh")
            self.b, self.a = np.ravel(bd), np.asarray(ad, dtype=float)

    def rest(self, source_um: float) -> FloatArray:
        """Filter state at rest with the source at ``source_um``."""
        if self.a.size == 1:
            return np.zeros(0)
        return signal.lfilter_zi(self.b, self.a) * (source_um - self.coupling.reference_um)

    def caused(self, source_um: FloatArray, zi: FloatArray) -> tuple[FloatArray, FloatArray]:
        x = source_um - self.coupling.reference_um
        if self.a.size == 1:
            return self.b[0] * x, zi
        y, zf = signal.lfilter(self.b, self.a, x, zi=zi)
        return np.asarray(y, dtype=float), zf


class CoupledPhysics:
    """C channel plants and their cross-coupling, behind the emulator's plant interface
    (``initial``, ``gain``, ``noise``, ``respond``; immutable after construction).

    Parameters
    ----------
    plants : list
        One plant per channel (each with 1-D ``respond``).
    coupling : tuple of (str, Coupling)
        By direction, ``"yx"`` (y caused by x) and ``"xy"``.
    sample_rate_hz : float
    """

    def __init__(self, plants: list[Any], coupling: tuple[tuple[str, Coupling], ...],
                 sample_rate_hz: float) -> None:
        self.plants = plants
        self.dt = 1.0 / sample_rate_hz
        self.directions = [_Direction(name, c, self.dt) for name, c in coupling]

    def initial(self) -> XYState:
        """Power-on: every plant at its own power-on state, the couplings at rest there."""
        states = tuple(p.initial() for p in self.plants)
        u0 = [float(p.respond(np.zeros(1), s)[0][0]) for p, s in zip(self.plants, states,
                                                                     strict=True)]
        return XYState(states, tuple(d.rest(u0[d.source]) for d in self.directions))

    def gain(self, run_index: int) -> FloatArray:
        """Each channel's applied-voltage gain for run ``run_index``, shape (C,)."""
        return np.array([p.gain(run_index) for p in self.plants])

    def noise(self, run_index: int, first: int, n: int) -> FloatArray:
        """Each channel's sensor noise, um, shape (n, C)."""
        return np.stack([p.noise(run_index, first, n) for p in self.plants], axis=1)

    def respond(self, v_cmd: FloatArray, state: XYState, gain: Any = 1.0,
                noise_um: FloatArray | None = None
                ) -> tuple[FloatArray, FloatArray, XYState]:
        """Run commanded samples ``v_cmd`` (V, shape (n, C)) through every plant and the
        coupling: readings (um) and stack voltages (V), each (n, C), and the new state."""
        v = np.asarray(v_cmd, dtype=float)
        g = np.broadcast_to(np.asarray(gain, dtype=float), (len(self.plants),))
        cols = [p.respond(v[:, c], s, float(g[c])) for c, (p, s)
                in enumerate(zip(self.plants, state.channels, strict=True))]
        clean = np.stack([u for u, _, _ in cols], axis=1)
        u = clean.copy()
        filters = []
        for d, zi in zip(self.directions, state.filters, strict=True):
            y, zf = d.caused(clean[:, d.source], zi)
            u[:, d.target] += y
            filters.append(zf)
        if noise_um is not None:
            u = u + noise_um
        return (u, np.stack([va for _, va, _ in cols], axis=1),
                XYState(tuple(s for _, _, s in cols), tuple(filters)))
