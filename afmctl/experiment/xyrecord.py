"""Record a two-axis sweep set on a stage of two channels (``afmctl sweep --axes x,y``).

Talks to the stage only through the interface of :mod:`drivers` (an object passed in): its
``play`` of an (N, 2) waveform, ``voltages()`` and, through
:func:`afmctl.experiment.runner.move_and_read`, the ramps between files. Every sample of both
channels is checked by the guard against its own axis's limits before anything is sent.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl import guard
from afmctl.errors import SamplesLostError
from afmctl.experiment import runner
from afmctl.files import xysweepfile as xs
from afmctl.model.xy import AXES

FloatArray = NDArray[np.float64]
Design = Sequence[tuple[str, float, FloatArray, Mapping[str, str]]]


def check_design(design: Design, dt_s: float, limits: Mapping[str, Any]) -> None:
    """:class:`~afmctl.errors.LimitError` unless every sample of every channel of every file is
    within its axis's ``limits`` (voltage and slew)."""
    for name, _, v, _ in design:
        for i, a in enumerate(AXES):
            guard.check(v[:, i], dt_s, limits[a], what=f"{name} (axis {a})")


def record(stage: Any, design: Design, sample_rate_hz: float, limits: Mapping[str, Any],
           out_dir: Path, meta: Mapping[str, str],
           say: Callable[[str], None] = lambda _m: None) -> list[Path]:
    """Record every file of ``design`` in order and write it to ``out_dir/<name>.csv``.

    Before each file both outputs are ramped (one channel at a time, the other holding) to its
    first sample and rest :data:`afmctl.experiment.runner.SETTLE_S`; the file is written
    atomically once complete (a file that lost samples is refused, not patched).
    """
    check_design(design, 1.0 / sample_rate_hz, limits)
    paths = []
    for name, freq, v, kinds in design:
        for i, a in enumerate(AXES):
            runner.move_and_read(stage, float(v[0, i]), limits[a], sample_rate_hz, 0.01, i)
        time.sleep(runner.SETTLE_S)
        say(f"recording {name} ({v.shape[0] / sample_rate_hz:.1f} s) ...")
        rec = stage.play(v)
        lost = int((~np.asarray(rec.valid)).sum())
        if lost:
            raise SamplesLostError(f"sweep {name}: {lost} samples were not received; record it "
                                   f"again")
        sweep = xs.from_arrays(v, np.asarray(rec.displacement_um, dtype=float), sample_rate_hz,
                               {**meta, **kinds, "frequency_hz": f"{freq:g}"}, name)
        path = out_dir / f"{name}.csv"
        xs.write(sweep, path)
        paths.append(path)
    return paths
