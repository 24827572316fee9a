"""Iterative learning control (ILC) on top of the model inverse: the law (pure numerics).

An AFM scans the same line again and again. Iteration 0 plays today's waveform (Algorithm 3
through the model on the desired trajectory ``y_d``, :func:`afmctl.planning.track.plan_inverse`); every
next iteration corrects the **reference** that Algorithm 3 inverts, not the voltage:

.. math::

    r_0 = y_d, \\qquad r_{j+1} = r_j + Q\\,[L\\, e_j], \\qquad e_j = y_d - \\hat y_j ,

where ``y^_j`` is the stage's true position in iteration ``j`` as the readings tell it (corrected
for the model's sensor effects, :func:`afmctl.model.effects.sensor_correct`: learning must move the
stage, not the readings) and the waveform of iteration ``j`` is Algorithm 3 of ``r_j`` (same
conditioning and inversion horizons every iteration). The model keeps inverting the hysteresis,
the rod and any plant effects it knows; learning removes only what the model misses
(inversion-based ILC, Leang & Devasia, Mechatronics 2006).

* ``L``, the learning filter, inverts ``G``, the plant seen through the inverse (reference to
  true position, linearized about the trajectory). Through its own inverse the model is the
  identity (Algorithm 3 meets its target at the samples), so the model's local linearization is
  ``G = 1``; iteration 0 measures where the stage departs from it: ``G_n = Y_n / R_n`` at every
  harmonic ``n f_0`` of the periodic trajectory where the reference has an amplitude well above
  the noise (:func:`tune`; least squares over the steady periods, no leakage). Per harmonic,
  ``L_n = rho / G^_n`` (``G^``: the measured ``G`` interpolated, 1 at DC), its magnitude capped
  at :attr:`Law.max_boost`. The part of the error that is not periodic (creep, drift, the first
  period's transient) is learned in time with ``L = rho``. A trajectory without a period, or
  with fewer than three measured harmonics (a sine), uses ``L = rho z^m`` in time: a gain with a
  phase lead of ``m`` samples, the delay of ``y^_0`` behind ``r_0`` (:func:`lead_samples`).
* ``Q``: a zero-phase low-pass (2nd-order Butterworth run forward and backward, :func:`q_filter`;
  per harmonic its gain ``|H|^2``), cut-off :attr:`Law.cutoff_hz` (raised towards
  :attr:`Law.cutoff_max_hz` while the stage follows the model, :func:`reach_hz`) but never above
  the last measured harmonic: beyond it nothing is known of ``G``.

**Convergence.** The error of the learned part contracts every iteration where

.. math::  |Q(\\omega)\\,(1 - L(\\omega)\\, G(\\omega))| < 1

for all frequencies ``omega``. With ``L = rho / G^`` that is ``|Q| |1 - rho G / G^| < 1``:
it holds wherever the measured ``G^`` is within ``|G^ - G| < |G|`` of the truth (for
``rho = 1``), which the 8-standard-error threshold on each measured harmonic keeps (and, where
a later step stalls and ``G^`` is re-measured on it, :func:`retune`'s guards); where
``|G| < 1 / max_boost`` the cap gives ``|1 - rho max_boost |G||`` < 1, slower but converging.
With the plain law ``L = rho z^m`` (``G = 1`` assumed) it needs ``|1 - rho e^{j omega m T}
G| < 1``: the phase of ``G e^{j omega m T}`` within 60 degrees for ``|G| = 1``, which an
unmodelled lag or resonance breaks above some frequency (e.g. the paper's linear filter, which
does not invert the rod: its phase passes 60 degrees at ~216 Hz on the default stage).
Above the cut-off nothing is learned and the error stays what the model leaves.

**Run-to-run variation.** A per-run gain ``g_j = 1 + delta_j`` of the applied voltage is not in
``G`` and no waveform can know the next run's: learning on ``e_j`` would chase each run's draw
(``e_{j+1}`` then carries ``delta_j - delta_{j+1}``: variance twice the draw's, ``sqrt 2`` times
its floor) and an unlucky draw would look like a divergence. So every iteration starts with the
same conditioning excursion, on which two runs' readings differ by nothing but their gains (and
noise): the coefficient of that difference along ``s = dy/dg`` (the model's position per unit
gain, :func:`gain_and_offset`) is the run's gain relative to iteration 0, ``d_j``. The law uses
the error the run would have made at the **mean gain** of the runs so far,

    e~_j = e_j + (d_j - mean(d_0 .. d_j)) s_j

in ``r_{j+1} = r_j + Q[L e~_j]``, and judges every iteration (best, divergence, floor) by its
``e~`` at the same latest mean. ``s_j`` is the gain direction of iteration ``j``'s **own**
waveform: ``dy/dg`` (roughly the local ``dy/dv`` times ``v``) depends on where on the
hysteresis the waveform runs, and a learned waveform runs elsewhere than iteration 0's (with
iteration 0's ``s`` the correction
itself put ``(d_j - mean d) (s_j - s_0)`` into ``e~``: up to 0.13 um on a stage whose inverse
was 3.6 um off, which drifted learning up past the floor and ended it as "diverging").

*Convergence under the variation* (first order, ``L G = rho`` per harmonic, ``Q = 1``): with
``x_j`` the waveform's error at the true mean gain, ``m_j`` the runs' mean gain's deviation from
it and ``n_j`` the noise learned from, ``e~_j = x_j - m_j s - n_j`` and

    x_{j+1} = (1 - rho) x_j + rho (m_j s + n_j):

the deterministic part contracts under the condition above (``e~`` is the error of one fixed
plant, the stage at the mean gain), and the random part neither chases the runs' draws (they are
removed) nor accumulates: with ``rho = 1`` the waveform carries the latest mean's error
(variance ``sigma^2 / (j + 1)``) and one run's noise (its variance ``rho / (2 - rho)`` = 1 times
the noise's, after ``Q`` and the harmonics: small beside the variation). The expected error over
future runs settles at ``sigma |s| sqrt(1 + 1/(j+1))`` (and the noise), the variation's floor
``sigma |s|`` (what a perfect waveform still makes) within 10 % from 5 runs on. The stop rules
use the resolution :func:`resolution`: the noise and that mean's uncertainty. Without the
conditioning (``--no-condition``) no gain is measured (``d_j = 0``) and the law is the plain one.

**Stopping** (:mod:`afmctl.experiment.learn` plays the iterations). Each waveform passes the guard
(voltage, slew, current) before it is sent: one that would not (or a reference out of the
stage's reach) is not sent, and learning ends with the best waveform so far. Learning also ends
at the noise floor (the steady error of the readings within :attr:`Law.floor_factor` of the
noise, estimated from the readings themselves, and of the mean gain's uncertainty under
run-to-run variation: :func:`resolution`) and on a diverging error (an iteration worse than
:attr:`Law.diverge_factor` times the best so far, the best counted no lower than that
resolution: within it, iterations cannot be told apart, at the smallest step: after an
iteration worse than the best the next step starts from the best at half the step, down to
:attr:`Law.min_step`).

**Creep and drift.** The conditioning also gives each run's slow offset against the first run
(the free offset of :func:`gain_and_offset`, with a free slope: carried to the tracking part,
where a creep that relaxes at another rate in each run has moved on); the next run's is predicted
(:func:`predicted_offset`), the reference shifted by the predicted change, and learning learns
from (and the divergence stop and the step look at) the error the run would have made at its
predicted offset: the drift's predictable part is followed, its unpredictable part not chased.

Judging is track's (at the samples and between them, the first period excluded) plus the imaging
region of a raster line: the central 80 % of every ramp between turning points (:func:`imaging_mask`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from afmctl.planning import track

FloatArray = NDArray[np.float64]
#: Fraction of every ramp (centred) that a raster line images.
IMAGING_FRACTION = 0.8


@dataclass(frozen=True)
class Law:
    """The learning law's parameters (see the module docstring).

    Parameters
    ----------
    cutoff_hz : float
        -3 dB frequency of the zero-phase robustness filter Q (each pass), Hz.
    gain : float
        ``rho`` of ``L = rho z^m`` (0 < rho < 2: for ``G = 1`` the error shrinks by
        ``|1 - rho|`` per iteration).
    max_lead_samples : int
        Largest phase lead ``m`` measured on iteration 0, samples.
    floor_factor : float
        Stop once the readings' steady RMS error (at the runs' mean gain) is within this
        factor of the resolution (:func:`resolution`: the noise, and the mean gain's
        uncertainty under run-to-run variation). 0: never stop there (to watch learning
        past the floor).
    diverge_factor : float
        Stop once an iteration is worse than this factor times the best so far (the best
        counted no lower than the resolution).
    region : str
        ``all``: learn from the error everywhere on the trajectory; ``imaging``: only from the
        imaging region of every ramp (:func:`imaging_mask`), leaving the turnarounds free, so a
        fast raster scan does not keep sharpening its corners up to the slew limit.
    max_boost : float
        Largest ``|L|`` of the per-harmonic law: where the stage responds far less than the
        model (``|G| < 1 / max_boost``) learning takes several smaller steps instead of one
        step that asks for the whole missing response at once (and for the slew it needs).
    min_step : float
        Smallest step, as a fraction of ``rho``: after an iteration worse than the best so far
        (its repeatable error) the next step starts from the best one at half the step, down
        to this; an iteration beyond ``diverge_factor`` at this step ends learning. 1: never
        shrink (every step the full ``rho``, from the last iteration).
    cutoff_max_hz : float or None
        Highest cut-off iteration 0 may raise ``Q``'s to, Hz (:func:`reach_hz`: up to where the
        stage stops following the model); None: ``cutoff_hz`` fixed.
    """

    cutoff_hz: float = 600.0
    gain: float = 1.0
    max_lead_samples: int = 10
    floor_factor: float = 1.1
    diverge_factor: float = 1.2
    region: str = "all"
    max_boost: float = 2.0
    min_step: float = 0.25
    cutoff_max_hz: float | None = None

    def __post_init__(self) -> None:
        if self.region not in ("all", "imaging"):
            raise ValueError(f"learning region must be 'all' or 'imaging', not {self.region!r}")
        if not (self.cutoff_hz > 0 and 0 < self.gain < 2 and self.max_lead_samples >= 0
                and (self.floor_factor >= 1 or self.floor_factor == 0) and self.diverge_factor > 1
                and self.max_boost >= 1 and 0 < self.min_step <= 1
                and (self.cutoff_max_hz is None or self.cutoff_max_hz >= self.cutoff_hz)):
            raise ValueError("learning law: need cutoff > 0, 0 < gain < 2, lead >= 0, "
                             "floor factor >= 1 (or 0), divergence factor > 1, max boost >= 1, "
                             "0 < min step <= 1, highest cut-off >= cut-off")

    @property
    def band_hz(self) -> float:
        """The highest cut-off ``Q`` may get, Hz."""
        return self.cutoff_hz if self.cutoff_max_hz is None else self.cutoff_max_hz


# ----------------------------------------------------------------------------------------------
# the law (pure)
# ----------------------------------------------------------------------------------------------


def q_filter(x: FloatArray, dt_s: float, cutoff_hz: float) -> FloatArray:
    """Zero-phase low-pass: 2nd-order Butterworth forward and backward (odd extension at the
    ends), so the correction neither lags nor leads the error it comes from."""
    wn = min(2 * cutoff_hz * dt_s, 0.99)
    sos = signal.butter(2, wn, output="sos")
    pad = min(x.size - 1, int(3 / (cutoff_hz * dt_s)) + 1)
    return signal.sosfiltfilt(sos, x, padtype="odd", padlen=pad)


def shift(x: FloatArray, m: int) -> FloatArray:
    """``x[k + m]`` (the last sample held): a lead of ``m`` samples (a lag for ``m < 0``)."""
    if m == 0:
        return x.copy()
    idx = np.clip(np.arange(x.size) + m, 0, x.size - 1)
    return x[idx]


def lead_samples(reference: FloatArray, position: FloatArray, skip: int, max_lead: int) -> int:
    """The delay ``m`` (samples, 0..max_lead) of the stage behind the reference: the shift of
    ``position`` that best matches ``reference`` beyond the first ``skip`` samples."""
    best, best_m = np.inf, 0
    for m in range(max_lead + 1):
        d = shift(position, m)[skip:] - reference[skip:]
        d = d[np.isfinite(d)]
        if d.size == 0:
            return 0
        rms = float(np.sqrt(np.mean(d**2)))
        if rms < best:
            best, best_m = rms, m
    return best_m


@dataclass(frozen=True)
class Tuning:
    """The learning filter ``L`` and ``Q``'s cut-off, set on iteration 0 (``G^`` re-measured
    where a later step stalls, :func:`retune`).

    ``freqs_hz`` are the trajectory's harmonics where iteration 0 measured the plant ``G`` seen
    through the inverse (``g``: ``Y / R`` there); with at least :data:`MIN_HARMONICS` of them
    ``L = rho / G^`` per harmonic (``G^``: ``g`` interpolated, 1 at DC), otherwise
    ``L = rho z^lead``.
    """

    lead: int
    cutoff_hz: float
    freqs_hz: FloatArray
    g: NDArray[np.complex128]

    @property
    def harmonic(self) -> bool:
        return self.freqs_hz.size >= MIN_HARMONICS


#: Cut-off of the time-domain Q for the non-periodic part of the error, as a fraction of Q's.
APERIODIC_FRACTION = 0.25
#: Fewest runs whose gains give a spread (two runs give one difference, no scale to trust).
MIN_RUNS_SPREAD = 3
#: Share of the last step of the slow offset continued into the next run while only two runs
#: tell it (:func:`predicted_offset`): a steady drift keeps its step (1), creep relaxing in
#: log-time shrinks it (ln(3/2) / ln 2 = 0.58 for the second run after a rest); half splits them.
FIRST_RATIO = 0.5
#: ``G^`` is re-measured (:func:`retune`) only where ``Q`` passes at least this much ...
RETUNE_Q = 0.5
#: ... and only if the step's ``dY / dR`` differs from it by more than this (relative).
RETUNE_CHANGE = 0.25
#: The cut-off rises (:func:`reach_hz`) until the stage's response falls short of the model's,
#: ``|G| < FOLLOWS``, on this many measured harmonics in a row.
SUSTAINED = 3
FOLLOWS = 0.8
#: Fewest reliably measured harmonics for the per-harmonic inverse of ``G``.
MIN_HARMONICS = 3
#: A harmonic's G is measured when the reference's amplitude there exceeds this many standard
#: errors of the noise (then ``|G^ - G| / |G| <~ 1 / RELIABLE``).
RELIABLE = 8.0
#: ... and at least this fraction of a neighbouring harmonic's: a harmonic the reference hardly
#: drives (a symmetric line's even harmonics) carries the stage's distortion of its neighbours
#: (the inverse leaves ~1 % of nonlinear error), not its response to the reference there.
HOLE = 0.1


def harmonics(x: FloatArray, t_s: FloatArray, f0_hz: float, n_max: int
              ) -> NDArray[np.complex128]:
    """Complex amplitudes ``c_0 .. c_n_max`` of ``x(t) = sum Re(c_n exp(j 2 pi n f0 t))``
    (least squares; exact for a periodic signal over any number of samples, no leakage).

    The normal equations are formed with ``einsum`` (no threaded BLAS: on a loaded host a
    BLAS thread pool next to a stage's I/O threads took seconds for this 0.1 ms problem)."""
    w = 2 * np.pi * f0_hz * np.outer(t_s, np.arange(1, n_max + 1))
    a = np.concatenate([np.ones((t_s.size, 1)), np.cos(w), np.sin(w)], axis=1)
    c = np.linalg.solve(np.einsum("ki,kj->ij", a, a), np.einsum("ki,k->i", a, x))
    return np.concatenate([[c[0]], c[1:n_max + 1] - 1j * c[n_max + 1:]])


def synthesize(c: NDArray[np.complex128], t_s: FloatArray, f0_hz: float) -> FloatArray:
    """The periodic signal of harmonic amplitudes ``c`` (see :func:`harmonics`) at ``t_s``."""
    n = np.arange(c.size)
    return np.real(np.einsum("kn,n->k", np.exp(2j * np.pi * f0_hz * np.outer(t_s, n)), c))


def q_gain(freqs_hz: FloatArray, dt_s: float, cutoff_hz: float) -> FloatArray:
    """|Q| at ``freqs_hz``: the Butterworth of :func:`q_filter`, squared (two passes)."""
    sos = signal.butter(2, min(2 * cutoff_hz * dt_s, 0.99), output="sos")
    _, h = signal.sosfreqz(sos, worN=freqs_hz, fs=1 / dt_s)
    return np.abs(h) ** 2


def _n_max(desired: track.Desired, cutoff_hz: float) -> int:
    """The harmonics the law works with under a ``Q`` cut off at ``cutoff_hz``: up to twice it."""
    assert desired.period_s is not None
    return max(1, int(min(2 * cutoff_hz, 0.4 / desired.dt_s) * desired.period_s))


def _harmonics_of(tuning: Tuning, desired: track.Desired, law: Law) -> int:
    """The harmonics :func:`next_reference` and :func:`retune` work with: those of the law's
    cut-off, or of ``tuning``'s where it rose above it."""
    return _n_max(desired, max(law.cutoff_hz, tuning.cutoff_hz))


def tune(reference: FloatArray, position: FloatArray, desired: track.Desired, law: Law,
         noise_um: float) -> Tuning:
    """``L`` and ``Q`` from iteration 0 (reference ``r_0`` and true-position estimate ``y_0``).

    For a periodic trajectory, ``G = Y / R`` at every harmonic whose reference amplitude is
    :data:`RELIABLE` standard errors of the noise or more (steady part) and no less than
    :data:`HOLE` times a neighbour's (a raster line's even harmonics, driven only by the slow
    axis's leak into it: there ``|G|`` was 5-28 on foreign-xy-1, the distortion of the odd
    ones, and its fast axis stalled at 7x its noise; interpolated, and tuned on its own
    motion, :func:`afmctl.experiment.scanlearn._tunings`, 1.7x). A small tone legitimately
    beside a large one (a multi-tone reference) is not measured either: its ``G`` is
    interpolated from its neighbours. ``G`` is measured up to twice the highest cut-off the
    law allows (:attr:`Law.band_hz`); ``Q``'s cut-off is ``law.cutoff_hz``, raised towards
    ``law.cutoff_max_hz`` while the stage follows the model (:func:`reach_hz`), but never above
    the last measured harmonic (beyond it nothing is known of ``G``, so ``|Q| <= 1/2``
    there); the measured ``G`` is kept up to the harmonics that cut-off works with
    (:func:`_harmonics_of`). The lead ``m`` of the plain law is the delay of
    :func:`lead_samples` (used where too few harmonics are measured, e.g. a sine).
    """
    skip = steady_part(desired).start
    m = lead_samples(reference, position, skip, law.max_lead_samples)
    if desired.period_s is None:
        return Tuning(m, law.cutoff_hz, np.zeros(0), np.zeros(0, complex))
    dt, f0, n_max = desired.dt_s, 1 / desired.period_s, _n_max(desired, law.band_hz)
    t = np.arange(skip, reference.size) * dt
    r = harmonics(reference[skip:], t, f0, n_max)[1:]
    y = harmonics(np.nan_to_num(position[skip:], nan=float(np.nanmean(position))), t, f0,
                  n_max)[1:]
    se = (noise_um if np.isfinite(noise_um) else 0.0) * np.sqrt(2 / max(t.size, 1))
    ok = (np.abs(r) > max(RELIABLE * se, 1e-9 * np.abs(r).max())) & ~_holes(np.abs(r))
    freqs, g = f0 * np.arange(1, n_max + 1)[ok], y[ok] / r[ok]
    fc = law.cutoff_hz
    if freqs.size >= MIN_HARMONICS:
        fc = min(reach_hz(freqs, g, law), float(freqs.max()))
    keep = freqs <= (_n_max(desired, max(law.cutoff_hz, fc)) + 0.5) * f0
    return Tuning(m, fc, freqs[keep], g[keep])


def reach_hz(freqs_hz: FloatArray, g: NDArray[np.complex128], law: Law) -> float:
    """``Q``'s cut-off from the ``G`` measured at ``freqs_hz`` (increasing): ``law.cutoff_hz``,
    raised up to ``law.cutoff_max_hz`` while the stage follows the model: up to the last
    measured harmonic before the first of :data:`SUSTAINED` measured ones in a row where
    ``|G|`` is below :data:`FOLLOWS` (a harmonic beyond the last measured one counts as short:
    nothing says the stage follows there). A run that starts below ``law.cutoff_hz`` keeps
    that. A stage that rolls off where its model does not (foreign-xy-4's x: ``|G|`` 0.92,
    0.80, 0.66, 0.53 from 630 to 810 Hz) made learning jump to 69x its noise at a fixed 1.2 kHz
    cut-off (and to 24x at 750 Hz, after four good frames), while a dip at a rod resonance the
    model puts a little off (foreign-xy-3's x: 0.80, 0.42, 1.86 at 0.99-1.11 kHz) is what the
    higher cut-off learns away (2.3x -> 1.25x its noise)."""
    if law.cutoff_max_hz is None:
        return law.cutoff_hz
    short = np.concatenate((np.abs(g) < FOLLOWS, np.ones(SUSTAINED, dtype=bool)))
    for i in np.flatnonzero(freqs_hz <= law.cutoff_max_hz):
        if short[i:i + SUSTAINED].all():
            return max(law.cutoff_hz, float(freqs_hz[i - 1]) if i else 0.0)
    return law.cutoff_max_hz


def retune(tuning: Tuning, refs: tuple[FloatArray, FloatArray],
           positions: tuple[FloatArray, FloatArray], errors: tuple[FloatArray, FloatArray],
           desired: track.Desired, law: Law, noise_um: float,
           region: NDArray[np.bool_] | None = None) -> Tuning:
    """``G^`` re-measured as ``dY / dR`` where a learning step stalled (pure numerics).

    ``Y / R`` of iteration 0 takes all of the position at a harmonic for the reference's
    response. Where the model leaves an error there that the reference does not drive (the
    rod ringing at its resonance after every turnaround), that error biases it: on
    pi-u-creep's 13th harmonic (363 Hz, on its 367 Hz rod) ``Y / R`` was 0.52 - 1.18j where the
    steps measured ``dY / dR`` = 0.96-0.99, and learning lost only 5 % of that harmonic's error
    per iteration (4.0x the noise after five).

    The step from ``refs[0]`` to ``refs[1]`` (um; ``law.gain`` the step's own, its scale
    included) moved the stage from ``positions[0]`` to ``positions[1]`` (um, the position as
    :func:`tune` took it) and left the learned errors ``errors`` (um; learned only in
    ``region``, as :func:`next_reference` does). It measures the local gain directly.
    ``G^`` becomes ``dY / dR`` at every measured harmonic where:

    * ``Q`` passes at least :data:`RETUNE_Q` (above the cut-off a right step also keeps most
      of the error, and the secant there is mostly noise);
    * the step stalled: the error kept more than half way between what a right ``G^`` leaves,
      ``|1 - rho Q|``, and all of itself;
    * the error before, and the step's response (``|dY|`` and ``|G^ dR|``), were each
      :data:`RELIABLE` standard errors of two runs' noise or more;
    * ``dY / dR`` differs from ``G^`` by more than :data:`RETUNE_CHANGE` (relative).

    Elsewhere it stays (a weakly excited harmonic's ``dY / dR`` carries the loop's change of
    shape with the offset, not the gain). Without a finite noise figure nothing is re-measured.
    """
    if not tuning.harmonic or desired.period_s is None or not np.isfinite(noise_um):
        return tuning
    skip = steady_part(desired).start
    dt, f0 = desired.dt_s, 1 / desired.period_s
    t = np.arange(skip, desired.u_um.size) * dt
    n = np.rint(tuning.freqs_hz / f0).astype(int)
    n_max = _harmonics_of(tuning, desired, law)

    def at(x: FloatArray) -> NDArray[np.complex128]:
        x = x[skip:]
        ok = np.isfinite(x)
        return harmonics(np.where(ok, x, np.mean(x[ok]) if ok.any() else 0.0), t, f0,
                         n_max)[n]

    def learned(e: FloatArray) -> NDArray[np.complex128]:
        return at(learned_error(e, region))

    d_r, d_y = at(refs[1]) - at(refs[0]), at(positions[1]) - at(positions[0])
    e0, e1 = learned(errors[0]), learned(errors[1])
    secant = d_y / np.where(d_r == 0, 1.0, d_r)
    q = q_gain(tuning.freqs_hz, dt, tuning.cutoff_hz)
    right = np.abs(1 - law.gain * q)
    big = RELIABLE * math.sqrt(2.0) * noise_um * math.sqrt(2 / max(t.size, 1))
    update = ((q >= RETUNE_Q) & (np.abs(e1) > 0.5 * (1 + right) * np.abs(e0))
              & (np.abs(e0) > big) & (np.minimum(np.abs(d_y), np.abs(tuning.g * d_r)) > big)
              & (np.abs(secant - tuning.g) > RETUNE_CHANGE * np.abs(tuning.g)))
    if not update.any():
        return tuning
    return replace(tuning, g=np.where(update, secant, tuning.g))


def _holes(a: FloatArray) -> NDArray[np.bool_]:
    """Harmonics whose amplitude ``a`` is below :data:`HOLE` times a neighbour's."""
    pad = np.concatenate([[0.0], a, [0.0]])
    return a < HOLE * np.maximum(pad[:-2], pad[2:])


def _g_hat(tuning: Tuning, freqs: FloatArray) -> NDArray[np.complex128]:
    """G^ at ``freqs``: the measured G interpolated (real and imaginary parts), 1 at DC, held
    beyond the last measured harmonic."""
    f = np.concatenate([[0.0], tuning.freqs_hz])
    g = np.concatenate([[1.0 + 0j], tuning.g])
    return np.interp(freqs, f, g.real) + 1j * np.interp(freqs, f, g.imag)


def next_reference(reference: FloatArray, error: FloatArray, desired: track.Desired, law: Law,
                   tuning: Tuning, region: NDArray[np.bool_] | None = None) -> FloatArray:
    """``r_{j+1} = r_j + Q[L e_j]`` (um); missing samples (NaN), and samples outside
    ``region`` if given, learn nothing of their own: the error there is bridged from the samples
    around them (:func:`bridged`).

    Per harmonic (``tuning.harmonic``): ``E_n`` from the steady part, ``dR_n = Q_n rho E_n /
    G^_n`` (magnitude at most ``law.max_boost``), synthesized over the tracking part and
    faded in over its first period (a raised
    cosine from 0: the reference keeps joining the ramp-in smoothly). Otherwise in time:
    ``Q[rho z^m e]``.
    """
    e = learned_error(error, region)
    dt = desired.dt_s
    if not tuning.harmonic or desired.period_s is None:
        return reference + q_filter(law.gain * shift(e, tuning.lead), dt, tuning.cutoff_hz)
    skip = steady_part(desired).start
    f0, n_max = 1 / desired.period_s, _harmonics_of(tuning, desired, law)
    ce = harmonics(e[skip:], np.arange(skip, e.size) * dt, f0, n_max)
    f = f0 * np.arange(n_max + 1)
    g = _g_hat(tuning, f)
    inv_g = np.exp(-1j * np.angle(g)) * np.minimum(1 / np.abs(g), law.max_boost)
    dr = law.gain * q_gain(np.maximum(f, 1e-9), dt, tuning.cutoff_hz) * ce * inv_g
    t = np.arange(e.size) * dt
    fade = 0.5 * (1 - np.cos(np.pi * np.minimum(np.arange(e.size) / max(skip, 1), 1.0)))
    aperiodic = e - synthesize(ce, t, f0)  # drift, creep, the first period's transient
    slow = q_filter(law.gain * aperiodic, dt, APERIODIC_FRACTION * tuning.cutoff_hz)
    return reference + fade * synthesize(dr, t, f0) + slow


def learned_error(error: FloatArray, region: NDArray[np.bool_] | None) -> FloatArray:
    """The error (um) learning works on: ``error`` at its finite samples in ``region`` (all of
    them without one), :func:`bridged` across the rest."""
    return bridged(error, np.isfinite(error) if region is None else np.isfinite(error) & region)


def bridged(x: FloatArray, keep: NDArray[np.bool_]) -> FloatArray:
    """``x`` where ``keep``, and elsewhere the straight line between the kept samples around
    (the nearest one held beyond the first and the last; 0 if none is kept).

    What learning works on outside the samples it learns from. Set to 0 there instead, the
    error put a step of its whole size into the reference at every edge of a raster's imaging
    region: on foreign-xy-2's slow axis (y, Bouc-Wen, 1 um too low over the frame) a comb of
    1 um notches at the line rate, whose minor loops an axis without wiping-out ratchets along
    the frame. Its first learned frame went from 91 to 80x the noise; bridged, to 33x, and the
    noise floor at the fourth."""
    if keep.all() or not keep.any():
        return np.where(keep, x, 0.0)
    k = np.arange(x.size)
    return np.interp(k, k[keep], x[keep])


def gain_and_offset(x: FloatArray, s: FloatArray, ramp_s: FloatArray | None = None
                    ) -> tuple[float, float, float]:
    """Least-squares coefficient of ``x`` (um) along the gain direction ``s`` (um per unit gain)
    with a free offset (NaN skipped), that offset (um) and the RMS the two leave unexplained
    (um): the change of the stage's gain that moves it by ``x``, and the constant shift (creep,
    drift) that comes with it.

    With ``ramp_s`` (s, each sample's time less the time the offset is wanted at) a free slope
    is fitted too, and the offset is the line's value where ``ramp_s`` is 0: the two runs'
    creep need not relax at the same rate (:func:`afmctl.experiment.learn.run_change`)."""
    k = np.isfinite(x) & np.isfinite(s)
    if not k.any():
        return 0.0, 0.0, 0.0
    along = s[k] if np.ptp(s[k]) > 0 else np.zeros(int(k.sum()))  # no gain where s is flat
    a = np.column_stack([along, np.ones(int(k.sum()))] + ([] if ramp_s is None else [ramp_s[k]]))
    c = np.linalg.lstsq(a, x[k], rcond=None)[0]
    return float(c[0]), float(c[1]), float(np.sqrt(np.mean((x[k] - a @ c) ** 2)))


def predicted_offset(offsets: FloatArray, first_step_um: float = 0.0) -> float:
    """The next run's slow offset (um) from the runs' offsets so far (creep, drift: measured on
    the conditioning, :func:`gain_and_offset`; runs follow one another at a steady pace): the
    last offset plus its last step times the ratio of the last two steps (clipped to 0..1:
    a steady drift keeps its step, ratio 1; creep relaxing in log-time after a rest takes
    steps that shrink, ratio ~0.5-0.6), :data:`FIRST_RATIO` of the step while there are only
    two runs, and the last offset plus ``first_step_um`` (um: a drift read before the first
    run, times the runs' pace) while there is one."""
    o = np.asarray(offsets, dtype=float)
    if o.size < 2:
        return float(o[-1]) + first_step_um if o.size else 0.0
    step = o[-1] - o[-2]
    ratio = FIRST_RATIO
    if o.size > 2:
        prev = o[-2] - o[-3]
        ratio = float(np.clip(step / prev, 0.0, 1.0)) if prev != 0 else 0.0
    return float(o[-1] + ratio * step)


def resolution(noise_um: float, gain_sigma: float, s_rms_um: float, runs: int) -> float:
    """The smallest error (um) learning can tell apart: the sensor noise and, under a per-run
    gain of spread ``gain_sigma`` (moving the stage ``s_rms_um`` per unit gain), the uncertainty
    of the mean gain of ``runs`` runs, ``gain_sigma s_rms / sqrt(runs)``, added in quadrature
    once there are :data:`MIN_RUNS_SPREAD` runs to measure a spread from."""
    if runs < MIN_RUNS_SPREAD:
        return noise_um
    return float(np.hypot(noise_um, gain_sigma * s_rms_um / np.sqrt(runs)))


def noise_estimate(error: FloatArray) -> float:
    """Sensor noise (um, 1 sigma) from the readings' error itself: the median absolute second
    difference (zero on straight stretches, robust to the corners), scaled for Gaussian noise
    (0.6745 sqrt 6)."""
    d = np.diff(error[np.isfinite(error)], 2)
    if d.size == 0:
        return float("nan")
    return float(np.median(np.abs(d - np.median(d))) / (0.6745 * np.sqrt(6)))


def steady_part(desired: track.Desired) -> slice:
    """The samples judged: all after the first period of a periodic trajectory."""
    if desired.period_s is None:
        return slice(0, None)
    return slice(min(int(round(desired.period_s / desired.dt_s)), desired.u_um.size - 1), None)


def imaging_mask(desired: track.Desired, fraction: float = IMAGING_FRACTION,
                 first_period: bool = False) -> NDArray[np.bool_]:
    """Samples in the central ``fraction`` of every ramp (monotone run between turning points)
    of the desired trajectory, the first period excluded unless ``first_period``: the imaging
    region of a raster line."""
    u = desired.u_um
    mask = np.zeros(u.size, dtype=bool)
    slope = np.sign(np.diff(u))
    turns = np.flatnonzero(slope[1:] * slope[:-1] < 0) + 1
    edges = np.concatenate(([0], turns, [u.size - 1]))
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        trim = 0.5 * (1 - fraction) * (b - a)
        mask[int(np.ceil(a + trim)):int(np.floor(b - trim)) + 1] = True
    if not first_period:
        mask[:steady_part(desired).start] = False
    return mask


def imaging_rms(desired: track.Desired, error: FloatArray, fine: int = 1) -> float:
    """RMS (um) of ``error`` over the imaging region; ``fine`` > 1 for an error sampled ``fine``
    times per sample (between samples: sub-sample i of sample k at index ``k * fine + i``)."""
    mask = imaging_mask(desired)
    if fine > 1:
        mask = np.repeat(mask, fine)[:error.size]
    e = error[: mask.size][mask[: error.size]]
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


def rms(x: FloatArray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")
