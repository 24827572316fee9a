"""The compiled time stepping of the out-of-family stages (:mod:`.family_stage`).

One sample of the commanded voltage is held over ``n_sub`` substeps of length ``h``; in each:

1. gain warm-up ``g(t) = 1 + delta (1 - exp(-t / T))`` on the command (a second form of
   ``voltage-gain-drift``), then the amplifier: three equal real poles (a second form of
   ``amplifier-lag``), exact for the substep's held input; its output clipped to the rails;
2. normalized input ``w = (v - lo) / (hi - lo)``; the hysteresis sees it through a first-order
   lag of ``tau_visc`` (the "viscous" dynamic Preisach: a second form of ``thermal-relaxation``);
3. the operator (Preisach / Prandtl-Ishlinskii / Bouc-Wen, :mod:`~afmctl.drivers.device.foreign.families`)
   plus the reversible part ``lam w``, normalized to the major loop and mapped by the output
   polynomial ``span (g1 s + g2 s^2 + g3 s^3)``, um;
4. creep operators driven by that output (exact over the substep), added;
5. the rod: one or two modes ``x_j'' + 2 zeta_j w_j x_j' + w_j^2 x_j = w_j^2 b_j x_in`` (two: a
   second form of ``second-mode``, modal superposition with its own residue), exact ZOH;
6. the position ``x_1 + x_2 + drift t``; the gauge averages it over the last ``M`` substeps (an
   integrating ADC: a second form of ``sensor-delay``) and may read through a capacitive gap law
   ``mid + G d / (G - d)``, ``d`` from ``mid`` (a second form of ``sensor-nonlinearity``).

The reading at sample ``k`` is taken at its start, before the sample acts.

Parameter vector ``P`` (float64) layout: the ``I_*`` indices below.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

from afmctl.drivers.device.foreign.families import (
    bouc_wen_step,
    creep_step,
    play_step,
    preisach_output,
    preisach_step,
)

FloatArray = NDArray[np.float64]

PREISACH, PI, BOUC_WEN = 0, 1, 2
(I_KIND, I_H, I_NSUB, I_LO, I_HI, I_LAM, I_YLO, I_YSCALE, I_G1, I_G2, I_G3, I_SPAN, I_DRIFT,
 I_ZERO, I_GAIN_D, I_GAIN_T, I_AMP, I_VISC, I_AVG, I_GAP, I_MID, I_BWA, I_BWB, I_BWG, I_BWN,
 I_ELOW, I_EH, I_B1, I_B2) = range(29)
N_PAR = 29
#: Scalar state: time, lagged input, Bouc-Wen z and its last input, two modes (x, v), amplifier
#: poles (3), stack length, ring position.
(S_T, S_WH, S_Z, S_WPREV, S_X1, S_V1, S_X2, S_V2, S_A1, S_A2, S_A3, S_N, S_RING) = range(13)
N_STATE = 13


@numba.njit(cache=True)
def core(P: FloatArray, F: FloatArray, r: FloatArray, p: FloatArray, s: FloatArray,
         mem: FloatArray, w: float) -> float:
    """Move the operator to input ``w`` and return the quasi-static output, um (step 3)."""
    kind = int(P[I_KIND])
    if kind == PREISACH:
        mem, n = preisach_step(mem, int(s[S_N]), w)
        s[S_N] = n
        y = preisach_output(F, P[I_ELOW], P[I_EH], mem, n)
    elif kind == PI:
        play_step(mem[:r.size], r, w)
        y = 0.0
        for i in range(r.size):
            y += p[i] * mem[i]
    else:
        s[S_Z] = bouc_wen_step(s[S_Z], s[S_WPREV], w, P[I_BWA], P[I_BWB], P[I_BWG], P[I_BWN])
        s[S_WPREV] = w
        y = -s[S_Z]  # x = d V - h (Low & Guo; Goldfarb & Celanovic): the loop turns as a stage's
    return y


@numba.njit(cache=True)
def output_map(P: FloatArray, y: float, w: float) -> float:
    """Operator output ``y`` and reversible part to displacement, um."""
    q = (y + P[I_LAM] * w - P[I_YLO]) * P[I_YSCALE]
    return P[I_SPAN] * (P[I_G1] * q + P[I_G2] * q * q + P[I_G3] * q * q * q)


@numba.njit(cache=True)
def _gauge(P: FloatArray, x: float) -> float:
    if P[I_GAP] == 0.0:
        return x
    d = x - P[I_MID]
    return P[I_MID] + P[I_GAP] * d / (P[I_GAP] - d)


@numba.njit(cache=True)
def run_kernel(P: FloatArray, F: FloatArray, r: FloatArray, p: FloatArray,
               creep_c: FloatArray, creep_decay: FloatArray, creep_mean: FloatArray,
               modes: FloatArray, amp: FloatArray, s: FloatArray, mem: FloatArray,
               creep: FloatArray, ring: FloatArray, v_cmd: FloatArray,
               true_out: FloatArray, read_out: FloatArray) -> None:
    """Run the held samples ``v_cmd`` (V) through the stage; states ``s``, ``mem``, ``creep``,
    ``ring`` are advanced in place. ``modes`` (2, 6): per mode the ZOH matrices
    ``[phi11, phi12, phi21, phi22, gam1, gam2]``; ``amp`` (12,): the amplifier's 3x3 ``phi``
    and 3 ``gam``, row-major."""
    nsub = int(P[I_NSUB])
    h = P[I_H]
    lo, hi = P[I_LO], P[I_HI]
    m_avg = int(P[I_AVG])
    visc = math.exp(-h / P[I_VISC]) if P[I_VISC] > 0 else 0.0
    for k in range(v_cmd.size):
        pos = s[S_X1] + s[S_X2] + P[I_DRIFT] * s[S_T]
        true_out[k] = pos
        if m_avg > 1:
            acc = 0.0
            for j in range(m_avg):
                acc += ring[j]
            pos = acc / m_avg
        read_out[k] = _gauge(P, pos) - P[I_ZERO]
        for _ in range(nsub):
            v = v_cmd[k]
            if P[I_GAIN_T] > 0:
                v *= 1.0 + P[I_GAIN_D] * (1.0 - math.exp(-s[S_T] / P[I_GAIN_T]))
            if P[I_AMP] > 0:
                a1, a2, a3 = s[S_A1], s[S_A2], s[S_A3]
                s[S_A1] = amp[0] * a1 + amp[1] * a2 + amp[2] * a3 + amp[9] * v
                s[S_A2] = amp[3] * a1 + amp[4] * a2 + amp[5] * a3 + amp[10] * v
                s[S_A3] = amp[6] * a1 + amp[7] * a2 + amp[8] * a3 + amp[11] * v
                v = s[S_A3]
            v = min(max(v, lo), hi)
            w = (v - lo) / (hi - lo)
            s[S_WH] = w + (s[S_WH] - w) * visc
            d = output_map(P, core(P, F, r, p, s, mem, s[S_WH]), w)
            x_in = d + creep_step(creep, d, creep_decay, creep_mean, creep_c)
            for j in range(2):
                b = P[I_B1 + j]
                if b == 0.0:
                    continue
                ix, iv = S_X1 + 2 * j, S_V1 + 2 * j
                x, xv = s[ix], s[iv]
                mo = modes[j]
                s[ix] = mo[0] * x + mo[1] * xv + mo[4] * b * x_in
                s[iv] = mo[2] * x + mo[3] * xv + mo[5] * b * x_in
            s[S_T] += h
            if m_avg > 1:
                i = int(s[S_RING])
                ring[i] = s[S_X1] + s[S_X2] + P[I_DRIFT] * s[S_T]
                s[S_RING] = (i + 1) % m_avg
