"""The out-of-family plants (issue 23) against their analytic limits: Preisach's wiping-out and
congruency and its closed form for a uniform density, Prandtl-Ishlinskii's closed-form inverse and
initial loading curve, Bouc-Wen's minor loops that do not close, creep's log-time slope, drift's
growth; and the random stages' loops measured on the plant (stroke, hysteresis, convexity)."""

from __future__ import annotations

import numpy as np
import pytest

from afmctl.drivers.device.foreign import families as fm
from afmctl.drivers.device.foreign import family_stage as fs


def _preisach(op: fs.Preisach) -> tuple[np.ndarray, float, float]:
    grid = np.linspace(op.low, 1.0, op.grid)
    return fm.everett_table(op.density, grid), op.low, float(grid[1] - grid[0])


def _output_after(path: list[float], F: np.ndarray, low: float, h: float) -> float:
    stack, n = fm.preisach_start(low, path[0])
    for w in path[1:]:
        stack, n = fm.preisach_step(stack, n, w)
    return fm.preisach_output(F, low, h, stack, n)


@pytest.fixture(scope="module")
def preisach() -> tuple[np.ndarray, float, float]:
    op = fs.random_operator(np.random.default_rng(5), "preisach")
    assert isinstance(op, fs.Preisach) and len(op.lobes) >= 2  # non-separable: a mixture
    return _preisach(op)


def test_preisach_uniform_density_matches_its_closed_form() -> None:
    """mu = 1 on the half-plane triangle: rising from ``low`` to M gives (M - low)^2 / 2, then
    falling to m removes (M - m)^2 / 2."""
    grid = np.linspace(-0.3, 1.0, 131)
    F, low, h = fm.everett_table(lambda a, b: np.ones_like(a), grid), -0.3, float(grid[1] - grid[0])
    assert _output_after([0.0, 0.8], F, low, h) == pytest.approx(1.1 ** 2 / 2, rel=1e-9)
    assert _output_after([0.0, 0.8, 0.25], F, low, h) == pytest.approx(
        1.1 ** 2 / 2 - 0.55 ** 2 / 2, rel=1e-9)


def test_preisach_wipes_out_the_extrema_it_passes(preisach) -> None:
    """Passing a previous maximum erases the loops inside it: the output equals that of the
    history without them, all along the way up."""
    F, low, h = preisach
    for top in (0.75, 0.8, 0.95):
        inner = _output_after([0.0, 0.9, 0.2, 0.7, 0.4, top], F, low, h)
        plain = _output_after([0.0, 0.9, 0.2, top], F, low, h)
        assert inner == pytest.approx(plain, abs=1e-12)
    # but not before the maximum is passed: the inner loop is still remembered
    assert abs(_output_after([0.0, 0.9, 0.2, 0.7, 0.4, 0.65], F, low, h)
               - _output_after([0.0, 0.9, 0.2, 0.65], F, low, h)) > 1e-4


def test_preisach_minor_loops_between_the_same_extrema_are_congruent(preisach) -> None:
    """Two histories ending at the same input, then the same back-and-forth: the loops differ in
    height but their shapes (output minus output at the start) are identical."""
    F, low, h = preisach
    cycle = list(np.linspace(0.3, 0.6, 31)) + list(np.linspace(0.6, 0.3, 31))
    loops = []
    for history in ([0.0, 1.0, 0.3], [0.0, 0.8, 0.1, 0.65, 0.3]):  # both fall to 0.3 from >= 0.6
        stack, n = fm.preisach_start(low, history[0])
        for w in history[1:]:
            stack, n = fm.preisach_step(stack, n, w)
        y = []
        for w in cycle:
            stack, n = fm.preisach_step(stack, n, w)
            y.append(fm.preisach_output(F, low, h, stack, n))
        loops.append(np.array(y))
    assert abs(loops[0][0] - loops[1][0]) > 1e-3  # different places ...
    np.testing.assert_allclose(loops[0] - loops[0][0], loops[1] - loops[1][0], atol=1e-12)
    assert np.ptp(loops[0]) > 1e-3 and loops[0][-1] == pytest.approx(loops[0][0], abs=1e-12)


