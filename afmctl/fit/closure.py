"""Do the measured minor loops close? Return-point memory checked on the sweeps themselves.

Every Preisach-type hysteresis (the paper's model with relay hysterons, any Preisach density,
the Preisach grid) has *return-point memory*: after a reversal at ``v_a``, an excursion to
``v_b`` and a return to ``v_a``, the output is again what it was at the reversal (the wiping-out
property erases the excursion), so every minor loop closes. A rate-independent hysteresis
without it (Bouc-Wen) leaves its minor loops open, and no Preisach-type model can fit such a
stage to its noise (issue 23 item 3). Creep and drift open loops as well (the stage moves between
the two passes), and so does thermal relaxation: the check says what the data show, not which.

The check (:func:`check`): for every reversal ``a`` of a sweep's voltage whose next excursion
returns to ``v_a`` (or beyond), the readings of the pass into the reversal and of the pass back
through ``v_a``, each within :data:`WINDOW` of the sweep's voltage range of ``v_a`` and moving
the same way, are each fitted by a quadratic in the voltage and evaluated at ``v_a``: the
*closure gap* is the difference, with its standard error from the fits' residuals. A loop is
*open* when its gap exceeds :data:`SIGMAS` standard errors and :data:`NOISES` times the sweep's
sensor noise (both: a gap the noise cannot make, and large enough to matter to a model judged
against that noise). A pass the quadratic does not describe to within :data:`SMOOTH` times the
noise (RMS) is not quasi-static: a fast triangle's turnaround rings the rod, and the "gap" of
two such passes is the ringing's phase, not memory (on a Preisach stage's 27.9 Hz triangle one
such loop was 5 standard errors open, and identify fitted Bouc-Wen for nothing); its loop is not
checked, and is counted as ``unsteady``. Nor is a loop whose two passes move at rates more than
:data:`RATE` apart: the rod's lag (and any rate dependence) is the same on two passes at one rate
and cancels from the gap, but not between a slow and a fast one (the separating sweep's
multisine left every Preisach and Prandtl-Ishlinskii stage of the family benches 10-23x the
noise "open", its passes 1.9-2.5 times apart in rate). Nor, lastly, is a loop with a pass
faster than :data:`SLOW_RANGES_PER_S`: two passes at one rate cancel the rod's lag, not its
inertia, which a fast pass that speeds up or slows down through ``v_a`` shows differently each
way (the same multisine's reversal at 79 V, about 5 V/ms, left Preisach and Prandtl-Ishlinskii
stages with 1100-1400 Hz rods 7-16x the noise "open", an independent tester's two among them;
``/tmp/s66/fastloops.py``). Pure numerics on sweeps already read: no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl.files.sweepfile import Sweep
from afmctl.fit.parametrization import turning_points

FloatArray = NDArray[np.float64]
#: Half-width of the voltage window each pass is fitted over, as a fraction of the sweep's range.
WINDOW = 0.04
#: A gap is open when it exceeds this many standard errors ...
SIGMAS = 5.0
#: ... and this many times the sweep's sensor noise.
NOISES = 3.0
#: Fewest samples a pass needs in its window (fewer: the loop is not checked).
MIN_SAMPLES = 8
#: A pass whose quadratic leaves a residual RMS above this many times the noise is not checked.
SMOOTH = 2.0
#: Two passes whose mean voltage rates differ by more than this factor are not compared.
RATE = 1.25
#: Nor two of which one moves (mean voltage rate) faster than this many times the sweep's range
#: per second: twice the 5.58 Hz triangle's slew, the reversals design's curves' rate.
SLOW_RANGES_PER_S = 4 * 5.58
#: An excursion that passes the reversal before ``v_a`` by more than this share of the sweep's
#: range wipes it out (:func:`loop_gaps`); by less it counts as returning there (a sampled
#: triangle's turning points differ by up to one step: 0.84 V at 27.9 Hz and 10 kHz on 150 V).
PASSED = 0.01


@dataclass(frozen=True)
class Gap:
    """One minor loop's closure: the sweep, the reversal voltage (V) and time (s), the gap
    (um, return minus reversal) and its standard error (um), and the sweep's noise (um)."""

    sweep: str
    voltage_v: float
    time_s: float
    gap_um: float
    stderr_um: float
    noise_um: float

    @property
    def open(self) -> bool:
        return (abs(self.gap_um) > SIGMAS * self.stderr_um
                and abs(self.gap_um) > NOISES * self.noise_um)


def _at(v: FloatArray, y: FloatArray, va: float) -> tuple[float, float, float]:
    """A quadratic in ``v - va`` fitted to ``y``: its value at ``va``, standard error and
    residual RMS (um)."""
    x = np.column_stack((np.ones_like(v), v - va, (v - va) ** 2))
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    res = y - x @ coef
    s2 = float(res @ res) / max(y.size - 3, 1)
    cov = s2 * np.linalg.pinv(x.T @ x)
    return float(coef[0]), float(np.sqrt(max(cov[0, 0], 0.0))), float(np.sqrt(np.mean(res ** 2)))


def _alike(into: FloatArray, back: FloatArray, fastest: float) -> bool:
    """Whether two passes' mean voltage rates (per sample, over the samples that move: a pause
    at the reversal is no slower pass) are within :data:`RATE` of each other, and neither
    above ``fastest`` (V per sample)."""
    a, b = (float(np.mean(m)) if (m := _moving(p)).size else 0.0 for p in (into, back))
    return max(a, b) <= min(RATE * min(a, b), fastest)


def _moving(v: FloatArray) -> FloatArray:
    """The voltage steps (V, absolute) of the samples of ``v`` that move."""
    d = np.abs(np.diff(v))
    return d[d > 0.0]


