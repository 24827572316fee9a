"""An interrupted sweep, a failed start and a resumed one leave a folder identify takes (issue 27
item 7): at most one ``NAME.incomplete.csv`` per sweep (the latest attempt's), none from a start
that received nothing, none once the sweep is recorded whole.

The stage is the in-process emulated one (real time, 0.9 s a sweep); an interrupt is a
KeyboardInterrupt raised where Ctrl-C lands (between blocks, in the progress callback).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from afmctl import guard
from afmctl.drivers.inprocess import InProcessStage
from afmctl.experiment import runner as experiment
from afmctl.files import sweepfile as sweeps
from afmctl.files.profile import Profile
from afmctl.planning import sweepdesign as sd

RATE = 10_000.0
META = {"profile": "emulated", "layer_thickness_um": "100"}


def wave() -> np.ndarray:
    return sd.loop(5.58, -150.0, 150.0, 5, RATE)


def interrupt_at(fraction: float):  # noqa: ANN201 (a progress callback)
    def progress(what: str, done: int, total: int) -> None:
        if done >= fraction * total:
            raise KeyboardInterrupt

    return progress


def record(stage: InProcessStage, path: Path, progress=None, voltage=None):  # noqa: ANN001, ANN201
    return experiment.record_sweep(stage, "triangle_5.58hz", 5.58,
                                   wave() if voltage is None else voltage, RATE, META, progress,
                                   path, settle_s=0.0)


def test_repeated_interrupts_keep_one_incomplete_file_and_a_whole_sweep_removes_it(
        profile: Profile, tmp_path: Path) -> None:
    path = tmp_path / "triangle_5.58hz.csv"
    with InProcessStage(profile) as stage:
        for fraction in (0.2, 0.4):
            with pytest.raises(KeyboardInterrupt):
                record(stage, path, interrupt_at(fraction))
        assert sorted(p.name for p in tmp_path.iterdir()) == ["triangle_5.58hz.incomplete.csv"]
        partial = tmp_path / "triangle_5.58hz.incomplete.csv"
        text = partial.read_text()
        assert text.count("# end: interrupted") == 1 and text.rstrip().endswith(")")
        kept = sweeps.read(partial)
        assert 0.4 * wave().size <= kept.time_s.size < wave().size  # the second attempt
        record(stage, path)  # --resume records it whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["triangle_5.58hz.csv"]
    assert sweeps.read_complete(path).time_s.size == wave().size  # identify takes the folder


def test_a_start_that_received_nothing_leaves_no_file(profile: Profile, tmp_path: Path) -> None:
    """A waveform the stage refuses before playing (here: beyond the slew limit) used to leave a
    header-only NAME.incomplete.csv behind."""
    steep = wave().copy()
    steep[10] += 40.0  # 40 V in one sample: 400 V/ms
    with InProcessStage(profile) as stage, pytest.raises(guard.LimitError):
        record(stage, tmp_path / "triangle_5.58hz.csv", voltage=steep)
    assert list(tmp_path.iterdir()) == []


def test_an_earlier_interrupted_attempt_survives_a_start_that_received_nothing(
        profile: Profile, tmp_path: Path) -> None:
    path = tmp_path / "triangle_5.58hz.csv"
    steep = wave().copy()
    steep[10] += 40.0
    with InProcessStage(profile) as stage:
        with pytest.raises(KeyboardInterrupt):
            record(stage, path, interrupt_at(0.2))
        before = (tmp_path / "triangle_5.58hz.incomplete.csv").read_text()
        with pytest.raises(guard.LimitError):
            record(stage, path, voltage=steep)
    assert (tmp_path / "triangle_5.58hz.incomplete.csv").read_text() == before
