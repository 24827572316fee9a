"""Ctrl-C during ``afmctl diagnose``: the candidates are fitted in worker processes; an interrupt
ends all of them, says so in one line, exits 130 and writes nothing."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.harness.paths import REPO, SHARED_DATA

ROOT = REPO
FOREIGN = SHARED_DATA / "foreign-stage" / "unipolar"


def _processes_naming(text: str) -> list[int]:
    """Pids whose command line contains ``text``."""
    out = []
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and text in (entry / "cmdline").read_bytes().decode(
                    errors="replace"):
                out.append(int(entry.name))
        except OSError:  # a process that ended meanwhile
            continue
    return out


@pytest.mark.slow
@pytest.mark.skipif(not FOREIGN.is_dir(), reason="the shared foreign-stage sweeps are not beside "
                                                  "the checkout")
def test_ctrl_c_in_diagnose_ends_every_worker_and_writes_nothing(tmp_path: Path) -> None:
    out = tmp_path / "diag"
    argv = [sys.executable, "-m", "afmctl", "diagnose", *map(str, sorted(FOREIGN.glob("*.csv"))),
            "--out", str(out), "--jobs", "2"]
    with subprocess.Popen(argv, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)},
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)
                          ) as proc:
        assert proc.stderr is not None
        seen = []
        for line in proc.stderr:  # the base fit is done: the candidates are being fitted
            seen.append(line)
            if "base fit" in line:
                break
        deadline = time.monotonic() + 60
        while len(_processes_naming(str(out))) < 3 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(_processes_naming(str(out))) >= 3, "".join(seen)  # diagnose and 2 workers
        proc.send_signal(signal.SIGINT)
        err = proc.stderr.read()
        proc.wait(timeout=30)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "afmctl: error: interrupted; no stage was touched"
    deadline = time.monotonic() + 10
    while _processes_naming(str(out)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _processes_naming(str(out)) == []
    assert not out.exists()
