"""Identification of a two-axis stage: each axis's model and the coupling both ways.

A two-axis set (:mod:`afmctl.files.xysweepfile`) holds files where one axis moves and the other
is held at a constant voltage, and files where both move. The steps:

1. The coupling of each direction (:mod:`afmctl.fit.coupling`) from the files where its target is
   held and its source moves: there the target's own transducer stands still, so its sensor sees
   the coupled motion alone (plus a constant, noise and drift), against the source's *measured*
   displacement.
2. Each axis's model by :func:`afmctl.fit.identify.fit` (everything it does for one axis: noise
   floor, envelope, uncertainty) on the files where that axis moves, its displacement less the
   motion the other axis's measured displacement causes through the coupling just identified.
   The two axes are independent problems and are fitted in two worker processes at once. Files
   where the axis carries a dynamic excitation (a chirp, a multisine: :func:`excitation`) are
   there for the coupling and are left out of the axis fit.
3. Each axis's second mechanical mode (:mod:`afmctl.fit.modes`), started at the shared modes the
   coupling found: a structural mode the axes share moves each of them a little and rings after
   every turning point of a fast sweep, below or above the axis's own resonance. It is kept
   where it brings the axis's worst sweep well down, or to identify's floor
   (:attr:`afmctl.fit.modes.ModeFit.kept`).
4. Where a mode is kept, the axis identified again on its readings with the mode taken out (the
   hysteresis of step 2 had bent to the ringing), the mode fitted again with that hysteresis
   held, and the better of the two kept (:func:`afmctl.fit.modes.reidentified`).

The coupling acts on the source's displacement relative to ``reference_um``: the source's mean
measured displacement over the files the target's model was fitted on (there the target's model
absorbed the coupling's static part at that position).
"""

from __future__ import annotations

import multiprocessing as mp
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl.errors import FitInputError
from afmctl.files.sweepfile import Sweep
from afmctl.files.xysweepfile import AXES, XYSweep
from afmctl.fit import cores
from afmctl.fit import coupling as fc
from afmctl.fit import identify as idf
from afmctl.fit import modes
from afmctl.fit import parametrization as pz
from afmctl.model import coupling as cp
from afmctl.model.xy import XYModel, direction

FloatArray = NDArray[np.float64]
#: Axis fits run in this many worker processes at once (1: in this process).
JOBS = 2
#: A file whose axis turns more often than this is a dynamic excitation (:func:`excitation`).
MAX_TURNS = 100


