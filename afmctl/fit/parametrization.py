"""Well-scaled internal parametrizations of the transducer, used by :mod:`afmctl.fit.identify`.

The physical parameters of the model (eqs. (13) and (16)) are not all identifiable from
displacement alone:

* ``(m, c, k, a1~, a2~)`` enter (16) only through ``c/m``, ``k/m``, ``a1~/m``, ``a2~/m``;
* ``P -> s P`` (``eta -> eta/s``, ``P_R -> s P_R``) with ``a1~ -> a1~/s``, ``a2~ -> a2~/s^2``
  leaves the force unchanged.

So ``m`` and ``P_R`` are fixed by convention (:class:`Scales`) and the fit works with
``Q = eta P = E + r H(E)``, ``r = eta P_R`` (MV/m), ``H = sum_i v_i erf(y_i / (sqrt(2) sigma_I))``
in [-1, 1] (the closed-form ``normal`` kernel of :mod:`afmctl.model.hysteresis`, ``y_i`` the play output
of half-width ``E_c,i``). The rod (16) then reads

``u = g1 L[Q] + g2 L[Q^2] + offset``

with ``L`` the unit-DC-gain second-order filter of natural frequency ``f_n`` and damping ratio
``zeta``, ``g1 = 1e6 a1~ / (k eta)`` (um per MV/m) and ``g2 = 1e6 a2~ / (k eta^2)``. The gains
``beta = (g1, g2, offset)`` enter linearly; a *space* maps the remaining vector ``x`` to the
design matrix ``[L[Q], L[Q^2], 1]`` and, with ``beta``, to a :class:`~afmctl.model.transducer.Transducer`.

Two spaces: :class:`LognormalSpace` (``nu_1`` lognormal, ``nu_2`` normal: six parameters) and
:class:`afmctl.fit.density.DiscreteSpace` (``nu_1`` a general nonnegative density, piecewise linear
between fixed nodes, smoothed by a Tikhonov penalty on its second differences; ``nu_2`` normal), as
in Section 2.2 of the paper.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from afmctl.files.sweepfile import Sweep
from afmctl.fit import cores
from afmctl.model import hysteresis as hy
from afmctl.model import rod as rd
from afmctl.model import transducer as td

FloatArray = NDArray[np.float64]
THETA_NAMES = ("median_MV_per_m", "sigma_ln", "std_MV_per_m", "r_MV_per_m", "natural_hz",
               "damping_ratio")
#: Hysteresis states a sweep may start from: depoled, poled either way (by a field beyond every
#: coercive field), or where the previous sweep of the set left it (sweeps recorded in sequence).
STARTS = ("depoled", "positive", "negative", "previous")


@dataclass(frozen=True)
class Scales:
    """The fixed scale conventions: effective mass ``m`` (kg) and remanence ``P_R`` (C/m^2)."""

    mass_kg: float = 0.05
    p_r: float = 0.3


# ----------------------------------------------------------------------------------------------
# data preparation
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Prepared:
    """One sweep ready for the residual: field (MV/m, full rate), the samples on which the
    hysteresis is evaluated, the residual mask, the measured displacement there (um), dt (s)."""

    field: FloatArray
    keep: NDArray[np.intp]
    mask: NDArray[np.bool_]
    y: FloatArray
    dt: float


def turning_points(x: FloatArray) -> NDArray[np.intp]:
    """Indices of the local extrema of ``x`` (a plateau counts at its end), plus both ends."""
    d = np.sign(np.diff(x))
    nz = np.flatnonzero(d)
    if nz.size < 2:
        return np.array([0, x.size - 1])
    flips = nz[1:][d[nz[1:]] != d[nz[:-1]]]
    return np.unique(np.concatenate(([0, x.size - 1], flips)))


def significant_extremes(x: FloatArray, share: float = 0.01) -> list[float]:
    """The values ``x`` starts at, reverses at and ends at, counting only reversals by more than
    ``share`` of its range (noise on a recorded voltage makes none).

    Examples
    --------
    >>> significant_extremes(np.array([0.0, 5.0, 4.99, 5.0, 10.0, 3.0, 7.0]))
    [0.0, 10.0, 3.0, 7.0]
    """
    tol = share * float(np.ptp(x))
    ext = x[turning_points(x)]
    out, last, rising = [float(ext[0])], float(ext[0]), None
    for v in (float(e) for e in ext[1:]):
        if rising is not False and v < last - tol:
            out += [last] if rising else []
            last, rising = v, False
        elif rising is not True and v > last + tol:
            out += [last] if rising is False else []
            last, rising = v, True
        elif (rising and v > last) or (rising is False and v < last):
            last = v
    return out + [last]


def decimation(field: FloatArray, step: float) -> NDArray[np.intp]:
    """Samples on which to evaluate the hysteresis: every turning point, both ends of every hold
    (a constant field), and one whenever the accumulated field variation has grown by ``step``
    (same units as ``field``).

    Model (13) depends only on the turning points; in between the output is a smooth function of
    the field, so linear interpolation over steps ``step`` errs by O(step^2). A hold between two
    moves the same way is no turning point, but interpolating across it in time would ramp the
    output over the hold: its ends are kept.
    """
    if step <= 0:
        return np.arange(field.size)
    diff = np.diff(field)
    travel = np.concatenate(([0.0], np.cumsum(np.abs(diff))))
    new = np.flatnonzero(np.diff(np.floor(travel / step)) > 0) + 1
    moving = diff != 0
    holds = np.flatnonzero(moving[1:] != moving[:-1]) + 1
    return np.unique(np.concatenate((new, holds, turning_points(field))))


@dataclass(frozen=True)
class FieldGrid:
    """The samples of a field on which ``eta`` is computed, and how every sample is interpolated
    from them in the field (:func:`field_grid`)."""

    keep: NDArray[np.intp]
    left: NDArray[np.intp]
    share: FloatArray

    def on_every_sample(self, q: FloatArray) -> FloatArray:
        """``q``, known on the samples :attr:`keep`, on every sample (interpolated in the
        field)."""
        if self.keep.size == self.left.size:
            return q
        return q[self.left] + self.share * (q[self.left + 1] - q[self.left])


def field_grid(field: FloatArray, step: float) -> FieldGrid:
    """:func:`decimation` of ``field`` by ``step`` (its units: every turning point and hold, and
    a sample whenever the field has moved by ``step``), with the sample before a kept one whose
    own move is over ``step``, and each sample's place between the two kept samples around it,
    as a share of the field's move between them (0 across a hold)."""
    keep = decimation(field, step)
    if step > 0 and keep.size > 2:
        # a kept sample whose own move is over a step (on a fast sweep, the first crossing
        # after a reversal that moved less than a step): the sample before it is kept too, so
        # that every interval with samples inside spans at most about a step of the field
        a, b = keep[:-1], keep[1:]
        keep = np.union1d(keep, b[(b - a >= 2) & (np.abs(field[b] - field[b - 1]) > step)] - 1)
    if keep.size == field.size:
        return FieldGrid(keep, np.arange(field.size), np.zeros(field.size))
    left = np.clip(np.searchsorted(keep, np.arange(field.size), side="right") - 1,
                   0, keep.size - 2)
    a, b = keep[left], keep[left + 1]
    move = field[b] - field[a]
    share = np.divide(field - field[a], move, out=np.zeros(field.size), where=move != 0)
    return FieldGrid(keep, left, np.clip(share, 0.0, 1.0))


