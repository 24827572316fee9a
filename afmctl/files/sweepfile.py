"""Sweep files: one recorded (voltage, displacement) history per file, and the standard set.

Format (text, UTF-8)::

    # frequency_hz: 5.58
    # layer_thickness_um: 100.0
    # profile: emulated
    time_s,voltage_V,displacement_um
    0.0000,0.0,0.012
    ...

``#`` lines before the header carry ``key: value`` metadata (all optional). The header must name
``time_s``, ``voltage_V`` and ``displacement_um`` in any order; extra columns are allowed and kept
out of the numerics. Time must be finite, strictly increasing and uniformly sampled (the model is
discretized at one sample period). Files from other tools load without any metadata; the sensor
zero is arbitrary (identification fits an offset) and the field follows from the voltage and the
layer thickness if the metadata gives it.

Anything malformed raises :class:`SweepFormatError` (a :class:`~afmctl.files.tomlfile.FileFormatError`,
hence a ``ValueError``) with one line naming the file and the problem.

The standard identification set (:func:`standard_set`) follows the paper: nested minor loops at
low frequency (Fig. 1(b)) and triangle sweeps at 0.279, 5.58 and 27.9 Hz (Figs. 2 and 7).
"""

from __future__ import annotations

import io
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl.errors import InputError, SweepFormatError

FloatArray = NDArray[np.float64]
COLUMNS = ("time_s", "voltage_V", "displacement_um")
#: How far a sample's time may be off the uniform grid, as a fraction of the period.
JITTER_TOL = 0.1
#: Fraction of a sweep's voltage range within which an extreme counts as reached (memory_index).
MEMORY_REACH = 0.995


@dataclass(frozen=True)
class Recorded:
    """A recorded history on a uniform clock: what one-axis and two-axis sweeps share.

    Parameters
    ----------
    time_s : ndarray, shape (N,)
        Sample instants, s, strictly increasing and uniform.
    voltage_v : ndarray, shape (N,) or (N, 2)
        Voltage held from each instant to the next, V (a column per axis for two axes).
    displacement_um : ndarray, shape (N,) or (N, 2)
        Measured displacement at each instant, um (arbitrary sensor zero).
    meta : dict
        Metadata from the ``#`` lines (strings).
    path : str
        Where it was read from ("" if built in memory).
    """

    time_s: FloatArray
    voltage_v: FloatArray
    displacement_um: FloatArray
    meta: Mapping[str, str] = field(default_factory=dict)
    path: str = ""

    @property
    def dt(self) -> float:
        """Sample period, s."""
        return float((self.time_s[-1] - self.time_s[0]) / (self.time_s.size - 1))

    @property
    def name(self) -> str:
        return Path(self.path).name if self.path else self.meta.get("name", "sweep")

    @property
    def started_s(self) -> float:
        """When the first sample went out, s, on the stage's clock (the ``started_s`` that
        ``afmctl sweep`` records); NaN if the file does not say."""
        value = self.meta.get("started_s")
        return math.nan if value is None else float(value)


