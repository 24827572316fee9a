"""Wire primitives of the device side: a select loop in a thread, raw ptys, blocking writes.

Every server binds 127.0.0.1 (:data:`LOOPBACK`) unless given another host explicitly.
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import tty
from typing import Any

LOOPBACK = "127.0.0.1"


class SelectLoop:
    """A select loop (``_serve``) in a background thread, started on entry and stopped on exit
    through a wake-up pipe (``_wake_r`` is among the descriptors it watches)."""

    def __init__(self, name: str) -> None:
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._serve, name=name, daemon=True)

    def _serve(self) -> None:
        raise NotImplementedError

    def _select(self, watch: list[Any]) -> list[Any] | None:
        """The ready ones of ``watch``; None when asked to stop."""
        ready, _, _ = select.select([self._wake_r, *watch], [], [])
        return None if self._wake_r in ready else ready

    def __enter__(self) -> Any:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        os.write(self._wake_w, b"x")
        self._thread.join()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)


# -- ASCII protocol on a pty or a socket ----------------------------------------------------------
def open_pty() -> tuple[int, int, str]:
    """A raw pty pair: (master fd, slave fd, slave path)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)



def write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        try:
            view = view[os.write(fd, view):]
        except BlockingIOError:
            select.select([], [fd], [], 1.0)
        except OSError:
            return