def test_prandtl_ishlinskii_closed_form_inverse_and_initial_loading_curve() -> None:
    """The PI operator of Kuhnen's inverse weights undoes the operator along a random input; from
    zero play states a rising input follows ``sum p_i max(w - r_i, 0)``."""
    op = fs.random_operator(np.random.default_rng(3), "prandtl-ishlinskii")
    r, p = np.array(op.thresholds), np.array(op.weights)
    p = p.copy()
    p[0] += 0.3  # the linear (r = 0) weight of a stage's PI
    r_inv, p_inv = fm.pi_inverse(r, p)
    rng = np.random.default_rng(0)
    w_path = np.cumsum(rng.normal(0.0, 0.05, 2000))
    z, zi, worst = np.zeros(r.size), np.zeros(r.size), 0.0
    for w in w_path:
        fm.play_step(z, r, w)
        fm.play_step(zi, r_inv, float(p @ z))
        worst = max(worst, abs(float(p_inv @ zi) - w))
    assert worst < 1e-12
    z = np.zeros(r.size)
    for w in np.linspace(0.0, 1.0, 101):
        fm.play_step(z, r, w)
        assert p @ z == pytest.approx(np.sum(p * np.maximum(w - r, 0.0)), abs=1e-12)


def test_bouc_wen_minor_loops_do_not_close() -> None:
    """Cycled between 0.3 and 0.6, Bouc-Wen's output does not return to where the cycle began
    (no closed minor loops, no wiping out); the gap shrinks from cycle to cycle as it settles."""
    z, w = 0.0, 0.0
    for target in (1.0, 0.3):
        z, w = fm.bouc_wen_step(z, w, target, 1.0, 3.0, 0.5, 1.0), target
    starts = [z]
    for _ in range(4):
        z = fm.bouc_wen_step(z, 0.3, 0.6, 1.0, 3.0, 0.5, 1.0)
        z = fm.bouc_wen_step(z, 0.6, 0.3, 1.0, 3.0, 0.5, 1.0)
        starts.append(z)
    gaps = np.abs(np.diff(starts))
    assert gaps[0] > 1e-3 * (1 / 3.5)  # open by more than 0.1 % of the saturation
    assert np.all(np.diff(gaps) < 0)


def _stage(family: str, seed: int = 1, **kw) -> fs.FamilyStage:
    return fs.random_family_stage(np.random.default_rng(seed), family, **kw)


def test_creep_grows_by_its_rate_per_time_decade() -> None:
    """After a step, the position creeps by ``per_decade`` of the step per time decade between
    the operators' shortest and longest time constants (Krejci-Kuhnen, 2 elements per decade:
    within 10 %), and not at all without creep."""
    for creep in (True, False):
        stage = _stage("preisach", 2, creep=creep, resonance_hz=1000.0, damping=0.3,
                       creep_per_decade=0.015)
        state = fs.idle(stage, fs.initial_state(stage), 1e4, 0.0)
        before = fs.run(stage, np.zeros(2), 1e4, state)[0][-1]
        true_um, _, state = fs.run(stage, np.linspace(0, 100.0, 11), 1e4, state)
        after_ms = fs.run(stage, np.full(20, 100.0), 1e4, state)
        step = after_ms[0][-1] - before  # 3 ms after the step: the rod has settled
        at = {}
        t, st = 0.003, after_ms[2]
        for t_next in (0.1, 1.0, 10.0, 100.0):
            st = fs.idle(stage, st, t_next - t, 100.0)
            at[t_next], t = fs.run(stage, np.full(1, 100.0), 1e4, st)[0][0], t_next
        per_decade = np.diff([at[x] for x in (0.1, 1.0, 10.0, 100.0)]) / step
        if creep:
            np.testing.assert_allclose(per_decade, 0.015, rtol=0.1)
        else:
            np.testing.assert_allclose(per_decade, 0.0, atol=1e-9)


