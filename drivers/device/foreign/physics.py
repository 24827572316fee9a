"""The emulated device's plant when its profile carries ``[emulator.foreign]``: a foreign stage.

:class:`ForeignPhysics` offers the emulator what :class:`~afmctl.drivers.device.plant.Physics` offers
(``initial``, ``gain``, ``noise``, ``draws``, ``respond``) but runs the independently written
stage of :mod:`afmctl.drivers.device.foreign.stage` instead of afmctl's own model: the stage is drawn by
:func:`~afmctl.drivers.device.foreign.stages.random_stage` from the table's ``seed`` with its drive range
set to the profile's voltage range and any parameter the table fixes, plus at most one hidden
effect (:func:`~afmctl.drivers.device.foreign.effects.random_effect`, from the same generator).

Conventions as in :mod:`afmctl.drivers.device.plant`: sample k is held one period and the
reading at k does not yet see it (:func:`afmctl.drivers.device.foreign.stage.run`'s convention
too); each run's voltage gain (:func:`afmctl.drivers.device.foreign.stage.start_run`, only a
``voltage-gain-drift`` stage has one) comes from
``numpy.random.default_rng((seed, run, 1))`` and its sensor noise (1 sigma the stage's own
``noise_um``) by global sample index, so a run played in pieces reads what one long run reads and
the whole session is reproducible from ``seed``. The recorded voltage is the commanded one: the
foreign amplifier's output is hidden, as on a stage without a voltage monitor.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from afmctl.drivers.device.foreign import stage as fs
from afmctl.drivers.device.foreign.effects import random_effect
from afmctl.drivers.device.foreign.stages import random_stage, with_effects
from afmctl.drivers.device.plant import Physics
from afmctl.files.profile import EmulatorConfig, ForeignStage

__all__ = ["ForeignPhysics", "foreign_stage"]

FloatArray = NDArray[np.float64]


def foreign_stage(spec: ForeignStage, drive_range_V: tuple[float, float]) -> fs.Stage:
    """The stage ``spec`` describes, driven over ``drive_range_V`` (V)."""
    rng = np.random.default_rng(spec.seed)
    stage = random_stage(rng, drive_range_V=drive_range_V, **dict(spec.overrides))
    if spec.effect is None:
        return stage
    return with_effects(stage, random_effect(spec.effect, rng, stage, spec.strength))


class ForeignPhysics(Physics):
    """A foreign stage behind the emulator's plant interface (immutable after construction).

    Parameters
    ----------
    config : EmulatorConfig
        With ``foreign`` set.
    sample_rate_hz : float
    drive_range_V : tuple of float
        The profile's voltage range, V (the stage's drive range).
    """

    def __init__(self, config: EmulatorConfig, sample_rate_hz: float,
                 drive_range_V: tuple[float, float]) -> None:
        spec = config.foreign
        if spec is None:
            raise ValueError("the emulator's configuration has no [emulator.foreign] table")
        self.stage = foreign_stage(spec, drive_range_V)
        # noise() and draws() are Physics's: keyed by the foreign seed, the stage's own sigma
        self.config = replace(config, seed=spec.seed, noise_um=self.stage.sensor.noise_um)
        self.start = spec.start
        self.sample_rate_hz = float(sample_rate_hz)
        self.dt = 1.0 / self.sample_rate_hz

    def initial(self) -> fs.PlantState:  # type: ignore[override]
        """Power-on state: the table's ``start`` history, at rest."""
        return fs.initial_state(self.stage, self.start)

    def gain(self, run_index: int) -> float:
        """Voltage gain of run ``run_index`` (1 unless the stage drifts)."""
        counted = replace(fs.initial_state(self.stage, "depoled"), runs=run_index)
        rng = np.random.default_rng((self.config.seed, run_index, 1))
        return fs.start_run(self.stage, counted, rng).gain

    def respond(self, v_cmd: FloatArray, state: fs.PlantState,  # type: ignore[override]
                gain: float = 1.0, noise_um: FloatArray | None = None
                ) -> tuple[FloatArray, FloatArray, fs.PlantState]:
        """Run commanded samples through the foreign stage.

        Parameters
        ----------
        v_cmd : ndarray, shape (N,)
            Commanded voltage held over each sample, V.
        state : afmctl.drivers.device.foreign.stage.PlantState
        gain : float
            Voltage gain of this run.
        noise_um : ndarray, shape (N,), optional
            Sensor noise to add, um.

        Returns
        -------
        u_um : ndarray, shape (N,)
            Gauge reading at each sample instant (before that sample acts), um.
        v_cmd : ndarray, shape (N,)
            The commanded voltage, V (the amplifier's output is not observable).
        state : afmctl.drivers.device.foreign.stage.PlantState
        """
        v = np.asarray(v_cmd, dtype=float)
        _, reading, state = fs.run(self.stage, v, self.sample_rate_hz,
                                   replace(state, gain=gain), None)
        if noise_um is not None:
            reading = reading + noise_um
        return reading, v, state