def prepare(sweep: Sweep, thickness_um: float, field_step: float,
            window_s: tuple[float, float] | None) -> Prepared:
    """:class:`Prepared` for ``sweep``; ``field_step`` is relative to the peak field."""
    e = sweep.voltage_v / thickness_um
    keep = decimation(e, field_step * float(np.max(np.abs(e))))
    mask = sweep.mask(window_s)
    if not mask.any():
        raise ValueError(f"{sweep.name}: no samples in the fit window {window_s}")
    return Prepared(e, keep, mask, sweep.displacement_um[mask], sweep.dt)


def thinned(prep: Prepared, rows: int) -> Prepared:
    """``prep`` with its residual on every ``k``-th of its samples, ``k`` the smallest stride
    that leaves at most ``rows`` (``prep`` itself when it has no more).

    The model is still simulated at the full rate (hysteresis, rod, effects); only the samples
    the misfit is summed over are fewer. For the fitted half of ``afmctl sweep``'s 40 s of
    nested minor loops at 10 kHz (200,000 samples of a 0.1 Hz triangle) every 10th (1 ms) still
    resolves the loops and the rod's ringing after a corner (4 ms period at 250 Hz), and the
    noise stays white. (``afmctl diagnose`` weighs each sweep the same whatever its row count
    and judges on every sample.)
    """
    mask, y, k = every_kth(prep.mask, prep.y, rows)
    return prep if k == 1 else replace(prep, mask=mask, y=y)


