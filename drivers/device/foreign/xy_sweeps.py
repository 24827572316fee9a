"""Two-axis sweep sets of the foreign x/y stage (:mod:`~afmctl.drivers.device.foreign.xy_stage`),
in a design of their own (not afmctl's).

Every file is sampled at ``RATE_HZ`` (10 kHz) and stays within each axis's drive range and
``SLEW_V_PER_MS`` (50 V/ms, i.e. 5 V per sample). The stage is run through the whole set in
recording order on one state; between files the held axis is ramped to its next level at the
slew limit and both rest ``REST_S``, unrecorded (as a lab's script would). Readings carry
Gaussian sensor noise (each axis's own sigma).

Designs
-------
``held``
    For each axis in turn: triangles over its whole range at ``TRIANGLE_HZ`` (0.21, 3.3, 23 Hz;
    2, 6 and 12 periods), the other axis held at 25 %, 60 % and 85 % of its range (not
    mid-range); then a band-limited excitation of that axis about 45 % of its range with the other
    held at 70 %: x gets a Schroeder-phased multisine (1 Hz lines, log-spaced from 1 Hz to
    ``band_hz``, three periods of 1 s after one settling period), y a logarithmic chirp from 1 Hz
    to ``band_hz`` in 6 s. ``band_hz`` is half the stage's shared mode.
``mixed``
    ``held`` plus one file where both axes move: triangles at 1.3 Hz (x) and 0.7 Hz (y).

File format: ``time_s,voltage_x_V,voltage_y_V,displacement_x_um,displacement_y_um`` after ``#``
``key: value`` metadata as one-axis sweep files (:mod:`afmctl.files.sweepfile`) carry them:
``frequency_hz`` (the triangle's, or the multisine's line spacing), ``waveform``
(``triangle``, ``multisine``, ``chirp``), ``layer_thickness_um`` (nominal 100),
``sample_rate_hz``, plus ``swept_axis`` (``x``, ``y`` or ``x,y``), ``held_voltage_x_V`` /
``held_voltage_y_V`` for a held axis, ``band_hz`` for the multisine and chirp, ``stage``.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from afmctl.drivers.device.foreign.xy_stage import (
    XYState,
    XYStage,
    initial_state,
    mode_hz,
    noise_um,
    run,
)

FloatArray = NDArray[np.float64]
RATE_HZ = 10000.0
SLEW_V_PER_MS = 50.0
#: Largest slew a design uses, V/ms (a margin under the limit).
DESIGN_SLEW_V_PER_MS = 40.0
TRIANGLE_HZ = ((0.21, 2), (3.3, 6), (23.0, 12))
HELD_LEVELS = (0.25, 0.60, 0.85)
REST_S = 0.2
DESIGNS = ("held", "mixed")
COLUMNS = ("time_s", "voltage_x_V", "voltage_y_V", "displacement_x_um", "displacement_y_um")


@dataclass(frozen=True)
class XYPlan:
    """One two-axis file to record: ``voltage_V`` (N, 2) at :data:`RATE_HZ` and its metadata."""

    name: str
    voltage_V: FloatArray
    meta: dict[str, str] = field(default_factory=dict)


def _level(rng_V: tuple[float, float], frac: float) -> float:
    lo, hi = rng_V
    return lo + frac * (hi - lo)


def triangle(lo: float, hi: float, freq_hz: float, periods: int) -> FloatArray:
    """Triangle from ``lo`` up to ``hi`` and back, ``periods`` times, sampled at RATE_HZ."""
    n = int(round(periods * RATE_HZ / freq_hz))
    phase = (np.arange(n + 1) * freq_hz / RATE_HZ) % 1.0
    return lo + (hi - lo) * (1.0 - np.abs(2.0 * phase - 1.0))


def _limit(centre: float, wave: FloatArray, half_range: float) -> FloatArray:
    """``centre + a wave`` with ``a`` the largest scale keeping within ``half_range`` and
    :data:`DESIGN_SLEW_V_PER_MS`."""
    peak = float(np.max(np.abs(wave)))
    slew = float(np.max(np.abs(np.diff(wave)))) * RATE_HZ / 1000.0
    return centre + wave * min(half_range / peak, DESIGN_SLEW_V_PER_MS / slew)


def multisine(band_hz: float, periods: int = 4) -> FloatArray:
    """Unit-free Schroeder-phased multisine: 1 Hz lines, about 30 log-spaced from 1 Hz to
    ``band_hz`` (equal amplitudes), ``periods`` periods of 1 s."""
    lines = np.unique(np.round(np.geomspace(1.0, band_hz, 30)))
    k = np.arange(1, lines.size + 1)
    phases = -math.pi * k * (k - 1) / lines.size
    t = np.arange(int(periods * RATE_HZ)) / RATE_HZ
    return np.sum(np.cos(2 * math.pi * lines[:, None] * t + phases[:, None]), axis=0)


def chirp(band_hz: float, half_range_V: float, seconds: float = 6.0) -> FloatArray:
    """Logarithmic chirp 1 Hz -> ``band_hz`` in ``seconds`` about 0 V: amplitude ``half_range_V``
    or, where that would slew faster, :data:`DESIGN_SLEW_V_PER_MS` over ``2 pi f(t)``; half-second
    cosine tapers at both ends."""
    t = np.arange(int(seconds * RATE_HZ)) / RATE_HZ
    r = math.log(band_hz)
    f = np.exp(r * t / seconds)
    amp = np.minimum(half_range_V, DESIGN_SLEW_V_PER_MS * 1000.0 / (2 * math.pi * f))
    taper = np.clip(np.minimum(t, seconds - t) / 0.5, 0.0, 1.0)
    return amp * 0.5 * (1 - np.cos(math.pi * taper)) * np.sin(
        2 * math.pi * (f - 1.0) * seconds / r)


def _pair(axis: int, moving: FloatArray, held_V: float) -> FloatArray:
    out = np.full((moving.size, 2), held_V)
    out[:, axis] = moving
    return out


def _held_files(stage: XYStage, axis: int, band_hz: float) -> list[XYPlan]:
    name, other = "xy"[axis], "xy"[1 - axis]
    lo, hi = stage.actuators[axis].drive_range_V
    o_range = stage.actuators[1 - axis].drive_range_V
    plans = []
    for (f, periods), frac in zip(TRIANGLE_HZ, HELD_LEVELS, strict=True):
        held = _level(o_range, frac)
        plans.append(XYPlan(f"xy_{name}_triangle_{f:g}Hz",
                            _pair(axis, triangle(lo, hi, f, periods), held),
                            {"frequency_hz": f"{f:g}", "waveform": "triangle",
                             f"held_voltage_{other}_V": f"{held:g}"}))
    centre, half = _level((lo, hi), 0.45), 0.4 * (hi - lo)
    if axis == 0:
        wave, kind = _limit(centre, multisine(band_hz), half), "multisine"
        extra = {"frequency_hz": "1"}
    else:
        wave, kind = _limit(centre, chirp(band_hz, half), half), "chirp"
        extra = {}
    held = _level(o_range, 0.70)
    plans.append(XYPlan(f"xy_{name}_{kind}", _pair(axis, wave, held),
                        {**extra, "waveform": kind, "band_hz": f"{band_hz:g}",
                         f"held_voltage_{other}_V": f"{held:g}"}))
    return plans


def design_plans(stage: XYStage, design: str = "mixed") -> list[XYPlan]:
    """The files of ``design`` (one of :data:`DESIGNS`) for ``stage``, in recording order."""
    if design not in DESIGNS:
        raise ValueError(f"unknown design {design!r} (one of {', '.join(DESIGNS)})")
    band = 0.5 * mode_hz(stage.structure)
    plans = _held_files(stage, 0, band) + _held_files(stage, 1, band)
    if design == "mixed":
        (xlo, xhi), (ylo, yhi) = stage.drive_range_V
        x = triangle(xlo, xhi, 1.3, 4)
        y = triangle(ylo, yhi, 0.7, 2)[:x.size]
        both = np.column_stack([x, np.pad(y, (0, x.size - y.size), mode="edge")])
        plans.append(XYPlan("xy_both_triangles", both,
                            {"frequency_hz": "1.3", "waveform": "triangle"}))
    common = {"sample_rate_hz": f"{RATE_HZ:g}", "layer_thickness_um": "100.0",
              "stage": stage.name or "foreign-xy"}
    return [XYPlan(f"{i:02d}_{p.name}", p.voltage_V,
                   {**p.meta, **common, "swept_axis": _swept(p.voltage_V)})
            for i, p in enumerate(plans, 1)]


def _swept(voltage_V: FloatArray) -> str:
    moving = [ax for ax, col in zip("xy", voltage_V.T, strict=True) if np.ptp(col) > 0]
    return ",".join(moving)


def _move_to(stage: XYStage, state: XYState, start_V: FloatArray, target_V: FloatArray
             ) -> XYState:
    """Ramp both commands to ``target_V`` at the design slew, then rest REST_S (unrecorded)."""
    step = DESIGN_SLEW_V_PER_MS * 1000.0 / RATE_HZ
    n = int(math.ceil(float(np.max(np.abs(target_V - start_V))) / step)) + 1
    ramp = np.linspace(start_V, target_V, n)
    rest = np.repeat(target_V[None], int(REST_S * RATE_HZ), axis=0)
    _, _, state = run(stage, np.vstack([ramp, rest]), RATE_HZ, state)
    return state


def format_rows(plan: XYPlan, reading_um: FloatArray) -> str:
    """The file's text: metadata, header, rows."""
    n = plan.voltage_V.shape[0]
    out = io.StringIO()
    out.write("".join(f"# {k}: {v}\n" for k, v in plan.meta.items()) + ",".join(COLUMNS) + "\n")
    np.savetxt(out, np.column_stack([np.arange(n) / RATE_HZ, plan.voltage_V, reading_um]),
               delimiter=",", fmt=("%.5f", "%.4f", "%.4f", "%.5f", "%.5f"))
    return out.getvalue()