def test_drift_grows_without_limit() -> None:
    """At rest, the frame drift moves the position by rate x time, however long the wait."""
    stage = _stage("bouc-wen", 4, drift=True, drift_um_per_s=-0.02)
    state = fs.initial_state(stage)
    x0 = fs.run(stage, np.zeros(1), 1e4, state)[0][0]
    for wait in (10.0, 100.0, 1000.0, 1e5):
        x = fs.run(stage, np.zeros(1), 1e4, fs.idle(stage, state, wait, 0.0))[0][0]
        assert x - x0 == pytest.approx(-0.02 * wait, rel=1e-9)


def test_run_in_pieces_equals_one_run() -> None:
    stage = _stage("prandtl-ishlinskii", 6, creep=True, drift=True)
    v = 75 - 70 * np.cos(np.linspace(0, 6 * np.pi, 3000))
    whole = fs.run(stage, v, 1e4, fs.initial_state(stage))
    a = fs.run(stage, v[:1234], 1e4, fs.initial_state(stage))
    b = fs.run(stage, v[1234:], 1e4, a[2])
    np.testing.assert_allclose(np.concatenate([a[0], b[0]]), whole[0], atol=1e-9)
    np.testing.assert_allclose(np.concatenate([a[1], b[1]]), whole[1], atol=1e-9)


@pytest.mark.parametrize("family", fs.FAMILIES)
@pytest.mark.parametrize("drive", [(0.0, 150.0), (-150.0, 150.0)])
def test_random_stages_have_stage_like_loops(family: str, drive: tuple[float, float]) -> None:
    """Measured on the plant, driven slowly (1 Hz at 2 kHz sampling) for three cycles of the
    drive range: stroke 60-110 um, largest loop width 10-18 % of it, the ascending branch convex
    over the range (its slope over the upper half steeper than over the lower half, as on the
    real actuator of ``shared/data``; a Preisach branch may flatten near the top)."""
    for seed in range(3):
        stage = _stage(family, seed, drive_range_V=drive)
        lo, hi = drive
        n = 1000
        up, down = np.linspace(lo, hi, n), np.linspace(hi, lo, n)
        v = np.concatenate([np.linspace(0, hi, n // 2)] + [down, up] * 3)
        x = fs.run(stage, v, 2000.0, fs.initial_state(stage))[0]
        asc, desc = x[-n:], x[-2 * n:-n][::-1]
        stroke = max(asc.max(), desc.max()) - min(asc.min(), desc.min())
        width = np.max(desc - asc) / stroke
        assert 59.0 <= stroke <= 111.0, (seed, stroke)
        assert 0.095 <= width <= 0.185, (seed, width)
        half = n // 2
        assert asc[-1] - asc[half] > 1.15 * (asc[half] - asc[0]), seed


def test_second_forms_of_the_sensor_causes_act_as_written() -> None:
    """The integrating gauge reads a slow ramp half its window late; the capacitive gap law
    reads ``mid + G d / (G - d)`` of the true position, nothing else."""
    base = _stage("preisach", 8, density="separable")
    v = np.linspace(20.0, 130.0, 4000)
    window = fs.Extras(adc_window_s=0.0008)
    stage = fs.replace(base, extras=window)
    true_um, reading, _ = fs.run(stage, v, 1e4, fs.initial_state(stage))
    pos = reading + stage.zero_um
    mid = slice(1000, 3000)
    slope = np.gradient(true_um, 1e-4)[mid]
    lag_s = np.median((true_um[mid] - pos[mid]) / slope)
    assert lag_s == pytest.approx(0.0004, rel=0.05)
    gap = fs.Extras(gauge_gap_um=-900.0, gauge_mid_um=40.0)
    stage = fs.replace(base, extras=gap)
    true_um, reading, _ = fs.run(stage, v, 1e4, fs.initial_state(stage))
    d = true_um - 40.0
    np.testing.assert_allclose(reading + stage.zero_um, 40.0 + (-900.0) * d / (-900.0 - d),
                               atol=1e-9)
    assert np.max(np.abs(reading + stage.zero_um - true_um)) > 0.5  # a visible nonlinearity
