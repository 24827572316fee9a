"""Record a two-axis sweep set on a stage of two channels (``afmctl sweep --axes x,y``).

Talks to the stage only through the interface of :mod:`drivers` (an object passed in): its
``play`` of an (N, 2) waveform, ``voltages()`` and, through
:func:`afmctl.experiment.runner.move_and_read`, the ramps between files. Each file is recorded as
the one-axis sweeps are (:func:`afmctl.experiment.runner.record_sweep`): streamed to
``<name>.incomplete.csv`` as its samples arrive, and kept there, marked interrupted, if it is cut
short. Every sample of both channels is checked by the guard against its own axis's limits before
anything is sent.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl import guard
from afmctl.experiment import runner
from afmctl.model.xy import AXES

FloatArray = NDArray[np.float64]
Design = Sequence[tuple[str, float, FloatArray, Mapping[str, str]]]


def check_design(design: Design, dt_s: float, limits: Mapping[str, Any]) -> None:
    """:class:`~afmctl.errors.LimitError` unless every sample of every channel of every file is
    within its axis's ``limits`` (voltage and slew)."""
    for name, _, v, _ in design:
        for i, a in enumerate(AXES):
            guard.check(v[:, i], dt_s, limits[a], what=f"{name} (axis {a})")


def record_one(stage: Any, entry: tuple[str, float, FloatArray, Mapping[str, str]],
               sample_rate_hz: float, limits: Mapping[str, Any], path: Path,
               meta: Mapping[str, str], progress: runner.Progress | None = None) -> Any:
    """Record one file of a design to ``path`` (:func:`afmctl.experiment.runner.record_sweep`:
    streamed to ``<name>.incomplete.csv`` as it arrives, renamed complete, kept marked
    interrupted otherwise); the :class:`~afmctl.files.xysweepfile.XYSweep`.

    First both outputs are ramped (one channel at a time, the other holding) to the file's first
    sample; the sweep then rests :data:`afmctl.experiment.runner.SETTLE_S` before it plays.
    """
    name, freq, v, kinds = entry
    for i, a in enumerate(AXES):
        runner.move_and_read(stage, float(v[0, i]), limits[a], sample_rate_hz, 0.01, i)
    return runner.record_sweep(stage, name, freq, v, sample_rate_hz, {**meta, **kinds},
                               progress, path)


def record(stage: Any, design: Design, sample_rate_hz: float, limits: Mapping[str, Any],
           out_dir: Path, meta: Mapping[str, str],
           say: Callable[[str], None] = lambda _m: None) -> list[Path]:
    """Record every file of ``design`` in order to ``out_dir/<name>.csv`` (:func:`record_one`;
    a file that lost samples is refused, not patched)."""
    check_design(design, 1.0 / sample_rate_hz, limits)
    paths = []
    for entry in design:
        name, v = entry[0], entry[2]
        say(f"recording {name} ({v.shape[0] / sample_rate_hz:.1f} s) ...")
        path = out_dir / f"{name}.csv"
        record_one(stage, entry, sample_rate_hz, limits, path, meta)
        paths.append(path)
    return paths
