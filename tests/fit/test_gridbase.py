"""Diagnose's second base, the Preisach grid without and with creep (:mod:`afmctl.fit.gridbase`),
on independently written out-of-family stages (:mod:`afmctl.drivers.device.foreign.family_stage`:
a Preisach operator whose density is not the paper's, Krejci-Kuhnen creep of 1-2 % per decade, a
frame drift): a creeping stage is diagnosed ``creep`` through the whole of ``diagnose`` and its
files; a drifting stage is not, and gets a drift hint. The standard triangles at 5 kHz (the
stage's own gauge noise given: the estimate from the data is too high below that) and half the
Gauss-Newton steps keep it short; ``benchmarks/bench_diagnose.py --family-only`` runs
the full-size case on 14 stages."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from afmctl.drivers.device.foreign import family_stage as fst
from afmctl.cli.diagnose import _write
from afmctl.files import modelfile
from afmctl.files import sweepfile as sw
from afmctl.fit import diagnose as dg
from afmctl.fit import gridbase as gb
from afmctl.fit import identify as idf
from afmctl.fit import verdict as vd
from afmctl.model import creep as cr
from afmctl.model.preisach import PreisachGrid
from afmctl.planning import sweepdesign as sd

RATE_HZ = 5000.0
#: Half identify's Gauss-Newton steps: the test's budget (a coarser grid of 12 x 18 coefficients
#: left the creep stage at 8x the noise and the drift stage at 2.4x, where this one leaves 7.4x
#: and 1.2x).
FAST = dataclasses.replace(gb.GRID_SETTINGS, max_iter=20)


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


def test_the_shares_are_of_what_the_record_sees() -> None:
    # within 10 s the 1000 s element adds 1 - exp(-0.01) of its weight: a hundredth
    taus = np.array([0.01, 1000.0])
    assert gb.seen(taus, np.array([1.0, 3.0]), 10.0) == pytest.approx(
        [1.0, 3.0 * (1 - np.exp(-0.01))])
    assert gb.seen(taus, np.array([1.0, 3.0]), math.inf) == pytest.approx([1.0, 3.0])
    short, long, _ = gb.shares(taus, np.array([1.0, 3.0]), record=10.0)
    assert short == pytest.approx(1.0 / (1.0 + 3.0 * (1 - np.exp(-0.01))))
    assert long == pytest.approx(1.0 - short)


def test_the_elements_creep_per_decade_is_read_within_the_record() -> None:
    taus = np.logspace(-2, 3, 11)
    flat = np.full(11, 0.005)  # two elements per decade: about 1 % per decade
    creep = cr.Creep(tuple(taus), tuple(flat))
    assert gb.elements(taus, flat).per_decade == pytest.approx(creep.per_decade())
    lo, hi = cr.step_response(creep, np.array([0.1, 10.0]))
    within = gb.elements(taus, flat, record=10.0)
    assert within.per_decade == pytest.approx((hi - lo) / 2.0)
    # log-time creep adds the same per decade in any window; a slow trend does not
    assert within.per_decade == pytest.approx(creep.per_decade(), rel=0.02)
    slow = np.where(taus >= 100.0, 0.05, 0.0)
    assert gb.elements(taus, slow, record=10.0).per_decade < 0.25 * gb.elements(taus, slow).per_decade
    assert within.span_decades < gb.elements(taus, flat).span_decades
    # under a second of record the window is 0.1-1 s
    lo, hi = cr.step_response(creep, np.array([0.1, 1.0]))
    assert gb.elements(taus, flat, record=0.3).per_decade == pytest.approx(hi - lo)


def test_the_record_is_the_chain_of_sweeps_the_grid_follows() -> None:
    # 2 s, a hold of 0.5 s, 1 s: 3.5 s; a sweep without a link stands alone
    assert gb.record_s([2.0, 1.0], [math.nan, 0.5]) == pytest.approx(3.5)
    assert gb.record_s([2.0, 3.0], [math.nan, math.nan]) == pytest.approx(3.0)
    assert gb.record_s([2.0, 1.0, 1.0], [math.nan, math.nan, 0.25]) == pytest.approx(2.25)
    assert gb.record_s([2.0, 1.0], [math.nan, 0.5], chained=False) == pytest.approx(2.0)


def diagnosed(stage: fst.FamilyStage, seed: int) -> tuple[list[sw.Sweep], dg.Diagnosis]:
    """The stage's triangles diagnosed with the paper's model alone as the candidate (the grid
    comes in once it leaves them unexplained)."""
    sweeps = triangles(stage, seed)
    fast = idf.Settings(restarts=0, density="parametric")
    return sweeps, dg.diagnose(sweeps, dg.Settings(identify=fast, candidates=("none",), jobs=1,
                                                   grid_fit=FAST),
                               noise_um=[stage.noise_um] * 3)


def test_a_creeping_stage_out_of_the_family_is_diagnosed_creep(tmp_path: Path) -> None:
    stage = fst.random_family_stage(np.random.default_rng(11), "preisach", creep=True)
    sweeps, d = diagnosed(stage, 11)
    assert d.cause == "creep", d.evidence()
    g = d.grid
    assert g is not None and d.on_grid and g.creep() and not g.drift()
    assert g.gain >= 1.5 and g.seen.short_share >= 0.1 and g.seen.per_decade >= 0.003
    assert d.paper_rms_um > 1.5 * g.crept_rms_um  # the paper's model alone misses it
    assert d.extended_model.creep is not None and d.base_model.creep is None
    # the CLI's files: the models read back, the report and the JSON name the grid's verdict
    _write(d, sweeps, tuple(f"{s.path}.csv" for s in sweeps), tmp_path, "{}")
    doc = json.loads(json.dumps(d.as_dict(), allow_nan=False))
    assert doc["base_model"] == "the Preisach grid without creep" and doc["grid"]["creep"]
    # three full-range triangles: no reversal inside the range, so the creep model's loop
    # interior is the smoothing's guess, and the diagnosis says which sweeps would fix that
    assert doc["grid"]["interior_reversals"] == 0
    assert d.suggestions() == [gb.INTERIOR_HINT] and "--design full" in str(doc)
    assert "creep" in doc["explanation"] and "decade" in doc["evidence"]
    assert "Preisach grid" in doc["method"]
    assert "| preisach-grid with creep |" in (tmp_path / "report.md").read_text()
    assert "Preisach grid without creep" in (tmp_path / "base.toml").read_text()
    back = modelfile.read(tmp_path / "extended.toml")
    # what extended.toml predicts is what the grid with creep was judged by
    u = idf.predict_set(back, sweeps, d.extended.starts, d.extended.offsets_um)
    for s, a, b in zip(sweeps, u, g.crept_readings, strict=True):
        assert float(np.max(np.abs(a - b))) < 1e-6 * float(np.ptp(s.displacement_um))
    assert modelfile.read(tmp_path / "base.toml").creep is None


def test_a_drifting_stage_is_not_diagnosed_creep_and_gets_a_drift_hint(tmp_path: Path) -> None:
    """Unexplained (a drift), with the drift hint; the model files are the grid without creep
    (nothing absorbed), the best model diagnose fitted, not the paper's model it judged."""
    stage = fst.random_family_stage(np.random.default_rng(12), "preisach", drift=True)
    sweeps, d = diagnosed(stage, 12)
    assert d.grid is not None and not d.grid.creep() and d.grid.drift(), d.evidence()
    assert d.cause == "unexplained" and not d.on_grid
    assert d.suggestions()[0] == gb.DRIFT_HINT
    assert d.base_model.creep is None and d.extended_model.creep is None  # nothing absorbed
    assert d.kept_grid and d.grid.plain_rms_um < 0.5 * d.paper_rms_um
    _write(d, sweeps, tuple(f"{s.path}.csv" for s in sweeps), tmp_path, "{}")
    for name in ("base.toml", "extended.toml"):
        back = modelfile.read(tmp_path / name)
        assert isinstance(back.polarization, PreisachGrid) and back.creep is None
    assert "the Preisach grid without creep kept" in (tmp_path / "extended.toml").read_text()
    assert d.as_dict()["model_files"] == "the Preisach grid without creep (no cause named)"


