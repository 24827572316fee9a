"""Waveform files: a voltage waveform to replay on a stage (``afmctl play``).

Layout (what ``afmctl track --learn`` writes as ``waveform_learned.csv``)::

    # afmctl-waveform: 1
    # profile: emulated
    # model: model.toml
    # trajectory: triangle 27.9 Hz, 27.04 um
    # period_s: 0.0358423
    time_s,voltage_V,desired_um
    0.0000000,0.000000,
    ...

``time_s`` must be uniformly spaced at the stage's sample period; ``desired_um`` is optional (empty
on the conditioning and the ramps) and, when present, is what a replay is scored against.
``reference_um`` (optional, learned waveforms) is the reference the waveform's voltages invert
(Algorithm 3's target: the desired trajectory plus what learning added), which a replay that
re-learns (``afmctl play --relearn``) starts from. Any ``time_s,voltage_V`` file with ``#``
metadata lines (or none) is a waveform file.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from afmctl.errors import FileFormatError
from afmctl.files import sweepfile as sweeps

FloatArray = NDArray[np.float64]
FORMAT_VERSION = 1


@dataclass(frozen=True)
class WaveformFile:
    """A waveform read back: samples every ``dt_s`` seconds, desired NaN where absent, the
    learned reference (um, NaN where absent) or None without that column."""

    meta: dict[str, str]
    dt_s: float
    voltage_v: FloatArray
    desired_um: FloatArray
    reference_um: FloatArray | None = None


def format_text(time_s: FloatArray, voltage_v: FloatArray, desired_um: FloatArray,
                meta: Mapping[str, object], reference_um: FloatArray | None = None) -> str:
    """The file's text: metadata, header, one row per sample (desired and the optional
    reference empty where NaN)."""
    head = {"afmctl-waveform": FORMAT_VERSION, **meta}
    lines = [f"# {k}: {str(v).replace(chr(10), ' ')}" for k, v in head.items()]
    cols = [desired_um] if reference_um is None else [desired_um, reference_um]
    lines.append("time_s,voltage_V,desired_um" + ("" if reference_um is None else ",reference_um"))
    lines += [f"{t:.7f},{v:.6f}," + ",".join('' if math.isnan(x) else f'{x:.6f}' for x in xs)
              for t, v, *xs in zip(time_s, voltage_v, *cols, strict=True)]
    return "\n".join(lines) + "\n"


def _cells(where: str, n: int, row: list[str], width: int) -> list[float]:
    if len(row) != width:
        raise FileFormatError(f"{where}: line {n}: {len(row)} columns, expected {width}")
    try:
        vals = [float(c) if c.strip() else math.nan for c in row]
    except ValueError:
        raise FileFormatError(f"{where}: line {n}: not a number") from None
    return vals


def parse(text: str, where: str = "<waveform>") -> WaveformFile:
    """Read a waveform file's text.

    Raises
    ------
    FileFormatError
        Missing ``time_s`` or ``voltage_V``, a non-number, a missing voltage, a non-finite or not
        uniformly increasing time.
    """
    meta: dict[str, str] = {}
    header: list[str] | None = None
    rows: list[list[float]] = []
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        if line.startswith("#"):
            key, _, val = line[1:].strip().partition(":")
            meta[key.strip()] = val.strip()
        elif header is None:
            header = [c.strip() for c in line.split(",")]
            for col in ("time_s", "voltage_V"):
                if col not in header:
                    raise FileFormatError(f"{where}: missing column {col}")
        else:
            rows.append(_cells(where, n, line.split(","), len(header)))
    if header is None or len(rows) < 2:
        raise FileFormatError(f"{where}: no header or fewer than 2 samples")
    data = np.array(rows)
    t, v = data[:, header.index("time_s")], data[:, header.index("voltage_V")]
    d = data[:, header.index("desired_um")] if "desired_um" in header else np.full(t.size, np.nan)
    r = data[:, header.index("reference_um")] if "reference_um" in header else None
    if not (np.isfinite(t).all() and np.isfinite(v).all()):
        raise FileFormatError(f"{where}: time_s and voltage_V must be finite in every row")
    steps = np.diff(t)
    dt = float(np.mean(steps))
    if dt <= 0 or np.max(np.abs(steps - dt)) > 1e-3 * dt + 1e-7:
        raise FileFormatError(f"{where}: time_s must increase in equal steps")
    return WaveformFile(meta, dt, v, d, r)


def read(path: str | Path) -> WaveformFile:
    """Read a waveform file (one line naming the file if it is absent, binary or malformed)."""
    return parse(sweeps.read_text(path), str(path))
