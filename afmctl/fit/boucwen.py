"""Identification of the Bouc-Wen polarization (:mod:`afmctl.model.boucwen`) from sweeps.

In the frame of the Preisach grid's fit (:mod:`afmctl.fit.preisach`), the reading is::

    u = L[g(Q~)] + offset_s,   g(Q) = Q + s Q^2,    Q = r E + c eta(E),              (um)
    Q~ = Q + w sum_j z_j[Q]    (creep elements of :mod:`afmctl.model.creep`, equal weights)

with ``L`` the rod (16) at unit DC gain (exact ZOH, (18)), ``eta`` the Bouc-Wen variable
normalized to its saturation (``eta' = a (1 - q |eta|^n)``, ``q = 1`` away from zero, ``kappa``
toward it: a Bouc-Wen model with ``A = a h_s``), the reversible slope ``r`` the margin ``m >= 0``
above the steepest slope of a subtracted loop (:func:`reversible`: the E-P relation stays
monotone), and the gain fixed by convention in ``g``. Nine parameters (``log a, kappa, n, m, c,
s, log f_n, log zeta, w``) and each sweep's start state (``state_<i>``: ``eta`` at its first
field, in [-1, 1]) are fitted by least squares (:func:`scipy.optimize.least_squares`, trust
region, bounds), each sweep's residual weighted by its sensor noise, its offset projected out
(the mean of its residual).

**Start states.** A Bouc-Wen stage forgets nothing, and its whole memory is ``eta``: a sweep
recorded after work the set does not hold (the moves between files, an excitation identify leaves
out, the other axis's files of a two-axis stage) starts wherever that work left ``eta``, which
no named state (depoled, poled, the previous sweep's end) need be. The fit therefore takes each
sweep's start state as a parameter (one number each; a named assignment only says where it
starts). On the foreign x/y stage foreign-xy-2, whose Bouc-Wen y axis saturates slowly
(``beta + gamma`` 1.6), the named assignments left its triangles at 5.3-6.7x the sensor noise
and the fitted states bring them to 1.00-1.02x, with ``kappa`` and ``n`` as the plant's to three
digits.

**Starts.** For every start assignment given and every ``kappa`` of :data:`START_SHAPES` the
best shape (``a, n``) with ``r, c`` solved linearly is screened (:func:`start`). The screening is
crude (its quasi-static error is 1e4 times the fitted one) and the cost has a second basin (on
foreign-xy-2's y axis and on the stage of tests/fit/test_boucwen_states.py, ``kappa`` -1.23 and
``n`` 1.96 at 6-18x the noise, where the plants have -1.02 and 1.7): so the screened starts are
fitted in their order, without creep, until one reaches :data:`GOOD` times the noise overall or
two end in the same minimum (at most :data:`MAX_STARTS`). Each first gets a coarse rod search
with the hysteresis held (:meth:`Problem.rod_search`: the rod identify starts from may be far
off, e.g. a paper's model fit that stayed at 25x the noise left foreign-xy-2's y axis a 1e8 Hz
rod, from whose bound the fit stopped at 5.7x), then a search of each sweep's start state with
the shape held (:meth:`Problem.state_search`: a start assignment knows only the recorded way to
a sweep), and the search of states again at the solved shape, the solve repeated from there if
it moved one (:func:`_searched`). The best gets the rod search again and then creep.

Nine parameters and a state per sweep against thousands of samples: the in-sample error is the
held-out one to within ``p / N`` (as for the HEM, :mod:`afmctl.fit.representation`), and is what
identify compares.
"""

from __future__ import annotations

import functools
import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import optimize

from afmctl.fit import cores
from afmctl.fit import stall
from afmctl.fit import uncertainty as unc
from afmctl.fit.parametrization import FieldGrid, every_kth, field_grid
from afmctl.fit.preisach_problem import Data
from afmctl.fit.rod_response import rod_filter
from afmctl.model import boucwen as bwm
from afmctl.model import creep as cr
from afmctl.model import hysteresis as hy
from afmctl.model import rod as rd
from afmctl.model import transducer as td

