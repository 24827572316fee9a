"""Run-data files: written as samples arrive, readable after any interruption.

Layout::

    # afmctl-run: 1
    # software: afmctl 0.1.0
    # profile: emulated
    # ... (key: value metadata, written and flushed before the first sample)
    seq,time_s,desired_um,voltage_V,displacement_um,status
    0,0.0000000,,0.000000,0.012345,ok
    ...
    # end: complete

Every block of rows is flushed and fsynced as it is written. A file whose last line is not
``# end: complete`` is incomplete (the run was interrupted, or the process died); it still reads, and
:func:`read` reports it. ``status`` is ``ok``, ``missing`` (the sample never arrived: its
displacement is left empty, never invented) or ``not played`` (after an interrupt or a failure:
the stage never played it, or is not known to have; its voltage is left empty too).

A run of several axes (a raster scan on an x/y stage) has one ``desired``, ``voltage`` and
``displacement`` column per axis, named by axis (:func:`columns`)::

    seq,time_s,desired_x_um,desired_y_um,voltage_x_V,voltage_y_V,displacement_x_um,displacement_y_um,status

and :class:`Run`'s arrays then have shape (N, axes) in the order of :attr:`Run.axes`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO

import numpy as np
from numpy.typing import NDArray

from afmctl._version import __version__
from afmctl.errors import FileFormatError

FORMAT_VERSION = 1
COLUMNS = ("seq", "time_s", "desired_um", "voltage_V", "displacement_um", "status")


def columns(axes: tuple[str, ...] = ()) -> tuple[str, ...]:
    """The header of a run of ``axes`` (none: the one-axis :data:`COLUMNS`)."""
    if not axes:
        return COLUMNS
    return ("seq", "time_s", *(f"desired_{a}_um" for a in axes),
            *(f"voltage_{a}_V" for a in axes), *(f"displacement_{a}_um" for a in axes), "status")


def _cells(values: NDArray[np.float64], digits: int) -> str:
    return ",".join(_cell(float(x), digits) for x in np.atleast_1d(values))


def _cell(x: float, digits: int) -> str:
    return "" if not math.isfinite(x) else f"{x:.{digits}f}"


class RunWriter:
    """Append-only writer of one run (context manager).

    Parameters
    ----------
    path : Path
        File to create (an existing file is refused: measured data is never overwritten).
    meta : mapping
        Metadata written first (profile, model, filter, ...); the software version is added.
    axes : tuple of str
        The axes of a run of several (:func:`columns`); none: a one-axis run.
    """

    def __init__(self, path: str | Path, meta: Mapping[str, object],
                 axes: tuple[str, ...] = ()) -> None:
        self.path = Path(path)
        self._fh: IO[str] = open(self.path, "x", encoding="utf-8")  # noqa: SIM115
        self._closed = False
        self.rows = 0
        head = {"afmctl-run": FORMAT_VERSION, "software": f"afmctl {__version__}", **meta}
        self._fh.write("".join(f"# {k}: {v}\n" for k, v in head.items()))
        self._fh.write(",".join(columns(axes)) + "\n")
        self._sync()

    def _sync(self) -> None:
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def write(self, seq: NDArray[np.int64], time_s: NDArray[np.float64],
              desired_um: NDArray[np.float64], voltage_v: NDArray[np.float64],
              displacement_um: NDArray[np.float64], status: str | None = None) -> None:
        """Append a block of samples (NaN displacement = missing; ``status`` for all of them
        instead, e.g. ``not played``) and flush it to disk. A run of several axes takes arrays
        of shape (m, axes)."""
        lines = []
        for s, t, d, v, u in zip(seq, time_s, desired_um, voltage_v, displacement_um, strict=True):
            if status is None:
                status_k = "ok" if np.isfinite(u).all() else "missing"
            else:
                status_k = status
            lines.append(f"{int(s)},{t:.7f},{_cells(d, 6)},{_cells(v, 6)},{_cells(u, 6)},"
                         f"{status_k}\n")
        self._fh.write("".join(lines))
        self.rows += len(lines)
        self._sync()

    def close(self, end: str = "complete") -> None:
        """Write the trailer ``# end: <end>`` (anything but ``complete`` marks it incomplete)."""
        if self._closed:
            return
        self._closed = True
        self._fh.write(f"# end: {end}\n")
        self._sync()
        self._fh.close()

    def __enter__(self) -> RunWriter:
        return self

    def __exit__(self, typ: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if typ is None:
            self.close("complete")
        else:
            self.close(f"interrupted ({typ.__name__}: {exc})".replace("\n", " "))


@dataclass(frozen=True)
class Run:
    """A run file read back. ``complete`` is False for an interrupted or truncated run. With
    ``axes`` (a run of several), ``desired_um``, ``voltage_v`` and ``displacement_um`` have shape
    (N, axes)."""

    meta: dict[str, str]
    seq: NDArray[np.int64]
    time_s: NDArray[np.float64]
    desired_um: NDArray[np.float64]
    voltage_v: NDArray[np.float64]
    displacement_um: NDArray[np.float64]
    complete: bool
    end: str
    axes: tuple[str, ...] = ()


def _float(cell: str) -> float:
    return float(cell) if cell else math.nan


def read(path: str | Path) -> Run:
    """Read a run file, complete or not (a torn last line from a crash is dropped)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FileFormatError(f"{p}: cannot read ({exc.__class__.__name__})") from None
    meta: dict[str, str] = {}
    rows: list[list[str]] = []
    end = "missing (the run did not finish)"
    header: tuple[str, ...] = ()
    axes: tuple[str, ...] = ()
    for line in text.splitlines(keepends=True):
        if line.startswith("# end: "):
            end = line[7:].strip()
        elif line.startswith("#"):
            key, _, val = line[1:].strip().partition(": ")
            meta[key] = val
        elif not header:
            header = tuple(line.strip().split(","))
            axes = _axes(header)
            if header != columns(axes):
                raise FileFormatError(f"{p}: not an afmctl run file (header {line.strip()!r})")
        elif line.endswith("\n") and line.count(",") == len(header) - 1:
            rows.append(line.rstrip("\n").split(","))
    if not header:
        raise FileFormatError(f"{p}: no column header")
    cols = list(zip(*rows, strict=True)) if rows else [()] * len(header)
    values = [np.array([_float(c) for c in col]) for col in cols[1:-1]]
    k = max(len(axes), 1)
    if axes:
        values = [values[0], *(np.column_stack(values[1 + i * k:1 + (i + 1) * k])
                               if rows else np.zeros((0, k)) for i in range(3))]
    return Run(meta, np.array(cols[0], dtype=np.int64), *values,
               complete=(end == "complete"), end=end, axes=axes)


def _axes(header: tuple[str, ...]) -> tuple[str, ...]:
    """The axes a header names (``desired_<axis>_um`` columns; none: a one-axis run)."""
    return tuple(c[len("desired_"):-len("_um")] for c in header
                 if c.startswith("desired_") and c.endswith("_um") and c != "desired_um")
