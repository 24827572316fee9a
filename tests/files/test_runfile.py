"""Run files are written as data arrives and stay readable, marked incomplete, after a crash."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from afmctl.files import runfile
from afmctl.files.tomlfile import FileFormatError


def block(start: int, n: int) -> tuple[np.ndarray, ...]:
    seq = np.arange(start, start + n)
    u = np.sin(seq / 10.0)
    u[::7] = np.nan  # missing samples stay missing
    return seq, seq * 1e-4, np.cos(seq / 10.0), seq * 0.01, u


def test_complete_run_round_trips(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    with runfile.RunWriter(path, {"profile": "emulated", "filter": "inverse"}) as w:
        w.write(*block(0, 50))
        w.write(*block(50, 50))
    run = runfile.read(path)
    assert run.complete and run.end == "complete"
    assert run.meta["profile"] == "emulated" and run.meta["software"].startswith("afmctl")
    seq, t, d, v, u = (np.concatenate(c) for c in zip(block(0, 50), block(50, 50), strict=True))
    np.testing.assert_array_equal(run.seq, seq)
    np.testing.assert_allclose(run.displacement_um, u, atol=1e-6)
    assert np.isnan(run.displacement_um).sum() == 16 and np.isnan(run.displacement_um[:50:7]).all()


def test_exception_marks_the_file_interrupted(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    with pytest.raises(RuntimeError), runfile.RunWriter(path, {}) as w:
        w.write(*block(0, 10))
        raise RuntimeError("link lost")
    run = runfile.read(path)
    assert not run.complete and "link lost" in run.end and run.seq.size == 10


def test_existing_data_is_never_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    path.write_text("precious")
    with pytest.raises(FileExistsError):
        runfile.RunWriter(path, {})
    assert path.read_text() == "precious"


def test_killed_writer_leaves_a_readable_incomplete_file(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    code = (
        "import sys, time, numpy as np\n"
        "from afmctl.files import runfile\n"
        f"w = runfile.RunWriter({str(path)!r}, {{'profile': 'x'}})\n"
        "for b in range(1000):\n"
        "    s = np.arange(b * 10, b * 10 + 10)\n"
        "    w.write(s, s * 1e-4, s * 0.0, s * 0.0, s * 1.0)\n"
        "    print(b, flush=True)\n"
        "    time.sleep(0.01)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    for _ in range(5):
        proc.stdout.readline()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    proc.stdout.close()
    run = runfile.read(path)
    assert not run.complete and run.seq.size >= 50
    np.testing.assert_array_equal(run.seq, np.arange(run.seq.size))  # no gaps, no torn rows


def test_foreign_file_is_refused(tmp_path: Path) -> None:
    (tmp_path / "x.csv").write_text("a,b\n1,2\n")
    with pytest.raises(FileFormatError, match="not an afmctl run file"):
        runfile.read(tmp_path / "x.csv")