FloatArray = NDArray[np.float64]
#: Shapes tried for the start: ``a`` times the field range, ``kappa``, ``n``.
START_SHAPES = tuple(itertools.product((1.0, 3.0, 8.0), (-2.0, -1.0, -0.5, 0.5), (1.0, 2.0)))
#: Least-squares evaluations allowed per solve and free parameter (a Jacobian costs one per
#: parameter): without start states a Bouc-Wen stage's fit converged in 10-50, with them
#: foreign-xy-2's y axis (12 parameters) in 88-99; a Preisach stage's, which Bouc-Wen cannot
#: fit, ran 300 at ~1 s each at 10 kHz.
NFEV_PER_PARAMETER = 12
#: Relative step of the finite-difference Jacobian (the RK4 substep count is a step function
#: of ``a``: steps below it see its jumps).
DIFF_STEP = 1e-5
#: Bounds of the rod's damping ratio.
ZETA_BOUNDS = (1e-3, 2.0)
#: The fitted shape's parameters, in order (``creep``: weight per creep element); each sweep's
#: start state follows them (:func:`names`).
NAMES = ("log_a", "kappa", "n", "margin", "c", "s", "log_fn", "log_zeta", "creep")
#: A start state begins at most this far toward saturation: at ``|eta| = 1`` a sweep that moves
#: on toward it leaves ``eta`` there, and the state has no derivative to leave the bound by (on
#: foreign-xy-2's y axis every sweep started at -1 stopped at 45x the cost of the fit started at
#: -1, -0.98, -0.98, -0.98).
STATE_START_MAX = 0.95
#: Start states (shares of the saturation) :meth:`Problem.state_search` tries for each sweep.
STATE_GRID = tuple(np.linspace(-STATE_START_MAX, STATE_START_MAX, 13))
#: Where the creep weight and the first start state are in a parameter vector.
CREEP_AT, STATES_AT = NAMES.index("creep"), len(NAMES)
#: Creep elements (:mod:`afmctl.model.creep`): two per decade, 10 ms to 1000 s, equal weights: a
#: straight line against log time, one parameter.
CREEP_TAUS_S = cr.DEFAULT_TAUS_S
#: The rod's coarse search: natural frequencies from this (Hz) to 0.45 of the sample rate, this
#: many log-spaced, times these damping ratios.
ROD_GRID = (100.0, 24, (0.02, 0.05, 0.1, 0.2, 0.4, 0.8))
#: Screened starts are fitted until the overall RMS is within this many times the noise ...
GOOD = 1.2
#: ... or this many have been.
MAX_STARTS = 4
#: ... or two have ended at costs within this share of each other (the same minimum).
SAME = 1e-6
#: A sweep with more judged samples is fitted on every k-th (its rows weighed by sqrt(k) over
#: the noise), down to about this many: ``afmctl sweep``'s 40 s of minor loops at 10 kHz
#: (400,000) by 8, the standard 0.279 Hz triangle at 10 kHz on a unipolar stage (53,854 judged)
#: by 2, on a bipolar one (44,893) not. The fit's readings and figures are then judged on every
#: sample.
MAX_ROWS = 50_000
#: A solve with ``give_up`` (:func:`_solve`) stalls when its cost falls by less than this share
#: of itself in :data:`afmctl.fit.stall.STEPS` steps while over ``give_up`` times the noise
#: (the stall's default, 0.1 %, let preisach-u-drift's Bouc-Wen crawl from 50.05x to 49.92x the
#: noise in 20 more steps, 1.4 s, where 4.5x was asked: a hundredth of the cost needed). From
#: there, falling 1 % in 10 steps, the solve would need thousands of steps to reach ``give_up``.
GIVE_UP_SHARE = 1e-2
#: Start, upper bound and least weight kept (below it: no creep) per element.
CREEP_START, CREEP_MAX, CREEP_MIN = 1e-3, 0.05, 1e-5


@dataclass(frozen=True)
class BoucWenFit:
    """Outcome of :func:`fit` (the attributes identify reads, as :class:`~afmctl.fit.preisach.
    PreisachFit`'s).

    Attributes
    ----------
    model : transducer.Transducer
        The Bouc-Wen polarization, the rod, the last sweep's sensor zero and start state (its
        initial one).
    starts : tuple of str
        Each sweep's fitted start state, named by its value
        (:func:`afmctl.model.hysteresis.bouc_wen_state`).
    offsets : ndarray
        Each sweep's sensor zero, um.
    heldout_rms_um : ndarray
        Per sweep, the RMS on its judged samples, um (in-sample: see the module).
    iterations, converged, seconds
        Function evaluations, whether the solver met its tolerance, wall time (s).
    how : str
        How the solve ended: ``converged``, ``stopped on its budget``, or the stall's message
        (:mod:`afmctl.fit.stall`: stopped where it crawled, far off).
    predicted : list of ndarray
        The fit's readings on every sample of each sweep (um), with the sweep's sensor zero.
    parameters : dict
        The fitted shape in the normalized frame (``a`` in 1/(MV/m), ``kappa``, ``n``, ``s`` in
        1/um, the rod) and each sweep's start state (``state_<i>``, share of the saturation).
    uncertainty : dict
        :func:`afmctl.fit.uncertainty.summary` of those parameters (offsets projected out).
    """

    model: td.Transducer
    starts: tuple[str, ...]
    offsets: FloatArray
    heldout_rms_um: FloatArray
    iterations: int
    converged: bool
    seconds: float
    predicted: list[FloatArray]
    parameters: dict[str, float]
    uncertainty: dict[str, Any]
    how: str


