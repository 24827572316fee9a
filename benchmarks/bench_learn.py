"""Issue 13 figures: learning from repeated scans (iterative learning control on the inverse).

Stages: the shipped emulated stage, and that stage carrying one hidden effect of ``afmctl
diagnose``'s catalogue each (:func:`afmctl.drivers.device.plant.with_hidden_effect`, case ``2 i`` of the
seeded diagnose batch: the first of each cause; true parameters printed). On each, the three
standard triangles are recorded through the driver interface (device clock 4x real time) and the
model is identified from them (:func:`afmctl.fit.identify.fit`, never the stage's true parameters);
for the sensor effects (delay, gauge) ``diagnose`` runs on the same sweeps and learning uses its
extended model (readings cannot tell where the stage is without it). Then ``learn.run`` plays the
27.9 Hz / 27.04 um triangle (3 periods) and up to 5 learning iterations.

The stage with run-to-run gain variation (8 iterations) is judged against its variation's floor
(``variation_floor_um``: the true error a perfect waveform still makes under the gain spread) by
each iteration's expected error over the spread (``expected_rms_um_by_iteration``), and learning
is run again past the floor (its stop off) to show it does not diverge there. For the sensor
effects learning on diagnose's base model is run too (``base_model_rms_um_by_iteration``).

Judged by the stage's **true position**: the emulator's own state (the applied voltage it
recorded, run through its true plant, no sensor effects, no noise), at the samples, first period
excluded. ``noise_um`` is the stage's sensor noise (1 sigma). ``seconds_per_iteration_compute``
is the host's work per iteration (correction, Algorithm 3, guard, judging at the samples) on the
default stage, ``compute_over_stage`` its ratio to the time the stage takes to play the iteration
(conditioning included).

Foreign stages (``--foreign``): the independently written plant of
:mod:`afmctl.drivers.device.foreign.stage` (a random stage, 0 .. 150 V, ``[emulator.foreign]`` of the shipped
``emulated-foreign`` profile) clean and with each hidden effect at strength 0.5, served over the
serial protocol on a pty; its standard triangles recorded through the driver and the model from
``afmctl identify`` on them, or ``afmctl diagnose``'s extended model for the sensor effects;
judged by its true position in the lab's calibration frame (:mod:`foreign_learn`).

Out-of-family stages (issue 23, ``benchmarks/family_sets.py``; ``--family-only`` runs this part
alone): on each, the model identify gives on its standard triangles (``--family-cache DIR``:
bench_identify's fits) and ``learn.run`` on a 27.9 Hz triangle (27.04 um, or 60 % of the fast
sweep's span if less, about its middle), 5 iterations, judged by the stage's true position;
then the kept waveform is replayed after 60 s of device time (creep and drift go on), and
re-learned from there for up to 2 iterations (``learn.run`` resumed from the kept iteration:
the replay measures how far the stage has moved). ``family_learn_ok`` counts the stages within
2x the noise, ``family_replay_ok`` those whose replay is within 2x again after at most 2
re-learning iterations, ``family_replay_raw_ok`` those whose replay as it was already is.
``family_replay_moved_ok`` counts those within 2x whose replay, on the same stage learned again
in a session of its own, is played as ``afmctl play --model`` plays a learned waveform
(:func:`afmctl.experiment.replay.moved_replay`: the conditioning first, the rest moved for how
far its last 0.1 s says the stage has moved; one run, no re-learning).

Run: ``python benchmarks/bench_learn.py --json`` (last line one JSON object); ``--stage
sensor-nonlinearity`` (any name of ``--stages``, or ``foreign:<effect>``, or ``foreign:earlier``)
for one stage alone (the same row as in the whole bench; no seed comparison, no 100 Hz run).
"""

from __future__ import annotations

import argparse
import dataclasses as dc
import json
import sys
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from afmctl.drivers.device import plant as em
from afmctl.drivers.inprocess import InProcessStage, accelerated
from afmctl.errors import LimitError, StageError
from afmctl.experiment import calibration, learn
from afmctl.files.profile import Profile, default_profile
from afmctl.fit import diagnose as dg
from afmctl.fit import identify
from afmctl.model import effects as fx
from afmctl.model import transducer as tr
from afmctl.planning import ilc, track

