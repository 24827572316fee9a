"""What the model gets wrong, why, and what an extended model gains on data the fit did not see.

Given measured sweeps, :func:`diagnose`

1. splits every sweep in time: the first half is fitted, the second half judged (the model state
   is carried from the sweep's start through both: held-out periods, not held-out samples);
2. fits the paper's model (``none``) and every candidate extension of :mod:`afmctl.fit.extension`
   on the first halves, each sweep weighing the same;
3. measures each one's RMS error on the second halves (the root mean of the per-sweep mean squares)
   and its *gain* = base / extended held-out RMS;
4. reads every held-out RMS against the noise floor (the sensor noise of each sweep, as the
   caller or :mod:`afmctl.fit.noise` gives it) and decides (:mod:`afmctl.fit.verdict`): a candidate that
   brings the error near the floor, ``none`` when the paper's model is already there, or
   ``unexplained`` when nothing is (with how far, the residual's signature and what to measure);
5. analyses the base model's residuals against time, field, field rate, frequency, amplitude,
   turning points, a tone that is no harmonic of the drive, and between sweeps
   (:func:`afmctl.fit.residuals.residual_signature`). The model files are the fits on the first
   halves;
6. when the verdict is ``unexplained``, tries the causes again on identify's general coercive
   density with its hysteresis held (:mod:`afmctl.fit.heldbase`: a stage of the paper's family
   whose density the lognormal does not reach); a cause, ``none`` or ``indistinguishable`` there
   is the verdict, and the model files are those fits on the first halves;
7. when the verdict is still ``unexplained``, fits the Preisach grid identify chooses off the
   paper's family, without and with its log-time creep elements (:mod:`afmctl.fit.gridbase`:
   judged on held-out blocks, as identify judges it): ``creep`` when the elements describe creep,
   ``none`` when the grid alone is at the floor, ``unexplained`` otherwise (with a drift hint
   when the elements sit on the slowest time constants). The model files are then the grid's.

Pure numerics and data: files and plots are written by the CLI (:mod:`afmctl.cli`).
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from afmctl.errors import DiagnoseInputError
from afmctl.files.sweepfile import Sweep
from afmctl.fit import candidate_space as cs
from afmctl.fit import candidates as cd
from afmctl.fit import cores
from afmctl.fit import extension as ext
from afmctl.fit import gridbase as gb
from afmctl.fit import heldbase as hb
from afmctl.fit import identify as idf
from afmctl.fit import noise as ns
from afmctl.fit import parametrization as pz
from afmctl.fit import preisach as pf
from afmctl.fit import twins as tw
from afmctl.fit import verdict as vd
from afmctl.fit.diagnosis import Diagnosis, Judged
from afmctl.fit.residuals import residual_signature
from afmctl.model import transducer as td

FloatArray = NDArray[np.float64]



@dataclass(frozen=True)
class Settings:
    """Options of :func:`diagnose`: identification settings of the fits, the solver budget per run,
    the number of starts per candidate, the candidates, the verdict's thresholds, the number of
    candidates fitted at once (``jobs``, processes; None: one per core) and the stage's slew
    limit (V/s; None: unknown), which a suggested separating sweep keeps to
    (:func:`afmctl.fit.twins.proposals`); whether an unexplained verdict tries the causes on
    identify's general density with its hysteresis held (``held``, :mod:`afmctl.fit.heldbase`)
    and then the Preisach
    grid without and with creep (``grid``, :mod:`afmctl.fit.gridbase`), the grid's fit settings
    and the creep rule."""

    identify: idf.Settings = idf.Settings()
    max_nfev: int = 60
    n_starts: int = 2
    candidates: tuple[str, ...] = cd.NAMES
    rule: vd.Rule = vd.Rule()
    jobs: int | None = None
    max_slew_v_per_s: float | None = None
    held: bool = True
    grid: bool = True
    grid_fit: pf.Settings = gb.GRID_SETTINGS
    creep_rule: gb.CreepRule = gb.CreepRule()


# ----------------------------------------------------------------------------------------------
# held-out split and scoring
# ----------------------------------------------------------------------------------------------


def first_half(s: Sweep) -> Sweep:
    """The fitted part of a sweep: its first half in time."""
    return s.head(s.time_s.size // 2)


def heldout(space: cs.ExtendedSpace, fitted: ext.Extended,
            sweeps: Sequence[Sweep]) -> tuple[float, tuple[float, ...], float]:
    """Error of a fitted candidate on the second half of every sweep, the part no fit saw, and
    on the first halves it was fitted on.

    Parameters
    ----------
    space : ExtendedSpace
        The candidate on the whole sweeps
        (:meth:`~afmctl.fit.candidate_space.ExtendedSpace.on`): its
        readings are computed exactly as in the fit, the state carried from each sweep's start
        through both halves.
    fitted : Extended
        The candidate fitted on the first halves (its parameters, gains and sensor zeros).
    sweeps : sequence of Sweep

    Returns
    -------
    rms_um : float
        Root mean of the per-sweep mean squares, um (every sweep weighs the same).
    per_sweep_um : tuple of float
        RMS of each sweep's second half, um.
    fit_rms_um : float
        The same root mean on the first halves, um.
    """
    sq = [(s.displacement_um - u) ** 2
          for s, u in zip(sweeps, space.readings(fitted.x, fitted.beta), strict=True)]
    first = [np.arange(s.time_s.size) < s.time_s.size // 2 for s in sweeps]
    judged = [s.mask(None) for s in sweeps]
    rms, per = vd.judged_rms(sq, [m & ~f for m, f in zip(judged, first, strict=True)])
    return rms, per, vd.judged_rms(sq, [m & f for m, f in zip(judged, first, strict=True)])[0]


# ----------------------------------------------------------------------------------------------
# the diagnosis
# ----------------------------------------------------------------------------------------------


#: Fewest judged samples a sweep needs in each half (after its memory index).
MIN_SAMPLES = 50


def check(sweeps: Sequence[Sweep]) -> None:
    """DiagnoseInputError naming the first sweep that cannot be split into a fitted and a judged
    half with a voltage excursion in each."""
    if not sweeps:
        raise DiagnoseInputError("no sweeps given")
    for s in sweeps:
        m, h = s.mask(None), s.time_s.size // 2
        if np.ptp(s.voltage_v) == 0:
            raise DiagnoseInputError(f"{s.path or s.name}: the voltage never changes")
        if min(int(m[:h].sum()), int(m[h:].sum())) < MIN_SAMPLES:
            raise DiagnoseInputError(
                f"{s.path or s.name}: fewer than {MIN_SAMPLES} samples in a half after the first "
                f"full excursion (sample {s.memory_index}); record a longer sweep")


#: Most coercive nodes in the candidates' fits (the identification may ask for more; the held-out
#: predictions use 256).
MAX_COERCIVE = 256


#: Most residual rows a sweep keeps in the candidates' fits (:func:`pz.thinned`; the fitted half
#: of the standard set's 40 s of minor loops at 10 kHz has 200,000).
FIT_ROWS = 20_000


@dataclass(frozen=True)
class _Data:
    """Sweeps prepared once for every candidate's fit."""

    preps: list[pz.Prepared]
    base: pz.LognormalSpace
    e_max: float
    nyquist_hz: float