def names(n_sweeps: int) -> tuple[str, ...]:
    """The parameters of a fit to ``n_sweeps`` sweeps: :data:`NAMES`, then each start state."""
    return NAMES + tuple(f"state_{i + 1}" for i in range(n_sweeps))


class Problem:
    """The sweeps and the model's readings for a parameter vector (its shape, then each sweep's
    start state)."""

    def __init__(self, data: Data, field_step: float = 0.0, rows: int | None = None) -> None:
        """``field_step``: ``eta`` computed where the field moved by this share of its peak
        (:func:`_eta`); ``rows``: a sweep with more judged samples is judged on every k-th
        (:func:`afmctl.fit.parametrization.every_kth`), its rows weighed by sqrt(k) over the
        noise; the model is still simulated on every sample."""
        strides = [1] * len(data.fields)
        if rows is not None:
            parts = [every_kth(m, y, rows) for m, y in zip(data.masks, data.y, strict=True)]
            data = replace(data, masks=[p[0] for p in parts], y=[p[1] for p in parts], folds=[])
            strides = [p[2] for p in parts]
        self.data = data
        #: per sweep, the samples ``eta`` is computed on and interpolated from (:func:`_eta`)
        self.grids = [field_grid(e, field_step * float(np.max(np.abs(e)))) for e in data.fields]
        lo = min(float(np.min(e)) for e in data.fields)
        hi = max(float(np.max(e)) for e in data.fields)
        self.span, self.poling = max(hi - lo, 1e-9), (lo, hi)
        self.weights = [np.full(int(m.sum()), math.sqrt(k) / n) for m, n, k in
                        zip(data.masks, data.noise, strides, strict=True)]
        #: the judged samples the rows stand for (the residual's degrees of freedom)
        self.samples = sum(k * int(m.sum()) for m, k in zip(data.masks, strides, strict=True))

    def _operator(self, log_a: float, kappa: float, n: float) -> tuple[bwm.BoucWen, hy.Kernel]:
        bw = bwm.BoucWen(0.0, math.exp(log_a), 1.0, kappa, n, self.poling)
        return bw, bw.build_kernel()

    def shape(self, log_a: float, kappa: float, n: float, states: FloatArray) -> list[FloatArray]:
        """``eta`` per sweep (every sample), each from its start state ``states`` (``eta`` at
        its first field)."""
        op = self._operator(log_a, kappa, n)
        return [_eta(op, e, h, g) for e, h, g in zip(self.data.fields, states, self.grids,
                                                     strict=True)]

    def named_states(self, log_a: float, kappa: float, n: float, starts: Sequence[str]
                     ) -> FloatArray:
        """``eta`` at each sweep's first field when the sweeps start as ``starts`` name
        (:data:`afmctl.fit.parametrization.STARTS`; ``previous``: where the sweep before left
        it, the first depoled), within :data:`STATE_START_MAX`."""
        bw, k = self._operator(log_a, kappa, n)
        out, prev = [], None
        for e, grid, start in zip(self.data.fields, self.grids, starts, strict=True):
            st = prev if start == "previous" and prev is not None else hy.initial_state(
                bw, "depoled" if start == "previous" else start)
            q, prev = hy.run(k, e[grid.keep], st)
            out.append(float(q[0]))
        return np.clip(out, -STATE_START_MAX, STATE_START_MAX)

    def forces(self, x: FloatArray) -> list[FloatArray]:
        """``g(Q~)`` per sweep (every sample): ``Q`` with its creep, through the force law; the
        rod's input. The creep is chained as the grid's is
        (:meth:`afmctl.fit.preisach_problem.Problem.creep_starts`): a sweep that followed the
        one before after a known hold (:attr:`Data.gaps_s`) starts where that one left its
        elements, relaxed over the hold; else at rest at its first sample."""
        return self._chain(x, self.shape(x[0], x[1], x[2], x[STATES_AT:]))[0]

    def _chain(self, x: FloatArray, etas: Sequence[FloatArray]
               ) -> tuple[list[FloatArray], list[FloatArray | None]]:
        """Each sweep's force for its ``eta`` and the creep state it started from (None: at
        rest)."""
        gaps = self.data.gaps_s or [math.nan] * len(etas)
        creep = creep_of(x[CREEP_AT])
        out, starts, end = [], [], None
        for i, (eta, gap) in enumerate(zip(etas, gaps, strict=True)):
            start = None if end is None or not gap >= 0.0 else cr.held(creep, end, gap)
            f, end = self.force(x, i, eta, start)
            out.append(f)
            starts.append(start)
        return out, starts

    def force(self, x: FloatArray, i: int, eta: FloatArray, start: FloatArray | None = None
              ) -> tuple[FloatArray, FloatArray]:
        """``g(Q~)`` of sweep ``i`` (every sample) for its ``eta``, its creep elements from
        ``start`` (default: at rest at its first sample), and their state after it."""
        log_a, kappa, _, m, c, s, _, _, w = x[:STATES_AT]
        r = reversible(m, c, math.exp(log_a), kappa)
        creep, e = creep_of(w), self.data.fields[i]
        p_h = r * e + c * eta
        z0 = cr.rest_state(creep, float(p_h[0])) if start is None else start
        q, end = cr.run(creep, p_h, self.data.dts[i], z0)
        return q + s * q * q, end

    def state_search(self, x: FloatArray) -> FloatArray:
        """``x`` with each sweep's start state the best of its own and :data:`STATE_GRID`, the
        shape and rod held (each sweep has its own offset: they are independent given the
        shape). A start assignment names where a sweep starts only as far as the set records
        the way there: foreign-xy-6's y axis reached its both-axes file through the chirp
        identify leaves out, the chained state began it at the other saturation, and the fit
        stopped with that state near 0 and every sweep at 10-14x the noise (the plant's state
        lies two thirds of the way to negative saturation)."""
        op = self._operator(float(x[0]), float(x[1]), float(x[2]))
        fn, zeta = math.exp(x[6]), math.exp(x[7])
        out = np.array(x, float)
        starts = self._chain(x, self.shape(x[0], x[1], x[2], x[STATES_AT:]))[1]
        for i, (e, grid) in enumerate(zip(self.data.fields, self.grids, strict=True)):
            costs = []
            for h in (x[STATES_AT + i], *STATE_GRID):
                u = rod_filter(self.force(x, i, _eta(op, e, h, grid), starts[i])[0], fn, zeta,
                               self.data.dts[i])[self.data.masks[i]]
                r = self.data.y[i] - u
                costs.append((float(np.sum((r - r.mean()) ** 2)), float(h)))
            out[STATES_AT + i] = min(costs)[1]
        return out

    def readings(self, x: FloatArray, forces: list[FloatArray] | None = None
                 ) -> list[FloatArray]:
        """``L[g(Q~)]`` per sweep (every sample), without offsets (``forces``: those of ``x``,
        if already known)."""
        fn, zeta = math.exp(x[6]), math.exp(x[7])
        return [rod_filter(f, fn, zeta, dt) for f, dt in
                zip(forces if forces is not None else self.forces(x), self.data.dts, strict=True)]

    def cost(self, u: list[FloatArray]) -> float:
        """Half the sum of squares of :meth:`weighted` (as :func:`scipy.optimize.least_squares`
        counts it)."""
        return 0.5 * float(np.sum(self.weighted(u) ** 2))

    def rod_search(self, x: FloatArray) -> FloatArray:
        """``x`` with the rod of :data:`ROD_GRID` (natural frequencies to 0.45 of the sample
        rate, damping ratios) that fits best with the hysteresis held: the fast triangle alone
        pins the rod, and from a far start the fit stays in a far minimum (bw-u-creep's 1.93 kHz
        rod identified at 4.49 kHz from the grid's, its 27.9 Hz tracking 4x worse than the
        linear filter's)."""
        forces = self.forces(x)
        best = (self.cost(self.readings(x, forces)), x[6], x[7])
        for fn, zeta in itertools.product(np.geomspace(ROD_GRID[0], 0.45 / min(self.data.dts),
                                                       ROD_GRID[1]), ROD_GRID[2]):
            trial = np.concatenate((x[:6], [math.log(fn), math.log(zeta)], x[8:]))
            cost = self.cost(self.readings(trial, forces))
            if cost < best[0]:
                best = (cost, math.log(fn), math.log(zeta))
        return np.concatenate((x[:6], best[1:], x[8:]))

    def offsets(self, u: list[FloatArray]) -> FloatArray:
        return np.array([float(np.mean(y - p[m])) for y, p, m in
                         zip(self.data.y, u, self.data.masks, strict=True)])

    def weighted(self, u: list[FloatArray]) -> FloatArray:
        """Residuals of readings ``u`` on the judged samples over each sweep's noise, offsets
        projected out (1e6 each if ``u`` is not finite)."""
        if not all(np.all(np.isfinite(p)) for p in u):
            return np.full(sum(w.size for w in self.weights), 1e6)
        off = self.offsets(u)
        return np.concatenate([(y - p[m] - o) * w for y, p, m, o, w in
                               zip(self.data.y, u, self.data.masks, off, self.weights,
                                   strict=True)])

    def residual(self, x: FloatArray) -> FloatArray:
        return self.weighted(self.readings(x))