if __package__:  # python -m benchmarks.<name>, or imported by the tests
    from benchmarks import family_sets, foreign_learn, learn_judge
else:  # python benchmarks/<name>.py: Python puts this folder on the path
    import family_sets
    import foreign_learn
    import learn_judge

SPEED = 2.0  # device clock / real time (4 underran the sweep streams on a loaded host)
FREQ_HZ, AMP_UM = 27.9, 27.04
SENSOR = {"sensor-delay", "sensor-nonlinearity"}
#: Q cut-off at which learning through the linear filter meets the convergence condition (the
#: rod's phase lag, which the line does not invert, passes 60 degrees at ~216 Hz).
LINEAR_Q_HZ = 150.0
SEED_ITERATIONS = 15
FOREIGN_SEED = 1
#: One stage per cause of diagnose's catalogue, in the order the bench has always run them.
CAUSES = ("thermal-relaxation", "amplifier-lag", "second-mode", "voltage-gain-drift",
          "sensor-delay", "sensor-nonlinearity")


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


class TruthProbe:
    """A stage that also records the emulated device's true position of every run it plays."""

    def __init__(self, stage: InProcessStage) -> None:
        self.stage = stage
        self.positions: list[np.ndarray] = []
        self.gains: list[float] = []  # each run's applied-voltage gain (the emulator's draw)

    def voltage(self) -> float:
        return self.stage.voltage()

    def play(self, waveform_v: np.ndarray, on_block: Any = None, **kw: Any) -> Any:
        dev = self.stage.emulator
        before = dev.state
        self.gains.append(dev.physics.gain(dev.run_count))
        rec = self.stage.play(waveform_v, on_block, **kw)
        n = len(waveform_v)
        applied = dev.rec_v[np.arange(n) % dev.rec_v.size].astype(float)  # gain and lag applied
        u, _, _ = tr.simulate(dev.physics.compiled, applied, before.stage)
        self.positions.append(fx.add_mode(dev.physics.chain, u, before.mode_zi)[0])
        return rec


def model_for(profile: Profile, cause: str, folder: Path
              ) -> tuple[tr.Transducer, str, tr.Transducer | None, Any]:
    """The model learning uses (identify's; diagnose's extended one for a sensor effect), its
    source, for a sensor effect diagnose's base model (what learning would have without), and
    the first sweep recorded (from power-on: the slowest triangle)."""
    with InProcessStage(profile, clock=accelerated(SPEED)) as stage:
        sweeps = calibration.record_standard(stage, profile, folder)
    slowest = sweeps[0]
    if cause in SENSOR:
        d = dg.diagnose(sweeps)
        return d.extended_model, f"diagnose extended ({d.cause})", d.base_model, slowest
    fit = identify.fit(sweeps)
    return (fit.model, "identify" + ("" if fit.success else " (fit did not converge)"), None,
            slowest)


def calibration_frame(profile: Profile, slowest: Any) -> Any:
    """The true position as a lab's linear calibration of the gauge reports it (for a gauge
    nonlinearity): ``a + b x`` with ``reading = a + b x`` the least-squares line over the true
    positions ``x`` of the slowest recorded sweep (``slowest``, from power-on, noise-free),
    the frame bench_diagnose's track judge uses too. A gauge's offset and gain are a convention
    (no reading tells them from the rod's gain and offset); its curvature is not. Diagnose's
    extended model states positions in this frame (:func:`afmctl.model.effects.position_frame`, over
    the readings of that sweep). Identity without a gauge error."""
    assert profile.emulator is not None
    e = profile.emulator.effects
    if not (e.sensor_quadratic_per_um or e.sensor_cubic_per_um2):
        return lambda u: u
    ph = em.Physics(dc.replace(profile.emulator, effects=fx.Effects()), profile.sample_rate_hz)
    x = ph.respond(slowest.voltage_v, ph.initial())[0]
    return foreign_learn.calibration_frame(x, fx.gauge(e, x))


