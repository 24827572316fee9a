"""Identification of the coupling between two axes from their measured displacements.

What is identifiable: in a file where the *target* axis is held at a constant voltage and the
*source* axis moves, the target's own transducer stands still, so its sensor reads a constant
(plus noise and slow drift) plus the motion the source causes. The source's displacement is
measured, so the coupling is a linear system from one measured signal to another
(:mod:`afmctl.model.coupling`, um of target per um of source) and is estimated as one:

* the static gain by least squares on both displacements low-passed well below any shared mode
  (:data:`STATIC_CUTOFF_HZ`), with an offset and a slow drift per file (the held axis creeps);
* the frequency response by the cross-spectral (H1) estimate ``S_st / S_ss`` on each file
  (Welch, Hann segments), where the coherence says how much of the target's motion the source
  explains (its variance ``(1 - g^2) / (2 n g^2) |H|^2``, Bendat & Piersol 9.90);
* the low-order form ``static + (gain_hp r^2 + gain_bp 2 zeta r) / (r^2 + 2 zeta r + 1)``
  (``r = j f / mode_hz``) fitted to those estimates, weighted by their variance, with the static
  estimate as one more measurement: variable projection (the gains are linear), the mode and its
  damping by :func:`scipy.optimize.least_squares` in logs from a grid. Its 1-sigma comes from
  the Jacobian, and is carried to the response at each frequency.

Above the excited band the mode is an extrapolation; :attr:`CouplingFit.band_hz` says where the
data were, and the uncertainty says how far the mode is fixed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import optimize, signal

from afmctl.errors import FitInputError
from afmctl.model import coupling as cp

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]
#: Low-pass corner for the static gain, Hz (far below the 150-800 Hz shared modes of x/y stages).
STATIC_CUTOFF_HZ = 2.0
#: A file enters the static gain if this share of its source's variance lies below the cutoff.
SLOW_SHARE = 0.25
#: Frequency resolution of the cross-spectral estimate, Hz.
RESOLUTION_HZ = 0.5
#: Estimates with a lower coherence are left out of the fit (the source explains too little).
MIN_COHERENCE = 0.5
#: Estimates where the source's power lies more than this below its peak are left out: a
#: triangle's far harmonics and the band above a multisine's carry the source's noise and the
#: products of any nonlinearity (a flexure's arc turns a triangle's comb into a denser one).
SOURCE_RANGE_DB = 60.0
#: The arc's quadratic is kept when it lies this many of its 1-sigma from zero.
ARC_SIGMAS = 3.0
#: Estimates the fitted form leaves this many robust sigmas away are outliers (:func:`fit_form`).
OUTLIER = 5.0
#: The first screening for outliers fits a mode at least this damped (:func:`fit_form`).
SCREEN_DAMPING = 0.1
#: The coherence is clipped here (a single segment has coherence 1 and no variance estimate).
MAX_COHERENCE = 0.99
#: Frequencies of the reported response: at least 30 log-spaced from 1 Hz to 200 Hz or more.
REPORT_HZ = (1.0, 300.0, 40)
#: Range of the mode's natural frequency, Hz, and of its damping ratio, searched by the fit.
MODE_RANGE_HZ = (10.0, 20000.0)
DAMPING_RANGE = (0.005, 2.0)


@dataclass(frozen=True)
class Record:
    """One file's source and target displacement (target held), um, at interval ``dt_s``."""

    source_um: FloatArray
    target_um: FloatArray
    dt_s: float
    name: str = ""


@dataclass(frozen=True)
class Spectrum:
    """Cross-spectral estimates of the response: frequency (Hz), H (um/um), 1-sigma of each of
    its real and imaginary parts (um/um), coherence and the index of the file of each."""

    freq_hz: FloatArray
    h: ComplexArray
    sigma: FloatArray
    coherence: FloatArray
    file: NDArray[np.intp]