def _prepare(sweeps: Sequence[Sweep], thickness: float, settings: idf.Settings,
             starts: Sequence[str] | None = None, n_coercive: int | None = None) -> _Data:
    """The sweeps prepared for the fits (residual rows thinned to :data:`FIT_ROWS`): each from
    its start (None: chosen later), the hysteresis on ``n_coercive`` nodes (None: the
    identification's fitting count)."""
    preps = [pz.thinned(pz.prepare(s, thickness, settings.field_step, None), FIT_ROWS)
             for s in sweeps]
    space = pz.LognormalSpace(preps, settings.scales, n_coercive or settings.n_coercive_fit,
                              starts)
    return _Data(preps, space, *pz.extent(preps))


def _base_fit(halves: Sequence[Sweep], thickness: float, settings: Settings,
              start: td.Transducer | None, say: Callable[[str], None]) -> tuple[_Data, FloatArray]:
    """The robust base fit on the first halves (:func:`afmctl.fit.identify.fit`: each sweep's start
    state and sensor zero, the coercive node count), or ``start``'s parameters with the starts
    chosen for them: the data prepared for every candidate, and ``x`` of the base model."""
    if start is None:
        say("identifying the base model on the first halves ...")
        # the paper's model: the candidates extend it (a Preisach grid has no such candidates)
        res = idf.fit(halves, replace(settings.identify, representation="hem"))
        n_c = min(max(settings.identify.n_coercive_fit, res.model.polarization.n_coercive),
                  MAX_COERCIVE)
        say("  base fit: RMS / noise per half " + " / ".join(
            f"{e.rms_over_noise:.2f}" for e in res.sweeps) + f"; N_c = {n_c}")
        return _prepare(halves, thickness, settings.identify, [e.start for e in res.sweeps],
                        n_c), res.x
    x0 = pz.internal(start)
    data = _prepare(halves, thickness, settings.identify)
    y = np.concatenate([p.y for p in data.preps])
    return replace(data, base=idf.choose_starts(data.base, x0, y)), x0


