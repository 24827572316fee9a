"""A second two-channel device written from docs/reference/protocol.md v6 alone
(``tests/harness/second_xy_device.py``: no afmctl code), serving the foreign x/y stage of
drivers/device/foreign/xy_stage.py, checked over a real socket with lines taken from the document:
every row of §3.7 (and its read-only column), the §3.6 example, and a run whose held channel
records the plant's coupling."""

from __future__ import annotations

import ast
import math
import re
import socket
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

from afmctl.drivers.device.foreign import xy_stage as xs
from tests.harness import second_xy_device
from tests.harness.second_xy_device import SecondXYStage

STAGE_INDEX = 0  # foreign-xy-1: unipolar, -25 dB, shared mode 150 Hz


class ForeignXYPlant:
    """The foreign x/y stage behind the device's plant interface: device time in whole samples
    of the run's rate (idle at 10 kHz, then at rest once transients have died), Gaussian noise of
    each axis's own sigma; the recorder holds the command (``records_command``)."""

    IDLE_HZ = 10000.0

    def __init__(self, stage: xs.XYStage, seed: int = 1) -> None:
        self.stage, self.state = stage, xs.initial_state(stage)
        self.rng = np.random.default_rng(seed)
        self.owed_s = 0.0

    def start_run(self) -> None:
        pass

    def idle(self, v: np.ndarray, seconds: float) -> None:
        self.owed_s += seconds
        n = int(self.owed_s * self.IDLE_HZ)
        self.owed_s -= n / self.IDLE_HZ
        if n > 5000:  # half a second: every mode has rung down (slowest decay 0.2 s)
            self.state, n = xs.idle(self.stage, self.state, v), 0
        if n:
            _, _, self.state = xs.run(self.stage, np.tile(v, (n, 1)), self.IDLE_HZ, self.state)

    def play(self, v: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        _, reading, self.state = xs.run(self.stage, v, 1.0 / dt, self.state)
        return reading + xs.noise_um(self.stage) * self.rng.standard_normal(reading.shape), v


class Client:
    """Hand-typed lines (no tag, no CRC): the reply's payload, its CRC checked (§3.2(d))."""

    def __init__(self, url: str) -> None:
        host, port = url.removeprefix("socket://").split(":")
        self.sock = socket.create_connection((host, int(port)), timeout=2.0)
        self.buf = b""

    def ask(self, line: str) -> str:
        self.sock.sendall(line.encode() + b"\n")
        while b"\n" not in self.buf:
            self.buf += self.sock.recv(65536)
        raw, self.buf = self.buf.split(b"\n", 1)
        body, crc = raw[:-10], raw[-8:].decode()
        assert raw[-10:-8] == b" *" and f"{zlib.crc32(body):08x}" == crc, raw
        return body.decode()

    def close(self) -> None:
        self.sock.close()


@pytest.fixture(scope="module")
def stage() -> xs.XYStage:
    return xs.xy_stages()[STAGE_INDEX]


def serve(stage: xs.XYStage, **kw: object) -> SecondXYStage:
    limits = [(lo, hi, 50.0) for lo, hi in stage.drive_range_V]
    return SecondXYStage(channels=2, limits=limits, plant=ForeignXYPlant(stage),
                         records_command=True, **kw)


def test_the_second_xy_device_uses_no_afmctl_code() -> None:
    tree = ast.parse(Path(second_xy_device.__file__).read_text())
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert {n for n in names if n.split(".")[0] in ("afmctl", "drivers", "tests")} <= {
        "tests.harness.second_device", "tests.harness.second_server"}


#: §3.7: (row, lines, reply, read-only reply or None for "not sent"); an ERR compares its code,
#: ``key=v`` one STA? field.
ROWS = [
    ("SC1", ["CHN? 1"], "ERR 2", "ERR 2"),
    ("SC2", ["CH 1 SVA .25", "CH 1 VOL?"], "0.25", None),
    ("SC3", ["CH 1 SVA .25", "VOL?"], "0", None),
    ("SC4", ["CH 1 SVA .25", "CH 0 VOL?"], "0", None),
    ("SC5", ["ch 1 sva .25", "Ch 1 vol?"], "0.25", None),
    ("SC6", ["CH 1 SVA .25", "SAFE", "CH 1 VOL?"], "0", None),
    ("SC7", ["CH 99999 VOL?"], "ERR 6", "ERR 6"),
    ("SC8", ["CH -1 VOL?"], "ERR 6", "ERR 6"),
    ("SC9", ["CH 99999999999999999999 LIM?"], "ERR 6", "ERR 6"),
    ("SC10", ["CH x VOL?"], "ERR 2", "ERR 2"),
    ("SC11", ["CH 1.0 VOL?"], "ERR 2", "ERR 2"),
    ("SC12", ["CH"], "ERR 2", "ERR 2"),
    ("SC13", ["CH 1"], "ERR 2", "ERR 2"),
    ("SC14", ["CH 1 FOO"], "ERR 1", "ERR 1"),
    ("SC15", ["CH 1 WGO 1"], "ERR 2", "ERR 2"),
    ("SC16", ["CH 1 CH 0 VOL?"], "ERR 2", "ERR 2"),
    ("SC17", ["CH 1 SAFE"], "ERR 2", "ERR 2"),
    ("SC18", ["CH 1 VOL? 1"], "ERR 2", "ERR 2"),
    ("SC19", ["CH 99999 VOL? 1"], "ERR 2", "ERR 2"),
    ("SC20", ["CH 99999 SVA 0"], "ERR 6", "ERR 7"),
    ("SC21", ["CH 1 SVA 1e39"], "ERR 3", "ERR 7"),
    ("SC22", ["CH 1 WAV 0 1 1e39"], "ERR 3", "ERR 7"),
    ("SC23", ["CH 1 WAV 4 1 0"], "ERR 6", "ERR 7"),
    ("SC24", ["WTL 2", "CH 1 WAV 0 2 0 0", "STA?"], "complete=1", None),
    ("SC25", ["WTL 2", "WAV 0 2 0 0", "CH 1 WAV 0 1 0", "STA?"], "complete=0", None),
    ("SC26", ["WTL 2", "WAV 0 2 0 0", "CH 1 WAV 0 1 0", "WGO 1"], "ERR 9", None),
    ("SC27", ["CH 1 DRR? 1000000000000 1"], "1000000000000 1 nan nan",
     "1000000000000 1 nan nan"),
    ("SC28", ["CH 1 DRR? -1 1"], "ERR 6", "ERR 6"),
    ("SC29", ["CH 1 SVA 1e39", "ERR?"], "3", "7"),
]


def state_p(client: Client) -> None:
    """§3.5's state P: idle, outputs 0 V, 1000 Hz, a complete table of four 0 V samples (channel
    0; the others held), watchdog off, last error 0."""
    for line, want in (("SAFE", "OK"), ("WDT 0", "OK"), ("WTR 1000", "OK"), ("WTL 4", "OK"),
                       ("WAV 0 4 0 0 0 0", "OK")):
        assert client.ask(line) == want, line
    client.ask("ERR?")


def matches(reply: str, want: str) -> bool:
    if want.startswith("ERR"):
        return reply.split()[:2] == want.split()
    if "=" in want:
        return want in reply.split()
    return reply == want


@pytest.mark.parametrize("read_only", [False, True])
def test_every_row_of_section_3_7(stage, read_only: bool) -> None:
    with serve(stage, read_only=read_only) as server:
        client = Client(server.url)
        try:
            assert client.ask("VER?") == "4" and client.ask("CHN?") == "2"
            for row, lines, want, want_ro in ROWS:
                if read_only and want_ro is None:
                    continue
                if not read_only:
                    state_p(client)
                replies = [client.ask(line) for line in lines]
                expected = want_ro if read_only else want
                assert matches(replies[-1], expected), (row, replies, expected)
        finally:
            client.close()


def test_the_section_3_6_example_on_the_foreign_stage(stage) -> None:
    """The §3.6 session with this stage's limits (both 0-150 V, 50 V/ms): the recorder of each
    channel at the same indices, the command recorded (declared), SAFE bringing both to 0 V."""
    with serve(stage) as server:
        client = Client(server.url)
        try:
            assert client.ask("*IDN?").split(",")[1].endswith(";vrec=command")
            assert client.ask("CH 1 LIM?") == "0 150 50"
            for line in ("WTL 3", "WAV 0 3 0 2.5 5", "CH 1 WAV 0 3 0 1 2", "WGO 1"):
                assert client.ask(line) == "OK"
            time.sleep(0.01)
            y = client.ask("CH 1 DRR? 0 3").split()
            x = client.ask("DRR? 0 3").split()
            assert y[:2] == x[:2] == ["0", "3"]
            assert [float(v) for v in y[3::2]] == [0.0, 1.0, 2.0]
            assert [float(v) for v in x[3::2]] == [0.0, 2.5, 5.0]
            assert all(math.isfinite(float(v)) for v in x[2::2] + y[2::2])
            assert client.ask("STA?").split()[3] == "out=5"
            assert client.ask("SAFE") == "OK"
            assert client.ask("CH 1 VOL?") == "0" and client.ask("VOL?") == "0"
        finally:
            client.close()


def read_recorder(client: Client, channel: int, n: int) -> np.ndarray:
    out = []
    for first in range(0, n, 256):
        words = client.ask(f"CH {channel} DRR? {first} {min(256, n - first)}").split()[2:]
        out.append(np.array(words, dtype=float).reshape(-1, 2))
    return np.vstack(out)


def test_a_held_channel_records_the_plants_coupling(stage) -> None:
    """Channel 0 (x) plays a 5 Hz triangle over its range; channel 1 (y), set to 60 V and never
    written, is held there (§2.14(c)): its recorder holds 60 V and its reading moves with x by
    the stage's static coupling (within 1 %; measured 0.2 %)."""
    with serve(stage) as server:
        client = Client(server.url)
        try:
            for v in range(5, 65, 5):
                assert client.ask(f"CH 1 SVA {v}") == "OK"
            tri = 75.0 - 75.0 * np.cos(np.linspace(0.0, 2 * np.pi, 2001)[:-1])
            assert client.ask("WTL 2000") == "OK"
            for first in range(0, 2000, 200):
                chunk = " ".join(f"{v:.4f}" for v in tri[first:first + 200])
                assert client.ask(f"WAV {first} 200 {chunk}") == "OK"
            assert client.ask("WGO 1") == "OK"
            time.sleep(0.3)
            assert re.search(r"running=0 fill=2000", client.ask("STA?"))
            x, y = read_recorder(client, 0, 2000), read_recorder(client, 1, 2000)
        finally:
            client.close()
    assert np.all(y[:, 1] == 60.0)
    np.testing.assert_allclose(x[:, 1], tri.astype(np.float32), atol=1e-4)
    slope = np.polyfit(x[:, 0], y[:, 0], 1)[0]
    want = xs.true_coupling(stage, np.zeros(0))["yx_static"]
    assert slope == pytest.approx(want, rel=0.01)


def wav(client: Client, channel: int, first: int, values: np.ndarray) -> str:
    body = " ".join(f"{v:.4f}" for v in values)
    return client.ask(f"CH {channel} WAV {first} {values.size} {body}")


def test_a_stream_of_both_channels_and_an_underrun_of_one(stage) -> None:
    """§2.14(h) at 1 kHz through a 256-sample table: both channels refilled as played record
    exactly what a single run would (the commands, declared); then a stream whose channel 1 is
    not refilled underruns at the first sample channel 1 lacks (error 10, both outputs to 0 V),
    where a completed one leaves each output at its last sample (§2.2(d))."""
    n, table, block = 768, 256, 128
    k = np.arange(n)
    wave = np.column_stack([60 + 40 * np.sin(2 * np.pi * k / 300),
                            50 + 30 * np.sin(2 * np.pi * k / 200)])
    with serve(stage) as server:
        client = Client(server.url)
        try:
            for refill_y, want_end in ((True, "error=0"), (False, "error=10")):
                for line in ("SAFE", "WTR 1000", f"WTL {table}", "ERR?"):
                    client.ask(line)
                for c in (0, 1):
                    for first in range(0, table, block):
                        assert wav(client, c, first, wave[first:first + block, c]) == "OK"
                for c, v in enumerate(wave[0]):  # the step into sample 0 is checked (§2.6(e))
                    for step in np.linspace(0, v, 5)[1:]:
                        assert client.ask(f"CH {c} SVA {step:.4f}") == "OK"
                assert client.ask(f"WGS {n}") == "OK"
                refilled = (0, 1) if refill_y else (0,)
                last = n if refill_y else table + block  # channel 0 one block past channel 1
                for nxt in range(table, last, block):
                    while int(client.ask("POS?")) < nxt + block - table:
                        time.sleep(0.005)
                    for c in refilled:
                        assert wav(client, c, nxt, wave[nxt:nxt + block, c]) == "OK"
                time.sleep(0.9)
                status = client.ask("STA?").split()
                assert "running=0" in status and want_end in status
                if refill_y:
                    assert f"pos={n}" in status
                    x, y = read_recorder(client, 0, n), read_recorder(client, 1, n)
                    np.testing.assert_allclose(np.column_stack([x[:, 1], y[:, 1]]),
                                               wave.astype(np.float32), atol=1e-4)
                    outs = [float(client.ask(q)) for q in ("VOL?", "CH 1 VOL?")]
                    np.testing.assert_allclose(outs, wave[-1], atol=1e-4)  # the last held
                else:
                    assert f"pos={table}" in status
                    assert client.ask("VOL?") == "0" and client.ask("CH 1 VOL?") == "0"
        finally:
            client.close()
