"""The emulated two-axis device's plant when its profile carries ``[emulator.xy_foreign]``: the
independently written foreign x/y stage (:mod:`~afmctl.drivers.device.foreign.xy_stage`), both
axes and their coupling from its own formulas, behind the emulator's plant interface.

Conventions as in :mod:`~afmctl.drivers.device.xy_plant`: arrays (n, 2), x in column 0; sample k
is held one period and the reading at k does not yet see it (the stage's own convention). The
readings carry the stage's sensor offsets; sensor noise (1 sigma the stage's own per axis) is
drawn by global sample index from ``(seed, run, 2 + axis)`` blocks, so a run played in pieces
reads what one long run reads. The recorded voltage is the commanded one (the stage models no
amplifier), as for the one-axis foreign plant.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from afmctl.drivers.device.foreign import xy_stage as xs
from afmctl.drivers.device.plant import block_noise
from afmctl.files.profile import XYForeignSpec

FloatArray = NDArray[np.float64]


def foreign_xy_stage(spec: XYForeignSpec, drive_range_V: tuple[float, float]) -> xs.XYStage:
    """The stage ``spec`` describes, over ``drive_range_V`` (V, both axes); ValueError if a
    benchmark stage drives another range."""
    if spec.bench is not None:
        stage = xs.xy_stages()[spec.bench - 1]
    else:
        stage = xs.random_xy_stage(np.random.default_rng(spec.seed),
                                   unipolar=drive_range_V[0] == 0.0, coupling_db=spec.coupling_db,
                                   mode_hz=spec.mode_hz, name=f"xy-foreign-{spec.seed}")
    if any(tuple(r) != tuple(drive_range_V) for r in stage.drive_range_V):
        raise ValueError(f"foreign x/y stage {stage.name!r} drives {stage.drive_range_V} V, the "
                         f"profile's amplifiers {drive_range_V} V")
    return stage


class ForeignXYPhysics:
    """A foreign x/y stage as the plant of a two-channel emulated device (immutable after
    construction).

    Parameters
    ----------
    spec : XYForeignSpec
    sample_rate_hz : float
    drive_range_V : tuple of float
        The profile's voltage range, V (both axes).
    """

    def __init__(self, spec: XYForeignSpec, sample_rate_hz: float,
                 drive_range_V: tuple[float, float]) -> None:
        self.spec = spec
        self.stage = foreign_xy_stage(spec, drive_range_V)
        self.sample_rate_hz = float(sample_rate_hz)
        self.sigma_um = xs.noise_um(self.stage)

    def initial(self) -> xs.XYState:
        """Power-on: both actuators poled and back at 0 V, the structure at rest."""
        return xs.initial_state(self.stage)

    def gain(self, run_index: int) -> FloatArray:
        """Applied-voltage gains (1: the stage has no gain drift), shape (2,)."""
        return np.ones(2)

    def noise(self, run_index: int, first: int, n: int) -> FloatArray:
        """Each axis's sensor noise of samples ``first .. first+n-1``, um, shape (n, 2)."""
        return np.stack([s * block_noise((self.spec.seed, run_index, 2 + c), first, n)
                         for c, s in enumerate(self.sigma_um)], axis=1)

    def respond(self, v_cmd: FloatArray, state: xs.XYState, gain: object = 1.0,
                noise_um: FloatArray | None = None
                ) -> tuple[FloatArray, FloatArray, xs.XYState]:
        """Readings (um) and stack voltages (the commands, V), each (n, 2), and the new state."""
        v = np.asarray(v_cmd, dtype=float).reshape(-1, 2)
        _, reading, state = xs.run(self.stage, v, self.sample_rate_hz, state)
        return (reading if noise_um is None else reading + noise_um), v, state