def _eta(op: tuple[bwm.BoucWen, hy.Kernel], field: FloatArray, h: float,
         grid: FieldGrid) -> FloatArray:
    """``eta`` on ``field`` (every sample) for the operator and kernel ``op``, from the start
    state ``h`` (``eta`` at its first field): computed on the samples ``grid.keep`` and
    interpolated in between in the field (:func:`afmctl.fit.parametrization.field_grid`). The
    operator is rate independent, integrated in the field by substeps
    (:data:`afmctl.model.hysteresis.BW_SUBSTEP`), so ``eta`` at a kept sample is the full
    rate's to the integration's accuracy; between two kept samples with samples between them
    the field is monotone and moves by about a step, ``eta`` is a smooth function of it, and
    linear interpolation in the field errs by O(step^2). (In time it would not: the sample
    after a reversal, left out where the field had turned by less than a step, took half the
    next sample's move instead of its own 4 %, and missed by 0.085 um on a 27.9 Hz triangle.)"""
    bw, k = op
    q = hy.run(k, field[grid.keep], hy.initial_state(bw, hy.bouc_wen_state(float(h))))[0]
    return grid.on_every_sample(q)


def _linear_start(prob: Problem, log_a: float, kappa: float, n: float, states: FloatArray
                  ) -> tuple[float, float, float]:
    """``r, c`` of the quasi-static fit ``y = r E + c eta + offset_s`` and its weighted SSE."""
    rows, rhs = [], []
    k = len(prob.data.fields)
    for i, (e, eta, m, y, w) in enumerate(zip(prob.data.fields,
                                              prob.shape(log_a, kappa, n, states),
                                              prob.data.masks, prob.data.y, prob.weights,
                                              strict=True)):
        cols = np.zeros((int(m.sum()), 2 + k))
        cols[:, 0], cols[:, 1], cols[:, 2 + i] = e[m], eta[m], 1.0
        rows.append(cols * w[:, None])  # the fit's weights: sqrt(k) / noise
        rhs.append(y * w)
    a, b = np.vstack(rows), np.concatenate(rhs)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    return float(sol[0]), float(sol[1]), float(np.sum((a @ sol - b) ** 2))


