"""Bouc-Wen identification (afmctl.fit.boucwen) on a foreign Bouc-Wen stage, and tracking with it.

The stage is the independently written one of :mod:`afmctl.drivers.device.foreign.family_stage`
(its own Bouc-Wen integration, a cubic output map, a viscous input lag, its own rod and power-on
history), recorded in sequence at 2 kHz as ``afmctl sweep --design reversals`` records: the three
standard triangles and the reversal curves. Its minor loops do not close: the paper's model and
the Preisach grid stay far above the noise on it (bw-u of the benches: 42.7x and 41.6x held out).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.optimize import OptimizeResult

from afmctl.cli import main
from afmctl.files import modelfile as mf

from afmctl.drivers.device.foreign import family_stage as fst
from afmctl.files import sweepfile as sw
from afmctl.fit import boucwen as bf
from afmctl.fit import identify as idf
from afmctl.fit import parametrization as pz
from afmctl.fit import preisach_problem as pp
from afmctl.fit import stall
from afmctl.model import creep as cr
from afmctl.model import inverse as inv
from afmctl.model.boucwen import BoucWen
from afmctl.model import transducer as td
from tests.harness import family_set
from tests.harness.paths import PROFILES

RATE_HZ = 2000.0
V_RANGE = (0.0, 150.0)
THICKNESS_UM = 100.0
FIELD_STEP = idf.Settings().field_step  # identify's: the Bouc-Wen fit as identify runs it


@pytest.fixture(scope="module")
def stage_and_set() -> tuple[fst.FamilyStage, fst.FamilyState, list[sw.Sweep]]:
    stage = fst.random_family_stage(np.random.default_rng(302), "bouc-wen")
    recorded, state = family_set.record(stage, RATE_HZ, V_RANGE, 11)
    return stage, state, recorded


def _data(stage_and_set: tuple) -> tuple[pp.Data, list[tuple[str, ...]]]:
    _, _, sweeps = stage_and_set
    data = pp.Data([s.voltage_v / THICKNESS_UM for s in sweeps], [s.mask(None) for s in sweeps],
                   [s.displacement_um[s.mask(None)] for s in sweeps], [s.dt for s in sweeps],
                   np.full(len(sweeps), stage_and_set[0].noise_um))
    chained = [(first,) + ("previous",) * (len(sweeps) - 1)
               for first in ("depoled", "negative", "positive")]
    return data, chained


@pytest.fixture(scope="module")
def fitted(stage_and_set: tuple) -> bf.BoucWenFit:
    data, chained = _data(stage_and_set)
    return bf.fit(data, chained, (1000.0, 0.1), THICKNESS_UM, 0.05, 0.3, field_step=FIELD_STEP)


def test_the_field_grid_interpolates_in_the_field() -> None:
    """Between two kept samples the field is monotone, and a sample's share is its own move in
    the field: a function linear in the field is rebuilt exactly, on a noisy slow ramp, across
    an exact hold (share 0), and after a reversal whose first sample moved by less than a step
    on a fast ramp (that sample left out, the one before the next big move kept), where time
    would not."""
    rng = np.random.default_rng(3)
    slow = np.linspace(0.0, 1.0, 50) + 1e-4 * rng.standard_normal(50)
    fast = np.linspace(0.97, -0.43, 8)  # 0.2 per sample, over the step
    field = np.concatenate((slow, [1.0005], np.full(7, 1.0), [0.9999], fast))
    grid = pz.field_grid(field, 0.1)
    assert grid.keep.size < field.size // 2
    first = 58  # the reversal's first sample: 1.0 -> 0.9999, less than a step
    assert first not in grid.keep and first + 1 in grid.keep
    hold = np.arange(51, 58)
    assert np.all(grid.share[hold] == 0.0) or np.all(np.isin(hold, grid.keep))
    q = 3.0 * field[grid.keep] - 1.0
    rebuilt = grid.on_every_sample(q)
    assert np.max(np.abs(rebuilt - (3.0 * field - 1.0))) < 1e-12
    in_time = np.interp(np.arange(field.size), grid.keep, q)
    assert np.max(np.abs(in_time - (3.0 * field - 1.0))) > 1e-3


def test_eta_on_the_field_grid_is_the_full_rates(stage_and_set: tuple,
                                                 fitted: bf.BoucWenFit) -> None:
    """At the fitted shape and states, ``eta`` computed where the field moved by identify's
    field step and interpolated reads within 6 % of the noise (4 % measured) of ``eta`` on every sample, on
    every sweep of the foreign set; the slow triangle is computed on under a tenth of its
    samples."""
    stage, _, _ = stage_and_set
    data, _ = _data(stage_and_set)
    x = np.array([fitted.parameters[n] for n in bf.names(len(data.fields))])
    full, grid = bf.Problem(data), bf.Problem(data, FIELD_STEP)
    for a, b, m in zip(full.readings(x), grid.readings(x), data.masks, strict=True):
        assert float(np.sqrt(np.mean((a - b)[m] ** 2))) < 0.06 * stage.noise_um
    slow = int(np.argmax([e.size for e in data.fields]))
    assert grid.grids[slow].keep.size < 0.1 * data.fields[slow].size


def test_a_long_sweep_is_fitted_on_every_kth_sample_weighed(stage_and_set: tuple,
                                                             fitted: bf.BoucWenFit) -> None:
    """With at most 300 rows a sweep: each sweep judged on every k-th judged sample (k the
    least stride leaving at most 300), each row weighed by sqrt(k) over the noise, and the
    weighted residual on those rows is the full problem's there times sqrt(k), but for the
    sensor zero projected out on fewer rows (a constant per sweep)."""
    data, _ = _data(stage_and_set)
    x = np.array([fitted.parameters[n] for n in bf.names(len(data.fields))])
    full, thin = bf.Problem(data), bf.Problem(data, 0.0, 300)
    u = full.readings(x)
    r_full, r_thin = full.weighted(u), thin.weighted(u)
    at = np.concatenate(([0], np.cumsum([m.sum() for m in data.masks])))
    at_thin = np.concatenate(([0], np.cumsum([m.sum() for m in thin.data.masks])))
    for i, m in enumerate(data.masks):
        idx = np.flatnonzero(m)
        k = max(-(-idx.size // 300), 1)
        assert k > 1
        np.testing.assert_array_equal(np.flatnonzero(thin.data.masks[i]), idx[::k])
        np.testing.assert_allclose(thin.weights[i], np.sqrt(k) / data.noise[i], rtol=1e-15)
        sub = r_full[at[i]:at[i + 1]][::k] * np.sqrt(k)
        diff = r_thin[at_thin[i]:at_thin[i + 1]] - sub
        np.testing.assert_allclose(diff, diff[0], rtol=0, atol=1e-9)


def test_a_fit_on_thinned_rows_reports_the_full_rate(monkeypatch: pytest.MonkeyPatch,
                                                     stage_and_set: tuple) -> None:
    """With at most 300 rows a sweep in the fit (every sweep thinned), the figures and readings
    the fit returns are still the model's on every judged sample: the readings are
    ``predict_set`` of the written model, and the RMS per sweep is over every judged sample."""
    monkeypatch.setattr(bf, "MAX_ROWS", 300)
    data, chained = _data(stage_and_set)
    _, _, sweeps = stage_and_set
    quick = bf.fit(data, chained, (1000.0, 0.1), THICKNESS_UM, 0.05, 0.3, give_up=0.5,
                   field_step=FIELD_STEP)
    again = idf.predict_set(quick.model, sweeps, quick.starts, quick.offsets)
    for a, b, m, y, rms in zip(again, quick.predicted, data.masks, data.y, quick.heldout_rms_um,
                               strict=True):
        assert m.sum() > 300
        assert np.max(np.abs(a - b)) < 1e-6 * np.ptp(b)
        assert rms == pytest.approx(float(np.sqrt(np.mean((y - b[m]) ** 2))), rel=1e-12)


def test_a_fit_told_to_give_up_stops_after_its_first_start(stage_and_set: tuple,
                                                          fitted: bf.BoucWenFit) -> None:
    """``give_up`` below what any start reaches: the fit ends on its first start, without its
    creep solve, and says so, and why (the caller's reason: before any other representation
    is fitted there is none "far below" to name)."""
    data, chained = _data(stage_and_set)
    said: list[str] = []
    stopped = bf.fit(data, chained, (1000.0, 0.1), THICKNESS_UM, 0.05, 0.3, say=said.append,
                     give_up=0.5, give_up_why="not expected to reach the floor")
    assert said[-1].endswith("(stopped: above 0.5x, not expected to reach the floor)")
    assert stopped.model.creep is None and stopped.parameters["creep"] == 0.0
    assert np.all(stopped.heldout_rms_um >= 0.99 * fitted.heldout_rms_um)


def test_a_solve_is_far_off_where_all_its_sweeps_together_are_over_the_bound(
        stage_and_set: tuple, fitted: bf.BoucWenFit) -> None:
    """The stall rule's "far off" (:func:`bf._far`), on the fit's own residual: the RMS over the
    noise of every judged sample together, computed here from each sweep's RMS and count."""
    data, _ = _data(stage_and_set)
    prob = bf.Problem(data, FIELD_STEP, bf.MAX_ROWS)
    res = prob.residual(np.array([fitted.parameters[k] for k in bf.names(len(data.y))]))
    counts = np.array([y.size for y in data.y])
    together = float(np.sqrt(np.sum(counts * (fitted.heldout_rms_um / data.noise) ** 2)
                             / counts.sum()))
    state = OptimizeResult(cost=0.5 * float(res @ res))
    assert bf._far(prob, 0.97 * together)(state) and not bf._far(prob, 1.03 * together)(state)