@dataclass(frozen=True)
class CouplingFit:
    """One direction's identified coupling.

    ``coupling`` is the low-order form; ``static``/``static_stderr`` the low-passed regression's
    estimate; ``covariance`` that of ``(static, log mode_hz, log damping, gain_hp, gain_bp)``;
    ``spectrum`` the cross-spectral estimates the form was fitted to and ``band_hz`` the
    frequencies they covered (``dropped`` were left out as outliers); ``rms_over_sigma`` the
    weighted RMS residual of the low-order fit (1 when the form explains the estimates to within
    their scatter).
    """

    coupling: cp.Coupling
    static: float
    static_stderr: float
    covariance: FloatArray = field(repr=False)
    spectrum: Spectrum = field(repr=False)
    band_hz: tuple[float, float]
    rms_over_sigma: float
    files: tuple[str, ...] = ()
    dropped: int = 0
    quadratic_stderr: float = 0.0

    @property
    def stderr(self) -> tuple[float, ...]:
        """1-sigma of ``(static, ln mode_hz, ln damping, gain_hp, gain_bp)``."""
        return tuple(float(x) for x in np.sqrt(np.maximum(np.diag(self.covariance), 0.0)))

    def response(self, freq_hz: FloatArray) -> tuple[ComplexArray, FloatArray, FloatArray]:
        """The fitted response at ``freq_hz`` and the 1-sigma of its gain (um/um) and phase (deg),
        carried from the parameters' covariance (numerical Jacobian)."""
        p = _params(self.coupling)
        h = _h(p, freq_hz)
        jac = np.empty((2, freq_hz.size, p.size))
        for k in range(p.size):
            step = 1e-6 * max(abs(p[k]), 1e-3)
            q = p.copy()
            q[k] += step
            hq = _h(q, freq_hz)
            jac[0, :, k] = (np.abs(hq) - np.abs(h)) / step
            jac[1, :, k] = np.degrees(np.angle(hq / h)) / step
        sd = [np.sqrt(np.maximum(np.einsum("fk,kl,fl->f", j, self.covariance, j), 0.0))
              for j in jac]
        return h, sd[0], sd[1]

    def to_dict(self, freq_hz: FloatArray) -> dict[str, Any]:
        """JSON-ready: the form's parameters with 1-sigma and the response at ``freq_hz``."""
        c = self.coupling
        sd = self.stderr
        h, sg, sp = self.response(freq_hz)
        lo, hi = self.band_hz
        return {
            "static": c.static, "static_stderr": float(sd[0]), "static_db": c.static_db,
            "static_lowpass": self.static, "static_lowpass_stderr": self.static_stderr,
            "mode_hz": c.mode_hz, "mode_hz_stderr_rel": float(sd[1]),
            "damping": c.damping, "damping_stderr_rel": float(sd[2]),
            "gain_hp": c.gain_hp, "gain_hp_stderr": float(sd[3]),
            "gain_bp": c.gain_bp, "gain_bp_stderr": float(sd[4]),
            "reference_um": c.reference_um, "band_hz": [lo, hi],
            "quadratic_um_per_um2": c.quadratic, "quadratic_stderr": self.quadratic_stderr,
            "centre_um": c.centre_um,
            "rms_over_sigma": self.rms_over_sigma, "files": list(self.files),
            "estimates": int(self.spectrum.freq_hz.size), "dropped": self.dropped,
            "frf": [{"freq_hz": float(f), "gain": float(abs(v)),
                     "phase_deg": float(np.degrees(np.angle(v))), "gain_stderr": float(a),
                     "phase_stderr_deg": float(b), "measured": bool(lo <= f <= hi)}
                    for f, v, a, b in zip(freq_hz, h, sg, sp, strict=True)],
        }


def report_frequencies() -> FloatArray:
    """The frequencies (Hz) of the reported response: :data:`REPORT_HZ` log-spaced."""
    lo, hi, n = REPORT_HZ
    return np.geomspace(lo, hi, n)


# ----------------------------------------------------------------------------------------------
# the static gain
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Static:
    """The low-passed regression: the gain (um/um, the slope at source displacement
    ``centre_um``, um) and the arc's quadratic (um/um^2, 0 when not significant), each with its
    1-sigma."""

    gain: float
    stderr: float
    quadratic: float = 0.0
    quadratic_stderr: float = 0.0
    centre_um: float = 0.0


