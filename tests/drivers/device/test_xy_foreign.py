"""The foreign x/y stage (drivers/device/foreign/xy_*.py) against its analytic limits.

With linear actuators (hysteresis off) the stage is a linear structure followed by a quadratic
output map, so a sine's fundamental in y over its fundamental in x is exactly the small-signal
coupling about the sine's centre: the simulated ratio must match :func:`true_coupling`, and the
static ratio the closed form of the three-degree-of-freedom statics derived by hand below.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from afmctl.drivers.device.foreign import xy_actuator as xa
from afmctl.drivers.device.foreign import xy_stage as xs
from afmctl.drivers.device.foreign import xy_sweeps as xw
from afmctl.files import sweepfile

RATE = 10000.0


@pytest.fixture(scope="module")
def stages() -> list[xs.XYStage]:
    return xs.xy_stages()


def mid_voltages(stage: xs.XYStage) -> np.ndarray:
    return np.array([0.5 * sum(r) for r in stage.drive_range_V])


def sine_response(stage: xs.XYStage, source: int, freq_hz: float, amp_V: float = 3.0,
                  rate: float = RATE) -> tuple[np.ndarray, np.ndarray, float]:
    """A sine on ``source`` about mid-range (the other axis held there), after 1.5 s of settling
    (ten time constants of the slowest mode and more): ``(t, true_um, f)`` over whole periods
    of the frequency ``f`` (``freq_hz`` rounded to fit them)."""
    mid = mid_voltages(stage)
    state = xs.idle(stage, xs.initial_state(stage), mid)
    periods = max(2, round(0.5 * freq_hz))
    n_settle, n = int(1.5 * rate), int(round(periods * rate / freq_hz))
    freq_hz = periods * rate / n
    t = np.arange(n_settle + n) / rate
    v = np.tile(mid, (t.size, 1))
    v[:, source] += amp_V * np.sin(2 * math.pi * freq_hz * t)
    true_um, _, _ = xs.run(stage, v, rate, state)
    return t[n_settle:], true_um[n_settle:], freq_hz


def harmonic(t: np.ndarray, u: np.ndarray, freq_hz: float) -> complex:
    return complex(u @ np.exp(-2j * math.pi * freq_hz * t))


def sine_ratio(stage: xs.XYStage, source: int, freq_hz: float, amp_V: float = 3.0,
               rate: float = RATE) -> tuple[complex, float]:
    """Fundamental of the other axis over the source's (:func:`sine_response`), and ``f``."""
    t, u, f = sine_response(stage, source, freq_hz, amp_V, rate)
    return harmonic(t, u[:, 1 - source], f) / harmonic(t, u[:, source], f), f


@pytest.mark.parametrize("index", [0, 1, 3])
def test_sine_coupling_without_hysteresis_is_the_true_frf(stages, index) -> None:
    """Simulated sines at 3 Hz ... 1.3 x the shared mode, each direction: the ratio of the
    fundamentals agrees with true_coupling (continuous time) to 1e-4 at 40 kHz. The sampled
    plant differs from it only by the zero-order hold's aliases, which fall as the fourth power
    of the rate (measured on stage 2 at 1.3 x its 800 Hz mode: 7e-3 at 10 kHz, 3e-5 at 40 kHz;
    at 0.2 x the mode 2e-5 at 10 kHz)."""
    stage = xs.without_hysteresis(stages[index])
    mode = xs.mode_hz(stage.structure)
    for source, key in ((0, "yx_frf"), (1, "xy_frf")):
        for f in (3.0, 0.2 * mode, 0.5 * mode, mode, 1.3 * mode):
            got, f_exact = sine_ratio(stage, source, f, rate=40000.0)
            want = xs.true_coupling(stage, np.array([f_exact]))[key][0]
            assert abs(got / want - 1) < 1e-4, (source, f, got, want)


def hand_static(stage: xs.XYStage) -> tuple[float, float]:
    """The statics of K q = B d solved by hand (mass-normalized):
    theta = (e_s - k_s w_s / w_t) / (1 - kx^2 - ky^2), source q = 1 - k_s (w_t / w_s) theta,
    other q = -k_o (w_t / w_o) theta; then the linearized sensed positions."""
    s = stage.structure
    w = [2 * math.pi * f for f in s.axis_hz]
    wt = 2 * math.pi * s.shared_hz
    kap, eps, arm = s.stiffness_coupling, s.force_arm, s.sensor_arm
    q0 = xs.operating_point(stage)
    slope = (stage.flexures[0].misalignment + stage.flexures[0].arc_sign * 1.2
             * (q0[0] - stage.flexures[0].neutral_um) / stage.flexures[0].length_um,
             stage.flexures[1].misalignment + stage.flexures[1].arc_sign * 1.2
             * (q0[1] - stage.flexures[1].neutral_um) / stage.flexures[1].length_um)
    out = []
    for src in (0, 1):
        oth = 1 - src
        theta = (eps[src] - kap[src] * w[src] / wt) / (1 - kap[0] ** 2 - kap[1] ** 2)
        q_src = 1 - kap[src] * wt / w[src] * theta
        q_oth = -kap[oth] * wt / w[oth] * theta
        # slope[0] = d y / d x_p (x's guide), slope[1] = d x / d y_p
        tgt = q_oth + arm[oth] * theta + slope[src] * q_src
        own = q_src + arm[src] * theta + slope[oth] * q_oth
        out.append(tgt / own)
    return out[0], out[1]