def grid_of(plain: float, crept: float, per_decade: float = 0.01, short: float = 0.3,
            long: float = 0.2, span: float = 3.0) -> gb.GridBase:
    """A GridBase with these figures (held-out RMS in multiples of a floor of 1 um)."""
    figures = gb.Elements(per_decade, short, long, span)
    return gb.GridBase(None, None, plain, crept, (plain,), (crept,), (),  # type: ignore[arg-type]
                       figures, figures, 10.0, 1.0, gb.CreepRule(), vd.Rule(), 0.0)


@pytest.mark.parametrize(("figures", "verdict"), [
    ({"plain": 10.0, "crept": 2.0}, "creep"),
    ({"plain": 10.0, "crept": 2.0, "span": 1.0}, "unexplained"),  # one knee: not log-time creep
    ({"plain": 10.0, "crept": 2.0, "short": 0.05, "long": 0.9}, "unexplained"),  # a drift
    ({"plain": 10.0, "crept": 6.0}, "unexplained"),  # gain 1.7, but most of the misfit left
    ({"plain": 7.5, "crept": 2.6}, "unexplained"),  # 90 % of it: bw-b's memory, not creep
    ({"plain": 40.0, "crept": 5.0}, "creep"),  # 98 %: pi-u-creep, its play shape left
    ({"plain": 3.0, "crept": 2.5}, "unexplained"),  # too small a gain for creep, far from floor
    ({"plain": 1.4, "crept": 1.3}, "none"),  # the grid alone at the floor
    ({"plain": 1.4, "crept": 1.3, "short": 0.0, "long": 1.0}, "unexplained"),  # drifting
    ({"plain": 110.0, "crept": 60.0, "short": 0.0, "long": 1.0}, "unexplained"),  # no drift
    ({"plain": 2.0, "crept": 1.0, "per_decade": 0.001}, "unexplained"),  # no creep to speak of
], ids=["creep", "knee", "drift", "partial", "bouc-wen", "far", "small", "none",
        "none-but-drift", "thermal", "tiny"])
