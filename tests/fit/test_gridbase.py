"""Diagnose's second base, the Preisach grid without and with creep (:mod:`afmctl.fit.gridbase`),
on independently written out-of-family stages (:mod:`afmctl.drivers.device.foreign.family_stage`:
a Preisach operator whose density is not the paper's, Krejci-Kuhnen creep of 1-2 % per decade, a
frame drift): a creeping stage is diagnosed ``creep`` through the whole of ``diagnose`` and its
files; a drifting stage is not, and gets a drift hint. The standard triangles at 5 kHz (the
stage's own gauge noise given: the estimate from the data is too high below that), a coarser grid
and fewer Gauss-Newton steps keep it short; ``benchmarks/bench_diagnose.py --family-only`` runs
the full-size case on 14 stages."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from afmctl.drivers.device.foreign import family_stage as fst
from afmctl.files import modelfile
from afmctl.files import sweepfile as sw
from afmctl.fit import diagnose as dg
from afmctl.fit import diagnosis_report
from afmctl.fit import gridbase as gb
from afmctl.fit import identify as idf
from afmctl.fit import preisach as pf
from afmctl.planning import sweepdesign as sd

RATE_HZ = 5000.0
#: A coarser grid and fewer Gauss-Newton steps than identify's: the test's budget.
FAST = pf.Settings(coef_coercive=12, coef_interaction=18, max_iter=20)


def triangles(stage: fst.FamilyStage, seed: int) -> list[sw.Sweep]:
    """The three standard triangles over 0-150 V, played in sequence from power-on, with the
    stage's gauge noise."""
    state, rng = fst.initial_state(stage), np.random.default_rng(seed)
    out = []
    for name, f, v in sd.standard_set(sample_rate_hz=RATE_HZ, v_range=(0.0, 150.0))[:3]:
        _, reading, state = fst.run(stage, v, RATE_HZ, state)
        noisy = reading + stage.noise_um * rng.standard_normal(v.size)
        out.append(sw.from_arrays(v, noisy, RATE_HZ, {"layer_thickness_um": "100",
                                                      "frequency_hz": f"{f:g}"}, name))
    return out


def test_shares_of_the_creep_weight() -> None:
    taus = np.tile(np.logspace(-2, 3, 11), 2)  # two thresholds, eleven time constants each
    w = np.zeros(22)
    w[0], w[21] = 1.0, 3.0  # 10 ms on the first threshold, 1000 s on the second
    assert gb.shares(taus, w) == pytest.approx((0.25, 0.75, 5.0))
    flat = np.ones(22)  # 0.01, 0.0316, 0.1, 0.316 s; 100, 316, 1000 s; 80 % in 9 of 11
    assert gb.shares(taus, flat) == pytest.approx((4 / 11, 3 / 11, 4.0))
    assert gb.shares(taus, np.zeros(22)) == (0.0, 0.0, 0.0)


def test_a_creeping_stage_out_of_the_family_is_diagnosed_creep(tmp_path: Path) -> None:
    stage = fst.random_family_stage(np.random.default_rng(11), "preisach", creep=True)
    sweeps = triangles(stage, 11)
    fast = idf.Settings(restarts=0, density="parametric")
    d = dg.diagnose(sweeps, dg.Settings(identify=fast, candidates=("none",), jobs=1,
                                        grid_fit=FAST), noise_um=[stage.noise_um] * 3)
    assert d.cause == "creep", d.evidence()
    g = d.grid
    assert g is not None and d.on_grid and g.creep() and not g.drift()
    assert g.gain >= 1.5 and g.short_share >= 0.1 and g.per_decade >= 0.003
    # the base is the grid without creep, the extension the grid with it, both judged held out
    assert d.base_rms_um == g.plain_rms_um and d.extended_rms_um == g.crept_rms_um
    assert d.table["none"].heldout_rms_um > 1.5 * g.crept_rms_um  # the paper's model alone
    assert d.extended_model.creep is not None and d.base_model.creep is None
    doc = json.loads(json.dumps(d.as_dict(), allow_nan=False))
    assert doc["base_model"] == "the Preisach grid without creep"
    assert doc["grid"]["creep_gain"] == pytest.approx(g.gain)
    assert "creep" in doc["explanation"] and "decade" in doc["evidence"]
    assert "| preisach-grid with creep |" in diagnosis_report.report(d, "residuals.png")
    # the extended model file reads back and predicts what was judged
    modelfile.write(d.extended_model, tmp_path / "extended.toml")
    back = modelfile.read(tmp_path / "extended.toml")
    u = idf.predict_set(back, sweeps, d.extended.starts, d.extended.offsets_um)
    for s, a, b in zip(sweeps, u, g.crept_readings, strict=True):
        assert float(np.max(np.abs(a - b))) < 1e-6 * float(np.ptp(s.displacement_um))


def test_a_drifting_stage_is_not_diagnosed_creep_and_gets_a_drift_hint() -> None:
    stage = fst.random_family_stage(np.random.default_rng(12), "preisach", drift=True)
    sweeps = triangles(stage, 12)
    g = gb.judge(sweeps, 100.0, idf.Settings().mass_kg, [stage.noise_um] * 3, ("depoled",) * 3,
                 (stage.resonance_hz, stage.damping), lambda _m: None, FAST)
    assert not g.creep() and g.drift(), g.text(stage.noise_um)
    assert gb.verdict(g, stage.noise_um) == "unexplained"