def test_a_fit_stopped_where_it_stalls_says_so(monkeypatch: pytest.MonkeyPatch,
                                               stage_and_set: tuple) -> None:
    """A Bouc-Wen solve the stall rule stops is not "stopped on its budget": its ``how`` (what
    identify's message says of a chosen Bouc-Wen) is the stall's message."""
    def at_once(far, share=stall.SHARE):  # type: ignore[no-untyped-def]
        def callback(intermediate_result):  # type: ignore[no-untyped-def]
            raise StopIteration

        return callback

    monkeypatch.setattr(bf.stall, "callback", at_once)
    data, chained = _data(stage_and_set)
    stopped = bf.fit(data, chained, (1000.0, 0.1), THICKNESS_UM, 0.05, 0.3, give_up=0.5,
                     field_step=FIELD_STEP)
    assert not stopped.converged
    assert stopped.how.startswith("stalled: the cost fell by less than")
    assert stopped.how == stall.message("the sweeps over 0.5x their noise", bf.GIVE_UP_SHARE)


def test_a_solve_that_may_give_up_stalls_at_a_hundredth_in_ten_steps() -> None:
    """With ``give_up`` a solve stalls (far off) once its cost falls by less than
    :data:`bf.GIVE_UP_SHARE` (1 %) of itself in ten steps: a cost falling 0.05 % a step is
    stopped at the eleventh, which the stall's default share (0.1 %) lets go on."""
    def steps_until_stopped(share: float) -> int:
        check = stall.callback(lambda r: True, share)
        for step in range(1, 40):
            try:
                check(OptimizeResult(cost=1.0 * 0.9995 ** step))
            except StopIteration:
                return step
        return 0

    assert steps_until_stopped(bf.GIVE_UP_SHARE) == stall.STEPS + 1
    assert steps_until_stopped(stall.SHARE) == 0


