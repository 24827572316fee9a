"""One axis of a stage of several channels, as the one-axis stage every experiment drives.

``afmctl track --axis y`` runs today's one-axis experiment on channel 1 of a two-axis stage: the
waveform goes to that channel while every other channel holds the output it has (its present
voltage, repeated on every sample of the (N, C) waveform the stage receives: the stage's guard
checks each channel against its own axis's limits before anything is sent). What the held
channels' sensors read is kept: how far the held axes moved while this one was driven.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class AxisStage:
    """Channel ``channel`` of ``stage`` as a one-axis stage (other methods: the stage's own).

    Parameters
    ----------
    stage : Stage
        A stage of ``stage.channels`` channels (``afmctl.drivers``).
    channel : int
        The channel driven.
    """

    def __init__(self, stage: Any, channel: int) -> None:
        if not 0 <= channel < stage.channels:
            raise ValueError(f"channel {channel} of a stage of {stage.channels}")
        self._stage, self.channel = stage, channel
        self._held: list[tuple[FloatArray, FloatArray]] = []  # (voltage held, readings) per play

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stage, name)

    def voltage(self) -> float:
        """The driven channel's present output, V."""
        return float(self._stage.voltages()[self.channel])

    def set_voltage(self, v: float) -> None:
        self._stage.set_voltage(v, channel=self.channel)

    def play(self, waveform_v: Any, on_block: Callable[..., None] | None = None,
             **kw: Any) -> Any:
        """Play ``waveform_v`` (N,) on the channel, the others held at their present outputs;
        the recording of the channel alone (as a one-axis stage's)."""
        v = np.asarray(waveform_v, dtype=float)
        held = np.asarray(self._stage.voltages(), dtype=float)
        wave = np.tile(held, (v.size, 1))
        wave[:, self.channel] = v
        ch = self.channel

        def block(first: int, volt: Any, disp: Any, valid: Any) -> None:
            assert on_block is not None
            on_block(first, volt[:, ch], disp[:, ch], valid[:, ch])

        rec = self._stage.play(wave, block if on_block is not None else None, **kw)
        others = [c for c in range(wave.shape[1]) if c != ch]
        ok = np.all(np.asarray(rec.valid)[:, others], axis=1)
        self._held.append((held[others], np.asarray(rec.displacement_um)[ok][:, others]))
        return dataclasses.replace(rec, voltage_v=rec.voltage_v[:, ch],
                                   displacement_um=rec.displacement_um[:, ch],
                                   valid=rec.valid[:, ch])

    def held_motion(self) -> dict[str, float]:
        """How far the held channel moved over every play so far: RMS and peak of its readings
        about each play's mean, um, and the voltage it was held at (the last play's), V."""
        parts = [d - d.mean(axis=0) for _, d in self._held if d.shape[0]]
        if not parts:
            return {"rms_um": float("nan"), "peak_um": float("nan"), "samples": 0}
        dev = np.concatenate(parts)[:, 0]
        return {"rms_um": float(np.sqrt(np.mean(dev ** 2))), "peak_um": float(np.max(np.abs(dev))),
                "samples": int(dev.size), "held_voltage_V": float(self._held[-1][0][0])}
