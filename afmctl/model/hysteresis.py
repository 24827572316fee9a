"""Homogenized energy model of polarization (Hatch, Smith et al., Sections 2 and 2.3).

Units used throughout afmctl: electric field in MV/m (1 V/um = 1 MV/m, so field = voltage [V] /
layer thickness [um]), polarization in C/m^2, time in s. ``eta`` is therefore in (MV/m)/(C/m^2).

The kernel of the paper is a relay (hysteron) on the effective field ``E + E_I`` with coercive field
``E_c`` (eqs. (3)-(5)); the macroscopic polarization is its average over the densities
``nu_1(E_c)`` and ``nu_2(E_I)`` (eq. (11)), discretized as (13).

Two exact implementations of the relay kernel are provided, plus the thermally activated kernel:

``grid``
    The discretized model (13) on explicit nodes ``E_c,i`` x ``E_I,j``: identical to Algorithm 1.
    For a fixed coercive node all relays of the column share the half-width ``E_c,i``; in floating
    point the switching tests ``fl(fl(E + E_I,j) - E_c,i) >= 0`` (up) and
    ``fl(fl(E + E_I,j) + E_c,i) <= 0`` (down) are monotone in ``E_I,j``, so the column is always
    "down below a boundary index, up from it on". The state is that index per column: a play
    (backlash) operator in index form, O(N_i log N_j) per sample and bit-for-bit the same switching
    decisions as Algorithm 1.
``normal``
    For a normal interaction density the E_I integral of a column has the closed form
    ``int nu_2(E_I) sgn(E_I + y) dE_I = erf(y / (sqrt(2) sigma_I))`` where ``y`` is the output of a
    play operator of half-width ``E_c,i``. Only the E_c integral is discretized. This is the default:
    it converges smoothly (no staircase) in the number of coercive nodes.
``thermal``
    Kernel (6)-(10) on the grid: every hysteron carries the fraction ``x_+`` of positively oriented
    dipoles; see :func:`switching_rates` for the closed form of the likelihoods (7)-(8) and
    :mod:`afmctl.model.thermal` for the compiled kernel.

Tie rule (field exactly at a switching threshold, ``E + E_I = +-E_c``): the relay switches. This is
the reading of kernel (4), whose switching set contains the times at which ``E = +-E_c`` holds; the
literal ``sgn`` of Algorithm 1 would give the non-state 0 there, and :func:`algorithm1` resolves
``sgn(0)`` to the switched state accordingly.

Quadrature: both densities are integrated with the midpoint rule in the cumulative-probability
variable (node i at the ``(i - 1/2)/N`` quantile, weight ``1/N``). This maps the infinite domains
of (12) onto [0, 1]; the implied truncation is at the ``1/(2N)`` and ``1 - 1/(2N)`` quantiles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy import special

from afmctl.model.thermal import thermal_step

FloatArray = NDArray[np.float64]
ArrayLike = FloatArray | list[float] | tuple[float, ...]

KIND_NORMAL = 0
KIND_GRID = 1
KIND_THERMAL = 2
#: A non-separable weight matrix on a (coercive, interaction) grid (:mod:`afmctl.model.preisach`).
KIND_MATRIX = 3
#: A Bouc-Wen operator (:mod:`afmctl.model.boucwen`): state ``(h, E_last)``.
KIND_BOUC_WEN = 4
#: Largest change of the Bouc-Wen ``h`` over one RK4 substep, as a share of ``h_s`` (at its
#: steepest, ``|A| max(1, 1 - kappa)``).
BW_SUBSTEP = 0.02
#: Most Bouc-Wen substeps in one sample.
BW_MAX_SUBSTEPS = 5000


@dataclass(frozen=True)
class Lognormal:
    """Lognormal coercive-field density nu_1 (criteria (12)(i)).

    Parameters
    ----------
    median : float
        Median coercive field, MV/m (> 0).
    sigma : float
        Standard deviation of ``ln E_c`` (dimensionless, > 0).
    """

    median: float
    sigma: float

    def nodes(self, n: int) -> tuple[FloatArray, FloatArray]:
        """Quantile-midpoint nodes (MV/m) and weights (sum 1)."""
        q = (np.arange(n) + 0.5) / n
        return self.median * np.exp(self.sigma * special.ndtri(q)), np.full(n, 1.0 / n)


@dataclass(frozen=True)
class Normal:
    """Normal interaction-field density nu_2 with zero mean (criteria (12)(ii)).

    Parameters
    ----------
    std : float
        Standard deviation of E_I, MV/m (> 0).
    """

    std: float

    def nodes(self, n: int) -> tuple[FloatArray, FloatArray]:
        """Quantile-midpoint nodes (MV/m, symmetric about 0) and weights (sum 1)."""
        q = (np.arange(n) + 0.5) / n
        return self.std * special.ndtri(q), np.full(n, 1.0 / n)


@dataclass(frozen=True)
class Discrete:
    """A general discretized density: nonnegative values at fixed nodes.

    Parameters
    ----------
    nodes : tuple of float
        Strictly increasing abscissas, MV/m (coercive nodes must be > 0).
    values : tuple of float
        Density values at the nodes, 1/(MV/m), nonnegative.

    The quadrature weight of node i is ``values[i]`` times the width of its midpoint cell.
    """

    nodes: tuple[float, ...]
    values: tuple[float, ...]

    def __post_init__(self) -> None:
        x = np.asarray(self.nodes, dtype=float)
        v = np.asarray(self.values, dtype=float)
        if x.ndim != 1 or x.shape != v.shape or x.size < 1:
            raise ValueError("discrete density needs equally long, non-empty nodes and values")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
            raise ValueError("discrete density nodes and values must be finite")
        if np.any(np.diff(x) <= 0):
            raise ValueError("discrete density nodes must be strictly increasing")
        if np.any(v < 0):
            raise ValueError("discrete density values must be nonnegative")

    def nodes_weights(self) -> tuple[FloatArray, FloatArray]:
        x = np.asarray(self.nodes, dtype=float)
        if x.size == 1:
            return x, np.asarray(self.values, dtype=float)
        edges = np.concatenate(([x[0] - (x[1] - x[0]) / 2], (x[1:] + x[:-1]) / 2,
                                [x[-1] + (x[-1] - x[-2]) / 2]))
        return x, np.asarray(self.values, dtype=float) * np.diff(edges)

    def nodes_for(self, n: int) -> tuple[FloatArray, FloatArray]:
        return self.nodes_weights()


def _density_nodes(d: Lognormal | Normal | Discrete, n: int) -> tuple[FloatArray, FloatArray]:
    if isinstance(d, Discrete):
        return d.nodes_weights()
    return d.nodes(n)


@dataclass(frozen=True)
class Thermal:
    """Thermal activation for kernel (6)-(10).

    Parameters
    ----------
    field_scale : float
        ``sqrt(2 eta kT / V)`` expressed as a field, MV/m. It sets how far ahead of the coercive
        field thermally activated switching starts; 0 is the relay limit of Algorithm 1.
    attempt_rate : float
        ``epsilon sqrt(2 eta V / (pi kT)) / T(T)`` of (7)-(8), 1/s: the switching likelihood when the
        barrier has just vanished. Large values make relaxation fast.
    """

    field_scale: float
    attempt_rate: float


@dataclass(frozen=True)
class Polarization:
    """Parameters of the discretized homogenized energy model (13).

    Parameters
    ----------
    eta : float
        Reciprocal slope of the E-P relation after switching, (MV/m)/(C/m^2) (eq. (3)).
    p_r : float
        Remanence P_R of a single hysteron, C/m^2 (eq. (3)).
    coercive : Lognormal or Discrete
        Density nu_1 of coercive fields (MV/m).
    interaction : Normal or Discrete
        Density nu_2 of interaction fields (MV/m).
    n_coercive, n_interaction : int
        Quadrature nodes for parametric densities (ignored for :class:`Discrete`).
    kernel : {"auto", "normal", "grid"}
        ``auto`` uses the closed-form E_I integral when nu_2 is :class:`Normal` and the kernel is not
        thermal, else the grid.
    thermal : Thermal or None
        If given, the thermally activated kernel (10) replaces the relay kernel (4).
    """

    eta: float
    p_r: float
    coercive: Lognormal | Discrete
    interaction: Normal | Discrete
    n_coercive: int = 128
    n_interaction: int = 64
    kernel: Literal["auto", "normal", "grid"] = "auto"
    thermal: Thermal | None = None

    @property
    def kind(self) -> int:
        if self.thermal is not None:
            return KIND_THERMAL
        if self.kernel == "grid" or not isinstance(self.interaction, Normal):
            return KIND_GRID
        return KIND_NORMAL


@dataclass(frozen=True)
class Kernel:
    """Arrays for the compiled kernels, derived once from :class:`Polarization`.

    ``scal`` holds [eta, p_r, sigma_I, field_scale, attempt_rate, W_total, mean_E_I * W_total].
    """

    kind: int
    ec: FloatArray
    wc: FloatArray
    ei: FloatArray
    wi: FloatArray
    cw: FloatArray = field(repr=False)
    scal: FloatArray = field(repr=False)

    @property
    def state_size(self) -> int:
        if self.kind == KIND_THERMAL:  # x_+ per hysteron and their switched total
            return self.ec.size * self.ei.size + 1
        if self.kind == KIND_BOUC_WEN:  # h and the last field
            return 2
        return self.ec.size


def build_kernel(params: Polarization) -> Kernel:
    """Quadrature nodes, weights and packed scalars for ``params`` (pure). Any other polarization
    model (e.g. :class:`afmctl.model.preisach.PreisachGrid`) builds its own."""
    if not isinstance(params, Polarization):
        return params.build_kernel()
    ec, wc = _density_nodes(params.coercive, params.n_coercive)
    if np.any(ec <= 0):
        raise ValueError("coercive-field nodes must be positive")
    ei, wi = _density_nodes(params.interaction, params.n_interaction)
    sigma = params.interaction.std if isinstance(params.interaction, Normal) else 0.0
    th = params.thermal or Thermal(0.0, 0.0)
    if params.kind == KIND_NORMAL:
        wtot, mean = float(wc.sum()), 0.0
    else:
        wtot = float(wc.sum() * wi.sum())
        mean = float(wc.sum() * (wi * ei).sum())
    cw = np.concatenate(([0.0], np.cumsum(wi)))
    scal = np.array([params.eta, params.p_r, sigma, th.field_scale, th.attempt_rate, wtot, mean])
    return Kernel(params.kind, ec, wc, ei, wi, cw, scal)


@dataclass(frozen=True)
class PolarizationState:
    """Memory of the model: play outputs (``normal``, MV/m), boundary indices (``grid``) or dipole
    fractions x_+ (``thermal``, row-major N_i x N_j, then their switched total ``sum w (2 x_+ - 1)``).
    Treat as immutable: every run returns a new one.
    """

    kind: int
    values: FloatArray

    def copy_values(self) -> FloatArray:
        return self.values.copy()


Initial = Literal["depoled", "positive", "negative"]
#: Prefix of a Bouc-Wen state named by its value (:func:`bouc_wen_state`).
BW_STATE = "h="


def bouc_wen_state(share: float) -> str:
    """The name of the Bouc-Wen state ``h = share h_s`` at the first field the model sees
    (``h_s`` in the sense of ``A``: ``share`` 1 is ``positive``'s saturation, -1
    ``negative``'s): identify's fitted start of a sweep recorded after work it did not see (a
    Bouc-Wen stage's whole memory is ``h``, :mod:`afmctl.model.boucwen`)."""
    if not -1.0 <= share <= 1.0:
        raise ValueError(f"a Bouc-Wen state's share of its saturation must be in [-1, 1], "
                         f"got {share}")
    return f"{BW_STATE}{share:+.6f}"


def bouc_wen_share(how: object) -> float | None:
    """``share`` of a state named by :func:`bouc_wen_state` (None: not such a name).

    Raises
    ------
    ValueError
        A name with the prefix whose value is no number in [-1, 1].
    """
    if not isinstance(how, str) or not how.startswith(BW_STATE):
        return None
    try:
        share = float(how[len(BW_STATE):])
    except ValueError:
        share = math.nan
    if not -1.0 <= share <= 1.0:
        raise ValueError(f"unknown initial state {how!r}: {BW_STATE}<share of the saturation, "
                         "-1 ... 1> expected")
    return share


def initial_state(params: Polarization, how: Initial | str | NDArray = "depoled"
                  ) -> PolarizationState:
    """Initial state: depoled (Delta_init of Algorithm 1), poled +/- or a given Delta matrix.

    Parameters
    ----------
    params : Polarization
    how : {"depoled", "positive", "negative"} or ndarray of shape (N_i, N_j) with entries +-1
        A Delta matrix must be reachable, i.e. each row is -1 up to some column and +1 from there
        (for the ``normal`` kernel it is read on the E_I quantile nodes of ``n_interaction``).
        A Bouc-Wen model also takes a state named by its value (:func:`bouc_wen_state`).
    """
    k = build_kernel(params)
    if k.kind == KIND_BOUC_WEN:
        share = bouc_wen_share(how)
        if share is not None:  # h at the first field (NaN: the first field run takes it as is)
            return PolarizationState(k.kind, np.array([share * math.copysign(k.ec[1], k.ec[0]),
                                                       math.nan]))
        if not isinstance(how, str) or how not in ("depoled", "positive", "negative"):
            raise ValueError(f"unknown initial state {how!r} for a Bouc-Wen model")
        if how == "depoled":  # h = 0 at zero field, as the play outputs of the other kernels
            return PolarizationState(k.kind, np.zeros(2))
        up = how == "positive"  # saturated at the poling field (NaN: at the first field)
        h0 = (1.0 if up else -1.0) * math.copysign(k.ec[1], k.ec[0])
        return PolarizationState(k.kind, np.array([h0, k.ec[5] if up else k.ec[4]]))
    ni, nj = k.ec.size, k.ei.size
    if isinstance(how, str):
        delta = {"depoled": np.where(k.ei[None, :] > 0, 1.0, -1.0) * np.ones((ni, 1)),
                 "positive": np.ones((ni, nj)), "negative": -np.ones((ni, nj))}.get(how)
        if delta is None:
            raise ValueError(f"unknown initial state {how!r}")
        if how == "depoled" and k.kind in (KIND_NORMAL, KIND_MATRIX):
            return PolarizationState(k.kind, np.zeros(ni))
    else:
        delta = np.asarray(how, dtype=float)
        if delta.shape != (ni, nj) or not np.all(np.abs(delta) == 1):
            raise ValueError(f"Delta must be an {ni}x{nj} matrix of +-1")
    if not np.all(np.diff(delta, axis=1) >= 0):
        raise ValueError("each Delta row must be -1 below a boundary and +1 above it")
    if k.kind == KIND_THERMAL:
        total = float(np.sum(k.wc[:, None] * np.diff(k.cw)[None, :] * delta))
        return PolarizationState(k.kind, np.append((delta + 1) / 2, total))
    bound = (delta < 0).sum(axis=1).astype(float)
    if k.kind == KIND_GRID:
        return PolarizationState(k.kind, bound)
    # closed form: play output y with -y between the last down node and the first up node
    edges = np.concatenate(([-np.inf], k.ei, [np.inf]))
    lo, hi = edges[bound.astype(int)], edges[bound.astype(int) + 1]
    mid = np.where(np.isinf(lo), hi - 1.0, np.where(np.isinf(hi), lo + 1.0, (lo + hi) / 2))
    mid = np.where(np.isinf(lo) & np.isinf(hi), 0.0, mid)
    y = -mid
    y = np.where(bound == 0, np.inf, np.where(bound == nj, -np.inf, y))
    return PolarizationState(k.kind, y.astype(float))


# ----------------------------------------------------------------------------------------------
# compiled kernels
# ----------------------------------------------------------------------------------------------


@nb.njit(cache=True, nogil=True)
def _step(kind: int, e: float, dt: float, st: np.ndarray, out: np.ndarray, ec: np.ndarray,
          wc: np.ndarray, ei: np.ndarray, cw: np.ndarray, scal: np.ndarray) -> float:
    """Advance the state ``st`` by one sample at field ``e`` (MV/m) held for ``dt`` s into ``out``
    (which may alias ``st``) and return the polarization (C/m^2)."""
    eta, p_r, sigma, fscale, nu0, wtot, mean = (scal[0], scal[1], scal[2], scal[3], scal[4],
                                               scal[5], scal[6])
    acc = 0.0
    ni = ec.size
    nj = ei.size
    if kind == 0:
        inv = 1.0 / (math.sqrt(2.0) * sigma)
        for i in range(ni):
            y = st[i]
            lo = e - ec[i]
            hi = e + ec[i]
            if y < lo:
                y = lo
            elif y > hi:
                y = hi
            out[i] = y
            acc += wc[i] * math.erf(y * inv)
        return (e * wtot + mean) / eta + p_r * acc
    if kind == 3:
        return (e * wtot + mean) / eta + p_r * _matrix_step(e, st, out, ec, cw)
    if kind == 4:
        return (e * wtot + mean) / eta + _bouc_wen_step(e, st, out, ec)
    if kind == 1:
        wi_tot = cw[nj]
        for i in range(ni):
            b = int(st[i])
            # lowest j switched up: fl(fl(e + ei[j]) - ec[i]) >= 0 (monotone in j)
            if b > 0 and (e + ei[b - 1]) - ec[i] >= 0.0:
                lo, hi = 0, b - 1
                while lo < hi:
                    mid = (lo + hi) // 2
                    if (e + ei[mid]) - ec[i] >= 0.0:
                        hi = mid
                    else:
                        lo = mid + 1
                b = lo
            # highest j switched down: fl(fl(e + ei[j]) + ec[i]) <= 0
            if b < nj and (e + ei[b]) + ec[i] <= 0.0:
                lo, hi = b, nj - 1
                while lo < hi:
                    mid = (lo + hi + 1) // 2
                    if (e + ei[mid]) + ec[i] <= 0.0:
                        lo = mid
                    else:
                        hi = mid - 1
                b = lo + 1
            out[i] = b
            acc += wc[i] * (wi_tot - 2.0 * cw[b])
        return (e * wtot + mean) / eta + p_r * acc
    return (e * wtot + mean) / eta + p_r * thermal_step(e, dt, st, out, ec, wc, ei, cw, fscale, nu0)


@nb.njit(cache=True, nogil=True)
def _matrix_step(e: float, st: np.ndarray, out: np.ndarray, ec: np.ndarray, tab: np.ndarray) -> float:
    """Kernel of a weight matrix on the grid (:mod:`afmctl.model.preisach`): per coercive row the
    play output ``y_i``, then the row's ``g_i(y_i) = sum_j w_ij erf((y_i + E_I,j) / (sqrt(2)
    sigma))``, read from its table by cubic Hermite interpolation (O(1) per row, whatever the
    number of interaction nodes). ``tab`` packs ``[y_0, 1/h, n]`` (the table's first output,
    MV/m, the reciprocal of its step and its length), then per row the ``n`` pairs ``(g, h g')``;
    outside the table the row is constant (every cell switched down or up: ``-+sum_j w_ij``)."""
    y0, inv_h, n = tab[0], tab[1], int(tab[2])
    acc = 0.0
    for i in range(ec.size):
        y = st[i]
        lo = e - ec[i]
        hi = e + ec[i]
        if y < lo:
            y = lo
        elif y > hi:
            y = hi
        out[i] = y
        base = 3 + 2 * n * i
        s = (y - y0) * inv_h
        if not s > 0.0:  # below the table (or -inf: poled negative)
            acc += tab[base]
        elif s >= n - 1:
            acc += tab[base + 2 * n - 2]
        else:
            k = int(s)
            t = s - k
            j = base + 2 * k
            t2 = t * t
            t3 = t2 * t
            acc += ((2.0 * t3 - 3.0 * t2 + 1.0) * tab[j] + (t3 - 2.0 * t2 + t) * tab[j + 1]
                    + (3.0 * t2 - 2.0 * t3) * tab[j + 2] + (t3 - t2) * tab[j + 3])
    return acc


@nb.njit(cache=True, nogil=True)
def _bouc_wen_slope(h: float, s: float, a: float, hs: float, kappa: float, n: float) -> float:
    q = 1.0 if s * a * h > 0.0 else kappa  # |h| grows: 1; toward zero: kappa
    return a * (1.0 - q * abs(h / hs) ** n)


@nb.njit(cache=True, nogil=True)
def _bouc_wen_step(e: float, st: np.ndarray, out: np.ndarray, ec: np.ndarray) -> float:
    """Bouc-Wen ``h`` (:mod:`afmctl.model.boucwen`, ``ec = [A, h_s, kappa, n]``) after the field
    moves monotonically from ``st[1]`` to ``e`` (MV/m) from ``st[0]``: RK4 in ``E``; ``out`` (may
    alias ``st``) gets ``(h, e)``. A NaN ``st[1]`` (no field yet) takes ``e`` as it is."""
    h, e0 = st[0], st[1]
    a, hs, kappa, n = ec[0], ec[1], ec[2], ec[3]
    de = 0.0 if math.isnan(e0) else e - e0
    if de != 0.0:
        s = 1.0 if de > 0.0 else -1.0
        steep = abs(de * a) * max(1.0, 1.0 - kappa)  # the largest |dh/dE| is |A| max(1, 1 - kappa)
        m = min(max(1, int(math.ceil(steep / (BW_SUBSTEP * hs)))), BW_MAX_SUBSTEPS)
        d = de / m
        for _ in range(m):
            k1 = _bouc_wen_slope(h, s, a, hs, kappa, n)
            k2 = _bouc_wen_slope(h + 0.5 * d * k1, s, a, hs, kappa, n)
            k3 = _bouc_wen_slope(h + 0.5 * d * k2, s, a, hs, kappa, n)
            k4 = _bouc_wen_slope(h + d * k3, s, a, hs, kappa, n)
            h += d * (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0
    out[0] = h
    out[1] = e
    return h


@nb.njit(cache=True, nogil=True)
def banded(kind: int) -> bool:
    """Whether the kernel has a quiet band (:func:`_quiet_band`): play outputs or relays."""
    return kind == 0 or kind == 1 or kind == 3


@nb.njit(cache=True, nogil=True)
def _quiet_band(kind: int, st: np.ndarray, ec: np.ndarray, ei: np.ndarray) -> tuple[float, float]:
    """Open field interval (MV/m) inside which no relay of the state ``st`` can switch.

    Shrunk by a margin far above round-off, so a field inside it provably leaves every
    ``fl(fl(E + E_I) -+ E_c)`` test as it was: skipping such samples is exact.
    """
    lo, hi = -math.inf, math.inf
    nj = ei.size
    for i in range(ec.size):
        if kind != 1:  # play outputs (normal and matrix kernels)
            up, dn = st[i] + ec[i], st[i] - ec[i]
        else:
            b = int(st[i])
            up = ec[i] - ei[b - 1] if b > 0 else math.inf
            dn = -ec[i] - ei[b] if b < nj else -math.inf
        hi = min(hi, up)
        lo = max(lo, dn)
    return lo + 1e-9 * (1.0 + abs(lo)), hi - 1e-9 * (1.0 + abs(hi))


@nb.njit(cache=True, nogil=True)
def _run(kind: int, e: np.ndarray, dt: np.ndarray, st: np.ndarray, ec: np.ndarray, wc: np.ndarray,
         ei: np.ndarray, cw: np.ndarray, scal: np.ndarray) -> np.ndarray:
    p = np.empty(e.size)
    lin = scal[5] / scal[0]
    off = scal[6] / scal[0]
    lo, hi, p_switch = 0.0, -1.0, 0.0  # empty quiet band until the first full step
    for k in range(e.size):
        if lo < e[k] < hi:  # no relay can switch: only the reversible part E/eta changes
            p[k] = e[k] * lin + off + p_switch
            continue
        p[k] = _step(kind, e[k], dt[k], st, st, ec, wc, ei, cw, scal)
        if banded(kind):
            p_switch = p[k] - (e[k] * lin + off)
            lo, hi = _quiet_band(kind, st, ec, ei)
    return p


def run(params: Polarization | Kernel, field_mv_m: ArrayLike, state: PolarizationState,
        dt: float | FloatArray = 1e-4) -> tuple[FloatArray, PolarizationState]:
    """Polarization response to a field history (eq. (13), fast exact kernels).

    Parameters
    ----------
    params : Polarization or Kernel
    field_mv_m : array_like, shape (N,)
        Field samples, MV/m; each is held for ``dt`` (only the thermal kernel depends on ``dt``).
    state : PolarizationState
        Memory before the first sample (see :func:`initial_state`).
    dt : float or ndarray, shape (N,)
        Sample period, s, or how long each sample is held (a non-uniform record).

    Returns
    -------
    p : ndarray, shape (N,)
        Polarization after each sample, C/m^2.
    state : PolarizationState
        Memory after the last sample. The input state is not modified.

    Examples
    --------
    >>> pol = Polarization(eta=2.0, p_r=0.3, coercive=Lognormal(0.6, 0.4), interaction=Normal(0.3))
    >>> p, s = run(pol, [0.0, 1.0, 3.0, 0.0], initial_state(pol))
    >>> bool(p[2] > p[1] > p[0])
    True
    """
    k = params if isinstance(params, Kernel) else build_kernel(params)
    if state.kind != k.kind or state.values.size != k.state_size:
        raise ValueError("state does not belong to this model (kernel or grid size differs)")
    e = np.ascontiguousarray(field_mv_m, dtype=float)
    st = state.copy_values()
    holds = np.ascontiguousarray(np.broadcast_to(np.asarray(dt, dtype=float), e.shape))
    p = _run(k.kind, e, holds, st, k.ec, k.wc, k.ei, k.cw, k.scal)
    return p, PolarizationState(k.kind, st)



def algorithm1(params: Polarization, field_mv_m: ArrayLike,
               delta_init: NDArray | None = None) -> tuple[FloatArray, NDArray]:
    """Algorithm 1 written literally (the slow reference oracle of the ``grid`` kernel).

    The Delta matrix update ``Delta = sgn(E_k + E_c .* Delta_prev)`` over all N_i x N_j hysterons, with
    ``sgn(0)`` resolved to the switched state ``-Delta_prev`` (see the module's tie rule).

    Returns the polarization (C/m^2) per sample and the final Delta.
    """
    ec, wc = _density_nodes(params.coercive, params.n_coercive)
    ei, wi = _density_nodes(params.interaction, params.n_interaction)
    v, w = wc[:, None], wi[:, None]
    emat_c = np.repeat(ec[:, None], ei.size, axis=1)
    if delta_init is None:
        delta_init = np.where(ei[None, :] > 0, 1.0, -1.0) * np.ones((ec.size, 1))
    delta_prev = np.array(delta_init, dtype=float)
    out = np.empty(len(field_mv_m))
    for k, e in enumerate(np.asarray(field_mv_m, dtype=float)):
        ek = e + np.repeat(ei[None, :], ec.size, axis=0)
        x = ek + emat_c * delta_prev
        delta = np.sign(x)
        delta[delta == 0] = -delta_prev[delta == 0]
        pbar = ek / params.eta + params.p_r * delta
        out[k] = (v.T @ pbar @ w).item()
        delta_prev = delta
    return out, delta_prev


def switching_rates(field_eff: FloatArray, ec: FloatArray, th: Thermal) -> tuple[FloatArray,
                                                                                  FloatArray]:
    """Likelihoods p_{+-}, p_{-+} (1/s) of (7)-(8) in the inflection-point approximation.

    With the Gibbs energy (1) quadratic on each branch and the integrals of (7) taken from the
    inflection points +-P_I (the approximation named after (10)), the ratio of the integrand at the
    barrier to the integral over the well is a Gaussian tail, giving

    ``p_{+-} = nu0 / erfcx(-(E + E_c)/E_th)``, ``p_{-+} = nu0 / erfcx((E - E_c)/E_th)``

    where ``E_th = field_scale`` and ``nu0 = attempt_rate``. As E_th -> 0 the rate is 0 inside the
    well and infinite beyond the coercive field: the relay (4).
    """
    zm = -(field_eff + ec) / th.field_scale
    zp = (field_eff - ec) / th.field_scale
    with np.errstate(over="ignore", divide="ignore"):
        return th.attempt_rate / special.erfcx(zm), th.attempt_rate / special.erfcx(zp)


def n_coercive_for(params: Polarization, fields: list[FloatArray], tol: float,
                   n_min: int = 64, n_max: int = 4096,
                   starts: tuple[Initial, ...] = ("depoled", "positive", "negative")) -> int:
    """Smallest number of coercive nodes ``n_min * 2^j`` that resolves (13) to ``tol``.

    The midpoint rule in the cumulative probability of ``nu_1`` converges at about first order
    once the node spacing is below the interaction width ``sigma_I`` (each column of the closed
    form switches over a field range ~ sigma_I; a narrower ``nu_2`` makes every column a step and
    the sum a staircase until the nodes are denser). The error of ``N`` nodes is estimated as the
    largest difference from ``2N`` nodes over the field histories ``fields`` (MV/m), each run from
    each of the ``starts``; the first ``N`` whose difference is at most ``tol / 2`` (C/m^2) is
    returned (for first-order convergence its error is then below ``tol``), at most ``n_max``.
    Parameters with a discrete coercive density have their own nodes: ``n_min`` is returned.
    """
    if isinstance(params.coercive, Discrete):
        return n_min

    def runs(n: int) -> list[FloatArray]:
        pol = replace(params, n_coercive=n)
        kern = build_kernel(pol)
        return [run(kern, e, initial_state(pol, how))[0] for e in fields for how in starts]

    n, coarse = n_min, runs(n_min)
    while n < n_max:
        fine = runs(2 * n)
        if max(float(np.max(np.abs(a - b))) for a, b in zip(coarse, fine, strict=True)) <= tol / 2:
            return n
        n, coarse = 2 * n, fine
    return n_max


def saturation(params: Polarization, e_max: float) -> tuple[float, float]:
    """Remanent polarization (C/m^2) after poling at +e_max and returning to 0 (Section 3)."""
    p, _ = run(params, np.array([e_max, 0.0]), initial_state(params))
    return float(p[0]), float(p[1])