def static_gain(records: Sequence[Record], cutoff_hz: float = STATIC_CUTOFF_HZ) -> Static:
    """Static gain and arc from the displacements low-passed at ``cutoff_hz``.

    Only files whose source moves mostly below the cutoff (:data:`SLOW_SHARE`) enter, each
    without the filter's edge transients (``1 / cutoff_hz`` s at either end); per file an offset
    and a quadratic drift in time (the held axis creeps) are fitted beside the shared gain and the
    shared arc ``quadratic (x - centre)^2``, ``centre`` the middle of the files' source range (so
    the gain is the slope at the middle of the major loop, what a static coupling means for a
    flexure's arc). The arc is kept when it is at least :data:`ARC_SIGMAS` of its 1-sigma from
    zero; else the gain is refitted without it. The 1-sigma counts one independent sample per
    ``1 / (2 cutoff_hz)`` s (the low-pass correlates the residual over that time).
    """
    parts = [p for p in (_slow_part(r, cutoff_hz) for r in records) if p is not None]
    if not parts:
        raise FitInputError(f"no file whose source moves slowly enough (below {cutoff_hz:g} Hz) "
                            f"and long enough for the static coupling")
    raw = np.concatenate([p.raw for p in parts])
    centre = 0.5 * float(raw.min() + raw.max())
    arc = [signal.sosfiltfilt(p.sos, (p.raw - centre) ** 2)[p.edge:-p.edge] for p in parts]
    n_eff = sum(2 * cutoff_hz * p.source.size * p.dt_s for p in parts)
    cols, ys = [p.source for p in parts], [p.target for p in parts]
    beta, sd = _regress(cols, ys, arc, n_eff)
    if abs(beta[1]) >= ARC_SIGMAS * sd[1]:
        return Static(float(beta[0]), float(sd[0]), float(beta[1]), float(sd[1]), centre)
    beta, sd = _regress(cols, ys, None, n_eff)
    return Static(float(beta[0]), float(sd[0]), centre_um=centre)


class _Slow(NamedTuple):
    """A file's low-passed source and target (um, edges cut), its interval (s), raw source (um),
    low-pass filter and edge length (samples)."""

    source: FloatArray
    target: FloatArray
    dt_s: float
    raw: FloatArray
    sos: FloatArray
    edge: int


def _slow_part(r: Record, cutoff_hz: float) -> _Slow | None:
    """A file as the static gain sees it; None for a file too fast or too short for it."""
    edge = int(math.ceil(1.0 / (cutoff_hz * r.dt_s)))
    if 2 * cutoff_hz * r.dt_s >= 1 or r.source_um.size < 4 * edge:
        return None
    sos = signal.butter(4, cutoff_hz, fs=1.0 / r.dt_s, output="sos")
    s = signal.sosfiltfilt(sos, r.source_um - r.source_um.mean())[edge:-edge]
    if np.var(s) < SLOW_SHARE * np.var(r.source_um):
        return None  # a fast sweep: its low-passed source is its edges, not its motion
    t = signal.sosfiltfilt(sos, r.target_um - r.target_um.mean())[edge:-edge]
    return _Slow(s, t, r.dt_s, np.asarray(r.source_um, dtype=float), sos, edge)


