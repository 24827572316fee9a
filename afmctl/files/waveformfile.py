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

A two-axis waveform (what ``afmctl scan raster --learn-frames`` writes) has a voltage and a
desired column per axis, channel 0 x and 1 y::

    time_s,voltage_x_V,voltage_y_V,desired_x_um,desired_y_um

and :class:`WaveformFile`'s arrays then have shape (N, 2).
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
from afmctl.model.xy import AXES

FloatArray = NDArray[np.float64]
FORMAT_VERSION = 1


@dataclass(frozen=True)
class WaveformFile:
    """A waveform read back: samples every ``dt_s`` seconds, desired NaN where absent, shape (N,)
    or, for a two-axis file, (N, 2); the learned reference (um, NaN where absent) or None without
    that column (one-axis files only)."""

    meta: dict[str, str]
    dt_s: float
    voltage_v: FloatArray
    desired_um: FloatArray
    reference_um: FloatArray | None = None


def format_text(time_s: FloatArray, voltage_v: FloatArray, desired_um: FloatArray,
                meta: Mapping[str, object], reference_um: FloatArray | None = None) -> str:
    """The file's text: metadata, header, one row per sample (desired and the optional
    reference empty where NaN); a two-axis file for voltages of shape (N, 2)."""
    head = {"afmctl-waveform": FORMAT_VERSION, **meta}
    lines = [f"# {k}: {str(v).replace(chr(10), ' ')}" for k, v in head.items()]
    two = np.ndim(voltage_v) == 2
    n = len(time_s)
    extra = () if reference_um is None else ("reference_um",)
    lines.append(",".join((*_columns(two), *extra)))
    v2 = np.asarray(voltage_v, dtype=float).reshape(n, -1)
    d2 = np.asarray(desired_um, dtype=float).reshape(n, -1)
    if reference_um is not None:
        d2 = np.column_stack([d2, np.asarray(reference_um, dtype=float).reshape(n, -1)])
    lines += [f"{t:.7f}," + ",".join(f"{x:.6f}" for x in v) + ","
              + ",".join("" if math.isnan(x) else f"{x:.6f}" for x in d)
              for t, v, d in zip(time_s, v2, d2, strict=True)]
    return "\n".join(lines) + "\n"


def _columns(two: bool) -> tuple[str, ...]:
    if not two:
        return ("time_s", "voltage_V", "desired_um")
    return ("time_s", *(f"voltage_{a}_V" for a in AXES), *(f"desired_{a}_um" for a in AXES))


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
            wanted = ("time_s", "voltage_x_V" if "voltage_x_V" in header else "voltage_V")
            for col in (*wanted, *(("voltage_y_V",) if "voltage_x_V" in header else ())):
                if col not in header:
                    raise FileFormatError(f"{where}: missing column {col}")
        else:
            rows.append(_cells(where, n, line.split(","), len(header)))
    if header is None or len(rows) < 2:
        raise FileFormatError(f"{where}: no header or fewer than 2 samples")
    data = np.array(rows)
    t = data[:, header.index("time_s")]
    v, d = _channels(data, header, "voltage_x_V" in header)
    r = data[:, header.index("reference_um")] if "reference_um" in header else None
    if not (np.isfinite(t).all() and np.isfinite(v).all()):
        raise FileFormatError(f"{where}: time_s and voltage_V must be finite in every row")
    steps = np.diff(t)
    dt = float(np.mean(steps))
    if dt <= 0 or np.max(np.abs(steps - dt)) > 1e-3 * dt + 1e-7:
        raise FileFormatError(f"{where}: time_s must increase in equal steps")
    return WaveformFile(meta, dt, v, d, r)


def _channels(data: FloatArray, header: list[str], two: bool) -> tuple[FloatArray, FloatArray]:
    """The voltage and desired columns, (N,) or (N, 2) for a two-axis file (desired NaN where
    absent)."""
    cols = _columns(two)[1:]
    half = len(cols) // 2
    missing = np.full(data.shape[0], np.nan)
    got = [data[:, header.index(c)] if c in header else missing for c in cols]
    if not two:
        return got[0], got[1]
    return np.column_stack(got[:half]), np.column_stack(got[half:])


def read(path: str | Path) -> WaveformFile:
    """Read a waveform file (one line naming the file if it is absent, binary or malformed)."""
    return parse(sweeps.read_text(path), str(path))