def learn_on(profile: Profile, model: tr.Transducer, desired: track.Desired, out: Path,
             iterations: int, law: ilc.Law, seed: str = "inverse", frame: Any = None
             ) -> tuple[learn.Result, list[float], list[float]]:
    """Learning's result, the true RMS error of each iteration (in ``frame``, if given) and each
    run's true gain."""
    assert profile.emulator is not None
    with InProcessStage(profile, clock=accelerated(SPEED)) as stage:
        probe = TruthProbe(stage)
        res = learn.run(probe, model, desired, profile.limits, out, {}, iterations, law,
                        profile.emulator.true_model, seed)  # type: ignore[arg-type]
    rms = [learn_judge.true_rms(p if frame is None else frame(p), it, desired)
           for p, it in zip(probe.positions, res.iterations, strict=False)]
    return res, rms, probe.gains


def respond_for(profile: Profile) -> learn_judge.Respond:
    """The stage's true position (um) for a run from power-on at an applied-voltage gain, without
    the gain effect's own draw (:func:`learn_judge.gain_spread` sets the gain)."""
    assert profile.emulator is not None
    ph = em.Physics(dc.replace(profile.emulator, effects=fx.Effects()), profile.sample_rate_hz)
    return lambda v, g: ph.respond(g * v, ph.initial())[0]


def describe(profile: Profile) -> str:
    assert profile.emulator is not None
    e, pol = profile.emulator.effects, profile.emulator.model.polarization
    parts = [f"{k}={v}" for k, v in dc.asdict(e).items() if v not in (None, 0.0)]
    if pol.thermal is not None:
        parts.append(f"thermal={pol.thermal}")
    return ", ".join(parts) or "none"


def stage_row(base: Profile, cause: str, index: int, tmp: Path) -> dict[str, Any]:
    prof = base if cause == "none" else em.with_hidden_effect(base, cause, index)
    assert prof.emulator is not None
    t0 = time.perf_counter()
    model, source, base_model, slowest = model_for(prof, cause, tmp / f"{cause}-sweeps")
    desired = track.triangle(FREQ_HZ, AMP_UM, 0.0, 3, 1 / prof.sample_rate_hz)
    n = learn_judge.GAIN_ITERATIONS if cause == "voltage-gain-drift" else 5
    frame = calibration_frame(prof, slowest)
    res, rms, gains = learn_on(prof, model, desired, tmp / cause, n, ilc.Law(), frame=frame)
    noise = prof.emulator.noise_um
    final = rms[res.best]
    row: dict[str, Any] = {
        "effect": cause, "truth": describe(prof), "model": source, "noise_um": noise,
        "rms_um_by_iteration": rms,
        "rms_between_um_by_iteration": [it.outcome.score.rms_between_um
                                        for it in res.iterations],
        "readings_rms_um_by_iteration": [it.steady_um for it in res.iterations],
        "kept_iteration": res.best, "stop": res.stop, "lead_samples": res.lead,
        "true_position_frame": ("the gauge's linear calibration on the slowest sweep"
                                if cause == "sensor-nonlinearity" else "the stage's own"),
        "q_cutoff_Hz": res.tuning.cutoff_hz,
        "final_over_noise": final / noise,
        "seconds_per_iteration_compute": float(np.mean(res.compute_s)),
    }
    if cause == "voltage-gain-drift":
        sigma = prof.emulator.effects.voltage_gain_sigma
        spread = partial(learn_judge.gain_spread, respond_for(prof), desired, 1.0, sigma)
        # learning continued past the floor (its stop off): does it stay there or diverge?
        c_res, c_rms, _ = learn_on(prof, model, desired, tmp / f"{cause}-continued", n,
                                   ilc.Law(floor_factor=0))
        row.update(learn_judge.variation_row(spread, res, spread, c_res))
        row.update({"continued_rms_um_by_iteration": c_rms, "gain_sigma_true": sigma,
                    "gain_sigma_measured": res.gain_sigma,
                    "gain_change_by_iteration": [it.gain_change for it in res.iterations],
                    "gain_change_true_by_iteration": [g / gains[0] - 1 for g in gains]})
        log(f"{cause:20s} continued past the floor: expected / floor " + " -> ".join(
            f"{x:.2f}" for x in row["continued_expected_over_floor_by_iteration"])
            + f"; {c_res.stop[:60]}")
    else:
        row["target"] = "final_over_noise <= 2 within 5 iterations"
        row["ok"] = bool(final / noise <= 2)
    if base_model is not None:  # a sensor effect: what learning on the base model does
        b_res, b_rms, _ = learn_on(prof, base_model, desired, tmp / f"{cause}-base", 5,
                                   ilc.Law(floor_factor=1.0), frame=frame)
        row.update({"base_model_rms_um_by_iteration": b_rms,
                    "base_model_readings_rms_um_by_iteration":
                        [it.steady_um for it in b_res.iterations],
                    "base_model_stop": b_res.stop})
        log(f"{cause:20s} on the base model: true RMS "
            f"{' -> '.join(f'{x:.4f}' for x in b_rms)} um; readings "
            f"{' -> '.join(f'{it.steady_um:.4f}' for it in b_res.iterations)} um")
    log(f"{cause:20s} ({row['truth']}) model {source}: true RMS "
        f"{' -> '.join(f'{x:.4f}' for x in rms)} um, kept {res.best}, {res.stop[:60]}; lead "
        f"{res.lead}, Q {res.tuning.cutoff_hz:.0f} Hz; "
        f"final/noise {final / noise:.2f} ({time.perf_counter() - t0:.0f} s)")
    return row