@dataclass(frozen=True)
class Sweep(Recorded):
    """One recorded sweep of one axis: :class:`Recorded` with arrays of shape (N,)."""

    @property
    def thickness_um(self) -> float | None:
        """Layer thickness from the metadata, um, or None if the file does not say."""
        val = self.meta.get("layer_thickness_um")
        return None if val is None else float(val)

    @property
    def frequency_hz(self) -> float | None:
        val = self.meta.get("frequency_hz")
        return None if val is None else float(val)

    @property
    def memory_index(self) -> int:
        """First sample at which the stage's state no longer depends on its unknown history.

        A sweep starts wherever earlier work left the stage. By the wiping-out property of the
        relay kernel (4), a monotone excursion to the sweep's largest voltage sets every hysteron
        that it can switch up, and one to its smallest voltage every hysteron it can switch down;
        from the later of the two first reaches on, a model started depoled and the stage agree
        (up to hysterons that no voltage of the sweep can switch: a constant offset). A voltage
        within ``1 - MEMORY_REACH`` of the range from an extreme counts as reaching it (peaks that
        differ in their last digits must not push the index to the last one).
        """
        v = self.voltage_v
        tol = (1 - MEMORY_REACH) * float(np.ptp(v))
        return max(int(np.argmax(v >= v.max() - tol)), int(np.argmax(v <= v.min() + tol)))

    def head(self, n: int) -> Sweep:
        """The sweep's first ``n`` samples (the same metadata and path)."""
        return Sweep(self.time_s[:n], self.voltage_v[:n], self.displacement_um[:n], self.meta,
                     self.path)

    def mask(self, window_s: tuple[float, float] | None) -> NDArray[np.bool_]:
        """Samples with ``t0 <= t < t1`` (all if ``window_s`` is None) from :attr:`memory_index`
        on: the samples on which a model run from the sweep's start can be judged."""
        m = np.ones(self.time_s.size, dtype=bool) if window_s is None else (
            (self.time_s >= window_s[0]) & (self.time_s < window_s[1]))
        m[:self.memory_index] = False
        return m


def _meta_line(line: str) -> tuple[str, str] | None:
    body = line.lstrip("#").strip()
    if ":" not in body:
        return None
    key, val = body.split(":", 1)
    return key.strip(), val.strip()


def _check_number(text: str) -> str:
    """Validate a metadata value that must be a positive finite number."""
    try:
        val = float(text)
    except ValueError:
        return "not a number"
    return "" if math.isfinite(val) and val > 0 else "must be a positive finite number"


def _delimiter(header_line: str) -> str:
    """``,`` unless the header is separated by ``;`` or tabs (spreadsheet exports)."""
    if "," not in header_line:
        for d in (";", "\t"):
            if d in header_line:
                return d
    return ","


def _split(where: str, text: str) -> tuple[dict[str, str], list[str], list[str], str]:
    meta: dict[str, str] = {}
    lines = text.splitlines()
    i = 0
    while i < len(lines) and (lines[i].startswith("#") or not lines[i].strip()):
        kv = _meta_line(lines[i]) if lines[i].startswith("#") else None
        if kv:
            meta[kv[0]] = kv[1]
        i += 1
    if i == len(lines):
        raise SweepFormatError(f"{where}: empty (no header line {','.join(COLUMNS)})")
    delim = _delimiter(lines[i])
    header = [h.strip().strip('"').strip() for h in lines[i].split(delim)]
    body = [ln for ln in lines[i + 1:] if ln.strip() and not ln.startswith("#")]
    return meta, header, body, delim


#: Unit spellings accepted in column names, and the factor to afmctl's unit (s, V, um).
UNITS = {
    "s": {"s": 1.0, "sec": 1.0, "ms": 1e-3, "us": 1e-6, "\u00b5s": 1e-6, "\u03bcs": 1e-6},
    "V": {"v": 1.0, "mv": 1e-3, "kv": 1e3},
    "um": {"um": 1.0, "\u00b5m": 1.0, "\u03bcm": 1.0, "micron": 1.0, "nm": 1e-3, "mm": 1e3,
           "m": 1e6},
}
#: Names of each quantity afmctl reads, lower case, and afmctl's unit for it.
QUANTITIES = {"time": (("time", "t"), "s"), "voltage": (("voltage", "volt", "v"), "V"),
              "displacement": (("displacement", "position", "disp"), "um"),
              "desired": (("desired",), "um")}
_NAME = re.compile(r"^\s*(?:([xy])\s*[_ ]\s*)?([a-z]+)\s*(?:[_ ]\s*([xy]))?\s*"
                   r"(?:[_ ]\s*([^\s()\[\]]+)|[_ ]?\s*[(\[]\s*([^\s()\[\]]+)\s*[)\]])\s*$")


