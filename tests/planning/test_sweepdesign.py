"""The separating sweep design (issue 12, point 5): every sample within the profile's limits, the
files written and read like the standard ones, each half of the separating sweep holding every
segment kind, and diagnose's held-out machinery exact on holds (on a foreign stage)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl import guard
from afmctl.cli import main
from afmctl.drivers.device.foreign import stage as plant
from afmctl.drivers.device.foreign.stages import random_stage
from afmctl.files import sweepfile as sw
from afmctl.files.profile import default_profile
from afmctl.fit import diagnose as dg
from afmctl.fit import identify as idf
from afmctl.fit import parametrization as pz
from afmctl.planning import sweepdesign as sd

RANGES = [(0.0, 150.0), (-30.0, 150.0), (-150.0, 150.0), (0.0, 20.0)]


@pytest.mark.parametrize("v_range", RANGES, ids=["unipolar", "semi", "bipolar", "narrow"])
@pytest.mark.parametrize("slew_v_per_ms", [50.0, 2.0])
def test_every_sample_passes_the_guard(v_range: tuple[float, float],
                                       slew_v_per_ms: float) -> None:
    limits = guard.Limits(v_range[0], v_range[1], slew_v_per_ms, 100.0, 2.0)
    for name, _, v, meta in sd.design_set("separating", 10_000.0,
                                          limits.max_rate_v_per_ms * 1e3, v_range):
        if name != "separating" and slew_v_per_ms < 10:
            continue  # the paper's triangles have fixed rates (a slow amplifier refuses them)
        guard.check(v, 1e-4, limits, what=name)
        assert meta["design"] == "separating"
    v, segs = sd.separating_sweep(v_range, 10_000.0, limits.max_rate_v_per_ms * 1e3)
    assert v[0] == v[-1] == min(max(0.0, v_range[0]), v_range[1])  # from and to the safe output
    assert v.min() == v_range[0] and v.max() == v_range[1]  # the memory index is reached


def test_each_half_holds_every_segment_and_the_file_says_which() -> None:
    v, segs = sd.separating_sweep((0.0, 150.0), 10_000.0, 5e4)
    half = v.size // 2
    first = {s.kind for s in segs if s.stop <= half}
    second = {s.kind for s in segs if s.start >= half}
    assert first == second == {"ramp", "hold", "step", "multisine"}
    held = [s for s in segs if s.kind == "hold"]
    assert all(np.ptp(v[s.start:s.stop]) == 0 for s in held)
    assert segs[0].start == 1 and segs[-1].stop == v.size
    assert all(a.stop == b.start for a, b in zip(segs, segs[1:], strict=False))
    name, f, v2, meta = sd.design_set("separating", 10_000.0, 5e4, (0.0, 150.0))[-1]
    s = sw.parse(sw.format_text(sw.from_arrays(v2, 0 * v2, 10_000.0,
                                               {**meta, "frequency_hz": f"{f:g}"})))
    kinds = {part.split()[0] for part in s.meta["segments"].split("; ")}
    assert name == "separating" and kinds == {"ramp", "hold", "step", "multisine"}
    np.testing.assert_allclose(s.voltage_v, v2, atol=1e-6)


def test_multisine_tones_are_whole_cycles_within_amplitude_and_slew() -> None:
    v = sd.multisine(10.0, 5.0, 2e4, 0.2, 10_000.0)
    assert np.max(np.abs(v - 10.0)) <= 5.0 and np.max(np.abs(np.diff(v))) * 1e4 <= 2e4
    spec = np.abs(np.fft.rfft(np.concatenate([[10.0], v[:-1]]) - 10.0))
    velocity = spec * np.arange(spec.size)  # equal velocity amplitudes: amplitude x frequency
    lines = np.flatnonzero(velocity > 0.5 * velocity.max())
    assert lines.size == 4 and (lines * 5.0).max() <= 10_000.0 / 20  # 5 Hz bins, up to fs/20
    np.testing.assert_allclose(velocity[lines], velocity[lines].max(), rtol=0.05)


def test_decimation_keeps_holds_so_q_is_exact_over_them() -> None:
    """A hold between two moves the same way is no turning point; the relay model (13) keeps Q
    constant at a constant field, so the decimated Q must be the full-rate one over every hold
    (it ramped across the hold before both ends were kept)."""
    v, segs = sd.separating_sweep((0.0, 150.0), 2_000.0, 5e4)
    e = v / 100.0
    keep = pz.decimation(e, 0.004 * float(e.max()))
    theta = np.array([0.6, 0.5, 0.1, 0.4, 300.0, 0.3])
    q_full = pz.hysteresis(theta, [e], 64, starts=["depoled"])[0]
    q_keep = pz.hysteresis(theta, [e[keep]], 64, starts=["depoled"])[0]
    q = pz.at_full_rate(e.size, keep, q_keep)
    for s in segs:
        if s.kind == "hold":
            np.testing.assert_allclose(q[s.start:s.stop], q_full[s.start:s.stop], atol=1e-12)
    triangle = sd.standard_set(sample_rate_hz=10_000.0, v_range=(0.0, 150.0))[2][2] / 100.0
    travel = np.concatenate(([0.0], np.cumsum(np.abs(np.diff(triangle)))))
    step = 0.004 * float(triangle.max())
    old = np.unique(np.concatenate((np.flatnonzero(np.diff(np.floor(travel / step)) > 0) + 1,
                                    pz.turning_points(triangle))))
    np.testing.assert_array_equal(pz.decimation(triangle, step), old)  # triangles: unchanged


def foreign_separating_set() -> list[sw.Sweep]:
    """A 27.9 Hz triangle and the separating sweep, recorded in sequence on a clean foreign stage."""
    rng = np.random.default_rng(5)
    stage = random_stage(rng, drive_range_V=(0.0, 150.0))
    state, out = plant.initial_state(stage, "depoled"), []
    rate = default_profile().limits.max_rate_v_per_ms * 1e3
    for name, f, v, meta in sd.design_set("separating", 10_000.0, rate, (0.0, 150.0)):
        if name in ("triangle_27.9hz", "separating"):
            _, reading, state = plant.run(stage, v, 10_000.0, state, rng)
            out.append(sw.from_arrays(v, reading, 10_000.0, {
                **meta, "frequency_hz": f"{f:g}",
                "layer_thickness_um": f"{stage.material.layer_thickness_um:g}"}, name))
    return out


@pytest.mark.slow
def test_diagnose_reads_a_separating_set(tmp_path: Path) -> None:
    """Written and read back as files, the set splits into fitted and judged halves; the paper's
    model, fitted on the first halves, predicts the second halves (holds, steps, multisine) of
    a clean foreign stage near the sensor noise."""
    for s in foreign_separating_set():
        sw.write(s, tmp_path / f"{s.path}.csv")
    sweeps = [sw.read_complete(tmp_path / f"{n}.csv") for n in ("triangle_27.9hz", "separating")]
    dg.check(sweeps)
    fast = idf.Settings(restarts=0, density="parametric")
    d = dg.diagnose(sweeps, dg.Settings(identify=fast, candidates=("none",), jobs=1))
    assert d.cause in ("none", "unexplained") and set(d.table) == {"none"}
    assert d.base_over_noise < 1.5, d.evidence()


def test_cli_sweep_separating_design_writes_the_extra_sweep(tmp_path: Path) -> None:
    out = tmp_path / "s"
    res = CliRunner().invoke(main, ["sweep", "--out", str(out), "--design", "separating",
                                    "--only", "separating"])
    assert res.exit_code == 0, res.output
    s = sw.read_complete(out / "separating.csv")
    prof = default_profile()
    guard.check(s.voltage_v, s.dt, prof.limits)
    assert s.meta["design"] == "separating" and "multisine" in s.meta["segments"]
    bad = CliRunner().invoke(main, ["sweep", "--out", str(tmp_path / "t"), "--only",
                                    "separating"])
    assert bad.exit_code == 2 and "not in the standard set" in bad.output
    assert not (tmp_path / "t").exists()


def test_standard_design_is_todays_set() -> None:
    ours = sd.design_set("standard", 10_000.0, 5e4, (-150.0, 150.0))
    today = sd.standard_set(sample_rate_hz=10_000.0, v_range=(-150.0, 150.0))
    assert [(n, f) for n, f, _, _ in ours] == [(n, f) for n, f, _ in today]
    for (_, _, a, _), (_, _, b) in zip(ours, today, strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="unknown sweep design"):
        sd.design_set("chirp", 10_000.0, 5e4, (0.0, 1.0))


def test_cli_offers_every_design() -> None:
    """``afmctl sweep --design`` lists its choices literally (the CLI imports no numerics at
    start-up); they must be :data:`afmctl.planning.sweepdesign.DESIGNS`."""
    from afmctl.cli.sweep import sweep
    option = next(p for p in sweep.params if p.name == "design")
    assert tuple(option.type.choices) == sd.DESIGNS


def test_triangle_and_standard_set() -> None:
    v = sd.voltage_triangle(27.9, 150.0, 10, 10_000.0)
    assert v[0] == 0 and v.max() == pytest.approx(150.0, rel=1e-3)
    assert v.min() == pytest.approx(-150.0, rel=1e-3)
    sets = sd.standard_set(150.0, 1000.0)
    assert [f for _, f, _ in sets] == [0.279, 5.58, 27.9, 0.1]
    loops = sets[3][2]
    assert loops.max() == pytest.approx(150.0) and loops[-1] == 0.0


@pytest.mark.parametrize("v_range", [(-150.0, 150.0), (0.0, 150.0), (-30.0, 150.0)])
def test_every_sweep_ends_exactly_where_it_started(v_range: tuple[float, float]) -> None:
    """Issue 27 item 16: the 27.9 Hz sweep ended one sample short of 0 V (-0.384 V) and the next
    track planned from there; every sweep of every design ends at its start (0 V here)."""
    for name, _, v, _ in sd.design_set("full", 10_000.0, 5e4, v_range):
        assert v[0] == 0.0 and v[-1] == 0.0, (name, v[-1])
        assert np.abs(np.diff(v)).max() <= 5.0, name  # no step: within 50 V/ms at 10 kHz


@pytest.mark.parametrize("v_range", [(0.0, 150.0), (-150.0, 150.0)])
def test_full_design_is_the_separating_and_the_reversals_designs(
        v_range: tuple[float, float]) -> None:
    """A lab's first calibration (the guide's step 4) records both extra sweeps: the separating
    sweep for diagnose and the reversal curves for the Preisach grid's interior."""
    full = sd.design_set("full", 10_000.0, 5e4, v_range)
    parts = sd.design_set("separating", 10_000.0, 5e4, v_range) + \
        sd.design_set("reversals", 10_000.0, 5e4, v_range)[-1:]
    assert [(n, f) for n, f, _, _ in full] == [(n, f) for n, f, _, _ in parts]
    for (_, _, a, meta), (_, _, b, theirs) in zip(full, parts, strict=True):
        np.testing.assert_array_equal(a, b)
        assert meta == {**theirs, "design": "full"}