def every_kth(mask: NDArray[np.bool_], y: FloatArray, rows: int
              ) -> tuple[NDArray[np.bool_], FloatArray, int]:
    """The judged samples ``mask`` (readings ``y`` on them) thinned to every ``k``-th, ``k`` the
    smallest stride that leaves at most ``rows``: the mask, the readings on it and ``k`` (the
    samples each row stands for; ``mask`` and ``y`` themselves when ``k`` is 1)."""
    idx = np.flatnonzero(mask)
    k = -(-idx.size // rows)
    if k <= 1:
        return mask, y, 1
    out = np.zeros_like(mask)
    out[idx[::k]] = True
    return out, y[::k], k


def at_full_rate(n: int, keep: NDArray[np.intp], q_keep: FloatArray) -> FloatArray:
    """``q_keep``, known at the samples ``keep`` of ``n``, interpolated to all ``n`` samples."""
    return q_keep if keep.size == n else np.interp(np.arange(n), keep, q_keep)


def _full_rate(prep: Prepared, q_keep: FloatArray) -> FloatArray:
    return at_full_rate(prep.field.size, prep.keep, q_keep)


def unit_filter(x: FloatArray, fn: float, zeta: float, dt: float) -> FloatArray:
    """``L[x]``: rod (16) normalized to unit DC gain (exact ZOH, (18)), at rest with ``x[0]``."""
    w = 2 * math.pi * fn
    rod = rd.Rod(m=1.0, c=2 * zeta * w, k=w * w, a1=1.0)
    disc = _discretize(float(fn), float(zeta), float(dt))
    u, _ = rd.simulate(rod, disc, x * (rod.k * 1e-6), np.array([x[0] * 1e-6, 0.0]))
    return u


_DISC_CACHE: dict[tuple[float, float, float], rd.Discrete] = {}
K = TypeVar("K")
V = TypeVar("V")


def cached(cache: dict[K, V], key: K, make: Callable[[], V], limit: int) -> V:
    """``cache[key]``, made by ``make()`` and kept if missing (the cache emptied first once it
    holds more than ``limit``). One lookup, so threads may share a cache (the solver's
    evaluations side by side, :func:`afmctl.fit.cores.mapped`): a check, another thread's
    ``clear()``, then a read would fail.

    Examples
    --------
    >>> c = {}
    >>> cached(c, "a", lambda: 1, 2), cached(c, "a", lambda: 2, 2)
    (1, 1)
    """
    got = cache.get(key)
    if got is None:
        if len(cache) > limit:
            cache.clear()
        got = cache[key] = make()
    return got


def _discretize(fn: float, zeta: float, dt: float) -> rd.Discrete:
    return cached(_DISC_CACHE, (fn, zeta, dt), lambda: unit_oscillator_zoh(fn, zeta, dt), 256)


def unit_oscillator_zoh(fn: float, zeta: float, dt: float) -> rd.Discrete:
    """Exact zero-order-hold discretization (18) of ``u'' + 2 zeta w u' + w^2 u = f`` in closed
    form (the same as :func:`afmctl.model.rod.discretize` of a unit-mass rod, without a matrix
    exponential): ``e^{A t} = e^{-zeta w t} (cosh(mu t) I + sinh(mu t)/mu (A + zeta w I))`` with
    ``mu = w sqrt(zeta^2 - 1)`` (imaginary when underdamped), ``Gamma = A^-1 (Phi - I) B``."""
    w = 2 * math.pi * fn
    a = np.array([[0.0, 1.0], [-w * w, -2 * zeta * w]])
    mu = w * np.sqrt(complex(zeta * zeta - 1.0))
    x, decay = mu * dt, zeta * w * dt
    # e^{-decay} cosh(x) and e^{-decay} sinh(x) / mu from e^{+-x - decay}: no overflow when a
    # heavily overdamped rod makes both cosh(x) and sinh(x) huge
    up, down = np.exp(x - decay), np.exp(-x - decay)
    ch = float((0.5 * (up + down)).real)
    sh = (float((0.5 * (up - down) / mu).real) if abs(x) > 1e-8
          else dt * (1 + float((x * x).real) / 6) * math.exp(-decay))
    phi = ch * np.eye(2) + sh * (a + zeta * w * np.eye(2))
    a_inv = np.array([[a[1, 1], -a[0, 1]], [-a[1, 0], a[0, 0]]]) / (w * w)
    gamma = a_inv @ (phi - np.eye(2)) @ np.array([0.0, 1.0])
    return rd.Discrete(phi, gamma, float(dt))


def sweep_columns(q: FloatArray, fn: float, zeta: float, dt: float) -> FloatArray:
    """``[L[Q], L[Q^2], 1]`` of one sweep at the full rate, shape (N, 3)."""
    return np.column_stack((unit_filter(q, fn, zeta, dt), unit_filter(q * q, fn, zeta, dt),
                            np.ones(q.size)))


def offset_columns(preps: Sequence[Prepared]) -> FloatArray:
    """One indicator column per sweep on the stacked residual samples: each sweep has its own
    sensor zero (a gauge re-zeroed between sweeps, or drifting, costs nothing then)."""
    sizes = [int(p.mask.sum()) for p in preps]
    return np.repeat(np.eye(len(sizes)), sizes, axis=0)


def columns(q_keep: Sequence[FloatArray], fn: float, zeta: float,
            preps: Sequence[Prepared]) -> FloatArray:
    """Design matrix ``[L[Q], L[Q^2], 1_s]`` on the residual samples of all sweeps, stacked
    (``1_s``: :func:`offset_columns`)."""
    gains = np.vstack([sweep_columns(_full_rate(prep, q_k), fn, zeta, prep.dt)[prep.mask, :2]
                       for q_k, prep in zip(q_keep, preps, strict=True)])
    return np.hstack((gains, offset_columns(preps)))


def hysteresis(theta: FloatArray, fields: Sequence[FloatArray], n_coercive: int,
               thermal: hy.Thermal | None = None, n_interaction: int = 16,
               holds: Sequence[FloatArray] | None = None,
               starts: Sequence[str] | None = None) -> list[FloatArray]:
    """``Q = E + r H(E)`` (MV/m) of (13) for each field history (MV/m).

    ``theta[:4]`` = (median E_c, sigma_ln, sigma_I, r). With ``thermal`` the kernel (10) runs on
    an ``n_coercive`` x ``n_interaction`` grid, each sample held for ``holds`` (s). ``starts``
    gives each history's initial state (one of :data:`STARTS`; default all depoled).
    """
    median, sig, std, r = (float(v) for v in theta[:4])
    pol = hy.Polarization(eta=1.0, p_r=r, coercive=hy.Lognormal(median, sig),
                          interaction=hy.Normal(std), n_coercive=n_coercive,
                          n_interaction=n_interaction, thermal=thermal)
    dts: Sequence[FloatArray | float] = holds if holds is not None else [1e-4] * len(fields)
    return run_from(pol, fields, starts, dts)


QCache = dict[tuple[bytes, int, tuple[str, ...]], tuple[FloatArray, hy.PolarizationState]]


def zero_sweep(starts: Sequence[str], skip: Sequence[int] = ()) -> int:
    """Index of the sweep whose sensor zero (offset) is the model's: the last of the sweeps whose
    start is the first sweep's (the model's initial state, :func:`with_initial`) or, all the way
    back, where such a sweep left the stage (``previous``); not one of ``skip`` (sweeps held out
    of the fit), unless every such sweep is.

    A sweep's offset is fitted together with its start: the hysterons its field cannot switch
    keep the start's orientation, a constant in the polarization that the offset absorbs. A
    model run from its initial state is therefore in the frame of those sweeps only; the
    offset of a sweep fitted from another start (on the out-of-family Bouc-Wen stage bw-u the
    reversal curves' depoled start, -15.48 um against 0.32 um) would put every plan that far
    off. The last of them, not the best-fitted: on a creeping stage the most recent zero is the
    nearest to the stage's position when the model is used (bw-u-creep's tracking missed by
    1.95 / 2.73 um at 0.279 Hz with the best-fitted triangle's, 1.16 / 1.67 um with the last's).
    """
    first = starts[0] if starts and starts[0] != "previous" else "depoled"
    chained = [0]
    for i in range(1, len(starts)):
        if starts[i] == first or (starts[i] == "previous" and chained[-1] == i - 1):
            chained.append(i)
    return next((i for i in reversed(chained) if i not in skip), chained[-1])


def with_initial(model: td.Transducer, starts: Sequence[str]) -> td.Transducer:
    """``model`` with its initial state (:attr:`afmctl.model.transducer.Transducer.initial`) the
    start of the first sweep (depoled if that start is unknown, ``previous``): where the stage was
    before the sweeps it was fitted to, so that track and learning start from it too."""
    first = starts[0] if starts else "depoled"
    return replace(model, initial=first if first != "previous" else "depoled")  # type: ignore[arg-type]


def run_from(pol: hy.Polarization, fields: Sequence[FloatArray], starts: Sequence[str] | None,
             dts: Sequence[FloatArray | float] | None = None, cache: QCache | None = None,
             key: bytes = b"") -> list[FloatArray]:
    """Polarization (13) of ``pol`` for each field history (MV/m), each from its start.

    ``starts[i]`` is one of :data:`STARTS`; ``previous`` carries the state the history before
    left (the first history has none before it: depoled). With a ``cache`` (and a ``key`` that
    identifies ``pol``), each history's result is kept per start sequence up to it, so trying
    other starts, or other rod parameters, re-runs only what changed.
    """
    starts = tuple(starts or ["depoled"] * len(fields))
    kern: hy.Kernel | None = None
    out, state = [], None
    for i, (e, start, dt) in enumerate(zip(fields, starts, dts or [1e-4] * len(fields),
                                          strict=True)):
        def simulated(e: FloatArray = e, start: str = start, dt: FloatArray | float = dt,
                      before: hy.PolarizationState | None = state
                      ) -> tuple[FloatArray, hy.PolarizationState]:
            nonlocal kern
            if start == "previous" and before is not None:
                st = before
            else:
                st = hy.initial_state(pol, "depoled" if start == "previous" else start)  # type: ignore[arg-type]
            kern = kern or hy.build_kernel(pol)
            return hy.run(kern, e, st, dt)

        q, state = (simulated() if cache is None else
                    cached(cache, (key, pol.n_coercive, starts[:i + 1]), simulated, 256))
        out.append(q)
    return out


def project(a: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Linear least-squares gains ``beta`` and the residual ``y - A beta``."""
    beta, *_ = np.linalg.lstsq(a.T @ a, a.T @ y, rcond=None)  # normal equations: 3 columns
    return beta, y - a @ beta


def extent(preps: Sequence[Prepared]) -> tuple[float, float]:
    """Peak field (MV/m) and Nyquist frequency (Hz) over the sweeps."""
    e_max = max(float(np.max(np.abs(p.field))) for p in preps) or 1.0
    return e_max, 0.5 / min(p.dt for p in preps)


# ----------------------------------------------------------------------------------------------
# internal parameters -> physical model
# ----------------------------------------------------------------------------------------------


def build_model(polarization: hy.Polarization, r: float, fn: float, zeta: float,
                beta: FloatArray, scales: Scales, thickness_um: float) -> td.Transducer:
    """Physical transducer from the shape of ``polarization`` (its eta and P_R are replaced),
    ``r`` (MV/m), rod ``f_n`` (Hz) and ``zeta``, and ``beta = (g1, g2, offset)``.

    ``eta = r / P_R``, ``k = m (2 pi f_n)^2``, ``c = 2 zeta sqrt(k m)``, ``a1~ = g1 k eta / 1e6``,
    ``a2~ = g2 k eta^2 / 1e6`` (eq. (16) with u in um).
    """
    g1, g2, off = (float(b) for b in beta)
    eta, m = float(r) / scales.p_r, scales.mass_kg
    k = m * (2 * math.pi * float(fn)) ** 2
    rod = rd.Rod(m=m, c=2 * float(zeta) * math.sqrt(k * m), k=k, a1=g1 * k * eta / 1e6,
                 a2=g2 * k * eta ** 2 / 1e6, offset_um=off)
    pol = hy.Polarization(eta=eta, p_r=scales.p_r, coercive=polarization.coercive,
                          interaction=polarization.interaction,
                          n_coercive=polarization.n_coercive)
    return td.Transducer(pol, rod, thickness_um)


def to_model(theta: FloatArray, beta: FloatArray, scales: Scales, thickness_um: float,
             n_coercive: int = 256) -> td.Transducer:
    """Model for the lognormal/normal ``theta`` (values, order of :data:`THETA_NAMES`)."""
    median, sig, std, r, fn, zeta = (float(v) for v in theta)
    pol = hy.Polarization(1.0, 1.0, hy.Lognormal(median, sig), hy.Normal(std),
                          n_coercive=n_coercive)
    return build_model(pol, r, fn, zeta, beta, scales, thickness_um)


def internal(model: td.Transducer) -> FloatArray:
    """``log(theta)`` (order of :data:`THETA_NAMES`) of a lognormal/normal model: the inverse of
    :func:`to_model` for the nonlinear parameters. ValueError for other densities."""
    pol = model.polarization
    if not isinstance(pol, hy.Polarization):
        kind = "Bouc-Wen" if pol.kernel == "bouc-wen" else "Preisach-grid"
        raise ValueError(f"is a {kind} model: diagnose extends the paper's parametric model "
                         "(lognormal/normal densities); run it without --model and it fits its "
                         "own")
    if not isinstance(pol.coercive, hy.Lognormal) or not isinstance(pol.interaction, hy.Normal):
        raise ValueError("needs a lognormal coercive-field and a normal interaction-field density")
    return np.log([pol.coercive.median, pol.coercive.sigma, pol.interaction.std,
                   pol.eta * pol.p_r, model.rod.natural_hz, model.rod.damping_ratio])


def rod_of(x: FloatArray) -> tuple[float, float]:
    """The rod's natural frequency (Hz) and damping ratio of the internal parameters ``x``
    (:func:`internal`): a start for the other representations' fits."""
    return math.exp(float(x[4])), math.exp(float(x[5]))


def lognormal_equivalent(model: td.Transducer) -> td.Transducer:
    """``model`` in the lognormal/normal family :func:`internal` takes: a general (discrete)
    coercive density, as identify writes one, replaced by the lognormal with the same mean and
    standard deviation of ``ln E_c`` (weighted by its quadrature weights), a discrete interaction
    density by the normal of the same second moment; everything else kept. A start for fits in
    the lognormal space (``afmctl diagnose --model``), not the same model.

    Examples
    --------
    >>> import numpy as np
    >>> from afmctl.files.profile import default_profile
    >>> m = default_profile().emulator.model
    >>> x = np.geomspace(0.2, 5.0, 48)
    >>> d = hy.Discrete(tuple(x), tuple(np.exp(-0.5 * (np.log(x) / 0.4) ** 2) / x))
    >>> g = replace(m, polarization=replace(m.polarization, coercive=d))
    >>> c = lognormal_equivalent(g).polarization.coercive
    >>> round(c.median, 2), round(c.sigma, 2)
    (1.0, 0.4)
    """
    pol = model.polarization
    if not isinstance(pol, hy.Polarization):  # a grid or Bouc-Wen: no densities to replace
        return model
    coercive, interaction = pol.coercive, pol.interaction
    if isinstance(coercive, hy.Discrete):
        x, w = coercive.nodes_weights()
        w = w / float(np.sum(w))
        mu = float(np.sum(w * np.log(x)))
        sigma = math.sqrt(float(np.sum(w * (np.log(x) - mu) ** 2)))
        coercive = hy.Lognormal(math.exp(mu), max(sigma, 0.05))
    if isinstance(interaction, hy.Discrete):
        x, w = interaction.nodes_weights()
        interaction = hy.Normal(max(math.sqrt(float(np.sum(w * x ** 2) / np.sum(w))), 1e-3))
    return replace(model, polarization=replace(pol, coercive=coercive, interaction=interaction))


def describe(model: td.Transducer) -> list[tuple[str, float, str]]:
    """The free physical parameters of ``model`` as (name, value, unit)."""
    pol, rod = model.polarization, model.rod
    out = [("eta", pol.eta, "(MV/m)/(C/m^2)")]
    if isinstance(pol.coercive, hy.Lognormal):
        out += [("coercive_median", pol.coercive.median, "MV/m"),
                ("coercive_sigma_ln", pol.coercive.sigma, "1")]
    elif isinstance(pol.coercive, hy.Discrete):
        out += [(f"coercive_density@{x:.4g}", v, "1/(MV/m)")
                for x, v in zip(pol.coercive.nodes, pol.coercive.values, strict=True)]
    std = pol.interaction.std if isinstance(pol.interaction, hy.Normal) else float("nan")
    return out + [("interaction_std", std, "MV/m"), ("c", rod.c, "N s/m"), ("k", rod.k, "N/m"),
                  ("a1", rod.a1, "N/(C/m^2)"), ("a2", rod.a2, "N/(C/m^2)^2"),
                  ("offset", rod.offset_um, "um"), ("natural_frequency", rod.natural_hz, "Hz"),
                  ("damping_ratio", rod.damping_ratio, "1")]


# ----------------------------------------------------------------------------------------------
# the spaces
# ----------------------------------------------------------------------------------------------


class LognormalSpace:
    """``x = log(theta)``, theta = (median E_c, sigma_ln, sigma_I, r, f_n, zeta): criteria (12)
    with a lognormal ``nu_1`` and a normal ``nu_2``."""

    def __init__(self, preps: Sequence[Prepared], scales: Scales, n_coercive: int,
                 starts: Sequence[str] | None = None, cache: QCache | None = None) -> None:
        self.preps, self.scales, self.n_coercive = list(preps), scales, n_coercive
        self.starts = tuple(starts or ["depoled"] * len(self.preps))
        self._cache: QCache = {} if cache is None else cache
        self.x_scale: str | float = 1.0  # logs: unit steps are natural
        self.names = tuple(f"log_{n}" for n in THETA_NAMES)

    def with_starts(self, starts: Sequence[str], n_coercive: int | None = None) -> LognormalSpace:
        """The same space with other initial states (one of :data:`STARTS` per sweep) and
        optionally another number of coercive nodes."""
        return LognormalSpace(self.preps, self.scales, n_coercive or self.n_coercive, starts,
                              self._cache)

    def design(self, x: FloatArray) -> FloatArray:
        theta = np.exp(x)
        median, sig, std, r = (float(v) for v in theta[:4])
        pol = hy.Polarization(eta=1.0, p_r=r, coercive=hy.Lognormal(median, sig),
                              interaction=hy.Normal(std), n_coercive=self.n_coercive)
        q = run_from(pol, [p.field[p.keep] for p in self.preps], self.starts,
                     cache=self._cache, key=np.asarray(x[:4], dtype=float).tobytes())
        return columns(q, theta[4], theta[5], self.preps)

    def penalty(self, x: FloatArray) -> FloatArray:
        return np.empty(0)

    def bounds(self) -> tuple[FloatArray, FloatArray]:
        e_max, nyq = extent(self.preps)
        lo = np.log([1e-3 * e_max, 0.02, 1e-3 * e_max, 1e-4 * e_max, 0.5, 0.003])
        hi = np.log([10 * e_max, 3.0, 10 * e_max, 100 * e_max, 20 * nyq, 5.0])
        return lo, hi

    def starts_ranked(self, cost: Callable[[FloatArray], float]) -> list[FloatArray]:
        """Starting ``x`` from the data alone, best first: the peak field scales a grid over the
        coercive median and the hysteretic weight (rod static at 0.45 of the Nyquist frequency);
        see :meth:`tune_rod` for the rod."""
        e_max, nyq = extent(self.preps)
        grid = [np.log([mf * e_max, 0.5, 0.3 * mf * e_max, rf * e_max, 0.45 * nyq, 0.5])
                for mf in (0.2, 0.5, 0.9) for rf in (0.05, 0.2, 0.6)]
        costs = cores.together([functools.partial(cost, x) for x in grid])  # side by side
        return [grid[i] for i in np.argsort(costs)]

    def tune_rod(self, x: FloatArray, cost: Callable[[FloatArray], float]) -> FloatArray:
        """``x`` with the best natural frequency of a grid below the Nyquist frequency
        (damping 0.3), or unchanged if none is better."""
        _, nyq = extent(self.preps)
        freqs = [f for f in (30.0, 100.0, 300.0, 1000.0, 3000.0) if f < 0.45 * nyq]
        cands = [x] + [np.concatenate((x[:4], np.log([f, 0.3]))) for f in freqs]
        costs = cores.together([functools.partial(cost, x) for x in cands])
        return cands[min(range(len(cands)), key=costs.__getitem__)]  # as min(cands, key=cost)

    def model(self, x: FloatArray, beta: FloatArray, thickness_um: float) -> td.Transducer:
        return with_initial(to_model(np.exp(x), beta, self.scales, thickness_um), self.starts)