@dataclass(frozen=True)
class XYFitResult:
    """Outcome of :func:`fit`: each axis's one-axis result and each direction's coupling fit."""

    axes: dict[str, idf.FitResult]
    coupling: dict[str, fc.CouplingFit]
    seconds: float

    @property
    def model(self) -> XYModel:
        return XYModel({a: r.model for a, r in self.axes.items()},
                       {d: c.coupling for d, c in self.coupling.items()})

    @property
    def finite(self) -> bool:
        return all(r.finite for r in self.axes.values())

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: ``axes`` (each axis's one-axis keys), ``coupling`` (``yx_static``,
        ``xy_static``, ``yx_frf``, ``xy_frf`` and each direction's whole fit) and ``seconds``."""
        freq = fc.report_frequencies()
        coupling: dict[str, Any] = {}
        for d, c in self.coupling.items():
            doc = c.to_dict(freq)
            coupling[f"{d}_static"] = doc["static"]
            coupling[f"{d}_frf"] = [{k: p[k] for k in ("freq_hz", "gain", "phase_deg")}
                                    for p in doc["frf"]]
            coupling[d] = doc
        return {"axes": {a: r.to_dict() for a, r in self.axes.items()}, "coupling": coupling,
                "seconds": round(self.seconds, 3), "finite": self.finite,
                "at_noise_floor": all(r.at_noise_floor for r in self.axes.values())}


def _other(axis: str) -> str:
    return AXES[1 - AXES.index(axis)]


def coupling_records(sweeps: Sequence[XYSweep], target: str) -> list[fc.Record]:
    """The files where ``target`` is held and the other axis moves, as coupling records."""
    i, j = AXES.index(target), 1 - AXES.index(target)
    return [fc.Record(s.displacement_um[:, j], s.displacement_um[:, i], s.dt, s.name)
            for s in sweeps if s.moving == (AXES[j],)]


def axis_sweeps(sweeps: Sequence[XYSweep], axis: str, couplings: dict[str, cp.Coupling]
                ) -> list[Sweep]:
    """Axis ``axis`` of the files where it moves (not as a dynamic excitation): its own motion
    (:func:`afmctl.model.coupling.own_motion`), its readings less what the other axis's own
    motion causes in them. Where the other axis is held this axis's reading is its own, and the
    coupling there goes round the loop (this axis moves the other, which moves this one back by
    ``c_xy c_yx``, about 1e-4) as part of this axis's motion.
    """
    i, j = AXES.index(axis), 1 - AXES.index(axis)
    here, back = couplings[direction(axis, AXES[j])], couplings[direction(AXES[j], axis)]
    return [replace(s.axis(axis), displacement_um=cp.own_motion(
        here, back, s.displacement_um[:, i], s.displacement_um[:, j], s.dt))
        for s in sweeps if axis in s.moving and not excitation(s, axis)]


def excitation(s: XYSweep, axis: str) -> bool:
    """True if ``axis`` carries a dynamic excitation in ``s`` (a chirp, a multisine: more than
    :data:`MAX_TURNS` turning points): it identifies the coupling's dynamics, not the axis's
    hysteresis, and would cost the axis fit most of its time (the hysteresis is evaluated at
    every turning point)."""
    return significant_turns(s.voltage_v[:, AXES.index(axis)]) > MAX_TURNS


def significant_turns(v: FloatArray, share: float = 0.01) -> int:
    """Reversals of ``v`` by more than ``share`` of its range (noise on a recorded voltage does
    not count)."""
    return len(pz.significant_extremes(v, share)) - 2


def reference_um(sweeps: Sequence[XYSweep], target: str) -> float:
    """Mean measured displacement of the source (um) over the files where ``target`` moves."""
    j = 1 - AXES.index(target)
    parts = [s.displacement_um[:, j] for s in sweeps if target in s.moving]
    return float(np.mean(np.concatenate(parts))) if parts else 0.0


def _check(sweeps: Sequence[XYSweep]) -> None:
    for a in AXES:
        if not any(a in s.moving for s in sweeps):
            raise FitInputError(f"axis {a} moves in no file: its model cannot be identified")


def fit(sweeps: Sequence[XYSweep], settings: idf.Settings = idf.Settings(),
        progress: Callable[[str], None] | None = None, jobs: int = JOBS) -> XYFitResult:
    """Identify both axes and the coupling both ways from a two-axis set (recorded order).

    Parameters
    ----------
    sweeps : sequence of XYSweep
    settings : identify.Settings
        The one-axis fit's settings, for each axis (a per-axis layer thickness comes from each
        file's ``layer_thickness_<axis>_um`` metadata).
    progress : callable, optional
        One-line progress messages.
    jobs : int
        Worker processes for the axis fits (1: fit them here, one after the other).

    Raises
    ------
    FitInputError
        An axis that never moves, or a direction with no file to identify its coupling from.
    """
    say = progress or (lambda _msg: None)
    t0 = time.perf_counter()
    _check(sweeps)
    couplings: dict[str, fc.CouplingFit] = {}
    for target in AXES:
        d = direction(target, _other(target))
        cf = fc.identify(coupling_records(sweeps, target), reference_um(sweeps, target))
        couplings[d] = cf
        say(f"coupling {d} ({target} caused by {_other(target)}): static {cf.coupling.static:.5g}"
            f" um/um ({cf.coupling.static_db:.1f} dB), mode {cf.coupling.mode_hz:.4g} Hz, "
            f"estimates {cf.band_hz[0]:.3g} ... {cf.band_hz[1]:.4g} Hz")
    found = {d: c.coupling for d, c in couplings.items()}
    modes_hz = tuple(c.mode_hz for c in found.values())
    tasks = [(a, axis_sweeps(sweeps, a, found), settings, modes_hz) for a in AXES]
    say(f"fitting axes {', '.join(AXES)} ({min(jobs, len(AXES))} at a time) ...")
    if jobs <= 1:
        results = [_fit_axis(t, say) for t in tasks]
    else:
        with mp.get_context("fork").Pool(min(jobs, len(tasks)), cores.pool_worker) as pool:
            results = pool.map(_fit_axis, tasks)
    axes = dict(zip(AXES, results, strict=True))
    for a, r in axes.items():
        worst = max(s.rms_over_noise for s in r.sweeps)
        say(f"axis {a}: {len(r.sweeps)} sweep(s), worst {worst:.2f}x its sensor noise "
            f"({r.seconds:.1f} s)")
    return XYFitResult(axes, couplings, time.perf_counter() - t0)


def _fit_axis(task: tuple[str, list[Sweep], idf.Settings, tuple[float, ...]],
              say: Callable[[str], None] | None = None) -> idf.FitResult:
    """One axis's model (:func:`afmctl.fit.identify.fit`), then its second mode
    (:func:`afmctl.fit.modes.refined`) started at the coupling's shared modes ``modes_hz``, and
    where one is kept the axis identified again without its ringing
    (:func:`afmctl.fit.modes.reidentified`)."""
    axis, data, settings, modes_hz = task
    tell = None if say is None else (lambda m: say(f"[{axis}] {m}"))
    result = modes.refined(idf.fit(data, settings, tell), data, modes_hz, settings.window_s)
    return modes.reidentified(result, data, modes_hz, settings, tell)