def column_scale(name: str, column: str) -> float | None:
    """Factor from the unit in the header cell ``name`` to afmctl's unit for ``column`` (e.g.
    ``time_s``, or ``voltage_x_V`` for one axis of a two-axis file), or None if ``name`` is not
    that quantity (``displacement_nm`` -> 1e-3 for ``displacement_um``; ``Voltage (V)`` -> 1 for
    ``voltage_V``; ``time_ms`` -> 1e-3; ``X voltage (mV)`` -> 1e-3 for ``voltage_x_V``)."""
    if name == column:
        return 1.0
    parts = column.split("_")
    quantity, axis = parts[0], (parts[1] if len(parts) == 3 else None)
    spellings, unit = QUANTITIES[quantity]
    m = _NAME.match(name.lower())
    if m is None or m.group(2) not in spellings or (m.group(1) and m.group(3)):
        return None
    if (m.group(1) or m.group(3)) != axis:
        return None
    return UNITS[unit].get(m.group(4) or m.group(5))


def _locate(where: str, header: list[str], columns: tuple[str, ...]
            ) -> tuple[list[int], list[float]]:
    """Index and unit factor of each wanted column in ``header``."""
    index, scale, missing = [], [], []
    for col in columns:
        found = [(i, f) for i, h in enumerate(header) if (f := column_scale(h, col)) is not None]
        if not found:
            missing.append(col)
        else:
            index.append(found[0][0])
            scale.append(found[0][1])
    if missing:
        raise SweepFormatError(f"{where}: missing column {', '.join(missing)} "
                               f"(header is {','.join(header)})")
    return index, scale


def _decimal_comma(where: str, header: list[str], body: list[str], delim: str) -> None:
    """Name decimal commas in a comma-separated file as the cause of a ragged row."""
    if delim != ",":
        return
    for row, line in enumerate(body, 1):
        if line.count(",") + 1 != len(header):
            raise SweepFormatError(
                f"{where}: data row {row} has {line.count(',') + 1} fields for {len(header)} "
                f"columns: decimal commas in a comma-separated file? Save it with decimal points "
                f"or with ';' between columns")


def _parse_rows(where: str, header: list[str], body: list[str], delim: str,
                columns: tuple[str, ...] = COLUMNS) -> FloatArray:
    cols, scale = _locate(where, header, columns)
    if not body:
        raise SweepFormatError(f"{where}: no data rows")
    if delim != ",":  # ';' or tab between columns: a comma inside a number is a decimal comma
        body = [ln.replace(",", ".") for ln in body]
    else:
        _decimal_comma(where, header, body, delim)
    try:
        data = np.loadtxt(io.StringIO("\n".join(body)), delimiter=delim, usecols=cols, ndmin=2,
                          comments="#")
    except ValueError as exc:
        raise SweepFormatError(f"{where}: bad data row ({str(exc).splitlines()[-1]})") from None
    bad = np.flatnonzero(~np.all(np.isfinite(data), axis=1))
    if bad.size:
        raise SweepFormatError(f"{where}: non-finite value (NaN/inf) in data row {bad[0] + 1}")
    return data * np.asarray(scale)


def _check_increasing(where: str, t: FloatArray) -> None:
    if t.size < 2:
        raise SweepFormatError(f"{where}: need at least 2 samples, got {t.size}")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise SweepFormatError(f"{where}: time not strictly increasing at data row {bad[0] + 2}")


