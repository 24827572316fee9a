"""Learning on a foreign stage (:mod:`drivers.device.foreign`): an independently written plant.

The foreign plant has no stage interface of its own yet (its selection in the emulator's profile
has not landed), so :class:`ForeignStage` drives it in-process through the two calls learning
needs (``play``, ``voltage``). The model is identified from the paper's standard sweep design
(0 .. 150 V, 1/5/10 kHz) recorded on the stage; learning is judged by the plant's own true
position (plus the sensor's zero, the frame the readings and the model share).
"""

from __future__ import annotations

import dataclasses as dc
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from afmctl import identify, ilc, learn, track
from afmctl import sweeps as sw
from afmctl.guard import Limits
from drivers.device import foreign as fp
from drivers.device.foreign_effects import random_effect
from drivers.device.foreign_stages import random_stage
from drivers.device.foreign_sweeps import sweep_set

RATE_HZ = 10_000.0
LIMITS = Limits(v_min=0.0, v_max=150.0, slew_v_per_ms=50.0, current_ma=100.0, capacitance_uf=2.0)


class ForeignStage:
    """A foreign plant behind ``play``/``voltage``; keeps every run's true position (um)."""

    def __init__(self, stage: fp.Stage, seed: int) -> None:
        self.stage = stage
        self.rng = np.random.default_rng(seed)
        self.state = fp.initial_state(stage, "poled+")
        self.out_v = 0.0
        self.true: list[np.ndarray] = []

    def voltage(self) -> float:
        return self.out_v

    def play(self, waveform_v: np.ndarray, on_block: Any = None, rate_hz: float = RATE_HZ,
             **_: Any) -> Any:
        v = np.asarray(waveform_v, dtype=float)
        self.state = fp.start_run(self.stage, self.state, self.rng)
        true, reading, self.state = fp.run(self.stage, v, rate_hz, self.state, self.rng)
        self.true.append(true + self.stage.sensor.offset_um)
        self.out_v = float(v[-1])
        valid = np.ones(v.size, dtype=bool)
        if on_block is not None:
            on_block(0, v, reading, valid)
        return SimpleNamespace(displacement_um=reading, valid=valid)


def make_stage(cause: str, seed: int) -> fp.Stage:
    rng = np.random.default_rng([seed, 13])
    stage = random_stage(rng, drive_range_V=(0.0, 150.0))
    if cause != "none":
        stage = dc.replace(stage, effects=(random_effect(cause, rng, stage, 0.5),))
    return stage


def identified(dev: ForeignStage) -> tuple[Any, sw.Sweep]:
    """Model identified from the standard design recorded on ``dev``; the 27.9 Hz sweep."""
    recorded = []
    for plan in sweep_set("standard", 0.0, 150.0, np.random.default_rng(0)):
        rec = dev.play(plan.voltage_V, rate_hz=plan.sample_rate_hz)
        meta = {"frequency_hz": f"{plan.frequency_hz:g}",
                "layer_thickness_um": f"{dev.stage.material.layer_thickness_um:g}"}
        recorded.append(sw.from_arrays(plan.voltage_V, rec.displacement_um,
                                       plan.sample_rate_hz, meta, plan.name))
    dev.true.clear()
    return identify.fit(recorded).model, recorded[-1]


def learn_foreign(cause: str, seed: int, out: Path, iterations: int = 5) -> dict[str, Any]:
    """One foreign stage: identify, then learn the 27.9 Hz triangle (27.04 um, or 60 % of the
    span the fast sweep covered if that is less), judged by the plant's true position."""
    stage = make_stage(cause, seed)
    dev = ForeignStage(stage, seed)
    model, fast = identified(dev)
    steady = fast.displacement_um[fast.displacement_um.size // 2:]
    lo, hi = float(np.min(steady)), float(np.max(steady))
    amp = min(27.04, 0.6 * (hi - lo))
    desired = track.triangle(27.9, amp, 0.5 * (lo + hi), 3, 1 / RATE_HZ)
    res = learn.run(dev, model, desired, LIMITS, out, {}, iterations, ilc.Law())
    part = ilc.steady_part(desired)
    rms = [float(np.sqrt(np.mean((t[it.outcome.waveform.tracking] - desired.u_um)[part] ** 2)))
           for t, it in zip(dev.true, res.iterations, strict=False)]
    noise = stage.sensor.noise_um
    return {"effect": cause, "plant": "foreign", "truth": fp.describe(stage)["effects"],
            "model": "identify (standard design, 0..150 V)", "amplitude_um": amp,
            "noise_um": noise, "rms_um_by_iteration": rms,
            "readings_rms_um_by_iteration": [it.steady_um for it in res.iterations],
            "kept_iteration": res.best, "stop": res.stop,
            "final_over_noise": rms[res.best] / noise, "ok": rms[res.best] / noise <= 2,
            "target": "final_over_noise <= 2 within 5 iterations",
            "seconds_per_iteration_compute": float(np.mean(res.compute_s))}
