"""Run planned waveforms on a stage and keep every measured sample.

This module talks to a stage only through the interface of :mod:`drivers` (an object passed in),
so it imports no device library. Each filter's run streams into its own run file as samples arrive
(:mod:`afmctl.files.runfile`); afterwards the runs are scored, and a combined CSV, ``summary.json`` and a
plot like the paper's Figs. 9-11 are written.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from afmctl.files import runfile
from afmctl.model import effects as fx
from afmctl.model import transducer as tr
from afmctl.planning import track

FloatArray = NDArray[np.float64]
Progress = Callable[[str, int, int], None]

#: Rest before every recorded sweep, s: the stage rings after the last sweep's end, so a sweep
#: started at once began on a transient that depended on how soon the host started it (two
#: recordings of one foreign stage differed by up to 1.3x its noise over the fast sweep's first
#: 50 ms, and diagnose's verdict on it changed between recordings). Half a second is 20 decay
#: times of a rod at 300 Hz with damping 0.02 (2 of one at 100 Hz with 0.005).
SETTLE_S = 0.5


class PlayingStage(Protocol):
    """What an experiment needs of a stage (see ``afmctl.drivers.StageBase``)."""

    def play(self, waveform_v: FloatArray, on_block: Callable[..., None] | None = None,
             **kw: Any) -> Any: ...

    def voltage(self) -> float: ...


@dataclass(frozen=True)
class Outcome:
    """One filter's run: measured displacement (NaN where missing) and its score."""

    waveform: track.Waveform
    displacement_um: FloatArray
    voltage_v: FloatArray
    score: track.Score
    complete: bool
    run_file: Path

    def as_dict(self) -> dict[str, Any]:
        missing = int(np.isnan(self.displacement_um).sum())
        return {**self.score.as_dict(), "max_slew_V_per_ms": self.waveform.max_slew_v_per_ms,
                "horizon": self.waveform.horizon, "horizons": list(self.waveform.horizons),
                "samples": int(self.waveform.voltage_v.size),
                "missing_samples": missing, "complete": self.complete,
                "run_file": self.run_file.name}


def stream(stage: PlayingStage, wf: track.Waveform, path: Path, meta: Mapping[str, object],
           progress: Progress | None = None) -> tuple[FloatArray, FloatArray, bool]:
    """Play ``wf`` on ``stage``, appending each block to the run file ``path`` as it arrives.

    Returns (displacement_um, voltage_v, complete); samples never received are NaN. Any exception
    (including KeyboardInterrupt) leaves the run file readable and marked interrupted, and is
    re-raised (the stage's ``play`` has already put it in its safe state).
    """
    n = wf.voltage_v.size
    u = np.full(n, np.nan)
    v = np.full(n, np.nan)
    t = wf.time_s
    with runfile.RunWriter(path, {**meta, "filter": wf.filter, "samples": n}) as writer:

        def on_block(first: int, volt: FloatArray, disp: FloatArray, valid: Any) -> None:
            sl = slice(first, first + len(disp))
            u[sl] = np.where(valid, disp, np.nan)
            v[sl] = volt
            writer.write(np.arange(sl.start, sl.stop), t[sl], wf.desired_um[sl],
                         wf.voltage_v[sl], u[sl])
            if progress is not None and np.any(valid):  # an interrupt hands the rest as missing
                progress(wf.filter, sl.stop, n)

        stage.play(wf.voltage_v, on_block)
    return u, v, bool(np.isfinite(u).all())


def run_all(stage: PlayingStage, plans: Mapping[str, track.Waveform], desired: track.Desired,
            out: Path, meta: Mapping[str, object], between_model: tr.Transducer | None,
            progress: Progress | None = None, sensor: fx.Effects | None = None,
            estimate: bool = False) -> dict[str, Outcome]:
    """Run each plan in turn (inverse first) and score it; run files go to ``out`` (created).

    The readings are scored as the stage's position: corrected for the ``sensor`` effects the
    model knows (delay, gauge; none by default). The run files keep the raw readings.
    ``estimate``: ``between_model`` is the fitted model, not the stage's truth, so the error
    between the samples carries the model's misfit at the samples
    (:func:`afmctl.planning.track.between_samples` with the readings).
    """
    out.mkdir(parents=True, exist_ok=True)
    outcomes = {}
    for name, wf in plans.items():
        path = out / f"run_{name}.csv"
        u, v, complete = stream(stage, wf, path, meta, progress)
        where = fx.sensor_correct(fx.compile_chain(sensor or fx.Effects(), wf.dt_s), u)
        between = None
        if between_model is not None:
            between = track.between_samples(between_model, wf, desired, tr.initial(between_model),
                                            where if estimate else None)
        outcomes[name] = Outcome(wf, u, v, track.score(wf, desired, where, between), complete,
                                 path)
    return outcomes


def atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def write_waveform_csv(wf: track.Waveform, path: Path) -> None:
    """``time_s,desired_um,voltage_V`` (desired empty on the ramps), for ``--dry-run``."""
    rows = [f"{t:.7f},{'' if np.isnan(d) else f'{d:.6f}'},{v:.6f}"
            for t, d, v in zip(wf.time_s, wf.desired_um, wf.voltage_v, strict=True)]
    atomic_write(path, "time_s,desired_um,voltage_V\n" + "\n".join(rows) + "\n")


def write_combined_csv(outcomes: Mapping[str, Outcome], desired: track.Desired,
                       path: Path) -> None:
    """The tracking part of every filter side by side on one time axis (s from tracking start)."""
    cols = {"time_s": np.arange(desired.u_um.size) * desired.dt_s, "desired_um": desired.u_um}
    for name, o in outcomes.items():
        cols[f"voltage_V_{name}"] = o.waveform.voltage_v[o.waveform.tracking]
        cols[f"displacement_um_{name}"] = o.displacement_um[o.waveform.tracking]
    lines = [",".join(cols)]
    for row in zip(*cols.values(), strict=True):
        lines.append(",".join("" if np.isnan(x) else f"{x:.7g}" for x in row))
    atomic_write(path, "\n".join(lines) + "\n")


def summary(outcomes: Mapping[str, Outcome], desired: track.Desired,
            meta: Mapping[str, object]) -> dict[str, Any]:
    """The ``--json`` object: per-filter errors and the linear/inverse RMS ratios (both over the
    steady part, like the headline figures; ``_between`` from the errors between samples)."""
    out: dict[str, Any] = {**meta, "trajectory": desired.label,
                           "amplitude_um": desired.amplitude_um,
                           "filters": {k: o.as_dict() for k, o in outcomes.items()}}
    if {"inverse", "linear"} <= outcomes.keys():
        lin, inv = outcomes["linear"].score, outcomes["inverse"].score
        out["ratio_linear_over_inverse"] = lin.rms_um / inv.rms_um
        if lin.rms_between_um is not None and inv.rms_between_um:
            out["ratio_linear_over_inverse_between"] = lin.rms_between_um / inv.rms_between_um
    return out


def write_summary(data: Mapping[str, Any], path: Path) -> None:
    atomic_write(path, json.dumps(data, indent=2, allow_nan=False) + "\n")


