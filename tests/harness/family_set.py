"""The identification set of ``afmctl sweep --design reversals`` recorded on an independently
written out-of-family stage (:mod:`afmctl.drivers.device.foreign.family_stage`), in sequence, with
its gauge noise: the three standard triangles and the reversal curves (with the interior loops)."""

from __future__ import annotations

import numpy as np

from afmctl.drivers.device.foreign import family_stage as fst
from afmctl.files import sweepfile as sw
from afmctl.planning import sweepdesign as sd


def record(stage: fst.FamilyStage, rate_hz: float, v_range: tuple[float, float],
           noise_seed: int) -> tuple[list[sw.Sweep], fst.FamilyState]:
    """The set recorded from the stage's power-on at ``rate_hz`` over ``v_range`` (V), and the
    stage's state after it."""
    state, rng = fst.initial_state(stage), np.random.default_rng(noise_seed)
    plays = [(n, f, v) for n, f, v in sd.standard_set(sample_rate_hz=rate_hz, v_range=v_range)[:3]]
    name, f, v, _ = sd.reversals_sweep(v_range, rate_hz, 150e3)
    recorded = []
    for n, f, v in plays + [(name, f, v)]:
        _, reading, state = fst.run(stage, v, rate_hz, state)
        noisy = reading + stage.noise_um * rng.standard_normal(v.size)
        meta = {"layer_thickness_um": "100", "frequency_hz": f"{f:g}"}
        recorded.append(sw.from_arrays(v, noisy, rate_hz, meta, n))
    return recorded, state