def start(prob: Problem, rod0: tuple[float, float], starts: Sequence[str]
          ) -> list[tuple[float, FloatArray]]:
    """For each ``kappa`` of :data:`START_SHAPES`, the best shape by its quasi-static linear fit
    (:func:`_linear_start`) with the sweeps started as ``starts`` name
    (:meth:`Problem.named_states`), the reversible part as its margin, no quadratic, the rod at
    ``rod0``, no creep; with its weighted SSE (none for a ``kappa`` whose shapes have no loop)."""
    best: dict[float, tuple[float, FloatArray]] = {}
    for a_span, kappa, n in START_SHAPES:
        log_a = math.log(a_span / prob.span)
        states = prob.named_states(log_a, kappa, n, starts)
        r, c, sse = _linear_start(prob, log_a, kappa, n, states)
        if c != 0 and (kappa not in best or sse < best[kappa][0]):
            margin = max(r - reversible(0.0, c, math.exp(log_a), kappa), 0.0)
            best[kappa] = (sse, np.concatenate(([log_a, kappa, n, margin, c, 0.0,
                                                 math.log(rod0[0]), math.log(rod0[1]), 0.0],
                                                states)))
    return list(best.values())


def _bounds(prob: Problem, x0: FloatArray) -> tuple[FloatArray, FloatArray]:
    nyquist = 0.5 / min(prob.data.dts)
    sign = 1.0 if x0[4] > 0 else -1.0  # the loop's sense: c keeps the start's sign
    lo = np.array([math.log(0.05 / prob.span), bwm.KAPPA_BOUNDS[0], 1.0, 0.0,
                   1e-9 * abs(x0[4]) if sign > 0 else -np.inf, -np.inf, math.log(0.5),
                   math.log(ZETA_BOUNDS[0]), 0.0])
    hi = np.array([math.log(200.0 / prob.span), bwm.KAPPA_BOUNDS[1], 4.0, np.inf,
                   np.inf if sign > 0 else -1e-9 * abs(x0[4]), np.inf, math.log(20 * nyquist),
                   math.log(ZETA_BOUNDS[1]), CREEP_MAX])
    n_s = len(prob.data.fields)
    return np.concatenate((lo, -np.ones(n_s))), np.concatenate((hi, np.ones(n_s)))


