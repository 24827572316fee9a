"""Issue 2 figures: forward/thermal/inverse speed, discretization convergence, Algorithm 3 tracking.

Run: ``python benchmarks/bench_model.py --json`` (last line: one JSON object). Every ratio is
measured in this one run on this machine against a baseline timed in the same run.
"""

from __future__ import annotations

import argparse
import dataclasses as dc
import json
import sys
import time

import numpy as np
from scipy.signal import sawtooth

from afmctl.files import modelfile
from afmctl.files.profile import default_profile
from afmctl.model import hysteresis as hy
from afmctl.model import inverse as inv
from afmctl.model import rod
from afmctl.model import transducer as tr

DT_S = 1e-4  # 10 kHz, the emulated stage's sample rate


def best_time(fn, repeat: int = 3) -> float:
    """Smallest wall time of ``repeat`` calls (s): the least disturbed measurement."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def worst_field(n: int, seed: int = 0) -> np.ndarray:
    """A field (MV/m) that switches relays at nearly every sample: a steep triangle with jitter."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / n
    return 2.5 * sawtooth(2 * np.pi * 50 * t, 0.5) + rng.normal(0, 0.002, n)


def speed(model: tr.Transducer) -> dict[str, float]:
    grid = dc.replace(model.polarization, n_coercive=64, n_interaction=64, kernel="grid")
    thermal = dc.replace(grid, thermal=hy.Thermal(0.02, 1e3))
    sweep = nested_loops_v(DT_S) / model.thickness_um  # 0.279 Hz nested loops at 10 kHz
    worst = worst_field(sweep.size)
    t_alg1 = best_time(lambda: hy.algorithm1(grid, sweep[::90]), 2) / sweep[::90].size
    k_grid, k_th = hy.build_kernel(grid), hy.build_kernel(thermal)
    s_grid, s_th = hy.initial_state(grid), hy.initial_state(thermal)
    hy.run(k_grid, sweep[:10], s_grid), hy.run(k_th, sweep[:10], s_th, DT_S)  # compile
    t_fast = best_time(lambda: hy.run(k_grid, sweep, s_grid)) / sweep.size
    t_worst = best_time(lambda: hy.run(k_grid, worst, s_grid)) / worst.size
    e_th = sweep[::9]
    t_th = best_time(lambda: hy.run(k_th, e_th, s_th, DT_S)) / e_th.size
    log(f"Algorithm 1 literal {t_alg1 * 1e6:.2f} us/sample; fast grid {t_fast * 1e6:.4f} "
        f"(worst case {t_worst * 1e6:.3f}); thermal {t_th * 1e6:.2f} (N_i = N_j = 64)")
    return {"alg1_samples_per_s": 1 / t_alg1, "forward_samples_per_s": 1 / t_fast,
            "forward_ratio": t_alg1 / t_fast, "forward_ratio_worst_case": t_alg1 / t_worst,
            "thermal_samples_per_s": 1 / t_th, "thermal_ratio": t_th / t_alg1}


def triangle_um(freq_hz: float, amplitude_um: float, periods: float, dt: float) -> np.ndarray:
    """Triangle of peak-to-peak ``amplitude_um`` about 0, rising from 0 at t = 0; samples 1..N."""
    t = np.arange(1, int(round(periods / freq_hz / dt)) + 1) * dt
    return 0.5 * amplitude_um * sawtooth(2 * np.pi * freq_hz * t + np.pi / 2, 0.5)


