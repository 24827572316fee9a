"""A real SIGINT to a real ``afmctl`` process, sent once it has got far enough."""

from __future__ import annotations

import signal
import subprocess
import time
from collections.abc import Callable


def interrupt_when(proc: subprocess.Popen[str], ready: Callable[[], bool],
                   timeout_s: float = 60.0) -> str:
    """Send SIGINT to ``proc`` once ``ready()`` (polled every 50 ms, up to ``timeout_s``), wait
    for it to end and return its stderr. The test fails if it ended before; it is killed if it
    outlives the interrupt by 30 s."""
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline and proc.poll() is None and not ready():
            time.sleep(0.05)
    except BaseException:
        _stopped(proc)
        raise
    assert proc.poll() is None, proc.communicate()
    return interrupt(proc, 30.0)[1]


def interrupt(proc: subprocess.Popen[str], timeout_s: float = 20.0) -> tuple[str, str]:
    """Send SIGINT to ``proc`` and return its stdout and stderr once it has ended. A process that
    outlives the interrupt by ``timeout_s`` is killed, never left running (a server would hold
    its port and pty after the run), and the test fails."""
    try:
        proc.send_signal(signal.SIGINT)
        return proc.communicate(timeout=timeout_s)
    finally:
        _stopped(proc)


def _stopped(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.communicate()
