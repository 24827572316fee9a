"""The images of a raster frame and its figures of merit (pure numerics).

The measured readbacks of both axes (the tracking part of a frame, one row per sample) are
sampled at every pixel of the trace and retrace images (:class:`~afmctl.planning.raster.PixelGrid`:
linear interpolation between the samples at the pixel's instant; a pixel next to a missing sample
is missing, never invented). Each image holds the measured x and y and the position error
(measured minus where the pixel should be) in x and y, per line and per frame.

Figures of merit (:func:`merit`), all over the image region (the overscan excluded):

* **fast-axis error**: the error along the fast direction (x for an unrotated frame), RMS and max,
  um and % of the frame width;
* **registration**: how far the same pixel of the trace and the retrace land apart along the fast
  direction, in pixels (RMS and max);
* **slow-axis deviation**: the error along the slow direction in line pitches (RMS and max);
* **line-synchronous slow motion**: the part of the slow error that repeats with the fast axis
  (the slow error less each line's mean): the motion the fast axis causes on the slow one through
  the coupling (what the feed-forward cancels), RMS um;
* per line (trace and retrace together): the RMS fast and slow error, um;
* the sensor noise of each axis (:func:`afmctl.planning.ilc.noise_estimate`, from the readings).

:func:`axis_errors` scores any two-axis run (a replayed waveform, no frame) per axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl.planning import ilc
from afmctl.planning.raster import AXES, Frame, PixelGrid

FloatArray = NDArray[np.float64]
DIRECTIONS = ("trace", "retrace")


@dataclass(frozen=True)
class Images:
    """A frame's images, each of shape (2, lines, pixels): index 0 the trace, 1 the retrace;
    rows by increasing slow coordinate; um. ``error_fast_um`` and ``error_slow_um`` are the
    error along the fast and the slow direction; ``registration_px`` (lines, pixels) how far
    the trace's pixel lands from the retrace's along the fast direction, in pixels."""

    x_um: FloatArray
    y_um: FloatArray
    error_x_um: FloatArray
    error_y_um: FloatArray
    error_fast_um: FloatArray
    error_slow_um: FloatArray
    registration_px: FloatArray

    def channels(self) -> dict[str, FloatArray]:
        """Every image by name (``x_trace``, ..., ``error_slow_retrace``), um."""
        out = {}
        for name in ("x", "y", "error_x", "error_y", "error_fast", "error_slow"):
            img = getattr(self, f"{name}_um")
            for k, d in enumerate(DIRECTIONS):
                out[f"{name}_{d}"] = img[k]
        return out


def sample_at(values: FloatArray, where: FloatArray) -> FloatArray:
    """``values`` (one per sample) linearly interpolated at the fractional sample indices
    ``where``; NaN next to a missing sample or outside the samples."""
    k = np.floor(where).astype(int)
    ok = (k >= 0) & (k + 1 < values.size)
    k = np.clip(k, 0, values.size - 2)
    w = where - k
    out = (1 - w) * values[k] + w * values[k + 1]
    return np.where(ok, out, np.nan)


def images(frame: Frame, grid: PixelGrid, measured_um: FloatArray) -> Images:
    """The images of one frame from its measured tracking part, shape (N, 2) (x, y; um)."""
    x = sample_at(measured_um[:, 0], grid.sample)
    y = sample_at(measured_um[:, 1], grid.sample)
    ex, ey = x - grid.x_um, y - grid.y_um
    a = math.radians(frame.angle_deg)
    fast = ex * math.cos(a) + ey * math.sin(a)
    slow = -ex * math.sin(a) + ey * math.cos(a)
    return Images(x, y, ex, ey, fast, slow, (fast[0] - fast[1]) / frame.pixel_um)


def _rms(x: FloatArray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")


def _max(x: FloatArray) -> float:
    x = x[np.isfinite(x)]
    return float(np.max(np.abs(x))) if x.size else float("nan")


def axis_errors(measured_um: FloatArray, desired_um: FloatArray) -> dict[str, dict[str, float]]:
    """Each axis's error, measured minus desired (arrays of shape (N, 2), column 0 x), um: its
    RMS (``rms_um``) and largest magnitude (``max_um``) over the samples where both are known
    (missing ones left out, never filled in; NaN for an axis with none).

    Examples
    --------
    >>> e = axis_errors(np.array([[1.0, 0.0], [3.0, np.nan]]), np.array([[0.0, 0.0], [0.0, 1.0]]))
    >>> e["x"]["rms_um"] == math.sqrt(5.0), e["x"]["max_um"], e["y"]["rms_um"]
    (True, 3.0, 0.0)
    """
    err = np.asarray(measured_um, dtype=float) - np.asarray(desired_um, dtype=float)
    return {a: {"rms_um": _rms(err[:, k]), "max_um": _max(err[:, k])} for k, a in enumerate(AXES)}


def line_synchronous(error_slow_um: FloatArray) -> FloatArray:
    """The slow error less each line's mean (trace and retrace together), um: what repeats with
    the fast axis, shape as given."""
    mean = np.nanmean(error_slow_um, axis=(0, 2), keepdims=True)
    return error_slow_um - mean


def merit(frame: Frame, img: Images, measured_um: FloatArray | None = None) -> dict[str, Any]:
    """The figures of merit of one frame (see the module docstring); ``measured_um`` (the
    tracking part's readings, (N, 2)) adds each axis's noise estimate."""
    fast, reg = img.error_fast_um, img.registration_px
    slow = img.error_slow_um / frame.line_pitch_um
    data: dict[str, Any] = {
        "fast_rms_um": _rms(fast), "fast_max_um": _max(fast),
        "fast_rms_pct": 100 * _rms(fast) / frame.width_um,
        "fast_max_pct": 100 * _max(fast) / frame.width_um,
        "fast_rms_um_by_direction": {d: _rms(fast[k]) for k, d in enumerate(DIRECTIONS)},
        "registration_px": _rms(reg), "registration_max_px": _max(reg),
        "slow_deviation_px": _rms(slow), "slow_deviation_max_px": _max(slow),
        "slow_line_synchronous_um": _rms(line_synchronous(img.error_slow_um)),
        "error_x_rms_um": _rms(img.error_x_um), "error_y_rms_um": _rms(img.error_y_um),
        "missing_pixels": int(np.sum(~np.isfinite(img.x_um) | ~np.isfinite(img.y_um))),
    }
    lines = per_line(img)
    data["fast_rms_um_by_line"] = [float(x) for x in lines["fast_rms_um"]]
    data["slow_rms_um_by_line"] = [float(x) for x in lines["slow_rms_um"]]
    if measured_um is not None:
        data["noise_um"] = {n: ilc.noise_estimate(measured_um[:, k])
                            for k, n in enumerate(AXES)}
    return data


def per_line(img: Images) -> dict[str, FloatArray]:
    """RMS fast and slow error of every line (trace and retrace together), um: shape (lines,)."""
    def rows(e: FloatArray) -> FloatArray:
        return np.sqrt(np.nanmean(e**2, axis=(0, 2)))
    return {"fast_rms_um": rows(img.error_fast_um), "slow_rms_um": rows(img.error_slow_um)}


def decoupling_db(without_um: float, with_um: float) -> float:
    """The reduction of the line-synchronous slow motion by the feed-forward, dB."""
    if not (with_um > 0 and without_um > 0):
        return float("nan")
    return 20 * math.log10(without_um / with_um)
