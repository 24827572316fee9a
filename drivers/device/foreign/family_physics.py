"""The emulated device's plant when its profile carries ``[emulator.family]``: an out-of-family stage.

:class:`FamilyPhysics` offers the emulator what :class:`~afmctl.drivers.device.plant.Physics`
offers (``initial``, ``gain``, ``noise``, ``draws``, ``respond``) and ``elapse`` (a hold longer
than the emulator simulates sample by sample: creep and drift go on), running a stage of
:mod:`afmctl.drivers.device.foreign.family_stage` drawn from the table's ``seed`` over the
profile's voltage range (:func:`family_stage_of`). Conventions as in
:mod:`afmctl.drivers.device.foreign.physics`: sample k is held one period and the reading at k
does not yet see it; the sensor noise (1 sigma the stage's ``noise_um``) is drawn by global sample
index from the table's seed; the recorded voltage is the commanded one.

Second forms of ``afmctl diagnose``'s causes (:func:`random_extras`, the stage's
:class:`~afmctl.drivers.device.foreign.family_stage.Extras`), drawn clearly visible at the
sweep rates (each moves the fast standard triangle's readings by many times the noise):

======================  ===========================================================
cause                   second form, range drawn
======================  ===========================================================
amplifier-lag           3 equal real poles at 0.4-1.5x the rod's resonance (>= 300 Hz)
thermal-relaxation      the hysteresis sees the input through a lag of 2-15 ms
second-mode             modal sum, a mode at 1.5-4x the resonance, residue +-(0.08-0.25)
sensor-delay            the gauge integrates over 0.2-1.0 ms (an integrating ADC)
sensor-nonlinearity     capacitive gap law, error at the range's end 30-150x the noise
voltage-gain-drift      gain warm-up 1 + delta (1 - exp(-t / T)), delta +-(1-3) %, T 3-20 s
======================  ===========================================================
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from afmctl.drivers.device.foreign import family_stage as fs
from afmctl.drivers.device.plant import Physics
from afmctl.files.profile import EmulatorConfig, FamilySpec

__all__ = ["FamilyPhysics", "family_stage_of", "random_extras", "SECOND_FORMS"]

FloatArray = NDArray[np.float64]
SECOND_FORMS = ("amplifier-lag", "thermal-relaxation", "second-mode", "sensor-delay",
                "sensor-nonlinearity", "voltage-gain-drift")


def _log(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def random_extras(cause: str, rng: np.random.Generator, stage: fs.FamilyStage) -> fs.Extras:
    """The second form of ``cause`` for ``stage`` (see the module docstring for the ranges)."""
    sign = float(rng.choice([-1.0, 1.0]))
    if cause == "amplifier-lag":
        return fs.Extras(amplifier_hz=max(300.0, stage.resonance_hz * _log(rng, 0.4, 1.5)))
    if cause == "thermal-relaxation":
        return fs.Extras(viscous_tau_s=_log(rng, 0.002, 0.015))
    if cause == "second-mode":
        return fs.Extras(mode2=(stage.resonance_hz * rng.uniform(1.5, 4.0),
                                rng.uniform(0.01, 0.04), sign * rng.uniform(0.08, 0.25)))
    if cause == "sensor-delay":
        return fs.Extras(adc_window_s=rng.uniform(0.0002, 0.001))
    if cause == "sensor-nonlinearity":
        half = 0.5 * stage.loop.span_um
        err = stage.noise_um * _log(rng, 30.0, 150.0)
        return fs.Extras(gauge_gap_um=sign * half * half / err, gauge_mid_um=half)
    if cause == "voltage-gain-drift":
        return fs.Extras(gain_delta=sign * rng.uniform(0.01, 0.03),
                         gain_tau_s=rng.uniform(3.0, 20.0))
    raise ValueError(f"unknown cause {cause!r} (one of {', '.join(SECOND_FORMS)})")


def family_stage_of(spec: FamilySpec, drive_range_V: tuple[float, float]) -> fs.FamilyStage:
    """The stage ``spec`` describes, driven over ``drive_range_V`` (V)."""
    rng = np.random.default_rng(spec.seed)
    stage = fs.random_family_stage(rng, spec.family, drive_range_V, spec.creep, spec.drift,
                                   spec.density, **dict(spec.overrides))
    if spec.effect is None:
        return stage
    return replace(stage, extras=random_extras(spec.effect, rng, stage))


class FamilyPhysics(Physics):
    """An out-of-family stage behind the emulator's plant interface (immutable after construction).

    Parameters
    ----------
    config : EmulatorConfig
        With ``family`` set.
    sample_rate_hz : float
    drive_range_V : tuple of float
        The profile's voltage range, V.
    """

    def __init__(self, config: EmulatorConfig, sample_rate_hz: float,
                 drive_range_V: tuple[float, float]) -> None:
        spec = config.family
        if spec is None:
            raise ValueError("the emulator's configuration has no [emulator.family] table")
        self.stage = family_stage_of(spec, drive_range_V)
        self.config = replace(config, seed=spec.seed, noise_um=self.stage.noise_um)
        self.sample_rate_hz = float(sample_rate_hz)
        self.dt = 1.0 / self.sample_rate_hz

    def initial(self) -> fs.FamilyState:  # type: ignore[override]
        """Power-on: poled (once over the drive range and back to 0 V), settled."""
        return fs.initial_state(self.stage)

    def gain(self, run_index: int) -> float:
        """1: these stages have no per-run gain draw (a warm-up is a function of time)."""
        return 1.0

    def respond(self, v_cmd: FloatArray, state: fs.FamilyState,  # type: ignore[override]
                gain: float = 1.0, noise_um: FloatArray | None = None
                ) -> tuple[FloatArray, FloatArray, fs.FamilyState]:
        """Run commanded samples (V) through the stage: readings (um, with ``noise_um`` added),
        the commanded voltage and the new state."""
        v = np.asarray(v_cmd, dtype=float)
        _, reading, state = fs.run(self.stage, gain * v, self.sample_rate_hz, state)
        if noise_um is not None:
            reading = reading + noise_um
        return reading, v, state

    def true_um(self, v_cmd: FloatArray, state: fs.FamilyState) -> FloatArray:
        """The platform's true position (um, drift included, no gauge) over a run of ``v_cmd``
        from ``state``."""
        return fs.run(self.stage, np.asarray(v_cmd, dtype=float), self.sample_rate_hz, state)[0]

    def elapse(self, state: fs.FamilyState, seconds: float, voltage_V: float
               ) -> fs.FamilyState:
        """A hold of ``seconds`` at ``voltage_V`` past what the emulator simulated sample by
        sample (exact: :func:`~afmctl.drivers.device.foreign.family_stage.idle`)."""
        return fs.idle(self.stage, state, seconds, voltage_V)