@dataclass(frozen=True)
class _Job:
    """What every candidate's fit and judgement needs (sent to the worker processes)."""

    data: _Data
    x0: FloatArray
    thickness: float
    range_um: float
    settings: Settings
    whole: list[pz.Prepared]
    sweeps: tuple[Sweep, ...]


def _space(name: str, job: _Job, progress: cs.Progress | None = None) -> cs.ExtendedSpace:
    """Candidate ``name`` on the first halves, from the base parameters ``job.x0``; a gauge error
    fitted in the frame of the whole sweeps' slowest readings and stated in that of a lab's
    linear calibration on the slowest of the recorded sweeps."""
    data = job.data
    cand = cd.catalogue(len(data.preps), data.e_max, data.nyquist_hz,
                         pz.rod_of(job.x0)[0], cd.field_rate_max(data.preps))[name]
    return cs.ExtendedSpace(cand, data.preps, data.base, job.settings.identify.field_step,
                             job.range_um, gauge_frame=cd.calibration_frame(job.whole),
                             calibration_um=cd.recorded_calibration(job.sweeps),
                             progress=progress)


def _fit(name: str, job: _Job, progress: cs.Progress | None = None
         ) -> tuple[ext.Extended, int, cs.ExtendedSpace]:
    """Fit candidate ``name`` (:func:`_space`): the fit, the parameters it adds, its space."""
    space = _space(name, job, progress)
    fitted, space = ext.fit(space, job.x0, job.thickness, job.settings.max_nfev,
                            job.settings.n_starts, job.settings.identify)
    return fitted, space.candidate.n_added, space


def _readings_on(table: dict[str, Judged], job: _Job, name: str, sweep: Sweep) -> FloatArray:
    """What fitted candidate ``name`` of ``table`` reads (um) on a sweep never recorded, from the
    state its first sweep started in (depoled if that carried on from an earlier history), with
    the last sweep's sensor zero."""
    fitted = table[name].fitted
    prep = pz.prepare(sweep, job.thickness, job.settings.identify.field_step, None)
    start = fitted.starts[0] if fitted.starts[0] != "previous" else "depoled"
    space = _space(fitted.name, job).on([prep], (start,))
    beta = np.concatenate((fitted.beta[:space.n_rod], fitted.beta[-1:]))
    return space.readings(fitted.x, beta)[0]


#: Where the candidates' fits say how far they are
#: (:class:`afmctl.fit.candidate_space.Progress`):
#: set by :func:`_judge_all` for its worker processes, which inherit it (forked).
_progress_say: Callable[[str], None] | None = None


def _judge(name: str, job: _Job) -> Judged:
    """Fit candidate ``name`` on the first halves and judge it on the second halves."""
    t1 = time.perf_counter()
    progress = None if _progress_say is None else cs.Progress(_progress_say, name)
    fitted, n_params, space = _fit(name, job, progress)
    rms, per, fit_rms = heldout(space.on(job.whole), fitted, job.sweeps)
    return Judged(fitted, n_params, rms, per, time.perf_counter() - t1, fit_rms)