def test_static_coupling_dc_limit(stages) -> None:
    """At DC: true_coupling's statics equal the closed form, the drawn dB, and (hysteresis off)
    the ratio of rest positions at mid +- 10 V (symmetric: the arc's curvature cancels)."""
    for stage, (_, c_db, _) in zip(stages, xs.BENCH_SPECS, strict=True):
        truth = xs.true_coupling(stage, np.zeros(0))
        yx, xy = hand_static(stage)
        assert truth["yx_static"] == pytest.approx(yx, rel=1e-9)
        assert truth["xy_static"] == pytest.approx(xy, rel=1e-9)
        assert xs.db(yx) == pytest.approx(c_db, abs=1e-6)
        assert -45.0 - 1e-9 <= xs.db(xy) <= -25.0 + 1e-9
        lin = xs.without_hysteresis(stage)
        mid = mid_voltages(lin)
        for src, key in ((0, "yx_static"), (1, "xy_static")):
            step = np.zeros(2)
            step[src] = 10.0
            state = xs.initial_state(lin)
            lo = xs.position_um(lin, xs.idle(lin, state, mid - step).mechanics[None, :3])[0]
            hi = xs.position_um(lin, xs.idle(lin, state, mid + step).mechanics[None, :3])[0]
            dp = hi - lo
            assert dp[1 - src] / dp[src] == pytest.approx(truth[key], rel=1e-9)


@pytest.mark.parametrize("index", [0, 1])
def test_hysteresis_does_not_enter_the_ratio(index) -> None:
    """The hysteretic actuators (all four kinds over stages 1 and 2), straight flexure beams (no
    arc: the output map is then linear and the ratio holds about any centre): a 30 V sine at 0.2 x
    the shared mode, whose source response carries the loop's harmonics (third: 0.1-3 % of the
    fundamental), gives true_coupling's ratio to 1e-5 (measured: 2e-7 at worst over the eight
    stages, at 40 kHz)."""
    stage = xs.xy_stages()[index]
    stage = replace(stage, flexures=tuple(replace(f, length_um=math.inf)
                                          for f in stage.flexures))
    f = 0.2 * xs.mode_hz(stage.structure)
    for src, key in ((0, "yx_frf"), (1, "xy_frf")):
        t, u, f_exact = sine_response(stage, src, f, amp_V=30.0, rate=40000.0)
        first = harmonic(t, u[:, src], f_exact)
        third = harmonic(t, u[:, src], 3 * f_exact)
        assert abs(third / first) > 5e-4  # the loop shows
        got = harmonic(t, u[:, 1 - src], f_exact) / first
        want = xs.true_coupling(stage, np.array([f_exact]))[key][0]
        assert abs(got / want - 1) < 1e-5


def test_blocks_stream_like_one_call(stages) -> None:
    """Every actuator kind, the mechanics: blocks of odd sizes give bit-identical outputs."""
    kinds = set()
    rng = np.random.default_rng(5)
    for stage in stages[:2]:
        kinds |= {a.kind for a in stage.actuators}
        n = 6000
        (xlo, xhi), (ylo, yhi) = stage.drive_range_V
        v = np.column_stack([rng.uniform(xlo, xhi) + np.cumsum(rng.normal(0, 2.0, n)),
                             np.linspace(ylo, yhi, n)])
        state = xs.initial_state(stage)
        whole_true, whole_read, end = xs.run(stage, v, RATE, state)
        parts, st, k = [], state, 0
        for size in (1, 7, 500, 1333, 4159):
            t, r, st = xs.run(stage, v[k:k + size], RATE, st)
            parts.append(np.hstack([t, r]))
            k += size
        np.testing.assert_array_equal(np.vstack(parts), np.hstack([whole_true, whole_read]))
        np.testing.assert_array_equal(st.mechanics, end.mechanics)
        assert whole_true.shape == (n, 2) and np.all(np.isfinite(whole_true))
    assert kinds == set(xa.KINDS)