def uniform_time(where: str, t: FloatArray, rate_hz: float | None = None) -> FloatArray:
    """The uniform clock ``t0 + k dt`` a sampled time column stands for.

    ``dt`` is ``1 / rate_hz`` (the file's ``sample_rate_hz`` metadata) or the least-squares step. Each
    sample may be off that grid by up to ``JITTER_TOL`` of the period (float32 time columns, DAQ
    timestamps with jitter); otherwise :class:`SweepFormatError` names the worst sample, its
    deviation and the period.
    """
    _check_increasing(where, t)
    k = np.arange(t.size, dtype=float)
    slope, t0 = np.polyfit(k, t, 1) if t.size > 2 else (t[1] - t[0], t[0])
    if rate_hz:
        if abs(slope * rate_hz - 1) > JITTER_TOL / t.size:
            raise SweepFormatError(f"{where}: metadata sample_rate_hz {rate_hz:g} disagrees with "
                                   f"the time column ({1 / slope:.6g} Hz)")
        slope, t0 = 1.0 / rate_hz, float(np.mean(t - k / rate_hz))
    dt = float(slope)
    grid = t0 + k * dt
    dev = np.abs(t - grid)
    worst = int(np.argmax(dev))
    if dev[worst] > JITTER_TOL * dt:
        rate = "the sample_rate_hz metadata" if rate_hz else "a least-squares fit"
        raise SweepFormatError(
            f"{where}: time is not uniformly sampled: data row {worst + 1} is {dev[worst]:.3g} s "
            f"off the {dt:.6g} s grid of {rate} ({100 * dev[worst] / dt:.0f} % of a period; "
            f"tolerated {100 * JITTER_TOL:.0f} %)")
    return grid


def _rate(where: str, meta: dict[str, str]) -> float | None:
    for key in ("sample_rate_hz", "sample_rate_Hz"):
        if key in meta:
            if problem := _check_number(meta[key]):
                raise SweepFormatError(f"{where}: metadata {key}: {problem} ({meta[key]!r})")
            return float(meta[key])
    return None


def parse(text: str, where: str = "<sweep>") -> Sweep:
    """Parse the text of a sweep file (see the module docstring for the format)."""
    meta, header, body, delim = _split(where, text)
    if any(column_scale(h, "voltage_x_V") is not None for h in header):
        raise SweepFormatError(f"{where}: a two-axis sweep file (voltage_x_V, voltage_y_V, ...): "
                               f"this command reads one-axis sweeps (time_s,{','.join(COLUMNS[1:])})")
    rate = _rate(where, meta)
    if rate is not None and not any(column_scale(h, "time_s") is not None for h in header):
        data = _parse_rows(where, header, body, delim, COLUMNS[1:])
        t = np.arange(data.shape[0]) / rate
        data = np.column_stack([t, data])
    else:
        data = _parse_rows(where, header, body, delim)
    t = uniform_time(where, data[:, 0], rate)
    for key in ("layer_thickness_um", "frequency_hz"):
        if key in meta and (problem := _check_number(meta[key])):
            raise SweepFormatError(f"{where}: metadata {key}: {problem} ({meta[key]!r})")
    return Sweep(t, data[:, 1].copy(), data[:, 2].copy(), meta, where)


#: The longest hold between two sweeps across which a model follows the stage from one to the
#: next, s (:func:`holds_s`): a longer one is another session, whose work is not known.
HOLD_MAX_S = 600.0


def holds_s(sweeps: Sequence[Recorded]) -> list[float]:
    """How long the stage held between each sweep's end and the next one's first sample, s,
    from their :attr:`Recorded.started_s` (the first sweep's: NaN); NaN where either lacks it,
    the sample periods differ, the next started before the last ended, or the hold is over
    :data:`HOLD_MAX_S`. What a creeping stage did between two sweeps of a set, when the set says."""
    out = [math.nan]
    for a, b in zip(sweeps[:-1], sweeps[1:]):
        gap = b.started_s - a.started_s - a.voltage_v.shape[0] * a.dt
        same = math.isclose(a.dt, b.dt, rel_tol=1e-9)
        out.append(gap if same and 0.0 <= gap <= HOLD_MAX_S else math.nan)
    return out