def build(x: FloatArray, prob: Problem, offsets: FloatArray, mass_kg: float, thickness_um: float,
          p_scale: float) -> td.Transducer:
    """The physical model of ``x``: ``P = k_s Q`` with ``k_s`` making the largest ``|Q|`` over the
    sweeps ``p_scale`` (C/m^2), so ``r = k_s r_Q``, ``h_s = k_s |c|``, ``A = a k_s c``; the rod
    ``k = m (2 pi f_n)^2``, ``a1 = 1e-6 k / k_s``, ``a2 = 1e-6 k s / k_s^2`` (as
    :func:`afmctl.fit.preisach.build`); its initial state and sensor zero the last sweep's (a
    consistent pair: the model run from that state predicts that sweep; the most recent, as
    :func:`afmctl.fit.parametrization.zero_sweep` takes it, is the nearest to where a creeping
    stage is when the model is used)."""
    log_a, kappa, n, m, c, s, log_fn, log_zeta, w = (float(v) for v in x[:STATES_AT])
    r = reversible(m, c, math.exp(log_a), kappa)
    q_max = max(float(np.max(np.abs(r * e + c * eta))) for e, eta in
                zip(prob.data.fields, prob.shape(log_a, kappa, n, x[STATES_AT:]),
                    strict=True)) or 1.0
    ks = p_scale / q_max
    pol = bwm.BoucWen(r * ks, math.exp(log_a) * c * ks, abs(c) * ks, kappa, n, prob.poling)
    fn, zeta = math.exp(log_fn), math.exp(log_zeta)
    k = mass_kg * (2 * math.pi * fn) ** 2
    rod = rd.Rod(m=mass_kg, c=2 * zeta * math.sqrt(k * mass_kg), k=k, a1=1e-6 * k / ks,
                 a2=1e-6 * k * s / ks ** 2, offset_um=float(offsets[-1]))
    return td.Transducer(pol, rod, thickness_um, initial=states(x)[-1], creep=creep_of(w))


def states(x: FloatArray) -> tuple[str, ...]:
    """Each sweep's fitted start state of ``x``, named by its value
    (:func:`afmctl.model.hysteresis.bouc_wen_state`; ``eta``'s share is ``h``'s)."""
    return tuple(hy.bouc_wen_state(float(np.clip(h, -1.0, 1.0))) for h in x[STATES_AT:])


def reversible(margin: float, c: float, a: float, kappa: float) -> float:
    """The reversible slope ``r`` (um per MV/m) whose least ``dQ/dE`` is ``margin``: ``r`` itself
    for a loop added (``c > 0``: ``dh/dE >= 0`` while ``|h| <= h_s``), ``margin + |c| a max(1,
    1 - kappa)`` for a loop subtracted (its steepest, just after a reversal at saturation). The
    fit's ``margin >= 0`` keeps the E-P relation monotone, as Algorithm 3 needs."""
    return margin + max(-c, 0.0) * a * max(1.0, 1.0 - kappa)


def creep_of(weight: float) -> cr.Creep | None:
    """Log-time creep of ``weight`` per element on :data:`CREEP_TAUS_S` (about twice that per
    decade), or None below :data:`CREEP_MIN`."""
    if weight < CREEP_MIN:
        return None
    return cr.Creep(CREEP_TAUS_S, (float(weight),) * len(CREEP_TAUS_S))