@pytest.mark.parametrize("v_range", [(0.0, 150.0), (-30.0, 150.0), (-150.0, 150.0)])
def test_reversals_design_adds_first_order_reversal_curves(v_range: tuple[float, float]) -> None:
    """The standard set and one sweep from each end of the range to 7 voltages evenly inside it
    and back, then the interior loops, at the 5.58 Hz triangle's slew (or half the amplifier's,
    if slower), starting and ending at the safe output."""
    rate, max_rate = 10_000.0, 1.5e3
    out = sd.design_set("reversals", rate, max_rate, v_range)
    assert [n for n, _, _, _ in out][:4] == [n for n, _, _ in sd.standard_set(
        sample_rate_hz=rate, v_range=v_range)]
    name, _, v, meta = out[-1]
    lo, hi = v_range
    v0 = min(max(0.0, lo), hi)
    assert name == "reversals" and meta["design"] == "reversals"
    assert v[0] == v0 and v[-1] == v0 and v.min() == lo and v.max() == hi
    assert np.max(np.abs(np.diff(v))) * rate <= sd.SLEW_USE * max_rate * (1 + 1e-9)
    curves = sd.reversal_curves(v_range, rate, sd.SLEW_USE * max_rate)
    np.testing.assert_array_equal(v[:curves.size], curves)
    np.testing.assert_array_equal(v[curves.size - 1:],
                                  sd.interior_loops(v_range, rate, sd.SLEW_USE * max_rate))
    d = np.sign(np.diff(curves))
    turns = curves[1:-1][d[1:] != d[:-1]]
    inner = lo + (hi - lo) * np.arange(1, 8) / 8
    for u in inner:  # each level reversed at twice: coming up from v_lo and down from v_hi
        assert np.sum(np.isclose(turns, u)) == 2


