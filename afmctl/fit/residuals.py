"""The residual of a fitted model on its sweeps: how it depends on time, field, field rate,
frequency, amplitude, turning points, between sweeps, and the strongest tone that is no harmonic
of the drive (``afmctl diagnose``'s analysis of the paper's model, read by
:func:`afmctl.fit.verdict.suggestions`). Pure numerics: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl.files.sweepfile import Sweep
from afmctl.fit import extension as ext
from afmctl.fit import identify as idf
from afmctl.fit import parametrization as pz

FloatArray = NDArray[np.float64]


def predicted(fitted: ext.Extended, sweeps: Sequence[Sweep]) -> list[FloatArray]:
    """Readings (um) the fitted candidate predicts for ``sweeps`` recorded in sequence: each from
    its start, with its sensor zero and applied-voltage gain (:func:`afmctl.fit.identify.predict_set`)."""
    return idf.predict_set(fitted.model, sweeps, fitted.starts, fitted.offsets_um, fitted.gains)




def _corr(a: FloatArray, b: FloatArray) -> float:
    if a.size < 3 or np.std(a) == 0 or np.std(b) == 0:
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])


def _after_turns(v: FloatArray, dt: float, window_s: float) -> NDArray[np.bool_]:
    """Samples within ``window_s`` after a turning point of the voltage."""
    near = np.zeros(v.size, dtype=bool)
    width = max(1, int(window_s / dt))
    for k in pz.turning_points(v)[1:-1]:
        near[k:k + width] = True
    return near


def tone_fraction(r: FloatArray, dt: float, drive_hz: float | None) -> float:
    """Fraction of the residual's power (mean removed, Hann window) in its strongest spectral line
    that is no harmonic of the drive (five bins around the peak; bins within three of a harmonic
    skipped). White noise gives about 5 ln(N) / N; interference at a fixed frequency approaches 1."""
    spec = np.abs(np.fft.rfft((r - np.mean(r)) * np.hanning(r.size))) ** 2
    spec[0] = 0.0
    total = float(np.sum(spec))
    if total == 0 or spec.size < 8:
        return 0.0
    f = np.fft.rfftfreq(r.size, dt)
    free = np.ones(spec.size, dtype=bool)
    if drive_hz:
        df = f[1]
        near = np.abs(f / drive_hz - np.round(f / drive_hz)) * drive_hz <= 3.5 * df
        free &= ~near
    if not free.any():
        return 0.0
    k = int(np.argmax(np.where(free, spec, 0.0)))
    return float(np.sum(spec[max(k - 2, 1):k + 3]) / total)


def residual_signature(fitted: ext.Extended, sweeps: Sequence[Sweep]) -> dict[str, Any]:
    """How the model's residual (measured - predicted, um) depends on time, field, field rate,
    frequency, amplitude, turning points, and how it differs between sweeps; the strongest tone
    that is no harmonic of the drive (:func:`tone_fraction`)."""
    per, r_all, e_all, rate_all = [], [], [], []
    model = fitted.model
    for s, u in zip(sweeps, predicted(fitted, sweeps), strict=True):
        m = s.mask(None)
        r = (s.displacement_um - u)[m]
        e = (s.voltage_v / model.thickness_um)[m]
        rate = np.gradient(s.voltage_v / model.thickness_um, s.dt)[m]
        period = 1.0 / s.frequency_hz if s.frequency_hz else s.time_s[-1] - s.time_s[0]
        turns = _after_turns(s.voltage_v, s.dt, 0.05 * period)[m]
        rms_turn = float(np.sqrt(np.mean(r[turns] ** 2))) if turns.any() else float("nan")
        per.append({
            "file": s.path or s.name, "frequency_hz": s.frequency_hz,
            "amplitude_pp_V": float(np.ptp(s.voltage_v)), "rms_um": float(np.sqrt(np.mean(r ** 2))),
            "mean_um": float(np.mean(r)), "corr_time": _corr(r, s.time_s[m]),
            "corr_field": _corr(r, e), "corr_field_squared": _corr(r, e * e),
            "corr_field_rate": _corr(r, rate),
            "rms_after_turning_points_um": rms_turn,
            "tone_fraction": tone_fraction(r, s.dt, s.frequency_hz),
            "rms_elsewhere_um": float(np.sqrt(np.mean(r[~turns] ** 2))) if (~turns).any()
            else float("nan")})
        r_all.append(r)
        e_all.append(e)
        rate_all.append(rate)
    r, e, rate = (np.concatenate(a) for a in (r_all, e_all, rate_all))
    means = [p["mean_um"] for p in per]
    freq = [(p["frequency_hz"], p["rms_um"]) for p in per if p["frequency_hz"]]
    turn = [p["rms_after_turning_points_um"] / p["rms_elsewhere_um"] for p in per
            if p["rms_elsewhere_um"] > 0 and math.isfinite(p["rms_after_turning_points_um"])]
    return {"sweeps": per, "rms_um": float(np.sqrt(np.mean(r ** 2))),
            "corr_field": _corr(r, e), "corr_field_squared": _corr(r, e * e),
            "corr_field_rate": _corr(r, rate),
            "corr_time": float(np.mean([p["corr_time"] for p in per])),
            "turning_point_ratio": max(turn, default=1.0),
            "tone_fraction": max(p["tone_fraction"] for p in per),
            "between_sweeps_mean_spread_um": float(np.ptp(means)) if len(means) > 1 else 0.0,
            "rms_vs_frequency": sorted(freq, key=lambda t: t[0])}