def _judge_all(names: Sequence[str], job: _Job, floor: float,
               say: Callable[[str], None]) -> dict[str, Judged]:
    """Every candidate judged, in ``names`` order; fitted ``job.settings.jobs`` at a time in
    worker processes (the fits are independent and pure), with one BLAS thread each (set by
    :func:`diagnose`, inherited): the processes take every core, and OpenBLAS's threads
    waiting on busy cores made a 4 x 4 ``expm`` take 15 ms instead of 0.03 ms."""
    global _progress_say
    jobs = min(job.settings.jobs or os.cpu_count() or 1, len(names))
    order = sorted(names, key=lambda n: cd.SLOWEST_FIRST.index(n) if n in cd.SLOWEST_FIRST else 9)
    say(f"fitting {len(names)} candidates, {jobs} at a time (a long fit says how far it is "
        f"every {cs.PROGRESS_S:.0f} s) ...")

    def said(name: str, j: Judged) -> Judged:
        say(f"  {name:20s} held-out RMS {j.heldout_rms_um:.4f} um = "
            f"{j.heldout_rms_um / floor:.2f}x noise ({j.fit_seconds:.1f} s)")
        return j

    _progress_say = say
    try:
        if jobs <= 1:
            done = {n: said(n, _judge(n, job)) for n in order}
        else:  # leaving the pool (an error, Ctrl-C) terminates the workers; they ignore SIGINT
            with mp.get_context("fork").Pool(jobs, cores.pool_worker) as pool:
                done = {n: said(n, j) for n, j in pool.imap_unordered(_named_judge,
                                                                      [(n, job) for n in order])}
    finally:
        _progress_say = None
    return {n: done[n] for n in names}


def _named_judge(task: tuple[str, _Job]) -> tuple[str, Judged]:
    return task[0], _judge(*task)



def candidate_names(n_sweeps: int, settings: Settings) -> list[str]:
    """The candidates tried on ``n_sweeps`` sweeps (gain drift needs two or more), and the
    actuator-side twin of every sensor-side one (:data:`afmctl.fit.candidates.TWINS`) that is a
    cause of its own (a twin only, :data:`~afmctl.fit.candidates.TWIN_ONLY`, is fitted from its
    sensor cause's fit: :func:`_twin_from`)."""
    names = [n for n in settings.candidates if n != "voltage-gain-drift" or n_sweeps >= 2]
    return names + [t for n in names if (t := cd.TWINS.get(n)) in cd.NAMES and t not in names]


def with_forms(names: Sequence[str]) -> list[str]:
    """``names`` and the second form of every cause in them (:data:`afmctl.fit.candidates.FORMS`)."""
    return list(names) + [f for f, cause in cd.FORMS.items() if cause in names and f not in names]


def in_forms(table: dict[str, Judged]) -> dict[str, Judged]:
    """The table with each cause fitted in several forms (:func:`with_forms`; or in a second
    form alone, asked for by its name) under the cause's name alone: the form with the lower RMS
    on the fitted halves (the held-out halves stay unseen by the choice), each form's RMS on
    both halves recorded."""
    out = {n: j for n, j in table.items() if n not in cd.FORMS}
    for form, cause in cd.FORMS.items():
        if form in table:
            tried = (out[cause], table[form]) if cause in out else (table[form],)
            best = min(tried, key=lambda j: (math.isnan(j.fit_rms_um), j.fit_rms_um))
            out[cause] = replace(best, forms=tuple((j.fitted.name, j.fit_rms_um,
                                                    j.heldout_rms_um) for j in tried))
    return out


def _twin_from(sensor: str, table: dict[str, Judged], job: _Job) -> Judged:
    """The twin-only candidate of ``sensor`` fitted from the sensor cause's fit (its model's
    ``x`` and start states; quasi-statically the two are the same readings) and judged on the
    second halves."""
    t1 = time.perf_counter()
    fitted = table[sensor].fitted
    space = _space(cd.TWINS[sensor], job).with_starts(fitted.starts)
    twin, space = ext.fit(space, fitted.x[:6], job.thickness, job.settings.max_nfev, 1,
                          job.settings.identify)
    rms, per, fit_rms = heldout(space.on(job.whole), twin, job.sweeps)
    return Judged(twin, space.candidate.n_added, rms, per, time.perf_counter() - t1, fit_rms)