def in_recorded_order(sweeps: Sequence[Recorded]) -> list[Recorded]:
    """``sweeps`` in the order they were recorded, when every one says when it started
    (``started_s``; a shell glob sorts ``triangle_27.9hz`` before ``triangle_5.58hz``); as given
    otherwise."""
    if any(not math.isfinite(s.started_s) for s in sweeps):
        return list(sweeps)
    return sorted(sweeps, key=lambda s: s.started_s)


def read_text(path: str | Path) -> str:
    """The UTF-8 text of a data file; :class:`SweepFormatError` if absent, binary or not UTF-8."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise SweepFormatError(f"{p}: no such file") from None
    except OSError as exc:
        raise SweepFormatError(f"{p}: cannot read ({exc.strerror})") from None
    if b"\x00" in raw:
        raise SweepFormatError(f"{p}: not a text file")
    try:
        text = raw.decode("utf-8-sig")  # tolerate a byte-order mark from spreadsheet tools
    except UnicodeDecodeError:
        raise SweepFormatError(f"{p}: not UTF-8 text") from None
    return text


def read(path: str | Path) -> Sweep:
    """Read and validate a sweep file; :class:`SweepFormatError` (one line) on anything wrong."""
    return parse(read_text(path), str(path))


def read_all(paths: str | Path | Sequence[str | Path]) -> list[Sweep]:
    """Read several sweep files, in the order given (the order they were recorded in matters to
    identification), or every file matching a glob pattern such as ``"sweeps/*.csv"``, sorted.

    Raises :class:`~afmctl.errors.SweepFormatError` for the first bad file, and
    :class:`~afmctl.errors.InputError` for a pattern that matches nothing."""
    if isinstance(paths, str | Path):
        pattern = Path(paths)
        if pattern.exists():
            return [read(pattern)]
        found = sorted(pattern.parent.glob(pattern.name))
        if not found:
            raise InputError(f"{paths}: no such file, and no sweep file matches it")
        return [read(p) for p in found]
    return [read(p) for p in paths]


def complete_text(path: str | Path) -> str:
    """:func:`read_text`, refusing a sweep that was interrupted while it recorded (``afmctl sweep``
    streams into ``<name>.incomplete.csv`` and ends it ``# end: interrupted (...)``): a fit on
    part of a sweep, or on it beside its completed rerun, would be judged on the wrong data."""
    text = read_text(path)
    if any(ln.startswith("# end: interrupted") for ln in text.splitlines()[-3:]):
        raise SweepFormatError(f"{path}: an interrupted sweep (ends '# end: interrupted'); record "
                               f"the rest with afmctl sweep --resume and fit the complete file")
    return text


def read_complete(path: str | Path) -> Sweep:
    """:func:`read`, refusing an interrupted sweep (:func:`complete_text`)."""
    return parse(complete_text(path), str(path))


def read_trajectory(path: str | Path) -> tuple[FloatArray, FloatArray]:
    """A desired trajectory for ``afmctl track file``: columns ``time_s,desired_um`` (other units
    spelt as for sweeps; any other columns and ``#`` metadata allowed; time strictly increasing,
    not necessarily uniform)."""
    where = str(path)
    _, header, body, delim = _split(where, read_text(path))
    data = _parse_rows(where, header, body, delim, ("time_s", "desired_um"))
    _check_increasing(where, data[:, 0])
    return data[:, 0].copy(), data[:, 1].copy()


def measured_kind(path: str | Path) -> str:
    """What measured data the file ``path`` holds ("a sweep file", "an afmctl run file"), or ""
    if it holds none that afmctl recognises (outputs may then replace it with --force)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536).decode("utf-8-sig", errors="replace")
    except OSError:
        return ""
    if "# afmctl-run:" in head:
        return "an afmctl run file"
    lines = [ln for ln in head.splitlines() if ln.strip() and not ln.startswith("#")]
    if not lines:
        return ""
    cells = [h.strip().strip('"').strip() for h in lines[0].split(_delimiter(lines[0]))]
    has = {col: any(column_scale(c, col) is not None for c in cells)
           for col in ("time_s", "voltage_V", "displacement_um")}
    if not (has["time_s"] or has["voltage_V"]):
        return ""
    if has["displacement_um"]:
        return "a sweep file"
    if any(c.lower().startswith(("displacement", "position")) for c in cells):
        return "measured displacements"  # e.g. track's run.csv: displacement_um_<filter>
    return ""


