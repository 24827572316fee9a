"""Benchmark for issue 23 (items 1, 2): the Preisach grid's cost and what identify reaches with it.

Speed, as ratios measured in the same run: the forward model (:func:`afmctl.model.transducer.simulate`)
and Algorithm 3 (:func:`afmctl.model.inverse.algorithm3`, horizon 2) on a 27.9 Hz, 0-150 V triangle
at 10 kHz, for the emulated stage's HEM (its own node count) and for a Preisach grid of the size
identify fits (64 x 48 cells, with creep); ``grid_over_hem_forward`` and ``grid_over_hem_inverse``
are the grid's time over the HEM's. ``creep_columns_speedup``: the creep of a fit's basis
columns computed in place against the basis copied first, and ``creep_groups_speedup``: three
play widths' creep in one pass against a call per width (:func:`creep_columns`).

Accuracy: ``identify`` (default settings) on each sweep set of ``../shared/data/other-family/``
(``--data`` overrides), the per-sweep RMS over the set's sensor noise as the README gives it,
the representation chosen and the wall time: ``other_family_rows``, ``other_family_worst_over_noise``,
``other_family_median_seconds``.

Run from the repo root: ``python -m benchmarks.bench_preisach --json`` (last line: one JSON object).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from afmctl.files import sweepfile as sw
from afmctl.files.profile import default_profile
from afmctl.fit import identify
from afmctl.model import creep as cr
from afmctl.model import inverse as inv
from afmctl.model import preisach as pr
from afmctl.model import transducer as tr
from afmctl.planning import sweepdesign as sd

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "other-family"
#: Sensor noise (1 sigma, um) of each set, from its README.
README_NOISE_UM = {"preisach": 0.0144, "preisach-creep": 0.0289}


def grid_model(hem: tr.Transducer) -> tr.Transducer:
    """A grid of identify's size with a smooth off-centre density, the HEM's rod, and creep."""
    ec = np.linspace(0.0, 0.75, 64)
    ei = np.sort(-np.linspace(-0.14, 1.64, 48))
    w = np.exp(-((ei[None, :] + 0.75 - 0.3 * ec[:, None]) / 0.4) ** 2 - (ec[:, None] / 0.4) ** 2)
    grid = pr.PreisachGrid(tuple(ec), tuple(ei), float(ei[1] - ei[0]),
                           tuple(map(tuple, 0.3 * w / w.sum())), 0.02)
    return tr.Transducer(grid, hem.rod, hem.thickness_um,
                         creep=cr.Creep(cr.DEFAULT_TAUS_S, (0.0075,) * 11))


def best_time(fn, repeats: int = 3) -> float:  # type: ignore[no-untyped-def]
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return min(out)


def speed() -> dict[str, float]:
    hem = default_profile().emulator.model  # type: ignore[union-attr]
    v = sd.loop(27.9, 0.0, 150.0, 10, 10_000.0)
    out: dict[str, float] = {}
    for name, model in (("hem", hem), ("grid", grid_model(hem))):
        cm = tr.compile_model(model, 1e-4)
        st = tr.initial(model)
        u = tr.simulate(cm, v, st)[0]
        tr.simulate(cm, v[:10], st)
        inv.algorithm3(cm, u[1:50], st, horizon=2, e_min=0.0, e_max=1.5)  # compile
        out[f"{name}_forward_us_per_sample"] = 1e6 * best_time(
            lambda cm=cm, st=st: tr.simulate(cm, v, st)) / v.size
        out[f"{name}_inverse_us_per_sample"] = 1e6 * best_time(
            lambda cm=cm, st=st, u=u: inv.algorithm3(cm, u[1:], st, horizon=2, e_min=0.0,
                                                     e_max=1.5)) / v.size
    out["grid_over_hem_forward"] = out["grid_forward_us_per_sample"] / out[
        "hem_forward_us_per_sample"]
    out["grid_over_hem_inverse"] = out["grid_inverse_us_per_sample"] / out[
        "hem_inverse_us_per_sample"]
    out.update(creep_columns())
    return out


def creep_columns(n: int = 100_000, k: int = 384) -> dict[str, float]:
    """The creep of a fit's basis columns at a play's held samples (``n`` samples, ``k``
    columns, three elements: the grid's linearization), :func:`afmctl.model.creep.add_lag_columns`:
    reading the basis where the play holds it (``creep_columns_in_place_s``) against the basis
    copied at the held samples first (``creep_columns_copy_s``, the way before stop 52, with the
    same compiled loop on the copy); and three play widths' groups written in one pass
    (``creep_groups_fused_s``, since stop 59) against a call per width
    (``creep_groups_one_by_one_s``: a pass over the columns per width, as before)."""
    rng = np.random.default_rng(0)
    x = rng.standard_normal((n, k))
    q = np.cumsum(rng.standard_normal(n))
    idx = cr.play_hold(q, 5.0)[1]
    tau, w = np.array([0.01, 0.1, 1.0]), np.array([0.3, 0.2, 0.1])
    every = np.arange(n)
    groups = [cr.Lags(tau[:2], w[:2], cr.play_hold(q, 0.0)[1]), cr.Lags(tau[1:], w[1:], idx),
              cr.Lags(tau[2:], w[2:], cr.play_hold(q, 20.0)[1])]

    def in_place() -> None:
        cr.add_lag_columns(x, [cr.Lags(tau, w, idx)], 1e-4)

    def copied() -> None:
        cr.add_lag_columns(x[idx], [cr.Lags(tau, w, every)], 1e-4)

    def fused() -> None:
        cr.add_lag_columns(x, groups, 1e-4)

    def one_by_one() -> None:
        for g in groups:
            cr.add_lag_columns(x, [g], 1e-4)

    in_place()
    slow, fast = best_time(copied), best_time(in_place)
    apart, together = best_time(one_by_one), best_time(fused)
    return {"creep_columns_copy_s": slow, "creep_columns_in_place_s": fast,
            "creep_columns_speedup": slow / fast, "creep_groups_one_by_one_s": apart,
            "creep_groups_fused_s": together, "creep_groups_speedup": apart / together}


def other_family(root: Path) -> dict[str, object]:
    rows = []
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        data = [sw.read_complete(str(f)) for f in sorted(folder.glob("sweep_*.csv"))]
        noise = README_NOISE_UM.get(folder.name)
        t0 = time.perf_counter()
        res = identify.fit(data)
        seconds = time.perf_counter() - t0
        ratios = [s.rms_um / (noise or s.noise_um) for s in res.sweeps]
        rows.append({"set": folder.name, "representation": res.representation,
                     "rms_over_noise": ratios, "at_floor": max(ratios) <= identify.FLOOR,
                     "heldout_over_noise": res.representations.get("preisach", {}).get(
                         "heldout_over_noise"), "seconds": seconds, "success": res.success})
        print(f"  {folder.name}: {res.representation}, RMS / noise "
              + " / ".join(f"{r:.2f}" for r in ratios) + f" ({seconds:.1f} s)", file=sys.stderr)
    return {"other_family_rows": rows,
            "other_family_worst_over_noise": max(max(r["rms_over_noise"]) for r in rows),
            "other_family_median_seconds": float(np.median([r["seconds"] for r in rows]))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="end with one JSON line (always printed)")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder of sweep sets")
    args = ap.parse_args()
    out: dict[str, object] = dict(speed())
    if args.data.is_dir():
        out.update(other_family(args.data))
    if not args.json:
        for k, v in out.items():
            print(f"{k:36s} {v}")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
