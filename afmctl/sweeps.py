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

Anything malformed raises :class:`SweepFormatError` (a :class:`~afmctl.tomlfile.FileFormatError`,
hence a ``ValueError``) with one line naming the file and the problem.

The standard identification set (:func:`standard_set`) follows the paper: nested minor loops at
low frequency (Fig. 1(b)) and triangle sweeps at 0.279, 5.58 and 27.9 Hz (Figs. 2 and 7).
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from afmctl.tomlfile import FileFormatError

FloatArray = NDArray[np.float64]
COLUMNS = ("time_s", "voltage_V", "displacement_um")
STANDARD_FREQUENCIES_HZ = (0.279, 5.58, 27.9)
UNIFORM_RTOL = 1e-3
#: Fraction of a sweep's voltage range within which an extreme counts as reached (memory_index).
MEMORY_REACH = 0.995


class SweepFormatError(FileFormatError):
    """A sweep file is malformed; the message is one line naming the file."""


@dataclass(frozen=True)
class Sweep:
    """One recorded sweep.

    Parameters
    ----------
    time_s : ndarray, shape (N,)
        Sample instants, s, strictly increasing and uniform.
    voltage_v : ndarray, shape (N,)
        Voltage held from each instant to the next, V.
    displacement_um : ndarray, shape (N,)
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
    def thickness_um(self) -> float | None:
        """Layer thickness from the metadata, um, or None if the file does not say."""
        val = self.meta.get("layer_thickness_um")
        return None if val is None else float(val)

    @property
    def frequency_hz(self) -> float | None:
        val = self.meta.get("frequency_hz")
        return None if val is None else float(val)

    @property
    def name(self) -> str:
        return Path(self.path).name if self.path else self.meta.get("name", "sweep")

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


def _split(where: str, text: str) -> tuple[dict[str, str], list[str], list[str]]:
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
    header = [h.strip().strip('"').strip() for h in lines[i].split(",")]
    body = [ln for ln in lines[i + 1:] if ln.strip() and not ln.startswith("#")]
    return meta, header, body


def _parse_rows(where: str, header: list[str], body: list[str],
                columns: tuple[str, ...] = COLUMNS) -> FloatArray:
    missing = [c for c in columns if c not in header]
    if missing:
        raise SweepFormatError(f"{where}: missing column {', '.join(missing)} "
                               f"(header is {','.join(header)})")
    if not body:
        raise SweepFormatError(f"{where}: no data rows")
    cols = [header.index(c) for c in columns]
    try:
        data = np.loadtxt(io.StringIO("\n".join(body)), delimiter=",", usecols=cols, ndmin=2,
                          comments="#")
    except ValueError as exc:
        raise SweepFormatError(f"{where}: bad data row ({str(exc).splitlines()[-1]})") from None
    bad = np.flatnonzero(~np.all(np.isfinite(data), axis=1))
    if bad.size:
        raise SweepFormatError(f"{where}: non-finite value (NaN/inf) in data row {bad[0] + 1}")
    return data


def _check_increasing(where: str, t: FloatArray) -> None:
    if t.size < 2:
        raise SweepFormatError(f"{where}: need at least 2 samples, got {t.size}")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise SweepFormatError(f"{where}: time not strictly increasing at data row {bad[0] + 2}")


def _check_time(where: str, t: FloatArray) -> None:
    _check_increasing(where, t)
    d = np.diff(t)
    dt = (t[-1] - t[0]) / (t.size - 1)
    if np.max(np.abs(d - dt)) > UNIFORM_RTOL * dt:
        raise SweepFormatError(f"{where}: time is not uniformly sampled (period {dt:g} s)")


def parse(text: str, where: str = "<sweep>") -> Sweep:
    """Parse the text of a sweep file (see the module docstring for the format)."""
    meta, header, body = _split(where, text)
    data = _parse_rows(where, header, body)
    _check_time(where, data[:, 0])
    for key in ("layer_thickness_um", "frequency_hz"):
        if key in meta and (problem := _check_number(meta[key])):
            raise SweepFormatError(f"{where}: metadata {key}: {problem} ({meta[key]!r})")
    return Sweep(data[:, 0].copy(), data[:, 1].copy(), data[:, 2].copy(), meta, where)


def _read_text(path: str | Path) -> str:
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
    return parse(_read_text(path), str(path))


def read_trajectory(path: str | Path) -> tuple[FloatArray, FloatArray]:
    """A desired trajectory for ``afmctl track file``: columns ``time_s,desired_um`` (any other
    columns and ``#`` metadata allowed; time strictly increasing, not necessarily uniform)."""
    where = str(path)
    _, header, body = _split(where, _read_text(path))
    data = _parse_rows(where, header, body, ("time_s", "desired_um"))
    _check_increasing(where, data[:, 0])
    return data[:, 0].copy(), data[:, 1].copy()


def format_text(sweep: Sweep) -> str:
    """The text of a sweep file for ``sweep``."""
    out = io.StringIO()
    for key, val in sweep.meta.items():
        out.write(f"# {key}: {val}\n")
    out.write(",".join(COLUMNS) + "\n")
    np.savetxt(out, np.column_stack([sweep.time_s, sweep.voltage_v, sweep.displacement_um]),
               delimiter=",", fmt=("%.7f", "%.6f", "%.6f"))
    return out.getvalue()


def write(sweep: Sweep, path: str | Path) -> None:
    """Write ``sweep`` atomically (temporary file, then rename)."""
    p = Path(path)
    tmp = p.with_name(p.name + ".partial")
    tmp.write_text(format_text(sweep), encoding="utf-8")
    os.replace(tmp, p)


# ----------------------------------------------------------------------------------------------
# the standard identification set (pure waveforms)
# ----------------------------------------------------------------------------------------------


def triangle(frequency_hz: float, amplitude_v: float, cycles: float,
             sample_rate_hz: float) -> FloatArray:
    """Triangle wave 0 -> +A -> -A -> 0 per cycle, sampled at ``sample_rate_hz``.

    Parameters
    ----------
    frequency_hz : float
        Hz.
    amplitude_v : float
        Peak voltage, V.
    cycles : float
        Number of periods.
    sample_rate_hz : float
        Hz.

    Returns
    -------
    ndarray, shape (round(cycles * sample_rate_hz / frequency_hz) + 1,)
        Voltage, V.

    Examples
    --------
    >>> v = triangle(1.0, 2.0, 1, 8.0)
    >>> v.tolist()
    [0.0, 1.0, 2.0, 1.0, 0.0, -1.0, -2.0, -1.0, 0.0]
    """
    n = int(round(cycles * sample_rate_hz / frequency_hz))
    phase = (np.arange(n + 1) * frequency_hz / sample_rate_hz + 0.25) % 1.0
    return amplitude_v * (1.0 - 4.0 * np.abs(phase - 0.5))


def nested_loops(frequency_hz: float, amplitude_v: float, levels: int,
                 sample_rate_hz: float) -> FloatArray:
    """Nested minor loops (paper Fig. 1(b)): one triangle cycle per level, amplitudes decreasing
    linearly from ``amplitude_v`` to ``amplitude_v / levels``, all loops through 0 V.

    Returns the voltage, V, sampled at ``sample_rate_hz``.
    """
    parts = [triangle(frequency_hz, amplitude_v * (levels - i) / levels, 1, sample_rate_hz)[:-1]
             for i in range(levels)]
    return np.concatenate(parts + [np.zeros(1)])


def standard_set(amplitude_v: float = 150.0, sample_rate_hz: float = 10_000.0,
                 minor_loop_hz: float = 0.1,
                 minor_levels: int = 4) -> list[tuple[str, float, FloatArray]]:
    """The standard identification set as (name, frequency_hz, voltage_v) triples.

    Triangle sweeps at 0.279 Hz (2 cycles), 5.58 Hz (5 cycles) and 27.9 Hz (10 cycles), amplitude
    ``amplitude_v``, as in Fig. 2 / Fig. 7 of the paper, then the nested minor loops of Fig. 1(b)
    at ``minor_loop_hz``. The first three are what :func:`afmctl.identify.fit` is benchmarked on.

    Examples
    --------
    >>> [name for name, _, _ in standard_set(sample_rate_hz=1000.0)]
    ['triangle_0.279hz', 'triangle_5.58hz', 'triangle_27.9hz', 'minor_loops_0.1hz']
    """
    cycles = {0.279: 2, 5.58: 5, 27.9: 10}
    out = [(f"triangle_{f:g}hz", f, triangle(f, amplitude_v, cycles[f], sample_rate_hz))
           for f in STANDARD_FREQUENCIES_HZ]
    out.append((f"minor_loops_{minor_loop_hz:g}hz", minor_loop_hz,
                nested_loops(minor_loop_hz, amplitude_v, minor_levels, sample_rate_hz)))
    return out


def from_arrays(voltage_v: FloatArray, displacement_um: FloatArray, sample_rate_hz: float,
                meta: Mapping[str, str] | None = None, path: str = "") -> Sweep:
    """A :class:`Sweep` on the uniform clock ``t_k = k / sample_rate_hz``."""
    v = np.asarray(voltage_v, dtype=float)
    return Sweep(np.arange(v.size) / sample_rate_hz, v, np.asarray(displacement_um, dtype=float),
                 dict(meta or {}), path)