def record(stage: XYStage, plans: list[XYPlan], rng: np.random.Generator | None
           ) -> list[FloatArray]:
    """Run ``plans`` in order from power-on (moving between them as the module says) and return
    each one's readings (N, 2), um, with sensor noise from ``rng`` (None: noise free)."""
    state, last, out = initial_state(stage), np.zeros(2), []
    sigma = noise_um(stage)
    for plan in plans:
        state = _move_to(stage, state, last, plan.voltage_V[0])
        _, reading, state = run(stage, plan.voltage_V, RATE_HZ, state)
        if rng is not None:
            reading = reading + sigma * rng.standard_normal(reading.shape)
        out.append(reading)
        last = plan.voltage_V[-1]
    return out


def write_sweep_set(stage: XYStage, out_dir: str | Path, rng: np.random.Generator, *,
                    design: str = "mixed", extra: Sequence[XYPlan] = ()) -> list[Path]:
    """Record ``design`` on ``stage`` (:func:`record`) and write one file per plan.

    Parameters
    ----------
    stage : XYStage
    out_dir : str or Path
        Created if absent.
    rng : numpy.random.Generator
        The sensor noise.
    design : str
        One of :data:`DESIGNS`.
    extra : sequence of XYPlan
        Files recorded after the design's, numbered on from them (e.g. a host's own sweeps).

    Returns
    -------
    list of Path
        The files, in recording order (``NN_<name>.csv``), each written atomically.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plans = design_plans(stage, design)
    plans += [XYPlan(f"{len(plans) + i:02d}_{p.name}", p.voltage_V, p.meta)
              for i, p in enumerate(extra, 1)]
    paths = []
    for plan, reading in zip(plans, record(stage, plans, rng), strict=True):
        path = out / f"{plan.name}.csv"
        tmp = path.with_name(path.name + ".partial")
        tmp.write_text(format_rows(plan, reading), encoding="utf-8")
        tmp.replace(path)
        paths.append(path)
    return paths