def _regress(cols: list[FloatArray], ys: list[FloatArray], arc: list[FloatArray] | None,
             n_eff: float) -> tuple[FloatArray, FloatArray]:
    """Shared gain (and arc) with an offset and a quadratic drift in time per file: the
    coefficients and their 1-sigma (``n_eff`` independent samples)."""
    shared = 1 if arc is None else 2
    n = sum(c.size for c in cols)
    a = np.zeros((n, shared + 3 * len(cols)))
    a[:, 0] = np.concatenate(cols)
    if arc is not None:
        a[:, 1] = np.concatenate(arc)
    row = 0
    for k, c in enumerate(cols):
        tau = np.linspace(-1.0, 1.0, c.size)
        a[row:row + c.size, shared + 3 * k:shared + 3 + 3 * k] = np.column_stack(
            [np.ones_like(tau), tau, tau ** 2])
        row += c.size
    y = np.concatenate(ys)
    beta, *_ = np.linalg.lstsq(a, y, rcond=None)
    resid = y - a @ beta
    dof = max(n_eff - a.shape[1], 1.0)
    s2 = float(np.sum(resid ** 2)) * (n_eff / n) / dof
    cov = s2 * np.linalg.pinv(a.T @ a) * (n / n_eff)
    return beta[:shared], np.sqrt(np.maximum(np.diag(cov)[:shared], 0.0))


# ----------------------------------------------------------------------------------------------
# the cross-spectral estimate
# ----------------------------------------------------------------------------------------------


