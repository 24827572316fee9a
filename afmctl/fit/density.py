"""A general coercive-field density for identify: piecewise linear between fixed nodes (Section 2.2).

The paper allows ``nu_1`` any nonnegative density, its ``N_i`` discretized values estimated by least
squares. :class:`DiscreteSpace` writes it as ``K`` weights on nodes from 0 up (``E_c = 0``
included: a stage's density need not vanish at small coercive fields, as a lognormal's does; a
Gaussian lobe cut at 0 is of the paper's family and out of a lognormal's reach), the density
linear between them and integrated on :data:`SUBNODES` quadrature nodes per cell, so ``K``
parameters describe a smooth density without the sawtooth of ``K`` plays.

A fit in this space from the lognormal's density alone stalls (the weights below the
lognormal's support start at 0 and a finite-difference solver does not move them far):
:meth:`DiscreteSpace.refined` first solves the problem linearized in the weights, with the
gains, by bounded least squares (damped Gauss-Newton steps, inside a search over sigma_I), and
identify's solver starts from there.

Pure numerics: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import optimize

from afmctl.fit.parametrization import (
    Prepared,
    Scales,
    at_full_rate,
    build_model,
    cached,
    extent,
    offset_columns,
    project,
    run_from,
    unit_filter,
    with_initial,
)
from afmctl.model import hysteresis as hy
from afmctl.model import transducer as td

FloatArray = NDArray[np.float64]
#: Quadrature nodes per cell between two of the density's nodes.
SUBNODES = 4
#: Damped Gauss-Newton steps per weight fit of :meth:`DiscreteSpace.refined`, at most (refused
#: ones included); a fit stops earlier once a step lowers the sum of squares by less than
#: :data:`REFINE_TOL` of it.
REFINE_STEPS = 12
REFINE_TOL = 1e-3
#: The search for ``sigma_I`` spans its start times exp(+-STD_SPAN), in at most STD_EVALS steps.
STD_SPAN = 0.7
STD_EVALS = 12


@dataclass(frozen=True)
class _Basis:
    field: FloatArray  # full rate (interpolated like Q), MV/m
    h: FloatArray      # (N, K) per-node hysteresis columns, full rate
    le: FloatArray     # L[field] on the mask
    lh: FloatArray     # (M, K) L[h] on the mask


def hats(nodes: FloatArray, sub: int = SUBNODES) -> tuple[FloatArray, FloatArray]:
    """Quadrature nodes (MV/m, ``sub`` per cell, at the midpoints of its ``sub`` equal parts) and
    the matrix ``T`` (quadrature nodes x ``nodes``): a density linear between ``nodes`` with value
    ``c_i / hbar`` at node ``i`` (``hbar`` the mean cell) puts ``T @ c`` on the quadrature
    nodes, each its value there times its share of the cell (on equal cells an inner node's
    column sums to 1, the two end nodes' to 1/2)."""
    widths = np.diff(nodes)
    frac = (np.arange(sub) + 0.5) / sub
    fine = (nodes[:-1, None] + widths[:, None] * frac[None, :]).ravel()
    cell = np.repeat(np.arange(widths.size), sub)
    f = np.tile(frac, widths.size)
    share = widths[cell] / sub / float(np.mean(widths))
    t = np.zeros((fine.size, nodes.size))
    rows = np.arange(fine.size)
    t[rows, cell] = (1.0 - f) * share
    t[rows, cell + 1] = f * share
    return fine, t


def reach(preps: Sequence[Prepared], starts: Sequence[str], std: float) -> float:
    """The largest coercive field (MV/m) whose hysterons' ``H = erf(y / (sqrt(2) sigma_I))``
    the sweeps change, over their field range ``lo .. hi``; ``y`` is the play output of
    half-width ``E_c``, and ``H`` moves only while ``y`` is within about ``3 sigma_I`` of 0.
    Depoled (``y = 0``), a play moves off 0 once the field passes ``+-E_c``: up to the peak
    field. Poled positive, ``y`` starts at the first field plus ``E_c`` and is never below
    ``lo + E_c``: ``E_c < -lo + 3 sigma_I`` (negative: ``E_c < hi + 3 sigma_I``); on a
    unipolar stage poled positive only the coercive fields below ``3 sigma_I`` switch.
    ``previous`` carries the start before it."""
    lo = min(float(np.min(p.field)) for p in preps)
    hi = max(float(np.max(p.field)) for p in preps)
    bounds = {"depoled": max(-lo, hi), "positive": -lo + 3 * std, "negative": hi + 3 * std}
    chain = [s for s in starts if s != "previous"] or ["depoled"]
    return max(bounds[s] for s in chain)


class DiscreteSpace:
    """``x = (c_1 ... c_K, log sigma_I, log f_n, log zeta)`` with ``c_i = r nu_1(E_c,i) hbar >= 0``
    the weights (MV/m) of a general coercive density, linear between the nodes ``E_c,i`` (the
    first at 0, ``hbar`` their mean spacing; Section 2.2: the discretized density values
    estimated by least squares), smoothed by the penalty ``sqrt(lambda N) g1 D2 c`` (second
    differences, um) appended to the residual."""

    def __init__(self, preps: Sequence[Prepared], scales: Scales, nodes: FloatArray,
                 smoothing: float, g1: float, starts: Sequence[str] | None = None) -> None:
        self.preps, self.scales, self.nodes = list(preps), scales, np.asarray(nodes, float)
        if self.nodes.size < 3 or self.nodes[0] < 0 or np.any(np.diff(self.nodes) <= 0):
            raise ValueError("a general density needs at least 3 increasing nodes from >= 0")
        self.fine, self.hat = hats(self.nodes)
        self.starts = tuple(starts or ["depoled"] * len(self.preps))
        self.names = tuple(f"c@{e:.4g}" for e in self.nodes) + (
            "log_std_MV_per_m", "log_natural_hz", "log_damping_ratio")
        n_obs = sum(int(p.mask.sum()) for p in self.preps)
        self.weight = math.sqrt(smoothing * n_obs) * abs(g1)
        self._h: dict[float, list[FloatArray]] = {}
        self._b: dict[tuple[float, float, float], list[_Basis]] = {}
        self.x_scale: str | float = "jac"  # weights (MV/m) and logs mixed

    @classmethod
    def around(cls, theta: FloatArray, preps: Sequence[Prepared], scales: Scales, n_nodes: int,
               smoothing: float, g1: float,
               starts: Sequence[str] | None = None) -> tuple[DiscreteSpace, FloatArray]:
        """Nodes from 0 to the largest coercive field that can switch (the lower of the
        lognormal fit ``theta``'s ``median exp(3 sigma_ln)`` and :func:`reach`; a hysteron
        beyond never switches, a constant the gains absorb): geometric over the lognormal's
        support from ``median exp(-3 sigma_ln)`` (where its mass is), equally spaced below it
        (a quarter of the nodes), or equally spaced throughout when that support starts above
        half the top. The starting ``x`` puts the lognormal's mass (normalized over all coercive
        fields, so the hysterons beyond the top are left out, not pushed onto the nodes) on
        them; a flat density if none of it is within reach."""
        median, sig, std, r, fn, zeta = theta
        top = min(median * math.exp(3 * sig), reach(preps, starts or (), std))
        bottom = median * math.exp(-3 * sig)
        k0 = min(max(2, n_nodes // 4), n_nodes - 2)
        if bottom < 0.5 * top and k0 >= 1:
            nodes = np.concatenate((np.linspace(0.0, bottom, k0, endpoint=False),
                                    np.geomspace(bottom, top, n_nodes - k0)))
        else:
            nodes = np.linspace(0.0, top, n_nodes)
        space = cls(preps, scales, nodes, smoothing, g1, starts)
        x = np.maximum(nodes, 1e-12 * top)
        pdf = np.exp(-0.5 * (np.log(x / median) / sig) ** 2) / (x * sig * math.sqrt(2 * math.pi))
        c = r * pdf * float(np.mean(np.diff(nodes)))
        if not np.any(c > 0):
            c = np.full(n_nodes, r / n_nodes)
        return space, np.concatenate((c, np.log([std, fn, zeta])))

    def _columns_h(self, std: float) -> list[FloatArray]:
        """Per node, its hat's share of ``erf(y_j / (sqrt(2) sigma_I))`` over the quadrature
        nodes ``j`` at the full rate (cached per sigma_I)."""
        def make() -> list[FloatArray]:
            fields = [p.field[p.keep] for p in self.preps]
            per_node = [run_from(hy.Polarization(1.0, 1.0, hy.Discrete((float(n),), (1.0,)),
                                                 hy.Normal(std)), fields, self.starts)
                        for n in self.fine]
            return [np.column_stack([at_full_rate(p.field.size, p.keep, q[i] - fields[i])
                                     for q in per_node]) @ self.hat
                    for i, p in enumerate(self.preps)]

        return cached(self._h, std, make, 4)

    def _basis(self, std: float, fn: float, zeta: float) -> list[_Basis]:
        """Per sweep: field, ``H`` and their filtered ``L[E]``, ``L[H]`` on the mask. ``Q`` and
        ``L[Q]`` are linear in the weights ``c``, so only ``L[Q^2]`` is filtered per evaluation."""
        def make() -> list[_Basis]:
            out = []
            for p, h in zip(self.preps, self._columns_h(std), strict=True):
                e = at_full_rate(p.field.size, p.keep, p.field[p.keep])
                le = unit_filter(e, fn, zeta, p.dt)[p.mask]
                lh = np.column_stack([unit_filter(col, fn, zeta, p.dt)[p.mask] for col in h.T])
                out.append(_Basis(e, h, le, lh))
            return out

        return cached(self._b, (std, fn, zeta), make, 4)

    def design(self, x: FloatArray) -> FloatArray:
        k = self.nodes.size
        c = x[:k]
        std, fn, zeta = (float(v) for v in np.exp(x[k:]))
        blocks = []
        for p, b in zip(self.preps, self._basis(std, fn, zeta), strict=True):
            q = b.field + b.h @ c
            lq2 = unit_filter(q * q, fn, zeta, p.dt)[p.mask]
            blocks.append(np.column_stack((b.le + b.lh @ c, lq2)))
        return np.hstack((np.vstack(blocks), offset_columns(self.preps)))

    def _jacobian(self, c: FloatArray, beta: FloatArray, design: FloatArray, fn: float,
                  zeta: float, basis: Sequence[_Basis]) -> FloatArray:
        """Columns of the linearized model in ``(c, g1, g2, zeros)``: ``g1 L[H_i] + 2 g2
        L[Q H_i]`` per weight, then the ``design`` at ``c`` (``L[Q]``, ``L[Q^2]`` and one sensor
        zero per sweep) with its gains ``beta``."""
        blocks = []
        for p, b in zip(self.preps, basis, strict=True):
            q = b.field + b.h @ c
            lqh = np.column_stack([unit_filter(q * col, fn, zeta, p.dt)[p.mask]
                                   for col in b.h.T])
            blocks.append(beta[0] * b.lh + 2 * beta[1] * lqh)
        return np.hstack((np.vstack(blocks), design))

    @property
    def _d2(self) -> FloatArray:
        """The smoothing penalty's matrix: weighted second differences of the weights."""
        return self.weight * np.diff(np.eye(self.nodes.size), 2, axis=0)

    def _cost(self, c: FloatArray, rest: FloatArray, y: FloatArray
              ) -> tuple[float, FloatArray, FloatArray, FloatArray]:
        """Sum of squares (penalty included), gains, residual and design at weights ``c``."""
        design = self.design(np.concatenate((c, rest)))
        beta, res = project(design, y)
        return float(res @ res + np.sum((self._d2 @ c) ** 2)), beta, res, design

    def refined(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """``x`` with its weights fitted to the problem linearized in them (:meth:`_weights`) and
        ``sigma_I`` chosen by a bounded scalar search around ``x``'s (the weights refitted at
        each, from the best so far, so the searched cost depends on the path; the best point is
        kept; the rod held): the weights and the interaction width trade off, and a width a few
        per cent off the lognormal fit's held the weights at 6x the noise on a stage the right
        width takes to the floor. A start from which the solver reaches densities the
        lognormal's support left out."""
        k = self.nodes.size
        first, value = self._weights(x, y)
        best, costs = [first], {float(x[k]): value}

        def cost(log_std: float) -> float:
            trial, value = self._weights(np.concatenate((best[0][:k], [log_std], x[k + 1:])), y)
            if value < min(costs.values()):
                best[0] = trial
            costs[log_std] = value
            return value

        optimize.minimize_scalar(cost, bounds=(float(x[k]) - STD_SPAN, float(x[k]) + STD_SPAN),
                                 method="bounded", options={"xatol": 0.01, "maxiter": STD_EVALS})
        return best[0]

    def _weights(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, float]:
        """``x`` with its weights moved by damped Gauss-Newton steps (Levenberg-Marquardt) of the
        problem linearized in the weights and the gains (``sigma_I`` and the rod held), each a
        bounded linear least-squares solve that keeps every weight nonnegative, with the
        smoothing penalty; a step is kept only if it lowers the sum of squares. Weights of
        hysterons that never switch are a constant the gains absorb: the damping holds them. Also
        the sum of squares there."""
        k, rest = self.nodes.size, x[self.nodes.size:]
        c = x[:k].copy()
        std, fn, zeta = (float(v) for v in np.exp(rest))
        basis = self._basis(std, fn, zeta)
        d2 = self._d2
        cost, beta, res, design = self._cost(c, rest, y)
        mu, jac = 1e-3, None
        for _ in range(REFINE_STEPS):
            if jac is None:  # a refused step keeps c: the same Jacobian, more damping
                jac = self._jacobian(c, beta, design, fn, zeta, basis)
                m = jac.shape[1] - k
                scale = np.linalg.norm(jac[:, :k], axis=0)
                scale = np.maximum(scale, 1e-8 * float(scale.max()) + 1e-300)
                lo = np.concatenate((-c, np.full(m, -np.inf)))
                b = np.concatenate((res, -d2 @ c, np.zeros(k)))
            damp = np.hstack((np.diag(math.sqrt(mu) * scale), np.zeros((k, m))))
            a = np.vstack((jac, np.hstack((d2, np.zeros((d2.shape[0], m)))), damp))
            step = optimize.lsq_linear(a, b, bounds=(lo, np.full(k + m, np.inf)),
                                       method="bvls").x
            trial = np.maximum(c + step[:k], 0.0)
            new, nbeta, nres, ndesign = self._cost(trial, rest, y)
            if new >= cost:
                mu *= 8.0
                continue
            done = new > cost * (1 - REFINE_TOL)
            c, cost, beta, res, design = trial, new, nbeta, nres, ndesign
            mu, jac = mu / 4.0, None
            if done:
                break
        return np.concatenate((c, rest)), cost

    def penalty(self, x: FloatArray) -> FloatArray:
        """Second differences of the weights by node index (on the geometric nodes a straight
        density is penalized a little too: the penalty only smooths, at lambda = 1e-6)."""
        return self.weight * np.diff(x[:self.nodes.size], 2)

    def bounds(self) -> tuple[FloatArray, FloatArray]:
        e_max, nyq = extent(self.preps)
        k = self.nodes.size
        lo = np.concatenate((np.zeros(k), np.log([1e-3 * e_max, 0.5, 0.003])))
        hi = np.concatenate((np.full(k, 100 * e_max), np.log([10 * e_max, 20 * nyq, 5.0])))
        return lo, hi

    def model(self, x: FloatArray, beta: FloatArray, thickness_um: float) -> td.Transducer:
        """The model: the density on the quadrature nodes, each value its node's mass over the
        midpoint cell :class:`~afmctl.model.hysteresis.Discrete` gives it (the quadrature is the
        design's exactly; next to a node between unequal cells a value differs from the linear
        density by a few per cent, its mass does not)."""
        k = self.nodes.size
        m = self.hat @ np.maximum(x[:k], 0.0)
        r = float(m.sum()) or 1e-12
        cells = hy.Discrete(tuple(self.fine), tuple(np.ones(self.fine.size))).nodes_weights()[1]
        dens = hy.Discrete(tuple(self.fine), tuple(float(v) for v in m / r / cells))
        std, fn, zeta = np.exp(x[k:])
        pol = hy.Polarization(1.0, 1.0, dens, hy.Normal(float(std)))
        return with_initial(build_model(pol, r, fn, zeta, beta, self.scales, thickness_um),
                            self.starts)
