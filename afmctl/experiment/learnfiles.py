"""Learning's files: ``summary.json`` (the ``--json`` object) and ``waveform_learned.csv`` (the
kept iteration's waveform, for ``afmctl play``), written after every iteration
(:func:`write_outputs`)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from afmctl.experiment import replay
from afmctl.experiment import runner as experiment
from afmctl.files import waveformfile
from afmctl.planning import ilc, track

if TYPE_CHECKING:
    from afmctl.experiment.learn import Iteration, Result


def summary(result: Result, desired: track.Desired, law: ilc.Law,
            meta: Mapping[str, object]) -> dict[str, Any]:
    """The ``--json`` object: track's per-run figures for iteration 0 and the best iteration, and
    one row per iteration (``iterations``)."""
    first, best = result.iterations[0], result.best_iteration
    outs = {"iteration_0": first.outcome, "learned": best.outcome}
    data = experiment.summary(outs, desired, meta)
    data.update({
        "iterations": [it.as_dict() for it in result.iterations],
        "best_iteration": best.index, "stop": result.stop,
        "noise_estimate_um": result.noise_um, "gain_sigma_estimate": result.gain_sigma,
        "law": {"max_cutoff_Hz": law.cutoff_hz, "cutoff_Hz": result.tuning.cutoff_hz,
                "gain": law.gain, "lead_samples": result.lead,
                "per_harmonic": result.tuning.harmonic,
                "measured_harmonics_Hz": [round(float(f), 3) for f in result.tuning.freqs_hz],
                "floor_factor": law.floor_factor, "diverge_factor": law.diverge_factor, "region": law.region},
        "seconds_per_iteration_compute": float(np.mean(result.compute_s)),
    })
    return data


def waveform_text(it: Iteration, desired: track.Desired, meta: Mapping[str, object]) -> str:
    """``waveform_learned.csv``: the iteration's whole waveform (conditioning and ramps
    included) with the desired trajectory on its tracking part, for ``afmctl play``."""
    wf = it.outcome.waveform
    info = {**meta, "trajectory": desired.label, "iteration": it.index,
            "rms_steady_um": f"{it.steady_um:.6g}", "run_file": it.outcome.run_file.name,
            "filter": wf.filter.rpartition("_iter")[0] or wf.filter,
            "horizons": ",".join(str(h) for h in wf.horizons),
            replay.OFFSET_MISS_KEY: f"{it.offset_um - it.predicted_offset_um:.9g}"}
    if desired.period_s is not None:
        info["period_s"] = f"{desired.period_s:.9g}"
    ref = None
    if it.reference_um is not None:
        ref = np.full(wf.voltage_v.size, np.nan)
        ref[wf.tracking] = it.reference_um
    return waveformfile.format_text(wf.time_s, wf.voltage_v, wf.desired_um, info, ref)


def write_outputs(result: Result, desired: track.Desired, law: ilc.Law,
                  meta: Mapping[str, object], out: Path) -> dict[str, Any]:
    """``summary.json`` and ``waveform_learned.csv`` (the best iteration), each replaced
    atomically: called after every iteration, so an interrupt keeps what finished (the CLI draws
    ``learn.png`` beside them: :func:`afmctl.plots.learn_figure`)."""
    data = summary(result, desired, law, meta)
    experiment.write_summary(data, out / "summary.json")
    experiment.atomic_write(out / "waveform_learned.csv",
                            waveform_text(result.best_iteration, desired,
                                          {**meta, replay.NOISE_KEY: f"{result.noise_um:.6g}"}))
    return data