def test_the_creep_rule(figures: dict[str, float], verdict: str) -> None:
    assert grid_of(**figures).verdict() == verdict


def test_creep_is_read_from_what_the_record_sees_and_a_drift_from_the_weights() -> None:
    def grid(plain: float, crept: float, seen: gb.Elements, weights: gb.Elements) -> gb.GridBase:
        return gb.GridBase(None, None, plain, crept, (plain,), (crept,), (),  # type: ignore[arg-type]
                           seen, weights, 8.65, 1.0, gb.CreepRule(), vd.Rule(), 0.0)

    # pi-b-creep's chained triangles: weights on the slowest elements, the record sees creep
    chained = grid(34.6, 3.48, gb.Elements(0.0144, 0.49, 0.13, 3.0),
                   gb.Elements(0.0336, 0.096, 0.667, 1.5))
    assert chained.creep() and chained.verdict() == "creep"
    assert not grid(34.6, 3.48, chained.weights, chained.weights).creep()
    assert not chained.drift()  # creep, read first, is not also a drift
    # preisach-u-drift's figures (stop 63): little within the record, the weights on the slowest
    drifting = grid(1.52, 1.03, gb.Elements(0.0018, 0.13, 0.87, 0.5),
                    gb.Elements(0.0096, 0.007, 0.99, 1.0))
    assert drifting.drift() and not drifting.creep() and drifting.verdict() == "unexplained"
    assert not grid(1.52, 1.03, drifting.seen, drifting.seen).drift()


def test_a_creep_verdict_asks_for_reversal_curves_only_when_the_sweeps_lack_them() -> None:
    """identify's rule (:data:`afmctl.fit.representation.REVERSALS_NEEDED` reversal voltages
    inside the range): the reversals design has 7 of each kind; full-range triangles none."""
    few = dataclasses.replace(grid_of(10.0, 2.0), interior_reversals=0)
    enough = dataclasses.replace(few, interior_reversals=7)
    assert few.verdict() == enough.verdict() == "creep"
    assert few.hints() == [gb.INTERIOR_HINT] and enough.hints() == []
    assert few.as_dict()["interior_reversals"] == 0


def test_the_drift_hint_needs_the_elements_to_explain_the_misfit() -> None:
    assert grid_of(1.5, 1.1, short=0.0, long=1.0).drift()  # preisach-u-drift's figures
    # thermal relaxation's: the slow elements take a third off a grid 110x off
    assert not grid_of(110.0, 60.0, short=0.0, long=1.0).drift()