def test_drawn_stages_are_stage_like(stages) -> None:
    """Spans 60-110 um, loop widths 10-18 %, the shared mode where asked, two kinds per stage,
    unipolar and bipolar, noise (2,), describe JSON-able."""
    for stage, (unipolar, _, mode) in zip(stages, xs.BENCH_SPECS, strict=True):
        d = xs.describe(stage)
        json.dumps(d)
        assert d["derived"]["mode_hz"] == pytest.approx(mode, rel=1e-6)
        for span in d["derived"]["static_span_um"]:
            assert 60.0 <= span <= 110.0
        for ax in "xy":
            assert 0.10 <= d["actuators"][ax]["loop_width"] <= 0.18 + 1e-3
        assert stage.actuators[0].kind != stage.actuators[1].kind
        assert stage.drive_range_V[0] == (xs.UNIPOLAR_V if unipolar else xs.BIPOLAR_V)
        assert xs.noise_um(stage).shape == (2,)
        assert min(d["derived"]["natural_hz"]) == pytest.approx(mode, rel=1e-6)


def test_random_stages_draw_within_the_issue_ranges() -> None:
    """Undirected draws: static couplings -45 .. -25 dB both ways, the shared mode 150 .. 800 Hz
    and the lowest, the range asked for."""
    for seed, unipolar in ((11, True), (12, False), (13, True)):
        stage = xs.random_xy_stage(np.random.default_rng(seed), unipolar=unipolar)
        d = xs.describe(stage)["derived"]
        for key in ("yx_static_db", "xy_static_db"):
            assert -45.0 - 1e-9 <= d[key] <= -25.0 + 1e-9
        assert 150.0 <= d["mode_hz"] <= 800.0 and d["mode_hz"] == min(d["natural_hz"])
        assert stage.drive_range_V[1] == (xs.UNIPOLAR_V if unipolar else xs.BIPOLAR_V)


def test_designs_keep_range_and_slew(stages) -> None:
    """Every file of every design within each axis's range, at most 50 V/ms at 10 kHz, one axis
    held (as its metadata says) or both moving, the excitation reaching half the shared mode."""
    for stage in stages:
        plans = xw.design_plans(stage, "mixed")
        assert [p.name for p in xw.design_plans(stage, "held")] == [p.name for p in plans[:-1]]
        assert len({p.name for p in plans}) == len(plans)
        for p in plans:
            v = p.voltage_V
            for ax, (lo, hi) in enumerate(stage.drive_range_V):
                assert lo <= v[:, ax].min() and v[:, ax].max() <= hi
            assert np.max(np.abs(np.diff(v, axis=0))) * RATE / 1000 <= xw.SLEW_V_PER_MS
            for ax, name in enumerate("xy"):
                held = p.meta.get(f"held_voltage_{name}_V")
                if held is not None:
                    assert np.all(v[:, ax] == float(held))
                    assert p.meta["swept_axis"] == "xy"[1 - ax]
            if "band_hz" in p.meta:
                assert float(p.meta["band_hz"]) == pytest.approx(
                    0.5 * xs.mode_hz(stage.structure), rel=1e-3)


def test_written_set_parses_and_is_noisy_truth(stages, tmp_path) -> None:
    """Files carry the two-axis header; each axis's columns, renamed to today's one-axis names,
    read with afmctl.files.sweepfile (its metadata conventions: frequency_hz, sample_rate_hz,
    layer_thickness_um); readings are the noise-free run plus each axis's noise."""
    stage = stages[0]
    paths = xw.write_sweep_set(stage, tmp_path, np.random.default_rng(0), design="mixed")
    assert [p.name for p in paths] == [f"{p.name}.csv" for p in xw.design_plans(stage)]
    plans = xw.design_plans(stage)
    read = {}
    for path, plan in zip(paths, plans, strict=True):
        text = path.read_text()
        header = next(ln for ln in text.splitlines() if not ln.startswith("#"))
        assert header == ",".join(xw.COLUMNS)
        for ax in "xy":
            one = text.replace(header, "time_s,volt_other,voltage_V,disp_other,displacement_um"
                               if ax == "y" else
                               "time_s,voltage_V,volt_other,displacement_um,disp_other")
            sweep = sweepfile.parse(one, str(path))
            assert sweep.dt == pytest.approx(1 / RATE)
            assert sweep.thickness_um == 100.0
            np.testing.assert_allclose(sweep.voltage_v, plan.voltage_V[:, "xy".index(ax)],
                                       atol=1e-4)
            assert dict(sweep.meta) == plan.meta
            read[path.name, ax] = sweep.displacement_um
    clean = xw.record(stage, plans, None)
    resid = np.vstack([np.column_stack([read[path.name, ax] for ax in "xy"]) - c
                       for path, c in zip(paths, clean, strict=True)])
    np.testing.assert_allclose(resid.mean(axis=0), 0.0, atol=1e-4)
    np.testing.assert_allclose(resid.std(axis=0), xs.noise_um(stage), rtol=0.02)
