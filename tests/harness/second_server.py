"""The second device (:mod:`tests.harness.second_device`) on ``socket://127.0.0.1:PORT``: lines in,
replies out, one connection at a time, and a 2 ms ticker so that its watchdog acts while nobody
talks. No afmctl import."""

from __future__ import annotations

import re
import socket
import threading

from tests.harness.second_device import MAX_LINE, Device


class SecondStage:
    """The device on ``socket://127.0.0.1:PORT`` (``url``), one connection at a time, with a 2 ms
    ticker; a context manager. Keyword arguments go to :class:`Device`."""

    def __init__(self, **device: object) -> None:
        self.device = Device(**device)  # type: ignore[arg-type]
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self.listener.getsockname()[1]}"
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self.serve, daemon=True),
                        threading.Thread(target=self.tick, daemon=True)]

    def tick(self) -> None:
        """Every 2 ms: let the watchdog act if its period has run out (the run itself is played
        when a command asks, in device time, so nobody can tell the difference)."""
        while not self.stop.wait(0.002):
            with self.device.lock:
                d = self.device
                now = d.clock()
                if d.armed and now > d.last_beat + d.period:
                    d.advance(now)

    def serve(self) -> None:
        self.listener.settimeout(0.05)
        while not self.stop.is_set():
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            with conn:
                self.talk(conn)

    def talk(self, conn: socket.socket) -> None:
        conn.settimeout(0.05)
        buf, skipping = b"", False
        split = re.compile(b"[\r\n]") if self.device.defect == "cr-ends-line" else re.compile(b"\n")
        while not self.stop.is_set():
            try:
                data = conn.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                return
            buf += data
            while (m := split.search(buf)) is not None:
                raw, buf = buf[:m.start()], buf[m.end():]
                if skipping:
                    skipping = False
                    continue
                reply = self.device.line(raw)
                if reply is not None:
                    conn.sendall(reply)
            if len(buf) > MAX_LINE and not skipping and self.device.defect != "overlong-accepted":
                buf, skipping = b"", True
                conn.sendall(self.device.line(b"x" * (MAX_LINE + 1)) or b"")
            elif skipping:
                buf = b""

    def __enter__(self) -> SecondStage:
        for t in self.threads:
            t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        for t in self.threads:
            t.join()
        self.listener.close()
