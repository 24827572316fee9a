"""Compiled time stepping of the foreign plant (see :mod:`drivers.device.foreign`).

One sample interval ``[t_k, t_k + dt)`` holds the commanded voltage ``V_k`` (the DAC's zero-order
hold) and is cut into ``n_sub`` equal substeps. Within each substep, in this order:

1. the amplifier (if present) is advanced by classical RK4 from the held input; the field is its
   output over the layer thickness (without an amplifier the field steps to ``g V_k / d`` at
   ``t_k`` and stays there);
2. the material is updated at the end field of a block of substeps (one block per sample without
   an amplifier, at most ``MAT_PER_SAMPLE`` with one) (relay hysterons with the interaction field
   integrated in closed form, or the thermally activated kernel on a 2-D hysteron grid, paper
   (6)-(10), with the rate equations integrated exactly for the substep's frozen rates);
3. the mechanics (one or two masses, paper (16)) are advanced by RK4 with the force linear in time
   across the block (constant under the zero-order hold);
4. the platform follows the rod through the linkage's play (if any), the gauge converts it
   (nonlinearity, saturation), and the sensor's anti-alias filter is advanced by RK4 with its input
   linear over the substep; the filtered signal and its slope are pushed into a history ring from
   which delayed readings are taken by cubic Hermite interpolation.

The reading of sample ``k`` is taken at ``t_k`` before its interval is integrated, so it depends
on ``V_0 .. V_{k-1}`` only (causal sampling). Every piece of state lives in the arrays passed in
and is updated in place (the caller copies); nothing is global.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

BIG = 1.0e9  # MV/m: a threshold beyond any field ("never switched")
SQRT2 = math.sqrt(2.0)
SQRT2PI = math.sqrt(2.0 * math.pi)

# Interaction-field families (codes shared with foreign.py)
NORMAL, LOGISTIC, LAPLACE = 0, 1, 2

# Layout of the scalar parameter vector ``par``
(P_THICK, P_CHI, P_F1, P_F2, P_GAIN, P_GRATE, P_ISCALE, P_IFAM,
 P_M1, P_C1, P_K1, P_M2, P_C2, P_K2, P_TWO,
 P_AMP, P_AW, P_AZ, P_SLEW, P_TAUS,
 P_THERM, P_ET, P_NU0,
 P_PLAY,
 P_GPOLY, P_GC, P_GR, P_Q2, P_Q3,
 P_GSAT, P_SC, P_SK, P_SW,
 P_AA, P_AAW, P_AAZ, P_DELAY) = range(37)
N_PAR = 37

# Layout of the scalar state vector ``st``
(S_T, S_U1, S_V1, S_U2, S_V2, S_VS, S_VA, S_WA, S_E, S_F, S_XP, S_Y, S_DY, S_S,
 S_HEAD, S_COUNT) = range(16)
N_ST = 16
MAT_PER_SAMPLE = 8  # material updates per sample at most, when an amplifier moves the field


@njit(cache=True)
def interaction_cdf(x: float, fam: int, scale: float) -> float:
    """CDF of the interaction-field density at ``x`` (MV/m); ``scale`` is its standard deviation."""
    if fam == NORMAL:
        return 0.5 * math.erfc(-x / (scale * SQRT2))
    if fam == LOGISTIC:
        s = scale * math.sqrt(3.0) / math.pi
        z = x / s
        if z >= 0:
            return 1.0 / (1.0 + math.exp(-z))
        e = math.exp(z)
        return e / (1.0 + e)
    b = scale / SQRT2
    if x >= 0:
        return 1.0 - 0.5 * math.exp(-x / b)
    return 0.5 * math.exp(x / b)


@njit(cache=True)
def relay_update(b: np.ndarray, ec: np.ndarray, field: float) -> None:
    """Move each coercive node's up/down boundary in the interaction field for one field value.

    For a coercive field ``E_c`` the relays (4) with ``E + E_I >= E_c`` switch up, those with
    ``E + E_I <= -E_c`` down; relays are order preserving, so the up set is always
    ``E_I > b``: one boundary ``b`` per coercive node carries the whole memory.
    """
    for i in range(ec.size):
        b[i] = min(max(b[i], -ec[i] - field), ec[i] - field)


@njit(cache=True)
def relay_polarization(b: np.ndarray, vc: np.ndarray, fam: int, scale: float) -> float:
    """Switched part of the polarization over P_R: sum_i v_i (1 - 2 F_I(b_i)) (paper (11))."""
    p = 0.0
    for i in range(b.size):
        p += vc[i] * (1.0 - 2.0 * interaction_cdf(b[i], fam, scale))
    return p


@njit(cache=True)
def relay_step(b: np.ndarray, cdf: np.ndarray, ec: np.ndarray, vc: np.ndarray, field: float,
               fam: int, scale: float) -> float:
    """:func:`relay_update` and :func:`relay_polarization` in one pass, evaluating the CDF only
    at nodes whose boundary moved (``cdf`` caches F_I(b_i))."""
    p = 0.0
    for i in range(ec.size):
        v = min(max(b[i], -ec[i] - field), ec[i] - field)
        if v != b[i]:
            b[i] = v
            cdf[i] = interaction_cdf(v, fam, scale)
        p += vc[i] * (1.0 - 2.0 * cdf[i])
    return p


@njit(cache=True)
def mills(z: float) -> float:
    """phi(z) / Phi(z) for the standard normal (the hazard of the lower tail), any z."""
    if z < -30.0:
        return -z - 1.0 / z
    return math.sqrt(2.0 / math.pi) * math.exp(-0.5 * z * z) / math.erfc(-z / SQRT2)


@njit(cache=True)
def thermal_update(x: np.ndarray, ec2: np.ndarray, ei2: np.ndarray, w2: np.ndarray,
                   field: float, dt: float, e_t: float, nu0: float, chi: float) -> float:
    """Advance the up-fractions x_+ of every hysteron by ``dt`` at a frozen field; return P/P_R.

    Rates (7)-(8) with the barrier at the inflection points: for the piecewise quadratic
    Helmholtz energy, z_- = (E_c - E_e)/E_T and z_+ = (E_c + E_e)/E_T with the thermal field
    E_T = sqrt(eta k T / V), p_{-+} = nu0 phi(z_-)/Phi(z_-), p_{+-} = nu0 phi(z_+)/Phi(z_+).
    The linear ODE for x_+ is solved exactly over ``dt``. The expected polarizations (9) are
    truncated-Gaussian means, <P_+>/P_R = 1 + chi E_e + chi E_T phi(z_+)/Phi(z_+) and
    <P_->/P_R = -1 + chi E_e - chi E_T phi(z_-)/Phi(z_-); the average (10) is weighted by the
    quadrature weights ``w2`` (sum 1).
    """
    p = 0.0
    cut = 9.0
    for i in range(ec2.size):
        for j in range(ei2.size):
            ee = field + ei2[j]
            zm = (ec2[i] - ee) / e_t
            zp = (ec2[i] + ee) / e_t
            xij = x[i, j]
            if zm < cut or zp < cut:
                hm = mills(zm)
                hp = mills(zp)
                rate_up = nu0 * hm
                rate_dn = nu0 * hp
                tot = rate_up + rate_dn
                xeq = rate_up / tot
                xij = xeq + (xij - xeq) * math.exp(-tot * dt)
                x[i, j] = xij
                p += w2[i, j] * (2.0 * xij - 1.0 + chi * e_t * (xij * hp - (1.0 - xij) * hm))
            else:
                p += w2[i, j] * (2.0 * xij - 1.0)
    return p + chi * field


@njit(cache=True)
def _material(par, b, cdf, ec, vc, x, ec2, ei2, w2, field, dt):
    if par[P_THERM] > 0.0:
        return thermal_update(x, ec2, ei2, w2, field, dt, par[P_ET], par[P_NU0], par[P_CHI])
    return par[P_CHI] * field + relay_step(b, cdf, ec, vc, field, int(par[P_IFAM]),
                                           par[P_ISCALE])


@njit(cache=True)
def _force(par, p):
    return par[P_F1] * p + par[P_F2] * p * p


@njit(cache=True)
def _mech_rhs(par, q, force, out):
    m1, c1, k1 = par[P_M1], par[P_C1], par[P_K1]
    if par[P_TWO] > 0.0:
        du = q[0] - q[2]
        dv = q[1] - q[3]
        coup = par[P_K2] * du + par[P_C2] * dv
        out[0] = q[1]
        out[1] = (force - c1 * q[1] - k1 * q[0] - coup) / m1
        out[2] = q[3]
        out[3] = coup / par[P_M2]
    else:
        out[0] = q[1]
        out[1] = (force - c1 * q[1] - k1 * q[0]) / m1
        out[2] = 0.0
        out[3] = 0.0


@njit(cache=True)
def _mech_step(par, q, f0, f1, h, k1, k2, k3, k4, tmp):
    """RK4 for (16) (or its two-mass form) with the force linear from f0 to f1 over h."""
    fm = 0.5 * (f0 + f1)
    _mech_rhs(par, q, f0, k1)
    for n in range(4):
        tmp[n] = q[n] + 0.5 * h * k1[n]
    _mech_rhs(par, tmp, fm, k2)
    for n in range(4):
        tmp[n] = q[n] + 0.5 * h * k2[n]
    _mech_rhs(par, tmp, fm, k3)
    for n in range(4):
        tmp[n] = q[n] + h * k3[n]
    _mech_rhs(par, tmp, f1, k4)
    for n in range(4):
        q[n] += h / 6.0 * (k1[n] + 2.0 * k2[n] + 2.0 * k3[n] + k4[n])


@njit(cache=True)
def _amp_rhs(par, vin, vs, va, wa):
    slew = par[P_SLEW]
    dvs = slew * math.tanh((vin - vs) / (slew * par[P_TAUS]))
    w = par[P_AW]
    dwa = w * w * (vs - va) - 2.0 * par[P_AZ] * w * wa
    return dvs, wa, dwa


@njit(cache=True)
def _amp_step(par, st, vin, h):
    """RK4 for the amplifier: smooth slew limiter, then a second-order low-pass."""
    vs, va, wa = st[S_VS], st[S_VA], st[S_WA]
    a1, b1, c1 = _amp_rhs(par, vin, vs, va, wa)
    a2, b2, c2 = _amp_rhs(par, vin, vs + 0.5 * h * a1, va + 0.5 * h * b1, wa + 0.5 * h * c1)
    a3, b3, c3 = _amp_rhs(par, vin, vs + 0.5 * h * a2, va + 0.5 * h * b2, wa + 0.5 * h * c2)
    a4, b4, c4 = _amp_rhs(par, vin, vs + h * a3, va + h * b3, wa + h * c3)
    st[S_VS] = vs + h / 6.0 * (a1 + 2 * a2 + 2 * a3 + a4)
    st[S_VA] = va + h / 6.0 * (b1 + 2 * b2 + 2 * b3 + b4)
    st[S_WA] = wa + h / 6.0 * (c1 + 2 * c2 + 2 * c3 + c4)


@njit(cache=True)
def gauge(par, x):
    """Static gauge characteristic: position (um) -> signal (um) and its slope."""
    s = x
    ds = 1.0
    if par[P_GPOLY] > 0.0:
        r = par[P_GR]
        y = (x - par[P_GC]) / r
        s = x + r * (par[P_Q2] * y * y + par[P_Q3] * y * y * y)
        ds = 1.0 + 2.0 * par[P_Q2] * y + 3.0 * par[P_Q3] * y * y
    if par[P_GSAT] > 0.0:
        c, knee, w = par[P_SC], par[P_SK], par[P_SW]
        d = s - c
        a = abs(d)
        if a > knee:
            e = a - knee
            th = math.tanh(e / w)
            sgn = 1.0 if d > 0 else -1.0
            s = c + sgn * (knee + w * th)
            ds = ds * (1.0 - th * th)
    return s, ds


@njit(cache=True)
def _aa_rhs(par, sig, y, dy):
    w = par[P_AAW]
    return dy, w * w * (sig - y) - 2.0 * par[P_AAZ] * w * dy


@njit(cache=True)
def _aa_step(par, st, s0, s1, h):
    """RK4 for the anti-alias filter (second order) with its input linear from s0 to s1."""
    y, dy = st[S_Y], st[S_DY]
    sm = 0.5 * (s0 + s1)
    a1, b1 = _aa_rhs(par, s0, y, dy)
    a2, b2 = _aa_rhs(par, sm, y + 0.5 * h * a1, dy + 0.5 * h * b1)
    a3, b3 = _aa_rhs(par, sm, y + 0.5 * h * a2, dy + 0.5 * h * b2)
    a4, b4 = _aa_rhs(par, s1, y + h * a3, dy + h * b3)
    st[S_Y] = y + h / 6.0 * (a1 + 2 * a2 + 2 * a3 + a4)
    st[S_DY] = dy + h / 6.0 * (b1 + 2 * b2 + 2 * b3 + b4)


@njit(cache=True)
def _push(st, hist, t, y, dy):
    cap = hist.shape[0]
    head = (int(st[S_HEAD]) + 1) % cap
    hist[head, 0] = t
    hist[head, 1] = y
    hist[head, 2] = dy
    st[S_HEAD] = head
    st[S_COUNT] = min(st[S_COUNT] + 1.0, cap)


@njit(cache=True)
def _lookup(st, hist, t):
    """Signal at time ``t`` from the history ring (cubic Hermite between stored points)."""
    cap = hist.shape[0]
    head = int(st[S_HEAD])
    n = int(st[S_COUNT])
    j = head
    for _ in range(n - 1):
        i = (j - 1) % cap
        if hist[i, 0] <= t:
            t0, y0, d0 = hist[i, 0], hist[i, 1], hist[i, 2]
            t1, y1, d1 = hist[j, 0], hist[j, 1], hist[j, 2]
            h = t1 - t0
            s = (t - t0) / h
            h00 = (1 + 2 * s) * (1 - s) ** 2
            h10 = s * (1 - s) ** 2
            h01 = s * s * (3 - 2 * s)
            h11 = s * s * (s - 1)
            return h00 * y0 + h10 * h * d0 + h01 * y1 + h11 * h * d1
        j = i
    return hist[j, 1]


@njit(cache=True)
def _sensed(par, st, hist, t):
    """Signal the sensor delivers at time ``t`` (before noise, hum and offset)."""
    if par[P_AA] > 0.0 or par[P_DELAY] > 0.0:
        return _lookup(st, hist, t - par[P_DELAY])
    return st[S_S]


@njit(cache=True)
def _platform(par, st, q):
    """Platform position through the linkage play, um, and its velocity."""
    u = q[2] if par[P_TWO] > 0.0 else q[0]
    v = q[3] if par[P_TWO] > 0.0 else q[1]
    half = 0.5 * par[P_PLAY]
    xp = st[S_XP]
    if half <= 0.0:
        return u, v
    if xp < u - half:
        return u - half, v
    if xp > u + half:
        return u + half, v
    return xp, 0.0


@njit(cache=True)
def _substep(par, st, q, hist, fa, fb, h, t, work):
    """Mechanics over one substep (force linear from fa to fb), then platform and sensor."""
    _mech_step(par, q, fa, fb, h, work[0], work[1], work[2], work[3], work[4])
    xp, vp = _platform(par, st, q)
    st[S_XP] = xp
    s0 = st[S_S]
    s1, ds1 = gauge(par, xp)
    st[S_S] = s1
    if par[P_AA] > 0.0:
        _aa_step(par, st, s0, s1, h)
        _push(st, hist, t, st[S_Y], st[S_DY])
    elif par[P_DELAY] > 0.0:
        _push(st, hist, t, s1, ds1 * vp)


@njit(cache=True)
def simulate(volts, dt, n_sub, par, st, q, b, ec, vc, x, ec2, ei2, w2, hist, true_out, sens_out):
    """Run the plant over held voltage samples; state arrays are updated in place.

    With an amplifier the field moves within a sample: the amplifier is stepped every substep
    and the material in blocks of ``ceil(n_sub / MAT_PER_SAMPLE)`` substeps, the force linear
    in time across each block. Without one, the field and force are constant over the sample.

    Parameters
    ----------
    volts : ndarray, shape (N,)
        Commanded voltage per sample, V (held over the sample interval).
    dt : float
        Sample period, s.
    n_sub : int
        Substeps per sample.
    par, st, q, b, ec, vc, x, ec2, ei2, w2, hist : ndarray
        Packed parameters and state (see :mod:`drivers.device.foreign`).
    true_out, sens_out : ndarray, shape (N,)
        Filled with the platform position at ``t_k`` (um) and the sensor signal at ``t_k``
        before noise, hum and offset (um).
    """
    h = dt / n_sub
    work = np.empty((5, 4))
    cdf = np.empty(b.size)
    for i in range(b.size):
        cdf[i] = interaction_cdf(b[i], int(par[P_IFAM]), par[P_ISCALE])
    amp = par[P_AMP] > 0.0
    stride = (n_sub + MAT_PER_SAMPLE - 1) // MAT_PER_SAMPLE if amp else n_sub
    for k in range(volts.size):
        t = st[S_T]
        true_out[k] = st[S_XP]
        sens_out[k] = _sensed(par, st, hist, t)
        vin = volts[k] * par[P_GAIN] * (1.0 + par[P_GRATE] * t)
        f_prev = st[S_F]
        j = 0
        while j < n_sub:
            m = min(stride, n_sub - j)
            if amp:
                for _ in range(m):
                    _amp_step(par, st, vin, h)
                field = st[S_VA] / par[P_THICK]
            else:
                field = vin / par[P_THICK]
            p = _material(par, b, cdf, ec, vc, x, ec2, ei2, w2, field, m * h)
            f_new = _force(par, p)
            if not amp:
                f_prev = f_new
            for r in range(m):
                fa = f_prev + (f_new - f_prev) * r / m
                fb = f_prev + (f_new - f_prev) * (r + 1) / m
                t += h
                _substep(par, st, q, hist, fa, fb, h, t, work)
            st[S_E] = field
            st[S_F] = f_new
            f_prev = f_new
            j += m
        st[S_T] = st[S_T] + dt