def fit(data: Data, starts_candidates: Sequence[Sequence[str]], rod0: tuple[float, float],
        thickness_um: float, mass_kg: float, p_scale: float,
        say: Callable[[str], None] | None = None, give_up: float | None = None,
        field_step: float = 0.0,
        give_up_why: str = "where another representation is far below") -> BoucWenFit:
    """Fit the Bouc-Wen model to ``data``.

    Parameters
    ----------
    data : Data
        The sweeps as :mod:`afmctl.fit.preisach` sees them.
    starts_candidates : sequence of sequences of str
        Start assignments (each sweep's start state,
        :data:`afmctl.fit.parametrization.STARTS`) the fitted start states begin at (see the
        module's **Starts**).
    rod0 : (float, float)
        Starting natural frequency (Hz) and damping ratio (e.g. the HEM fit's).
    thickness_um, mass_kg, p_scale : float
        Layer thickness (um), the fixed effective mass (kg) and polarization scale (C/m^2): scale
        conventions, as the other representations'.
    give_up : float, optional
        After a start (its state search included), stop if some sweep is still more than this
        many times its noise: another representation already fits so much better that the other
        starts and the creep are not expected to make Bouc-Wen win (identify passes
        :data:`afmctl.fit.representation.DECISIVE` times the grid's worst held-out error; on
        pi-u-creep, the grid at 1.53x, Bouc-Wen's first start left 62x, and the whole fit had
        taken 100 s to end at 43x). The fit returned is that start's, without creep.
        ``give_up_why`` says why in the progress line (the first try, before any other
        representation: that it will not reach the noise floor from there).
    field_step : float
        ``eta`` is computed where the field has moved by this share of its peak (and at every
        turning point and hold) and interpolated in between (:func:`_eta`; identify passes its
        ``field_step``, 0.004); 0: on every sample.
    """
    say = say or (lambda _m: None)
    t0 = time.perf_counter()
    rod = (min(max(rod0[0], 1.0), 0.4 / min(data.dts)),
           min(max(rod0[1], ZETA_BOUNDS[0]), ZETA_BOUNDS[1]))
    prob = Problem(data, field_step, MAX_ROWS)
    # each assignment's start shapes side by side (their Bouc-Wen runs release the lock)
    found = cores.mapped(functools.partial(start, prob, rod), starts_candidates)
    distinct = {tuple(np.round(x0, 3)): (sse, x0) for shapes in found
                for sse, x0 in shapes}  # assignments alike in effect: once
    if not distinct:
        raise ValueError("no Bouc-Wen shape has a loop (c = 0)")
    good = 0.5 * GOOD ** 2 * sum(y.size for y in data.y)  # the cost at GOOD x the noise
    best, hopeless = None, False
    for _, x0 in sorted(distinct.values(), key=lambda f: f[0])[:MAX_STARTS]:
        sol = _searched(prob, _solve(prob, prob.state_search(prob.rod_search(x0)),
                                     creep=False, give_up=give_up), good, give_up)
        again = best is not None and abs(sol.cost - best.cost) <= SAME * best.cost
        best = sol if best is None or sol.cost < best.cost else best
        if give_up is not None:
            scored = _rms(prob, best.x)
            hopeless = float(np.max(scored[0] / data.noise)) > give_up
        if best.cost <= good or again or hopeless:
            break
    assert best is not None
    if hopeless:
        sol = best
    else:
        crept = _solve(prob, _rod_searched(prob, best), creep=True)
        sol = crept if crept.cost < best.cost else best  # from its start the creep may end worse
    # the written model's readings, on every sample (``eta`` as the model file computes it)
    rms, off, predicted = _rms(Problem(data), sol.x)
    seconds = time.perf_counter() - t0
    say(f"  Bouc-Wen: {sol.nfev} evaluations, {seconds:.1f} s; RMS / noise per sweep "
        + " / ".join(f"{v:.2f}" for v in rms / data.noise)
        + (f" (stopped: above {give_up:.3g}x, {give_up_why})"
           if hopeless else ""))
    return BoucWenFit(build(sol.x, prob, off, mass_kg, thickness_um, p_scale), states(sol.x),
                      off, rms, int(sol.nfev), bool(sol.status > 0), seconds, predicted,
                      {k: float(v) for k, v in zip(names(len(off)), sol.x, strict=True)},
                      _uncertainty(sol, prob.samples),
                      "converged" if sol.status > 0 else
                      str(sol.message) if sol.status == -2 else "stopped on its budget")


def _rms(prob: Problem, x: FloatArray) -> tuple[FloatArray, FloatArray, list[FloatArray]]:
    """Per sweep at ``x``: the RMS on the judged samples (um), the sensor zeros (um) and the
    readings on every sample, zeros included."""
    u = prob.readings(x)
    off = prob.offsets(u)
    predicted = [p + o for p, o in zip(u, off, strict=True)]
    rms = np.array([float(np.sqrt(np.mean((y - p[m]) ** 2))) for y, p, m in
                    zip(prob.data.y, predicted, prob.data.masks, strict=True)])
    return rms, off, predicted


def _searched(prob: Problem, sol: optimize.OptimizeResult, good: float,
              give_up: float | None = None) -> optimize.OptimizeResult:
    """``sol``, or where its cost is above ``good`` and :meth:`Problem.state_search` moves a
    state at its shape, the solve from there if that ends lower. The start shape is crude and
    its state search may miss (foreign-xy-6's y axis: from the rod of identify's grid fit, every
    start ended with the both-axes file's state near 0 and the sweeps at 10-14x the noise); at
    the solved shape it does not. With ``give_up``, only if the search lowers the cost by
    :data:`GIVE_UP_SHARE` (on preisach-u-creep it moved a state for nothing, 29.86x the noise
    either way, and the solve from there took 11 steps, 1.2 s, to stall at 29.86x again)."""
    if sol.cost <= good:
        return sol
    x = prob.state_search(sol.x)
    if np.array_equal(x, sol.x) or (give_up is not None and not prob.cost(prob.readings(x))
                                    < (1.0 - GIVE_UP_SHARE) * sol.cost):
        return sol
    again = _solve(prob, x, creep=False, give_up=give_up)
    return again if again.cost < sol.cost else sol