@pytest.mark.parametrize("v_range", [(0.0, 150.0), (-30.0, 150.0), (-150.0, 150.0)])
def test_interior_loops_turn_above_and_below_each_centre_ever_closer(
        v_range: tuple[float, float]) -> None:
    """From and back to the safe output at the given slew; every node a turn, 7 about each
    centre (0.5, 0.3, 0.7 of the range), on alternate sides, each nearer the centre than the
    last; all but the first of each centre strictly inside the range."""
    lo, hi = v_range
    v0 = min(max(0.0, lo), hi)
    v = sd.interior_loops(v_range, 1000.0, 3000.0)
    assert v[0] == v0 and v[-1] == v0
    assert np.max(np.abs(np.diff(v))) <= 3.0 * (1 + 1e-9)
    d = np.sign(np.diff(v))
    turns = v[1:-1][d[1:] != d[:-1]]
    assert turns.size == 3 * sd.INTERIOR_REVERSALS
    for g, (centre, _) in enumerate(sd.INTERIOR_CENTRES):
        off = (turns[7 * g:7 * (g + 1)] - lo) / (hi - lo) - centre
        assert np.all(np.diff(np.sign(off)) != 0)  # alternate sides
        assert np.all(np.diff(np.abs(off)) < 0)  # ever closer
        assert np.all((turns[7 * g + 1:7 * (g + 1)] > lo) & (turns[7 * g + 1:7 * (g + 1)] < hi))