def loop_gaps(sweep: Sweep, noise_um: float) -> tuple[list[Gap], int]:
    """Every minor loop of ``sweep`` that returns to its reversal voltage, with its closure gap,
    and how many such loops were not checked because a pass is not quasi-static
    (:data:`SMOOTH`, :data:`SLOW_RANGES_PER_S`) or the two move at rates too far apart
    (:data:`RATE`). A loop is one only
    if its excursion stays within the reversal before ``v_a`` (a maximum's excursion does not
    go below the minimum it rose from): one that goes past it wipes that reversal out, and the
    return meets ``v_a`` on another branch, whatever the stage's memory (on the reversal-curve
    design 150 -> 55 -> 84 -> 0 -> 84 V, a Preisach stage's two readings at 84 V differ by
    4.3 um)."""
    v, y = sweep.voltage_v, sweep.displacement_um
    turns = turning_points(v)
    span = float(np.ptp(v))
    width = WINDOW * span
    out, unsteady = [], 0
    for i in range(1, turns.size - 1):
        a, b = int(turns[i - 1]), int(turns[i])
        end = int(turns[i + 2]) if i + 2 < turns.size else v.size - 1
        va, sign = float(v[b]), float(np.sign(v[b] - v[a]))
        nxt = int(turns[i + 1])
        back = np.flatnonzero(sign * (v[nxt:end + 1] - va) >= 0)  # the return reaches v_a
        wiped = sign * (v[nxt] - v[a]) < -PASSED * span  # past the reversal before
        if sign == 0 or back.size == 0 or wiped:
            continue
        into = np.arange(a, b + 1)
        into = into[np.abs(v[into] - va) <= width]
        ret = np.arange(nxt, nxt + int(back[0]) + 1)
        ret = ret[np.abs(v[ret] - va) <= width]
        if min(into.size, ret.size) < MIN_SAMPLES:
            continue
        y_into, se_into, rms_into = _at(v[into], y[into], va)
        y_back, se_back, rms_back = _at(v[ret], y[ret], va)
        if (max(rms_into, rms_back) > SMOOTH * noise_um
                or not _alike(v[into], v[ret], SLOW_RANGES_PER_S * span * sweep.dt)):
            unsteady += 1
            continue
        out.append(Gap(sweep.path or sweep.name, va, float(sweep.time_s[b]), y_back - y_into,
                       float(np.hypot(se_into, se_back)), noise_um))
    return out, unsteady


def check(sweeps: Sequence[Sweep], noise_um: Sequence[float]) -> dict[str, Any]:
    """The closure of every minor loop of ``sweeps`` (``noise_um``: each sweep's sensor noise):
    ``checked`` and ``open`` loops, ``unsteady`` ones (not checked: a pass not quasi-static, or
    two at rates too far apart), ``close`` (None: no loop checked, so the sweeps cannot tell),
    the widest gap (``worst``: sweep, voltage, time, gap and its standard error in um, gap over
    the noise) and one sentence (``text``)."""
    found = [loop_gaps(s, n) for s, n in zip(sweeps, noise_um, strict=True)]
    gaps = [g for each, _ in found for g in each]
    opened = [g for g in gaps if g.open]
    worst = max(gaps, key=lambda g: abs(g.gap_um) / g.noise_um, default=None)
    out: dict[str, Any] = {"checked": len(gaps), "open": len(opened),
                           "unsteady": sum(n for _, n in found),
                           "close": None if not gaps else not opened, "worst": None,
                           "thresholds": {"stderr": SIGMAS, "noise": NOISES, "smooth": SMOOTH,
                                          "rate": RATE, "slow_ranges_per_s": SLOW_RANGES_PER_S}}
    if worst is not None:
        out["worst"] = {"sweep": worst.sweep, "voltage_V": worst.voltage_v,
                        "time_s": worst.time_s, "gap_um": worst.gap_um,
                        "stderr_um": worst.stderr_um,
                        "gap_over_noise": abs(worst.gap_um) / worst.noise_um}
    out["text"] = _text(out, worst)
    return out


def _text(out: dict[str, Any], worst: Gap | None) -> str:
    if worst is None:
        if out["unsteady"]:
            return (f"minor loops: {out['unsteady']} return to their reversal point, but the "
                    f"quadratic does not describe their passes (not quasi-static: ringing, or "
                    f"sharper than the sweep resolves) or the two passes move at unlike rates, "
                    f"so return-point memory is not checked")
        return ("minor loops: none of these sweeps returns to a reversal point, so return-point "
                "memory cannot be checked")
    where = (f"{abs(worst.gap_um):.4f} um ({abs(worst.gap_um) / worst.noise_um:.1f}x the noise, "
             f"{abs(worst.gap_um) / max(worst.stderr_um, 1e-300):.0f} standard errors) at "
             f"{worst.voltage_v:g} V in {worst.sweep}")
    rang = (f" ({out['unsteady']} not quasi-static or at unlike rates, not checked)"
            if out["unsteady"] else "")
    if out["close"]:
        return (f"minor loops close: {out['checked']} checked{rang}, the widest gap {where}: "
                f"consistent with a Preisach-type hysteresis (return-point memory)")
    return (f"minor loops do NOT close: {out['open']} of {out['checked']} open{rang}, the widest by "
            f"{where}. The stage has no return-point memory (a rate-independent hysteresis "
            f"that is not of Preisach type, such as Bouc-Wen: no Preisach-type model, the "
            f"paper's or the Preisach grid, fits such loops to the noise), or it creeps or "
            f"drifts between the passes (a model with creep can close them)")
