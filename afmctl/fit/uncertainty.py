"""Uncertainty of identified parameters from the Jacobian at the least-squares solution.

The fit (:mod:`afmctl.fit.identify`) minimizes ``|y - A(x) beta|^2`` over the nonlinear internal
parameters ``x`` (logs of :data:`afmctl.fit.parametrization.THETA_NAMES`, or a discrete density's
weights) and the linear gains ``beta = (g1, g2, offset_1 ... offset_n)``. Linearized at the
solution, ``p = (x, beta)`` has covariance ``s^2 (J^T J)^+`` with ``J = d(A beta)/dp`` and
``s^2`` the residual variance per degree of freedom (Gauss-Newton; exact for white noise and a
correct model, too small when the residual is correlated or the model misses something).

A parameter is flagged **undetermined** when the data do not fix it: a 1-sigma relative error above
:data:`UNDETERMINED_REL` (for logs: the standard error of the log itself), or a correlation with
another parameter beyond :data:`UNDETERMINED_CORR` (the two trade off along a valley). Physical
parameters follow by the delta method (:func:`estimates`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from afmctl.fit import parametrization as pz
from afmctl.model import transducer as td

FloatArray = NDArray[np.float64]
#: 1-sigma relative error above which a parameter counts as undetermined.
UNDETERMINED_REL = 0.5
#: |correlation| above which both parameters of a pair count as undetermined.
UNDETERMINED_CORR = 0.999


@dataclass(frozen=True)
class Estimate:
    """One fitted parameter with its approximate 1-sigma interval (0 for fixed ones)."""

    name: str
    value: float
    stderr: float
    unit: str
    fixed: bool = False


class Space(Protocol):
    names: tuple[str, ...]

    def design(self, x: FloatArray) -> FloatArray: ...

    def model(self, x: FloatArray, beta: FloatArray, thickness_um: float) -> td.Transducer: ...


def gain_names(n_sweeps: int) -> tuple[str, ...]:
    """Names of the linear gains: g1 (um per MV/m), g2 (um per (MV/m)^2), one offset per sweep."""
    return ("g1_um_per_MV_per_m", "g2_um_per_MV2_per_m2") + tuple(
        f"offset_{i + 1}_um" for i in range(n_sweeps))


def covariance(space: Space, x: FloatArray, beta: FloatArray,
               y: FloatArray) -> tuple[FloatArray, tuple[str, ...]]:
    """``s^2 (J^T J)^+`` of ``(x, beta)`` (data rows only) and the parameter names."""
    a0 = space.design(x)
    r0 = y - a0 @ beta
    cols = []
    for i in range(x.size):
        step = 1e-5 * max(1.0, abs(float(x[i])))
        xs = x.copy()
        xs[i] += step
        cols.append(-((space.design(xs) - a0) @ beta) / step)
    jac = np.column_stack(cols + [-a0])
    s2 = float(r0 @ r0) / max(1, y.size - jac.shape[1])
    names = tuple(space.names) + gain_names(a0.shape[1] - 2)
    return s2 * np.linalg.pinv(jac.T @ jac), names


def estimates(space: Space, x: FloatArray, beta: FloatArray, cov: FloatArray,
              scales: pz.Scales, zero: int = -1) -> tuple[Estimate, ...]:
    """Delta-method 1-sigma for the physical parameters (:func:`afmctl.fit.parametrization.describe`
    of the model with sweep ``zero``'s offset, default the last); ``m`` and ``P_R`` reported as
    fixed."""
    n = x.size
    pick = np.r_[np.arange(n + 2), n + 2 + zero % (beta.size - 2)]  # x, g1, g2, its offset
    p = np.concatenate((x, beta))[pick]
    sub = cov[np.ix_(pick, pick)]

    def values(q: FloatArray) -> FloatArray:
        return np.array([v for _, v, _ in pz.describe(space.model(q[:n], q[n:], 1.0))])

    f0 = values(p)
    jac = np.empty((f0.size, p.size))
    for i in range(p.size):
        h = 1e-6 * max(1.0, abs(p[i]))
        pp = p.copy()
        pp[i] += h
        jac[:, i] = (values(pp) - f0) / h
    var = np.einsum("ij,jk,ik->i", jac, sub, jac)
    described = pz.describe(space.model(p[:n], p[n:], 1.0))
    out = [Estimate(name, float(v), float(np.sqrt(max(s, 0.0))), unit)
           for (name, v, unit), s in zip(described, var, strict=True)]
    out += [Estimate("m", scales.mass_kg, 0.0, "kg", fixed=True),
            Estimate("p_r", scales.p_r, 0.0, "C/m^2", fixed=True)]
    return tuple(out)


def _relative(name: str, value: float, stderr: float) -> float:
    if name.startswith("log_"):
        return stderr
    return stderr / abs(value) if value else float("inf")


def undetermined(names: Sequence[str], p: FloatArray, cov: FloatArray) -> list[str]:
    """Parameters whose relative 1-sigma exceeds :data:`UNDETERMINED_REL` or whose correlation
    with another exceeds :data:`UNDETERMINED_CORR` in magnitude (offsets excepted: one per sweep,
    each fixed by its own data)."""
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    corr = cov / np.outer(np.where(sd > 0, sd, 1.0), np.where(sd > 0, sd, 1.0))
    out = []
    for i, name in enumerate(names):
        if name.startswith("offset_"):
            continue
        others = [j for j in range(len(names)) if j != i and not names[j].startswith("offset_")]
        if (_relative(name, float(p[i]), float(sd[i])) > UNDETERMINED_REL
                or any(abs(corr[i, j]) > UNDETERMINED_CORR for j in others)):
            out.append(name)
    return out


def summary(names: Sequence[str], p: FloatArray, cov: FloatArray) -> dict[str, Any]:
    """JSON-ready uncertainty: per internal parameter value, 1-sigma and relative 1-sigma, the
    correlation matrix, and the undetermined parameters."""
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    corr = cov / np.outer(np.where(sd > 0, sd, 1.0), np.where(sd > 0, sd, 1.0))

    def num(v: float) -> float | None:
        return round(float(v), 6) if np.isfinite(v) else None

    return {
        "method": "Gauss-Newton s^2 (J^T J)^+ at the solution (logs for log_ parameters)",
        "parameters": {n: {"value": num(p[i]), "stderr": num(sd[i]),
                           "relative_stderr": num(_relative(n, float(p[i]), float(sd[i])))}
                       for i, n in enumerate(names)},
        "correlation": {"names": list(names),
                        "matrix": [[num(v) for v in row] for row in corr]},
        "undetermined": undetermined(names, p, cov),
    }