def refused_or(cause: str, row: Any) -> dict[str, Any]:
    """``row(folder)`` (a fresh folder name each attempt), or a failed row when the planner
    refuses the trajectory (out of reach) or the stage stops a run twice (a real-time stream
    the loaded host underran: the watchdog ramps the stage to 0 V; one retry, counted in
    ``stage_errors``)."""
    errors: list[str] = []
    while True:
        try:
            return {**row(f"try{len(errors)}"), "stage_errors": errors}
        except LimitError as exc:
            log(f"{cause}: refused: {exc}")
            stop = f"refused: {exc}"
        except StageError as exc:
            log(f"{cause}: stage error: {exc}")
            errors.append(str(exc))
            if len(errors) < 2:
                continue
            stop = f"stage error: {exc}"
        return {"effect": cause, "rms_um_by_iteration": [], "kept_iteration": None,
                "stop": stop, "final_over_noise": float("inf"), "ok": False,
                "stage_errors": errors}


#: Device time between learning and the replay of its kept waveform, s.
REPLAY_AFTER_S = 60.0
#: Re-learning iterations a replay may take when the stage has moved on (creep, drift).
RELEARN = 2


def family_row(case: family_sets.Case, cache: Path | None, tmp: Path) -> dict[str, Any]:
    """Learning on one out-of-family stage, and the replay :data:`REPLAY_AFTER_S` later: the
    kept waveform as it was (``replay_*``), then up to :data:`RELEARN` re-learning iterations
    from it (``learn.run`` resumed: ``relearned_*``; the drift it measured, ``replay_drift_um``).
    """
    with family_sets.session(case) as s:
        fit, desired = _fitted(case, cache, tmp, s)
        row: dict[str, Any] = {"stage": case.name, "family": case.family, "creep": case.creep,
                               "drift": case.drift, "noise_um": s.noise_um}

        def truly(res: learn.Result, first: int) -> list[float]:
            return [learn_judge.true_rms(s.probe.positions[first + i], it, desired)
                    for i, it in enumerate(res.iterations)]

        first = len(s.probe.positions)
        try:
            res = learn.run(s.probe, fit["model"], desired, s.profile.limits, tmp / "learn", {},
                            5, ilc.Law())
            rms = truly(res, first)
            s.clock.skip(REPLAY_AFTER_S)
            first = len(s.probe.positions)
            rep = learn.run(s.probe, fit["model"], desired, s.profile.limits, tmp / "replay",
                            {}, RELEARN, ilc.Law(),
                            resume=learn.Resume.kept(res))
        except (LimitError, StageError) as exc:
            return {**row, "stop": f"refused: {exc}", "ok": False, "replay_ok": False,
                    "replay_raw_ok": False}
        again = truly(rep, first)
    noise = s.noise_um
    row.update({"rms_um_by_iteration": rms, "kept_iteration": res.best, "stop": res.stop,
                "repeatable_um_by_iteration": [it.repeatable_um for it in res.iterations],
                "offset_um_by_iteration": [it.offset_um for it in res.iterations],
                "final_over_noise": rms[res.best] / noise, "ok": rms[res.best] <= 2 * noise,
                "replay_after_s": REPLAY_AFTER_S, "replay_rms_um": again[0],
                "replay_over_noise": again[0] / noise, "replay_raw_ok": again[0] <= 2 * noise,
                "replay_drift_um": rep.iterations[0].offset_um,
                "relearned_rms_um_by_iteration": again, "relearn_kept_iteration": rep.best,
                "relearn_offset_um_by_iteration": [it.offset_um for it in rep.iterations],
                "relearn_predicted_offset_um_by_iteration": [it.predicted_offset_um
                                                             for it in rep.iterations],
                "relearn_repeatable_um_by_iteration": [it.repeatable_um
                                                       for it in rep.iterations],
                "relearn_stop": rep.stop, "relearned_over_noise": again[rep.best] / noise,
                "replay_ok": again[rep.best] <= 2 * noise})
    log(f"  {case.name:18s}: true RMS {' -> '.join(f'{x:.4f}' for x in rms)} um "
        f"({rms[res.best] / noise:.2f}x noise, {res.stop[:40]}); replayed "
        f"{REPLAY_AFTER_S:g} s later {again[0] / noise:.2f}x (moved "
        f"{rep.iterations[0].offset_um:+.3f} um), re-learned "
        f"{' -> '.join(f'{x:.4f}' for x in again)} um: {again[rep.best] / noise:.2f}x")
    return row


