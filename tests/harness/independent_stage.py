"""A 0-150 V stage afmctl has never seen: the second device (:mod:`tests.harness.second_device`,
written from ``docs/reference/protocol.md`` alone) driving a foreign plant.

The device's protocol side is the second device's and uses no afmctl code; its physics is a foreign
stage (:mod:`afmctl.drivers.device.foreign.stage`, a plant written independently of afmctl's model:
relay hysterons, RK4 rod, gauge noise), drawn with a fixed seed, evolving while idle. Its DAQ cannot
measure the amplifier's output, so the recorder holds the command, and the device says so in
``*IDN?`` (§2.3(e)). Its table holds 16,384 samples (1.6 s at 10 kHz) and its recorder 65,536, so
long runs stream. The device logs the time of every ``WDT``, ``HB``, ``WGO``, ``WGS`` and ``SAFE``
(``device.commands``), so tests can see what a host does to it.
"""

from __future__ import annotations

import numpy as np

from afmctl.drivers.device.foreign import stage as foreign
from afmctl.drivers.device.foreign.stages import random_stage
from tests.harness.second_server import SecondStage

TABLE, RECORDER = 16384, 65536


class ForeignPlant:
    """The foreign stage drawn from ``seed`` (drive range 0-150 V, displacement span 90 um) in the
    second device's plant interface (``idle``, ``start_run``, ``play``)."""

    def __init__(self, seed: int = 5) -> None:
        self.rng = np.random.default_rng(seed)
        self.stage = random_stage(self.rng, span_um=90.0)  # 0-90 um: 45 +- 13.5 um in reach
        self.state = foreign.initial_state(self.stage, "poled+")
        self.amp = 0.0

    def idle(self, v_cmd: float, seconds: float) -> None:
        if seconds > 0:
            self.state = foreign.idle(self.stage, self.state, seconds, v_cmd)
        self.amp = v_cmd

    def start_run(self) -> None:
        self.state = foreign.start_run(self.stage, self.state, self.rng)

    def play(self, v_cmd: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Gauge readings at each sample instant, um, and the command (this DAQ's voltage)."""
        _, reading, self.state = foreign.run(self.stage, v_cmd, 1.0 / dt, self.state, self.rng)
        self.amp = float(v_cmd[-1])
        return reading, np.asarray(v_cmd, dtype=float)


class SocketStage(SecondStage):
    """The foreign stage behind the second device on ``socket://127.0.0.1:PORT`` (``url``)."""

    def __init__(self, seed: int = 5) -> None:
        super().__init__(plant=ForeignPlant(seed), records_command=True, table=TABLE,
                         recorder=RECORDER)