def test_a_state_search_that_gains_nothing_is_not_solved_again_when_giving_up(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """``_searched`` with ``give_up`` solves again from the state search only if the search
    lowered the cost by :data:`bf.GIVE_UP_SHARE`; without ``give_up`` whenever it moved a
    state."""
    solved: list[object] = []
    monkeypatch.setattr(bf, "_solve", lambda prob, x, creep, give_up=None:
                        solved.append(x) or OptimizeResult(x=x, cost=0.0))

    class Searched:  # the state search moves a state; the cost at it is ``after``
        def __init__(self, after: float) -> None:
            self.after = after

        def state_search(self, x: np.ndarray) -> np.ndarray:
            return x + 1.0

        def readings(self, x: np.ndarray) -> list[np.ndarray]:
            return [x]

        def cost(self, u: list[np.ndarray]) -> float:
            return self.after

    sol = OptimizeResult(x=np.zeros(3), cost=100.0)
    for after, give_up, again in ((99.5, 4.5, False), (98.0, 4.5, True), (99.5, None, True)):
        solved.clear()
        bf._searched(Searched(after), sol, 1.0, give_up)  # type: ignore[arg-type]
        assert bool(solved) == again, (after, give_up)


def test_fit_reaches_near_the_noise_on_every_sweep(stage_and_set: tuple,
                                                   fitted: bf.BoucWenFit) -> None:
    """Every sweep, the open reversal curves included, within 2x the stage's gauge noise."""
    stage, _, sweeps = stage_and_set
    ratios = fitted.heldout_rms_um / stage.noise_um
    assert np.all(ratios < 2.0), ratios
    # the physical model reproduces the fit's own readings (the same sweeps in sequence)
    again = idf.predict_set(fitted.model, sweeps, fitted.starts, fitted.offsets)
    for a, b in zip(again, fitted.predicted, strict=True):
        assert np.max(np.abs(a - b)) < 1e-6 * np.ptp(b)


def test_inverse_tracks_the_foreign_stage(stage_and_set: tuple, fitted: bf.BoucWenFit) -> None:
    """From where the set left the stage: a ramp to 20 % of the range, then a triangle over
    20-80 % at 2.79 Hz whose second half turns inside (minor loops), planned by Algorithm 3
    through the fitted model (its zero: the last sweep's, the frame of the readings) and played
    on the stage: its TRUE error is over 10x below the paper's linear filter's (fitted to the
    slow triangle), and within 2x the stage's gauge noise."""
    stage, state, sweeps = stage_and_set
    model, prev = fitted.model, None
    for s, start in zip(sweeps, fitted.starts, strict=True):
        st = idf.start_state(model, start, float(s.voltage_v[0]), prev)
        _, _, end = td.simulate(td.compile_model(model, s.dt), s.voltage_v, st)
        prev = end.polarization
    v_last = float(sweeps[-1].voltage_v[-1])
    here = float(fitted.predicted[-1][-1])
    span = float(np.ptp(sweeps[0].displacement_um))
    lo, hi = here + 0.2 * span, here + 0.8 * span
    t = np.arange(int(2.5 * RATE_HZ)) / RATE_HZ
    tri = lo + (hi - lo) * np.abs(((t * 2.79 + 0.5) % 1.0) * 2 - 1)
    tri = np.where(t > 1.5, tri - 0.3 * (tri - lo) * np.sin(np.pi * (t - 1.5)) ** 2, tri)
    target = np.concatenate((np.linspace(here, lo, int(0.5 * RATE_HZ)), tri))
    cm = td.compile_model(model, 1 / RATE_HZ)
    first = idf.start_state(model, "previous", v_last, prev)
    res = inv.algorithm3(cm, target[1:], first, e_init=v_last / THICKNESS_UM)
    v_inv = np.clip(res.voltage(THICKNESS_UM), *V_RANGE)  # sample k aims at target[k + 1]
    slow = sweeps[0]
    lin = inv.fit_linear(slow.voltage_v, slow.displacement_um)
    v_lin = np.clip(lin.voltage(target[1:]), *V_RANGE)
    judged = slice(int(0.6 * RATE_HZ), None)
    errs = []
    for v in (v_inv, v_lin):  # the noise-free gauge (this stage's reads its position exactly)
        _, reading, _ = fst.run(stage, v, RATE_HZ, state)
        errs.append(float(np.sqrt(np.mean((reading[1:][judged] - target[1:-1][judged]) ** 2))))
    assert errs[0] < 2 * stage.noise_um, errs
    assert errs[0] * 10 < errs[1], errs


@pytest.mark.slow
def test_identify_chooses_bouc_wen_through_the_cli(stage_and_set: tuple, tmp_path) -> None:
    """``afmctl identify --json`` on the set: the paper's model stays far above the noise, the
    loops are open, Bouc-Wen is fitted first and kept within the noise floor (the grid, which
    cannot open a loop, is not fitted, and the figures say why), and its model file reads back. The
    HEM without restarts (a profile's ``[identify] restarts = 0``): its restarts took 110 of the
    test's 150 s and leave it at 40x the noise on this stage (bw-u of the benches)."""
    _, _, sweeps = stage_and_set
    files = []
    for s in sweeps:
        files.append(str(tmp_path / f"{s.name}.csv"))
        sw.write(s, Path(files[-1]))
    prof = tmp_path / "p.toml"
    prof.write_text((PROFILES / "emulated.toml").read_text() + "\n[identify]\nrestarts = 0\n")
    res = CliRunner().invoke(main, ["identify", *files, "-o", str(tmp_path / "m.toml"), "--json",
                                    "--profile", str(prof)])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    figures = doc["representations"]
    assert doc["representation"] == figures["chosen"] == "bouc-wen", figures["why"]
    bw = figures["bouc_wen"]["worst_heldout_over_noise"]
    assert bw < 2.0
    assert f"bouc-wen {bw:.2f}x (in sample)" in figures["why"]  # not called held out
    assert figures["hem"]["worst_over_noise"] > 3 * figures["bouc_wen"]["worst_heldout_over_noise"]
    assert doc["minor_loops"]["close"] is False
    assert "minor loop stays open" in figures["preisach"]["skipped"]
    assert "a Bouc-Wen model first" in res.stderr and "fitting the Preisach grid" not in res.stderr
    assert isinstance(mf.read(tmp_path / "m.toml").polarization, BoucWen)


def test_estimates_list_the_models_creep(fitted: bf.BoucWenFit) -> None:
    """The parameters identify reports for a Bouc-Wen model carry its creep, as the grid's do."""
    from dataclasses import replace

    from afmctl.fit import representation as rep

    names = [e.name for e in rep.bw_estimates(fitted)]
    assert "bouc_wen_kappa" in names and ("creep_per_decade" in names) == (
        fitted.model.creep is not None)
    crept = replace(fitted, model=replace(fitted.model, creep=bf.creep_of(0.005)))
    by_name = {e.name: e.value for e in rep.bw_estimates(crept)}
    assert by_name["creep_per_decade"] == pytest.approx(crept.model.creep.per_decade())
    assert by_name["creep@1000s"] == 0.005


def test_creep_goes_on_across_a_known_hold_as_one_record_would() -> None:
    """Two sweeps 0.5 s apart (``gaps_s``): the second's force equals that of one record of the
    first, the hold at its last field and the second, run through the creep elements from rest
    (:func:`afmctl.model.creep.run`, the hold sample by sample); with the hold unknown it starts
    at rest, and differs."""
    dt, hold_n = 1e-3, 500
    t = np.arange(2000) * dt
    fields = [0.5 + 0.5 * np.sin(2 * np.pi * t), 0.2 + 0.3 * np.cos(3 * np.pi * t)]
    ones = [np.ones(f.size, dtype=bool) for f in fields]
    x = np.array([np.log(5.0), 0.5, 1.0, 0.1, 0.3, 0.05, np.log(1000.0), np.log(0.5), 0.01,
                  0.0, 0.2])

    def problem(gaps: list[float]) -> bf.Problem:
        return bf.Problem(pp.Data(fields, ones, [np.zeros(f.size) for f in fields], [dt, dt],
                                  np.ones(2), gaps_s=gaps))

    chained = problem([np.nan, hold_n * dt])
    etas = chained.shape(x[0], x[1], x[2], x[bf.STATES_AT:])
    r = bf.reversible(x[3], x[4], 5.0, 0.5)
    p1, p2 = (r * e + x[4] * eta for e, eta in zip(fields, etas, strict=True))
    creep = bf.creep_of(x[bf.CREEP_AT])
    whole, _ = cr.run(creep, np.concatenate((p1, np.full(hold_n, p1[-1]), p2)), dt,
                      cr.rest_state(creep, float(p1[0])))
    q = whole[-p2.size:]
    forces = chained.forces(x)
    assert np.allclose(forces[1], q + x[5] * q * q, rtol=0, atol=1e-12)
    unknown = problem([np.nan, np.nan]).forces(x)
    assert np.array_equal(unknown[0], forces[0])
    assert np.max(np.abs(unknown[1] - forces[1])) > 1e-4


@pytest.mark.slow
def test_a_fit_whose_differences_run_side_by_side_is_the_fit_alone(
        stage_and_set: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    """The solver's finite differences on two threads (:func:`afmctl.fit.cores.mapped`) and one
    after another: the same fit, to the last bit."""
    from afmctl.fit import cores

    data, chained = _data(stage_and_set)
    fits = []
    for n in (1, 2):
        monkeypatch.setattr(cores.os, "sched_getaffinity", lambda _pid, n=n: set(range(n)))
        fits.append(bf.fit(data, chained, (1000.0, 0.1), THICKNESS_UM, 0.05, 0.3,
                           field_step=FIELD_STEP))
    assert fits[0].parameters == fits[1].parameters and fits[0].iterations == fits[1].iterations
    np.testing.assert_array_equal(fits[0].heldout_rms_um, fits[1].heldout_rms_um)