def _fitted(case: family_sets.Case, cache: Path | None, tmp: Path, s: Any
            ) -> tuple[dict[str, Any], track.Desired]:
    """The standard sweeps recorded on ``s``, the fit on them (:func:`family_sets.identified`) and
    the triangle learned on the stage: 27.04 um, or 60 % of the fast sweep's span if less, about
    its middle."""
    sweeps = family_sets.record(s, tmp / "sweeps")
    fit = family_sets.identified(case, sweeps, s.noise_um, cache)
    lo, hi = family_sets.span_of(sweeps)
    return fit, track.triangle(FREQ_HZ, min(AMP_UM, 0.6 * (hi - lo)), 0.5 * (lo + hi), 3,
                               1 / s.profile.sample_rate_hz)


def moved_row(case: family_sets.Case, cache: Path | None, tmp: Path) -> dict[str, Any]:
    """The stage of :func:`family_row` in a session of its own, learned the same way, and its
    kept waveform played :data:`REPLAY_AFTER_S` later as ``afmctl play --model`` plays it
    (``moved_replay_*``: the move it read, um, and the trajectory's true RMS)."""
    with family_sets.session(case) as s:
        fit, desired = _fitted(case, cache, tmp, s)
        model = fit["model"]
        try:
            res = learn.run(s.probe, model, desired, s.profile.limits, tmp / "learn", {}, 5,
                            ilc.Law())
            s.clock.skip(REPLAY_AFTER_S)
            got = learn.replayed_moved(s.probe, model, desired, s.profile.limits, res,
                                       (tmp / "moved_conditioning.csv", tmp / "moved.csv"))
        except (LimitError, StageError) as exc:
            return {"moved_replay_stop": f"refused: {exc}", "moved_replay_ok": False}
        err = s.probe.positions[-1][got.waveform.tracking] - desired.u_um
    rms = float(np.sqrt(np.mean(err[ilc.steady_part(desired)] ** 2)))
    log(f"  {case.name:18s}: replayed {REPLAY_AFTER_S:g} s later as play does it: moved "
        f"{got.move_um if got.move_um is not None else float('nan'):+.3f} um, "
        f"{rms / s.noise_um:.2f}x noise{'' if got.moved else ' (as learned: ' + got.why + ')'}")
    return {"moved_replay_move_um": got.move_um, "moved_replay_moved": got.moved,
            "moved_replay_rms_um": rms, "moved_replay_over_noise": rms / s.noise_um,
            "moved_replay_ok": rms <= 2 * s.noise_um}


