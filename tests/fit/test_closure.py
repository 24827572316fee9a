"""Return-point memory checked on measured sweeps (issue 23 item 3, identify's half): on an
independent Bouc-Wen stage (:mod:`afmctl.drivers.device.foreign.family_stage`, written without
afmctl's model code) the minor loops do not close, and identify says so; on Preisach-type
stages of the same independent code they close."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.drivers.device.foreign import family_stage as fst
from afmctl.files import sweepfile as sw
from afmctl.fit import closure
from afmctl.planning import sweepdesign as sd
from benchmarks import family_sets
from tests.harness.paths import PROFILES

RATE_HZ = 1000.0


def minor_loops(seed: int, family: str,
                corners: tuple[float, ...] = (0.0, 150.0, 50.0, 110.0, 50.0, 110.0, 0.0),
                **fixed: float) -> sw.Sweep:
    """Ramps through ``corners`` (by default 0 -> 150 -> 50 -> 110 -> 50 -> 110 -> 0 V: two
    minor loops between 50 and 110 V, each returning to its reversal) at 150 V/s and 1 kHz on a
    drawn stage, with its noise."""
    v = np.concatenate([[0.0]] + [np.linspace(a, b, int(abs(b - a) / 150.0 * RATE_HZ) + 1)[1:]
                                  for a, b in zip(corners[:-1], corners[1:])])
    stage = fst.random_family_stage(np.random.default_rng(seed), family, **fixed)
    _, reading, _ = fst.run(stage, v, RATE_HZ, fst.initial_state(stage))
    noisy = reading + np.random.default_rng(seed + 100).normal(0.0, stage.noise_um, v.size)
    return sw.from_arrays(v, noisy, RATE_HZ, {"frequency_hz": "0.5",
                                              "layer_thickness_um": "100"},
                          path=f"{family}-{seed}.csv")


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_bouc_wen_minor_loops_do_not_close(seed: int) -> None:
    """Bouc-Wen (no wiping-out): each return misses its reversal by far more than the noise."""
    s = minor_loops(seed, "bouc-wen")
    out = closure.check([s], [fst.random_family_stage(np.random.default_rng(seed),
                                                      "bouc-wen").noise_um])
    assert out["checked"] >= 3 and out["close"] is False, out
    assert out["worst"]["gap_over_noise"] > 10 * closure.NOISES, out
    assert "do NOT close" in out["text"] and "Bouc-Wen" in out["text"]


@pytest.mark.parametrize(("seed", "family"), [(1, "preisach"), (2, "preisach"),
                                              (3, "prandtl-ishlinskii")])
def test_preisach_type_minor_loops_close(seed: int, family: str) -> None:
    """A Preisach operator with a non-separable density and a Prandtl-Ishlinskii one (both
    with return-point memory): every loop closes to within the thresholds."""
    noise = fst.random_family_stage(np.random.default_rng(seed), family).noise_um
    out = closure.check([minor_loops(seed, family)], [noise])
    assert out["checked"] >= 3 and out["close"] is True, out
    assert out["worst"]["gap_over_noise"] < closure.NOISES


def test_an_excursion_past_the_reversal_before_is_not_a_loop() -> None:
    """150 -> 55 -> 84 -> 0 -> 84 V (the reversal-curve design's shape): the descent to 0 V
    wipes out the minimum at 55 V, so the return meets 84 V on another branch and a Preisach
    stage's two readings there differ by far more than the noise. That pair is no minor loop:
    the check leaves it out, and the loops it keeps (84 -> 12 -> 72 -> 24 -> 72) close."""
    corners = (0.0, 150.0, 55.0, 84.0, 0.0, 84.0, 12.0, 72.0, 24.0, 72.0, 0.0)
    s = minor_loops(2, "preisach", corners)
    noise = fst.random_family_stage(np.random.default_rng(2), "preisach").noise_um
    at84 = np.flatnonzero(np.isclose(s.voltage_v, 84.0))
    assert abs(s.displacement_um[at84[1]] - s.displacement_um[at84[0]]) > 30 * noise
    gaps, _ = closure.loop_gaps(s, noise)
    assert 84.0 not in {g.voltage_v for g in gaps}
    out = closure.check([s], [noise])
    assert out["checked"] >= 2 and out["close"] is True, out


def test_a_ringing_turnaround_is_not_checked(tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """The independently written Preisach stage ``preisach-u`` (the family benches'): its 27.9
    Hz triangle rings the rod at the turnarounds, so a quadratic in the voltage does not describe
    the passes there and their "gaps" are the ringing's phase. Those loops are not checked, and
    the loops close. Taken as they come, one of them was 5 standard errors open, and identify
    fitted Bouc-Wen for nothing (97 of its 173 s). (Every pass of that triangle is also faster
    than :data:`closure.SLOW_RANGES_PER_S`, which alone leaves nothing checked.)"""
    case = family_sets.cases_named("preisach-u")[0]
    with family_sets.session(case) as s:
        sweeps = family_sets.record(s, tmp_path, reversals=False)
    fast = [w for w in sweeps if (w.frequency_hz or 0.0) > 20.0]
    assert closure.check(fast, [s.noise_um])["close"] is None  # all faster than SLOW_RANGES
    monkeypatch.setattr(closure, "SLOW_RANGES_PER_S", math.inf)  # the quadratic's rule alone
    out = closure.check(fast, [s.noise_um])
    assert out["unsteady"] >= 3 and out["close"] is True, out
    assert "not quasi-static" in out["text"]
    monkeypatch.setattr(closure, "SMOOTH", math.inf)  # every pass taken as it comes
    assert closure.check(fast, [s.noise_um])["close"] is False


def test_passes_at_unlike_rates_are_not_compared(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """The separating sweep (``afmctl sweep --design separating``) on the independently written
    Prandtl-Ishlinskii stage ``pi-u``: its multisine returns to its reversals, but the return
    moves about twice as fast as the pass into it, so the rod's lag does not cancel from the gap.
    Those loops are not compared (nothing is left to check), where taken as they come the stage,
    which has return-point memory, looked 20x the noise open."""
    case = family_sets.cases_named("pi-u")[0]
    with family_sets.session(case) as s:
        sweeps = family_sets.record(s, tmp_path, reversals=False, separating=True)
    sep = [w for w in sweeps if "separating" in (w.path or w.name)]
    out = closure.check(sep, [s.noise_um])
    assert out["checked"] == 0 and out["unsteady"] >= 5 and out["close"] is None, out
    assert "unlike rates" in out["text"]
    monkeypatch.setattr(closure, "RATE", math.inf)  # every pair compared, whatever its rates
    monkeypatch.setattr(closure, "SLOW_RANGES_PER_S", math.inf)
    loose = closure.check(sep, [s.noise_um])
    assert loose["close"] is False and loose["worst"]["gap_over_noise"] > 10, loose


@pytest.mark.parametrize("family, seed", [("preisach", 4), ("prandtl-ishlinskii", 1)])
def test_fast_passes_at_one_rate_are_not_compared(family: str, seed: int,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """The separating sweep's multisine on independently written stages with a 1400 Hz rod
    damped 0.25 (like an independent tester's, which drew the false warning): at its reversal
    at 79 V both passes move at about 5 V/ms, alike, and the rod's inertia, not the stage's
    memory, leaves them 8-14x the noise apart. Faster than twice the 5.58 Hz triangle's slew,
    they are not compared; taken as they come, the loop is open."""
    rate = 10_000.0
    v, _ = sd.separating_sweep((0.0, 150.0), rate, 5e4)
    stage = fst.random_family_stage(np.random.default_rng(seed), family, resonance_hz=1400.0,
                                    damping=0.25, noise_um=0.03)
    _, reading, _ = fst.run(stage, v, rate, fst.initial_state(stage))
    noisy = reading + np.random.default_rng(seed + 100).normal(0.0, stage.noise_um, v.size)
    sep = [sw.from_arrays(v, noisy, rate, {"layer_thickness_um": "100"}, path="separating.csv")]
    out = closure.check(sep, [stage.noise_um])
    assert out["checked"] == 0 and out["close"] is None and out["unsteady"] == 10, out
    monkeypatch.setattr(closure, "SLOW_RANGES_PER_S", math.inf)
    loose = closure.check(sep, [stage.noise_um])
    assert loose["close"] is False and loose["worst"]["gap_over_noise"] > 7, loose
    assert abs(loose["worst"]["voltage_V"] - 79.3) < 0.1


def test_no_return_to_a_reversal_cannot_tell() -> None:
    """A single ramp up and down never returns to a reversal: nothing to check (None)."""
    v = np.concatenate([np.linspace(0, 150, 500), np.linspace(150, 0, 500)[1:]])
    out = closure.check([sw.from_arrays(v, v * 0.5, RATE_HZ)], [0.01])
    assert out == {**out, "checked": 0, "close": None, "worst": None}


def test_identify_says_when_minor_loops_do_not_close(tmp_path: Path) -> None:
    """``afmctl identify --json`` carries ``minor_loops`` and warns on a Bouc-Wen stage."""
    path = tmp_path / "bw.csv"
    sw.write(minor_loops(1, "bouc-wen"), path)
    prof = tmp_path / "p.toml"
    prof.write_text((PROFILES / "emulated.toml").read_text()
                    + "\n[identify]\nmax_nfev = 2\nrestarts = 0\nn_coercive_fit = 32\n"
                    "representation = \"hem\"\n")  # the fit does not matter here: be quick
    res = CliRunner().invoke(main, ["identify", str(path), "-o", str(tmp_path / "m.toml"),
                                    "--json", "--profile", str(prof)])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["minor_loops"]["close"] is False and doc["minor_loops"]["open"] >= 1
    assert "minor loops do NOT close" in res.stderr