def spectrum(records: Sequence[Record], resolution_hz: float = RESOLUTION_HZ,
             min_coherence: float = MIN_COHERENCE) -> Spectrum:
    """H1 estimates ``S_st / S_ss`` of every file (Welch, Hann, half-overlapping segments of
    ``1 / resolution_hz`` s or a third of the file), kept where the coherence reaches
    ``min_coherence`` and the source's power is within :data:`SOURCE_RANGE_DB` of its peak, from
    the first nonzero frequency to a quarter of the sample rate."""
    out: list[FloatArray] = []
    for i, r in enumerate(records):
        fs = 1.0 / r.dt_s
        n = r.source_um.size
        nper = int(min(round(fs / resolution_hz), n // 3))
        if nper < 16:
            continue
        nper = 2 * n // (math.ceil(2 * n / nper) + 1) // 2 * 2  # the segments tile the file
        kw = {"fs": fs, "nperseg": nper, "noverlap": nper // 2, "detrend": "linear"}
        f, sss = signal.welch(r.source_um, **kw)
        _, stt = signal.welch(r.target_um, **kw)
        _, sst = signal.csd(r.source_um, r.target_um, **kw)
        n_seg = 1 + (n - nper) // (nper // 2)
        with np.errstate(divide="ignore", invalid="ignore"):
            h = sst / sss
            coh = np.clip(np.abs(sst) ** 2 / (sss * stt), 0.0, MAX_COHERENCE)
            sigma = np.sqrt((1 - coh) / (2 * n_seg * coh)) * np.abs(h)
        strong = sss >= np.max(sss[1:]) * 10 ** (-SOURCE_RANGE_DB / 10)
        keep = (f > 0) & (f <= fs / 4) & np.isfinite(h) & (coh >= min_coherence) & strong
        out.append(np.column_stack([f[keep], h[keep].real, h[keep].imag, sigma[keep],
                                    coh[keep], np.full(int(keep.sum()), i)]))
    rows = np.concatenate(out) if out else np.empty((0, 6))
    rows = rows[np.argsort(rows[:, 0], kind="stable")]
    return Spectrum(rows[:, 0], rows[:, 1] + 1j * rows[:, 2], rows[:, 3], rows[:, 4],
                    rows[:, 5].astype(np.intp))


# ----------------------------------------------------------------------------------------------
# the low-order form
# ----------------------------------------------------------------------------------------------


def _basis(log_mode: float, log_damp: float, freq_hz: FloatArray) -> ComplexArray:
    """Columns ``1, r^2 / D, 2 zeta r / D`` of the low-order form (``r = j f / mode``)."""
    r = 1j * np.asarray(freq_hz, dtype=float) / math.exp(log_mode)
    z = math.exp(log_damp)
    d = r * r + 2 * z * r + 1
    return np.column_stack([np.ones_like(r), r * r / d, 2 * z * r / d])


def _params(c: cp.Coupling) -> FloatArray:
    return np.array([c.static, math.log(c.mode_hz), math.log(c.damping), c.gain_hp, c.gain_bp])


def _h(p: FloatArray, freq_hz: FloatArray) -> ComplexArray:
    return _basis(p[1], p[2], freq_hz) @ p[[0, 3, 4]].astype(complex)


def _weighted(sp: Spectrum, static: tuple[float, float]
              ) -> tuple[FloatArray, FloatArray]:
    """The stacked real and imaginary estimates and the static one, each over its 1-sigma."""
    known = math.isfinite(static[0]) and math.isfinite(static[1])
    y = np.concatenate([sp.h.real / sp.sigma, sp.h.imag / sp.sigma,
                        [static[0] / static[1] if known else 0.0]])
    w = np.concatenate([1 / sp.sigma, 1 / sp.sigma, [1 / static[1] if known else 0.0]])
    return y, w


def _local(sp: Spectrum, known: bool) -> FloatArray:
    """Columns of each file's local static offset (real rows of its estimates), when the static
    gain is known from the low-passed regression (else none: the estimates fix it)."""
    files = np.unique(sp.file) if known else np.empty(0, dtype=np.intp)
    real = (sp.file[:, None] == files[None, :]).astype(float)
    return np.vstack([real, np.zeros_like(real), np.zeros((1, files.size))])


def _design(nl: FloatArray, sp: Spectrum, w: FloatArray, local: FloatArray) -> FloatArray:
    b = _basis(nl[0], nl[1], sp.freq_hz)
    a = np.vstack([b.real, b.imag, [[1.0, 0.0, 0.0]]])
    return np.hstack([a, local]) * w[:, None]


def _project(nl: FloatArray, sp: Spectrum, y: FloatArray, w: FloatArray, local: FloatArray
             ) -> tuple[FloatArray, FloatArray]:
    a = _design(nl, sp, w, local)
    norm = np.maximum(np.linalg.norm(a, axis=0), 1e-300)
    an = a / norm  # normal equations of the scaled columns: a few columns, thousands of rows
    beta = np.linalg.pinv(an.T @ an, rcond=1e-12) @ (an.T @ y) / norm
    return beta, a @ beta - y


def _solve(sp: Spectrum, static: tuple[float, float], min_damping: float = DAMPING_RANGE[0]
           ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The form on ``sp`` (damping at least ``min_damping``): ``(static, log mode, log damping,
    gain_hp, gain_bp)``, each file's local offset (zeros without a known static gain), the
    weighted residual, the weights and the columns of the local offsets."""
    y, w = _weighted(sp, static)
    local = _local(sp, bool(w[-1] > 0))
    lo = np.log([MODE_RANGE_HZ[0], min_damping])
    hi = np.log([MODE_RANGE_HZ[1], DAMPING_RANGE[1]])
    grid = [(m, d) for m in np.linspace(lo[0], hi[0], 40) for d in np.linspace(lo[1], hi[1], 10)]
    cost = [float(np.sum(_project(np.array(g), sp, y, w, local)[1] ** 2)) for g in grid]
    x0 = np.array(grid[int(np.argmin(cost))])
    sol = optimize.least_squares(lambda nl: _project(nl, sp, y, w, local)[1], x0,
                                 bounds=(lo, hi), x_scale=1.0)
    beta, resid = _project(sol.x, sp, y, w, local)
    offsets = np.zeros(int(sp.file.max(initial=-1)) + 1)
    if local.shape[1]:
        offsets[np.unique(sp.file)] = beta[3:]
    return (np.array([beta[0], sol.x[0], sol.x[1], beta[1], beta[2]]), offsets, resid, w,
            local)


def _subset(sp: Spectrum, keep: NDArray[np.bool_]) -> Spectrum:
    return Spectrum(sp.freq_hz[keep], sp.h[keep], sp.sigma[keep], sp.coherence[keep],
                    sp.file[keep])


def fit_form(sp: Spectrum, static: tuple[float, float], reference_um: float = 0.0
             ) -> tuple[cp.Coupling, FloatArray, float, NDArray[np.bool_]]:
    """The low-order form fitted to the estimates ``sp`` and the static ``(value, 1-sigma)``.

    A flexure's arc makes the static gain depend on where the source is: a file that excites it
    about another position than the full-range sweeps' middle sees another local static gain.
    When the static gain is known (finite 1-sigma), each file's estimates therefore get their own
    real offset and the static gain is the low-passed regression's (over full-range sweeps: the
    slope at the middle of the range); the files share the shape of the dynamic part.

    Estimates the form leaves more than :data:`OUTLIER` robust sigmas away are dropped and the
    form refitted (up to three times): a nonlinearity's product at a harmonic the source barely
    has (an arc squares a triangle: even harmonics in the target, hardly any in the source) is
    coherent and looks precise, but is no response of the coupling. The first screening fits a
    broad mode (damping at least :data:`SCREEN_DAMPING`), which cannot bend to a few such
    estimates as a narrow one can (a free first fit put a 46 Hz mode of damping 0.005 on them).

    Returns the coupling, the covariance of ``(static, log mode_hz, log damping, gain_hp,
    gain_bp)`` (Gauss-Newton, ``s^2 (J^T J)^+``, ``s^2`` at least 1: the estimates' own scatter),
    the weighted RMS residual and which estimates were kept.
    """
    keep = np.ones(sp.freq_hz.size, dtype=bool)
    for k in range(4):
        sub = _subset(sp, keep)
        p, offsets, resid, w, local = _solve(sub, static, SCREEN_DAMPING if not k else
                                             DAMPING_RANGE[0])
        r = np.abs(sp.h - _h(p, sp.freq_hz) - offsets[sp.file]) / sp.sigma
        scale = max(1.4826 * float(np.median(r[keep])), 1.0)
        new = r <= OUTLIER * scale
        if k and (np.array_equal(new, keep) or new.sum() < 3):
            break
        keep = new if new.sum() >= 3 else keep
    jac = np.hstack([_jacobian(p, sub, w), local * w[:, None]])
    dof = max(resid.size - jac.shape[1], 1)
    s2 = max(float(np.sum(resid ** 2)) / dof, 1.0)
    cov = s2 * np.linalg.pinv(jac.T @ jac)[:5, :5]
    c = cp.Coupling(float(p[0]), math.exp(p[1]), math.exp(p[2]), float(p[3]), float(p[4]),
                    reference_um)
    return c, cov, math.sqrt(float(np.sum(resid ** 2)) / resid.size), keep


def _jacobian(p: FloatArray, sp: Spectrum, w: FloatArray) -> FloatArray:
    """Jacobian of the weighted residual in ``(static, log mode, log damping, gain_hp, gain_bp)``."""

    def model(q: FloatArray) -> FloatArray:
        h = _h(q, sp.freq_hz)
        return np.concatenate([h.real, h.imag, [q[0]]]) * w

    base = model(p)
    jac = np.empty((base.size, p.size))
    for k in range(p.size):
        step = 1e-6 * max(abs(p[k]), 1e-3)
        q = p.copy()
        q[k] += step
        jac[:, k] = (model(q) - base) / step
    return jac


def identify(records: Sequence[Record], reference_um: float = 0.0) -> CouplingFit:
    """One direction's coupling from the files where its target is held and its source moves.

    Raises
    ------
    FitInputError
        No file, or no frequency at which the source explains the target's motion.
    """
    if not records:
        raise FitInputError("no file where the target axis is held and the source moves")
    try:
        static = static_gain(records)
    except FitInputError:  # no slow file: the response's low end alone fixes the static gain
        static = Static(float("nan"), float("inf"))
    sp = spectrum(records)
    if sp.freq_hz.size < 3:
        raise FitInputError("the source's motion explains the target's at too few frequencies "
                            "(coherence below %g)" % MIN_COHERENCE)
    c, cov, rms, keep = fit_form(sp, (static.gain, max(static.stderr, 1e-12)), reference_um)
    c = replace(c, quadratic=static.quadratic, centre_um=static.centre_um)
    return CouplingFit(c, static.gain, static.stderr, cov, _subset(sp, keep),
                       (float(sp.freq_hz[keep][0]), float(sp.freq_hz[keep][-1])), rms,
                       tuple(r.name for r in records), int((~keep).sum()),
                       static.quadratic_stderr)