def plot(outcomes: Mapping[str, Outcome], desired: track.Desired, thickness_um: float,
         path: Path) -> None:
    """Desired and achieved trajectories, errors, and the field-displacement loop (Figs. 9-11).

    The desired trajectory is drawn last (dashed, on top) so the filters cannot hide it; the first
    period, left out of the headline figures, is shaded, and each error's legend states its RMS.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.arange(desired.u_um.size) * desired.dt_s
    fig, ax = plt.subplots(3, 1, figsize=(8, 9.5), constrained_layout=True)
    colors = {"inverse": "tab:blue", "linear": "tab:red"}
    t0 = 0.0
    for name, o in outcomes.items():
        u = o.displacement_um[o.waveform.tracking]
        v = o.waveform.voltage_v[o.waveform.tracking]
        c = colors.get(name, None)
        t0 = o.score.steady_from_s
        ax[0].plot(t, u, color=c, lw=1.6, alpha=0.8, label=f"{name} filter")
        part = "steady part" if o.score.steady else "whole run"
        ax[1].plot(t, u - desired.u_um, color=c, lw=0.9,
                   label=f"{name}: RMS {o.score.rms_um:.3g} um ({o.score.rms_pct:.2g} %, {part})")
        ax[2].plot(v / thickness_um, u, color=c, lw=0.8, label=name)
    ax[0].plot(t, desired.u_um, "k--", lw=1.0, label="desired", zorder=5)
    for a in ax[:2]:
        if t0 > 0:
            a.axvspan(0, t0, color="0.9", zorder=0, label="first period (transient, not in RMS)")
    ax[0].set(xlabel="time (s)", ylabel="displacement (um)", title=f"Tracking: {desired.label}")
    ax[1].set(xlabel="time (s)", ylabel="error (um)")
    ax[2].set(xlabel="field (MV/m)", ylabel="displacement (um)", title="field-displacement")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(loc="best", fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def incomplete_path(path: Path) -> Path:
    """Where a sweep bound for ``path`` is streamed while it records: ``<stem>.incomplete.csv``,
    numbered if an earlier interrupted one is there (measured data is never overwritten)."""
    candidate = path.with_name(f"{path.stem}.incomplete.csv")
    k = 2
    while candidate.exists():
        candidate = path.with_name(f"{path.stem}.incomplete-{k}.csv")
        k += 1
    return candidate


def record_sweep(stage: PlayingStage, name: str, frequency_hz: float, voltage_v: FloatArray,
                 sample_rate_hz: float, meta: Mapping[str, str],
                 progress: Progress | None = None, path: Path | None = None,
                 settle_s: float = SETTLE_S) -> Any:
    """Play one identification waveform, after ``settle_s`` at rest (:data:`SETTLE_S`), and
    return it as a :class:`afmctl.files.sweepfile.Sweep`.

    The sweep's ``voltage_V`` is the commanded voltage (what a filter controls); a sweep that lost
    samples is refused rather than patched. With ``path``, the samples are also streamed as they
    arrive (flushed per block) into :func:`incomplete_path`; when the sweep completes it is written
    to ``path`` and that file removed, otherwise (interrupt, lost samples, stage failure) it stays
    as a valid sweep file of the samples received in order, ending ``# end: interrupted (...)``.
    """
    from afmctl.files import sweepfile as sweeps

    meta = {**meta, "frequency_hz": f"{frequency_hz:g}"}
    n = len(voltage_v)
    got = np.full(n, np.nan)
    streamed = incomplete_path(path) if path is not None else None
    fh = None if streamed is None else open(streamed, "x", encoding="utf-8")  # noqa: SIM115
    done = [0]  # samples received in order so far (what the incomplete file holds)

    def on_block(first: int, volt: FloatArray, disp: FloatArray, valid: Any) -> None:
        got[first:first + len(disp)] = np.where(valid, disp, np.nan)
        old = prefix = done[0]
        while prefix < n and np.isfinite(got[prefix]):
            prefix += 1
        done[0] = prefix
        if fh is not None and prefix > old:
            rows = np.column_stack([np.arange(old, prefix) / sample_rate_hz,
                                    voltage_v[old:prefix], got[old:prefix]])
            np.savetxt(fh, rows, delimiter=",", fmt=("%.7f", "%.6f", "%.6f"))
            fh.flush()
            os.fsync(fh.fileno())
        if progress is not None and np.any(valid):
            progress(name, first + len(disp), n)

    try:
        if fh is not None:
            fh.write("".join(f"# {k}: {v}\n" for k, v in meta.items()))
            fh.write(",".join(sweeps.COLUMNS) + "\n")
        time.sleep(settle_s)
        rec = stage.play(voltage_v, on_block)
        lost = int((~np.asarray(rec.valid)).sum())
        if lost:
            raise RuntimeError(f"sweep {name}: {lost} samples were not received; record it again")
        sweep = sweeps.from_arrays(voltage_v, rec.displacement_um, sample_rate_hz, meta, name)
        if path is not None:
            sweeps.write(sweep, path)
    except BaseException as exc:
        if fh is not None:
            why = f"{type(exc).__name__}: {exc}".replace("\n", " ")
            fh.write(f"# end: interrupted ({why})\n")
            fh.close()
        raise
    if fh is not None and streamed is not None:
        fh.close()
        streamed.unlink()
    return sweep