def tracking(model: tr.Transducer, horizon: int) -> tuple[float, float, float]:
    """Algorithm 3 round trip on the 27.04 um, 27.9 Hz triangle: RMS % (first period out),
    Algorithm 3 cost / forward cost, and the linear filter's RMS %."""
    cm = tr.compile_model(model, DT_S)
    f, amp = 27.9, 27.04
    ud = triangle_um(f, amp, 5, DT_S)
    state = tr.initial(model)
    e_max = 150.0 / model.thickness_um  # the stage's +-150 V
    inv.algorithm3(cm, ud[:50], state, horizon=horizon, e_max=e_max)  # compile
    t_inv = best_time(lambda: inv.algorithm3(cm, ud, state, horizon=horizon, e_max=e_max))
    res = inv.algorithm3(cm, ud, state, horizon=horizon, e_max=e_max)
    v = res.voltage(model.thickness_um)
    t_fwd = best_time(lambda: tr.simulate(cm, v, state))
    u, _, _ = tr.simulate(cm, v, state)
    keep = np.arange(ud.size) >= int(1 / f / DT_S)
    # linear filter: a line through the model's own quasi-static response (0.279 Hz, +-100 V)
    v_slow = 100 * sawtooth(2 * np.pi * 0.279 * np.arange(0, 2 / 0.279, 1e-3), 0.5)
    u_slow, _, _ = tr.simulate(tr.compile_model(model, 1e-3), v_slow, state)
    lin = inv.fit_linear(v_slow, u_slow)
    u_lin, _, _ = tr.simulate(cm, lin.voltage(ud), state)
    return _rms_pair(u, ud, keep, amp), t_inv / t_fwd, _rms_pair(u_lin, ud, keep, amp)


def _rms_pair(u: np.ndarray, ud: np.ndarray, keep: np.ndarray, amp: float) -> float:
    """RMS of ``u[k+1] - ud[k]`` (sample k's field acts on u at k+1) as % of amplitude."""
    err = u[1:] - ud[:-1]
    return float(100 * np.sqrt(np.mean(err[keep[:-1]] ** 2)) / amp)


def nested_loops_v(dt: float) -> np.ndarray:
    """0.279 Hz nested minor loops, 150 -> 30 V amplitude (like the paper's Fig. 1(b))."""
    one = lambda a: a * sawtooth(2 * np.pi * 0.279 * np.arange(0, 1 / 0.279, dt) - np.pi / 2, 0.5)  # noqa: E731
    return np.concatenate([one(a) for a in (150, 120, 90, 60, 30)])


def convergence(model: tr.Transducer, n_ref: int = 16_384) -> tuple[float, dict[str, float]]:
    """RMS (um) between the default discretization and a much finer one on nested loops, and the
    same for N_c = 16 ... 256 (the README's convergence table)."""
    dt = 1e-3
    v = nested_loops_v(dt)

    def sim(n: int) -> np.ndarray:
        mm = dc.replace(model, polarization=dc.replace(model.polarization, n_coercive=n))
        return tr.simulate(tr.compile_model(mm, dt), v, tr.initial(mm))[0]

    n_default = dc.fields(hy.Polarization)[4].default  # the package's default n_coercive
    assert dc.fields(hy.Polarization)[4].name == "n_coercive"
    default = sim(n_default)
    fine = sim(n_ref)
    log(f"convergence: N_c = {n_default} vs {n_ref}, range "
        f"{np.ptp(fine):.1f} um")
    by_n = {str(n): float(np.sqrt(np.mean((sim(n) - fine) ** 2))) for n in (16, 32, 64, 128, 256)}
    return float(np.sqrt(np.mean((default - fine) ** 2))), by_n


def _nominal() -> tr.Transducer:
    emu = default_profile().emulator
    assert emu is not None
    return emu.model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true", help="print the JSON object last")
    ap.add_argument("--model", help="model file (default: the emulated stage's true model)")
    args = ap.parse_args()
    model = modelfile.read(args.model) if args.model else _nominal()
    out: dict[str, float | int] = {"n_i": 64, "n_j": 64}
    out.update(speed(model))
    d = rod.smooth_horizon(rod.discretize(model.rod, DT_S))
    rms3, ratio, rms_lin = tracking(model, d)
    out.update({"alg3_rms_pct": rms3, "inverse_ratio": ratio, "linear_rms_pct": rms_lin,
                "alg3_horizon": d})
    out["convergence_um"], by_n = convergence(model)
    for k, v in out.items():
        log(f"{k:24s} {v:.6g}")
    log("convergence by N_c: " + ", ".join(f"{n} -> {v:.4f} um" for n, v in by_n.items()))
    out["convergence_um_by_n_coercive"] = by_n  # type: ignore[assignment]
    if args.json:
        print(json.dumps(out))


if __name__ == "__main__":
    main()