def family(names: str, cache: Path | None, design: str = "reversals") -> dict[str, Any]:
    """The ``family_*`` keys."""
    rows = []
    with tempfile.TemporaryDirectory() as td:
        for case in family_sets.cases_named(names, design=design):
            rows.append({**family_row(case, cache, Path(td) / case.name),
                         **moved_row(case, cache, Path(td) / f"{case.name}-moved")})
    return {"family_stages": len(rows), "family_learn_ok": sum(r["ok"] for r in rows),
            "family_replay_ok": sum(r["replay_ok"] for r in rows),
            "family_replay_raw_ok": sum(r["replay_raw_ok"] for r in rows),
            "family_replay_moved_ok": sum(r["moved_replay_ok"] for r in rows),
            "family_rows": rows}


def iterations_to(rms: list[float], level: float) -> int | None:
    return next((i for i, x in enumerate(rms) if x <= level), None)


def one(args: argparse.Namespace, stage: str) -> None:
    """Set ``args`` to run ``stage`` alone (see ``--stage``); ValueError on an unknown name."""
    kind, _, name = stage.rpartition(":")
    foreign = (*foreign_learn.CAUSES, "earlier")
    if not (kind == "" and name in ("none", *CAUSES) or kind == "foreign" and name in foreign):
        raise ValueError(f"unknown stage {stage!r} (one of none, {', '.join(CAUSES)}, or "
                         f"foreign:<{'|'.join(foreign)}>)")
    args.stages_only, args.earlier = True, name == "earlier" and kind == "foreign"
    args.stages = "" if kind else name
    args.foreign = name if kind and name != "earlier" else ""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true", help="print the JSON object last")
    ap.add_argument("--stages", default="none," + ",".join(CAUSES),
                    help="comma-separated effects (none = the default stage)")
    ap.add_argument("--foreign", default=",".join(foreign_learn.CAUSES),
                    help="comma-separated effects on the foreign plant ('' for none)")
    ap.add_argument("--no-earlier", dest="earlier", action="store_false",
                    help="leave out the earlier bench's clean foreign stage (116 Hz rod)")
    ap.add_argument("--stages-only", action="store_true",
                    help="only the stages (no seed comparison, no 100 Hz run)")
    ap.add_argument("--stage", default="",
                    help="one stage alone: an effect of --stages, foreign:<effect> or "
                         "foreign:earlier (implies --stages-only)")
    family_sets.add_arguments(ap)
    args = ap.parse_args()
    fam = ({} if args.family == "none" or args.stage else
           family(args.family, args.family_cache, args.family_design))
    if args.family_only:
        print(json.dumps(fam))
        return
    if args.stage:
        try:
            one(args, args.stage)
        except ValueError as exc:
            ap.error(str(exc))
    base = default_profile()
    assert base.emulator is not None
    out: dict[str, Any] = dict(fam)
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        rows = []
        for cause in args.foreign.split(",") if args.foreign else ():
            row = refused_or(cause, lambda f, c=cause: foreign_learn.learn_foreign(
                c, FOREIGN_SEED, tmp / f / f"foreign-{c}"))
            rows.append(row)
            log(f"foreign {cause:12s}: true RMS "
                f"{' -> '.join(f'{x:.4f}' for x in row['rms_um_by_iteration'])} um, kept "
                f"{row['kept_iteration']}, {row['stop'][:60]}; final/noise "
                f"{row['final_over_noise']:.2f}; resonance "
                f"{row.get('identified_resonance_Hz') or float('nan'):.0f} Hz identified, "
                f"{row.get('true_resonance_Hz', float('nan')):.0f} Hz true")
        if args.earlier:
            row = refused_or("none (earlier stage)", lambda f: foreign_learn.learn_foreign(
                "none", FOREIGN_SEED, tmp / f / "foreign-earlier",
                overrides=foreign_learn.EARLIER_CLEAN))
            rows.append({**row, "stage": "the earlier bench's clean foreign stage (116 Hz)"})
            log(f"foreign earlier clean stage: {row['stop'][:160]}")
        for cause in args.stages.split(",") if args.stages else ():
            index = 0 if cause == "none" else 2 * CAUSES.index(cause)
            rows.append(refused_or(cause, lambda f, c=cause, i=index: stage_row(base, c, i,
                                                                                 tmp / f)))
        out["stages"] = rows
        out["learn_ok"] = sum(r["ok"] for r in rows)
        out["stages_total"] = len(rows)
        out["stages_used"] = ("afmctl's emulated stage, clean and with each of its hidden effects "
                              "(case 2i of the diagnose batch); the foreign plant "
                              "(afmctl.drivers.device.foreign.stage, [emulator.foreign] seed "
                              f"{FOREIGN_SEED}, over the serial protocol on a pty) clean and "
                              "with each hidden effect at strength 0.5")
        if args.stages_only:
            if args.json:
                print(json.dumps(out))
            return
        model = model_for(base, "none", tmp / "default-sweeps")[0]
        noise = base.emulator.noise_um
        desired = track.triangle(FREQ_HZ, AMP_UM, 0.0, 3, 1 / base.sample_rate_hz)
        for seed, law in (("inverse", ilc.Law()), ("linear", ilc.Law()),
                          ("linear", ilc.Law(cutoff_hz=LINEAR_Q_HZ))):
            res, rms, _ = learn_on(base, model, desired, tmp / f"seed-{seed}-{law.cutoff_hz:g}",
                                SEED_ITERATIONS, dc.replace(law, floor_factor=1.0), seed)
            key = f"{seed}_seed_iterations" + ("" if law.cutoff_hz == 600 else "_q150")
            out[key] = iterations_to(rms, 2 * noise)
            out[key.replace("iterations", "rms_um_by_iteration")] = rms
            out[key.replace("iterations", "stop")] = res.stop
            log(f"seed {seed}, Q {law.cutoff_hz:g} Hz: true RMS "
                f"{' -> '.join(f'{x:.4f}' for x in rms)} um; {res.stop}")
            if seed == "inverse":
                run_s = res.iterations[0].outcome.waveform.voltage_v.size / base.sample_rate_hz
                out["seconds_per_iteration_compute"] = float(np.mean(res.compute_s))
                out["seconds_per_iteration_stage"] = run_s
                out["compute_over_stage"] = out["seconds_per_iteration_compute"] / run_s
        fast = track.triangle(100.0, AMP_UM, 0.0, 3, 1 / base.sample_rate_hz)
        res, rms, _ = learn_on(base, model, fast, tmp / "100hz", 10, ilc.Law(region="imaging"))
        img = [it.rms_imaging_between_um for it in res.iterations]
        out["rate_100hz_imaging_pct"] = 100 * img[res.best] / AMP_UM
        out["rate_100hz_imaging_um_by_iteration"] = img
        out["rate_100hz_true_rms_um_by_iteration"] = rms
        out["rate_100hz_stop"] = res.stop
        log(f"100 Hz imaging (between samples): {' -> '.join(f'{x:.4f}' for x in img)} um; "
            f"kept {res.best}: {out['rate_100hz_imaging_pct']:.3f} % ; {res.stop}")
    if args.json:
        print(json.dumps(out))


if __name__ == "__main__":
    main()