def scored(table: dict[str, Judged]) -> list[vd.Scored]:
    """The table's held-out RMS and parameters added, for the verdict."""
    return [vd.Scored(n, j.heldout_rms_um, j.n_params, j.fit_rms_um) for n, j in table.items()]


def choose(table: dict[str, Judged], floor_um: float, rule: vd.Rule) -> str:
    """The verdict on the candidate table against the noise floor ``floor_um`` (um):
    :func:`afmctl.fit.verdict.decide`."""
    return vd.decide(scored(table), floor_um, rule)


def _separating(readings: Callable[[str, Sweep], FloatArray], job: _Job, floor: float,
                pairs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The sweep that would separate the best sensor-side cause the sweeps left unseparated
    from its twin (:func:`afmctl.fit.twins.separating_sweep`, with what each fitted cause
    ``readings`` on a sweep), with both names and the bar."""
    pair = min((p for p in pairs if not p["separated"] and not p["refuted"]),
               key=lambda p: p["sensor_heldout_rms_um"])
    found = tw.separating_sweep(readings, pair["sensor"], job.sweeps, floor,
                                job.settings.max_slew_v_per_s)
    return {"sensor": pair["sensor"], "actuator": pair["actuator"], "needed": pair["needed"],
            **found}


def check_noise(sweeps: Sequence[Sweep], noise_um: Sequence[float]) -> tuple[float, ...]:
    """The per-sweep noise (um) as floats; DiagnoseInputError unless one positive finite value
    per sweep."""
    noise = tuple(float(n) for n in noise_um)
    if len(noise) != len(sweeps) or not all(math.isfinite(n) and n > 0 for n in noise):
        raise DiagnoseInputError(f"need one positive sensor noise (um) per sweep, got {noise}")
    return noise


def diagnose(sweeps: Sequence[Sweep], settings: Settings = Settings(),
             start: td.Transducer | None = None,
             progress: Callable[[str], None] | None = None,
             noise_um: Sequence[float] | None = None) -> Diagnosis:
    """Find what the model gets wrong on ``sweeps``, fit each candidate cause, give the verdict.

    Parameters
    ----------
    sweeps : sequence of Sweep
        Measured sweeps (at least one; ``voltage-gain-drift`` needs two).
    settings : Settings
    start : Transducer, optional
        A model (lognormal/normal densities) to start the fits from instead of identifying one.
    progress : callable, optional
        One-line progress messages.
    noise_um : sequence of float, optional
        The sensor noise (1 sigma, um) of each sweep: the floor every held-out RMS is read
        against. Default: estimated from each sweep's data (:func:`afmctl.fit.noise.sensor_noise_um`).

    Returns
    -------
    Diagnosis
        Verdict, base and extended held-out RMS (um), noise floor, the per-candidate table, and the
        base model and the winner (fitted on the first halves).

    Raises
    ------
    DiagnoseInputError
        Sweeps too short to split, or without a voltage excursion; a noise that is not positive.
    """
    say = progress or (lambda _m: None)
    t0 = time.perf_counter()
    check(sweeps)
    noise = check_noise(sweeps, noise_um if noise_um is not None else
                        [ns.sensor_noise_um(s.displacement_um) for s in sweeps])
    floor = vd.floor(noise)
    thickness, _ = idf.resolve_thickness(sweeps, settings.identify)
    halves = [first_half(s) for s in sweeps]
    range_um = max(float(np.ptp(s.displacement_um[s.mask(None)])) for s in sweeps)
    with threadpool_limits(limits=1, user_api="blas"):  # one BLAS thread: see _judge_all
        data, x0 = _base_fit(halves, thickness, settings, start, say)
        whole = [pz.prepare(s, thickness, settings.identify.field_step, None) for s in sweeps]
        job = _Job(data, x0, thickness, range_um, settings, whole, tuple(sweeps))
        table = in_forms(_judge_all(with_forms(candidate_names(len(sweeps), settings)), job,
                                    floor, say))
        for sensor in [n for n in cd.TWINS if n in table and cd.TWINS[n] in cd.TWIN_ONLY]:
            say(f"fitting {cd.TWINS[sensor]}, the twin of {sensor}, from its fit ...")
            j = table[cd.TWINS[sensor]] = _twin_from(sensor, table, job)
            say(f"  {cd.TWINS[sensor]:20s} held-out RMS {j.heldout_rms_um:.4f} um = "
                f"{j.heldout_rms_um / floor:.2f}x noise ({j.fit_seconds:.1f} s)")
        cause = choose(table, floor, settings.rule)
        pairs = tw.pairs(scored(table), settings.rule)
        separating = None
        if cause == vd.INDISTINGUISHABLE:
            say("the sensor-side cause and its twin are not separated: predicting fast sweeps "
                "with both ...")
            separating = _separating(lambda n, s: _readings_on(table, job, n, s), job, floor,
                                     pairs)
        held = None
        if cause == "unexplained" and settings.held and set(settings.candidates) - {"none"}:
            held, cause, held_pairs, held_separating = _held(job, halves, noise, floor, say)
            if cause != "unexplained":
                pairs, separating = held_pairs, held_separating
        grid = None
        if cause == "unexplained" and settings.grid:
            grid = _grid(job, noise, say)
            cause = grid.verdict()
    say(f"verdict: {cause}")
    signature = residual_signature(table["none"].fitted, sweeps)
    files = tuple(s.path or s.name for s in sweeps)
    if grid is not None and cause in ("creep", "none"):
        final = grid.crept if cause == "creep" else grid.plain
        return Diagnosis(cause, grid.plain_rms_um, grid.crept_rms_um if cause == "creep" else
                         grid.plain_rms_um, floor, noise, table, grid.plain, final, signature,
                         time.perf_counter() - t0, files, tuple(pairs), separating, grid, held)
    on = held.table if held is not None and cause != "unexplained" else table
    named = cause if cause in on else "none"
    return Diagnosis(cause, on["none"].heldout_rms_um, on[named].heldout_rms_um, floor,
                     noise, table, on["none"].fitted, on[named].fitted, signature,
                     time.perf_counter() - t0, files, tuple(pairs), separating, grid, held)


def _held(job: _Job, halves: Sequence[Sweep], noise: Sequence[float], floor: float,
          say: Callable[[str], None]
          ) -> tuple[hb.HeldBase, str, list[dict[str, Any]], dict[str, Any] | None]:
    """The causes on identify's general coercive density with its hysteresis held
    (:func:`afmctl.fit.heldbase.judge`): the fits, their verdict, every sensor-side cause with
    its twin and, if the two are not separated, the sweep that would separate them."""
    say("nothing of the paper's lognormal family explains the sweeps: trying the causes on "
        "identify's general coercive density, its hysteresis held ...")
    s = job.settings
    held = hb.judge(job.sweeps, halves, noise, s.identify,
                    candidate_names(len(job.sweeps), s), s.max_nfev, say)
    cause = choose(held.judged, floor, s.rule)
    pairs = tw.pairs(scored(held.judged), s.rule)
    separating = (_separating(held.readings, job, floor, pairs)
                  if cause == vd.INDISTINGUISHABLE else None)
    say(f"  on the general density: {cause} ({held.seconds:.0f} s)")
    return held, cause, pairs, separating


def _grid(job: _Job, noise: Sequence[float], say: Callable[[str], None]) -> gb.GridBase:
    """The Preisach grid without and with creep on the whole sweeps, judged on held-out blocks
    (:func:`afmctl.fit.gridbase.judge`), from the paper's model's starts and rod."""
    say("nothing of the paper's family explains the sweeps: fitting the Preisach grid (the "
        "representation identify chooses off the family) without and with creep ...")
    s = job.settings
    grid = gb.judge(job.sweeps, job.thickness, s.identify.mass_kg, noise, job.data.base.starts,
                    pz.rod_of(job.x0), say, s.grid_fit, s.creep_rule, s.rule)
    say(f"  Preisach grid: {grid.text()} ({grid.seconds:.0f} s)")
    return grid