def _rod_searched(prob: Problem, sol: optimize.OptimizeResult) -> FloatArray:
    """The solution, refitted without creep from :meth:`Problem.rod_search`'s rod if that moved
    it and the refit is better."""
    x = prob.rod_search(sol.x)
    if np.array_equal(x, sol.x):
        return sol.x
    again = _solve(prob, x, creep=False)
    return again.x if again.cost < sol.cost else sol.x


def _solve(prob: Problem, x0: FloatArray, creep: bool,
           give_up: float | None = None) -> optimize.OptimizeResult:
    """Least squares from ``x0``; without ``creep`` its weight is held at 0 (each start
    assignment is fitted so, and creep added to the best: free from the start, it led one
    assignment of a creep-free stage to a far minimum with the weight at its bound). With
    ``give_up``, stopped where it stalls (:mod:`afmctl.fit.stall`) while the RMS over the noise
    of all the sweeps together is over ``give_up``: some sweep is then over it too, and
    :func:`fit` would give up after this start (on pi-b-creep the first start crawled from 45
    to 125 steps at 99.2-99.3e6)."""
    x0 = np.array(x0, float)
    x0[CREEP_AT] = CREEP_START if creep else 0.0  # off its bound: the trust region starts moving
    lo, hi = _bounds(prob, x0)
    x0 = np.clip(x0, lo, hi)
    free = np.ones(x0.size, dtype=bool)
    free[CREEP_AT] = creep

    def full(z: FloatArray) -> FloatArray:
        x = x0.copy()
        x[free] = z
        return x

    sol = optimize.least_squares(lambda z: prob.residual(full(z)), x0[free],
                                 bounds=(lo[free], hi[free]), x_scale="jac",
                                 max_nfev=NFEV_PER_PARAMETER * int(free.sum()),
                                 diff_step=DIFF_STEP, workers=cores.mapped,
                                 callback=None if give_up is None else stall.callback(
                                     _far(prob, give_up), GIVE_UP_SHARE))
    if sol.status == -2:
        sol.message = stall.message(f"the sweeps over {give_up:.3g}x their noise", GIVE_UP_SHARE)
    sol.x, sol.free = full(sol.x), free
    return sol


def _far(prob: Problem, give_up: float) -> Callable[[optimize.OptimizeResult], bool]:
    """Whether a solve's state is over ``give_up`` times the noise: the RMS over the noise of
    every judged sample together (the residuals are over each sweep's noise; a row of a thinned
    sweep weighs ``k``, so twice the cost over :attr:`Problem.samples` is the full rate's mean
    square)."""
    return lambda r: math.sqrt(2.0 * float(r.cost) / prob.samples) > give_up


def _uncertainty(sol: optimize.OptimizeResult, samples: int) -> dict[str, Any]:
    """``s^2 (J^T J)^+`` at the solution (the residuals are already over each sweep's noise), of
    the parameters it fitted (without creep: not the creep weight). ``samples``: the judged
    samples the residual's rows stand for (a row of a thinned sweep weighs ``k``, so the cost
    and ``J^T J`` are about the full rate's, and so are the degrees of freedom)."""
    j = np.asarray(sol.jac, float)
    dof = max(samples - j.shape[1], 1)
    cov = np.linalg.pinv(j.T @ j) * (2.0 * float(sol.cost) / dof)
    x, free = np.asarray(sol.x, float), sol.free
    fitted = tuple(n for n, f in zip(names(x.size - STATES_AT), free, strict=True) if f)
    return unc.summary(fitted, x[free], cov)


def figures(fit_: BoucWenFit, noise: FloatArray) -> dict[str, Any]:
    """What ``identify --json`` says of the Bouc-Wen fit (``representations.bouc_wen``)."""
    pol = fit_.model.polarization
    assert isinstance(pol, bwm.BoucWen)
    return {"worst_heldout_over_noise": float(np.max(fit_.heldout_rms_um / noise)),
            "heldout_over_noise": [float(v) for v in fit_.heldout_rms_um / noise],
            "heldout_note": "in-sample error of nine parameters and a start state per "
            "sweep (optimism ~ p/N)",
            "kappa": pol.kappa, "exponent": pol.exponent, "evaluations": fit_.iterations,
            "start_states": list(fit_.starts),
            "creep_per_decade": None if fit_.model.creep is None else
            fit_.model.creep.per_decade(),
            "seconds": round(fit_.seconds, 3)}


__all__ = ["BoucWenFit", "Problem", "fit", "build", "start", "states", "names", "figures",
           "START_SHAPES"]