def _header(meta: Mapping[str, str], columns: Sequence[str] = COLUMNS) -> str:
    return "".join(f"# {key}: {val}\n" for key, val in meta.items()) + ",".join(columns) + "\n"


def _write_rows(fh: Any, time_s: FloatArray, voltage_v: FloatArray,
                displacement_um: FloatArray) -> None:
    """Rows ``time_s, voltage(s), displacement(s)``: arrays of shape (N,) or (N, C)."""
    rows = np.column_stack([time_s, voltage_v, displacement_um])
    np.savetxt(fh, rows, delimiter=",", fmt=("%.7f",) + ("%.6f",) * (rows.shape[1] - 1))


def format_text(sweep: Recorded, columns: Sequence[str] = COLUMNS) -> str:
    """The text of a sweep file for ``sweep`` (``columns``: its header, one voltage and one
    displacement column per axis)."""
    out = io.StringIO()
    out.write(_header(sweep.meta, columns))
    _write_rows(out, sweep.time_s, sweep.voltage_v, sweep.displacement_um)
    return out.getvalue()


class SweepStream:
    """A sweep file written as its samples arrive, in order: created with the first of them (a
    sweep that received none leaves no file), flushed and fsynced per block, and ended
    ``# end: interrupted (...)`` if the sweep is cut short (it then still reads as a sweep of the
    samples it holds). The same format as :func:`write`; ``columns`` names the header's columns
    (:data:`COLUMNS`; a two-axis file's, :data:`afmctl.files.xysweepfile.COLUMNS`, takes samples
    of shape (m, 2))."""

    def __init__(self, path: Path, meta: Mapping[str, str], sample_rate_hz: float,
                 columns: Sequence[str] = COLUMNS) -> None:
        self.path, self.meta, self.sample_rate_hz = path, dict(meta), sample_rate_hz
        self.columns = tuple(columns)
        self._fh: Any = None

    def append(self, first: int, voltage_v: FloatArray, displacement_um: FloatArray) -> None:
        """Samples ``first ...`` (their time from the sample rate), V and um, shape (m,) or
        (m, C) as the columns."""
        if self._fh is None:
            self._fh = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 (closed in close)
            self._fh.write(_header(self.meta, self.columns))
        t = np.arange(first, first + len(voltage_v)) / self.sample_rate_hz
        _write_rows(self._fh, t, voltage_v, displacement_um)
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def close(self, interrupted: str | None = None) -> None:
        """Close the file (if samples arrived), ended as interrupted with the reason if given."""
        if self._fh is None:
            return
        if interrupted is not None:
            self._fh.write(f"# end: interrupted ({interrupted})\n")
        self._fh.close()
        self._fh = None


def write(sweep: Sweep, path: str | Path) -> None:
    """Write ``sweep`` atomically (temporary file, then rename)."""
    write_atomic(path, format_text(sweep))


def write_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and a rename: never half a file."""
    p = Path(path)
    tmp = p.with_name(p.name + ".partial")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, p)


def from_arrays(voltage_v: FloatArray, displacement_um: FloatArray, sample_rate_hz: float,
                meta: Mapping[str, str] | None = None, path: str = "") -> Sweep:
    """A :class:`Sweep` on the uniform clock ``t_k = k / sample_rate_hz``."""
    v = np.asarray(voltage_v, dtype=float)
    return Sweep(np.arange(v.shape[0]) / sample_rate_hz, v,
                 np.asarray(displacement_um, dtype=float), dict(meta or {}), path)
