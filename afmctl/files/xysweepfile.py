"""Two-axis sweep files: one recorded (voltage, displacement) history of an x/y stage per file.

Format (text, UTF-8), the one-axis format of :mod:`afmctl.files.sweepfile` with a column per axis::

    # layer_thickness_x_um: 100.0
    # layer_thickness_y_um: 80.0
    # profile: emulated-xy
    time_s,voltage_x_V,voltage_y_V,displacement_x_um,displacement_y_um
    0.0000,0.0,75.0,0.012,0.431
    ...

The same ``#`` metadata and the same tolerance for lab spellings as one-axis files (units in the
header, ``;`` or tab separators with decimal commas, a byte-order mark, ``sample_rate_hz`` in place
of a time column), the axis named after the quantity or before it: ``Voltage X (V)``,
``x_displacement_nm``, ``displacement y [um]``. Metadata that differs per axis carries the axis in
its key (``layer_thickness_x_um``, ``frequency_y_hz``); a key without an axis holds for both.

A set may mix files where one axis moves and the other is held at any constant voltage, and files
where both move: :attr:`XYSweep.moving` says which axes a file drives, :meth:`XYSweep.axis` gives
one axis as a one-axis :class:`~afmctl.files.sweepfile.Sweep` (its per-axis metadata under the
one-axis keys) for everything one-axis code does.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from afmctl.errors import SweepFormatError
from afmctl.files import sweepfile as sw
from afmctl.model.xy import AXES

FloatArray = NDArray[np.float64]
COLUMNS = ("time_s", "voltage_x_V", "voltage_y_V", "displacement_x_um", "displacement_y_um")
#: Metadata keys that may differ per axis (``<stem>_<axis>_<unit>``), and their one-axis key.
AXIS_KEYS = {"layer_thickness": "um", "frequency": "hz"}
#: An axis whose voltage spans less than this (V) is held in that file.
HELD_SPAN_V = 1e-6


@dataclass(frozen=True)
class XYSweep(sw.Recorded):
    """One recorded sweep of a two-axis stage: :class:`~afmctl.files.sweepfile.Recorded` with
    ``voltage_v`` and ``displacement_um`` of shape (N, 2), axis x in column 0 and y in column 1."""

    @property
    def moving(self) -> tuple[str, ...]:
        """The axes whose voltage changes in this file (the others are held)."""
        return tuple(a for i, a in enumerate(AXES) if np.ptp(self.voltage_v[:, i]) > HELD_SPAN_V)

    def axis(self, name: str) -> sw.Sweep:
        """Axis ``name`` as a one-axis sweep (its per-axis metadata under the one-axis keys)."""
        i = AXES.index(name)
        meta = {k: v for k, v in self.meta.items() if not _axis_key(k)}
        for stem, unit in AXIS_KEYS.items():
            if (val := self.meta.get(f"{stem}_{name}_{unit}")) is not None:
                meta[f"{stem}_{unit}"] = val
        where = f"{self.path}[{name}]" if self.path else ""
        return sw.Sweep(self.time_s, self.voltage_v[:, i].copy(),
                        self.displacement_um[:, i].copy(), meta, where)


def _axis_key(key: str) -> bool:
    return any(key in (f"{stem}_{a}_{unit}" for a in AXES) for stem, unit in AXIS_KEYS.items())


def is_xy_header(header: Sequence[str]) -> bool:
    """True if a header names a per-axis voltage column (a two-axis sweep file)."""
    return any(sw.column_scale(h, "voltage_x_V") is not None for h in header)


def parse(text: str, where: str = "<sweep>") -> XYSweep:
    """Parse the text of a two-axis sweep file (see the module docstring)."""
    meta, header, body, delim = sw._split(where, text)
    rate = sw._rate(where, meta)
    if rate is not None and not any(sw.column_scale(h, "time_s") is not None for h in header):
        data = sw._parse_rows(where, header, body, delim, COLUMNS[1:])
        data = np.column_stack([np.arange(data.shape[0]) / rate, data])
    else:
        data = sw._parse_rows(where, header, body, delim, COLUMNS)
    t = sw.uniform_time(where, data[:, 0], rate)
    for key in meta:
        if (key in ("layer_thickness_um", "frequency_hz") or _axis_key(key)) and (
                problem := sw._check_number(meta[key])):
            raise SweepFormatError(f"{where}: metadata {key}: {problem} ({meta[key]!r})")
    return XYSweep(t, data[:, 1:3].copy(), data[:, 3:5].copy(), meta, where)


def read(path: str | Path) -> XYSweep:
    """Read a two-axis sweep file; :class:`SweepFormatError` (one line) on anything wrong,
    including an interrupted recording (``# end: interrupted``: see
    :func:`afmctl.files.sweepfile.complete_text`; :func:`parse` reads its rows) and a one-axis
    file."""
    return parse(sw.complete_text(path), str(path))


def is_xy_file(path: str | Path) -> bool:
    """True if ``path`` reads as text whose header names per-axis columns (a two-axis file)."""
    text = sw.read_text(path)
    _, header, _, _ = sw._split(str(path), text)
    return is_xy_header(header)


def read_set(paths: Sequence[str | Path]) -> list[XYSweep] | None:
    """Two-axis sweeps from ``paths`` if they are two-axis files, None if all are one-axis;
    :class:`SweepFormatError` for a set that mixes one- and two-axis files."""
    kinds = [is_xy_file(p) for p in paths]
    if not any(kinds):
        return None
    if not all(kinds):
        one = next(p for p, k in zip(paths, kinds, strict=True) if not k)
        raise SweepFormatError(f"{one}: a one-axis sweep file in a set of two-axis files "
                               f"(columns {','.join(COLUMNS)})")
    return [read(p) for p in paths]


def format_text(sweep: XYSweep) -> str:
    """The text of a two-axis sweep file for ``sweep``."""
    return sw.format_text(sweep, COLUMNS)


def write(sweep: XYSweep, path: str | Path) -> None:
    """Write ``sweep`` atomically (temporary file, then rename)."""
    sw.write_atomic(path, format_text(sweep))


def from_arrays(voltage_v: FloatArray, displacement_um: FloatArray, sample_rate_hz: float,
                meta: Mapping[str, str] | None = None, path: str = "") -> XYSweep:
    """An :class:`XYSweep` on the uniform clock ``t_k = k / sample_rate_hz`` (arrays (N, 2))."""
    s = sw.from_arrays(voltage_v, displacement_um, sample_rate_hz, meta, path)
    return XYSweep(s.time_s, s.voltage_v, s.displacement_um, s.meta, s.path)
