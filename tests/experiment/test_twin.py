"""The model's twin of a stage (afmctl.experiment.twin) and the sweeps' holds it follows
(afmctl.files.sweepfile.holds_s): against one simulation of everything the stage did, holds
included, sample by sample; and the stage's clock as the recordings report it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from afmctl.drivers.inprocess import InProcessStage
from afmctl.experiment import runner, twin
from afmctl.files import sweepfile
from afmctl.files.profile import default_profile
from afmctl.model import creep as cr
from afmctl.model import frame as fr
from afmctl.model import hysteresis as hy
from afmctl.model import rod as rd
from afmctl.model import transducer as tr

RATE = 2000.0


def creeping() -> tr.Transducer:
    pol = hy.Polarization(eta=2.5, p_r=0.3, coercive=hy.Lognormal(0.6, 0.4),
                          interaction=hy.Normal(0.25), n_coercive=64)
    return tr.Transducer(pol, rd.Rod(m=0.05, c=60.0, k=2.0e5, a1=3.0e4, a2=1.0e4), 100.0,
                         creep=cr.Creep(cr.DEFAULT_TAUS_S, (0.0075,) * len(cr.DEFAULT_TAUS_S)))


def triangle(n: int, top: float) -> np.ndarray:
    return np.interp(np.arange(n), [0, n // 2, n - 1], [0.0, top, 0.0])


def test_the_twin_is_one_simulation_of_the_sweeps_the_holds_and_the_runs() -> None:
    """Two sweeps 0.3 s apart, then a run 1.7 s later: the twin's state at the run's start, and
    after it, are those of one simulation of the whole record with the holds as held samples."""
    m = creeping()
    a, b, run = triangle(1000, 120.0), triangle(600, 80.0), 30.0 + triangle(400, 40.0)
    t_a, hold_ab, hold_br = 5.0, 0.3, 1.7
    sweeps = [sweepfile.from_arrays(v, np.zeros(v.size), RATE, {"started_s": f"{t:.6f}"})
              for v, t in ((a, t_a), (b, t_a + a.size / RATE + hold_ab))]
    assert sweepfile.holds_s(sweeps)[1] == pytest.approx(hold_ab, abs=1e-9)
    tw = twin.from_sweeps(m, sweeps)
    assert tw is not None
    start = tw.ended_s + hold_br
    whole = np.concatenate((a, np.full(int(round(hold_ab * RATE)), a[-1]), b,
                            np.full(int(round(hold_br * RATE)), b[-1]), run))
    cm = tr.compile_model(m, 1 / RATE)
    u, _, end = tr.simulate(cm, whole, tr.initial(m, voltage_v=0.0))
    at_run = tr.simulate(cm, run[:1], tw.at(start))[0][0]
    assert at_run == pytest.approx(u[-run.size], abs=1e-9)
    after = tw.after(run, start)
    np.testing.assert_allclose(after.state.creep, end.creep, rtol=0, atol=1e-10)
    assert after.ended_s == pytest.approx(start + run.size / RATE)
    assert after.held_v == run[-1]
    rest = tr.simulate(cm, run[:1], tr.initial(m, voltage_v=run[0]))[0][0]
    assert abs(rest - at_run) > 0.05  # at rest the model would start the run elsewhere


@pytest.mark.parametrize("second", [None, "-1.0", "1e9"])
def test_without_the_holds_there_is_no_twin(second: str | None) -> None:
    """A sweep without ``started_s``, one that starts before the last ended, or one an
    afternoon later: no hold is known, no twin (and the fit starts that sweep's creep at
    rest)."""
    v = triangle(400, 100.0)
    meta = [{"started_s": "0.0"}, {} if second is None else {"started_s": second}]
    sweeps = [sweepfile.from_arrays(v, np.zeros(v.size), RATE, mt) for mt in meta]
    assert math.isnan(sweepfile.holds_s(sweeps)[1])
    assert twin.from_sweeps(creeping(), sweeps) is None


def test_a_recorded_sweep_says_when_it_started_on_the_stages_clock(tmp_path: Path) -> None:
    """``started_s`` of two sweeps recorded on an in-process stage with a clock that steps
    per call: the device times their runs began, written to the files and read back; the
    hold between them is what the clock ran between the runs."""
    prof = default_profile()
    ticks = iter(np.arange(0.0, 1e4, 0.01))
    with InProcessStage(prof, clock=lambda: float(next(ticks))) as stage:
        v = triangle(int(0.2 * prof.sample_rate_hz), 50.0)
        got = []
        for k in range(2):
            path = tmp_path / f"s{k}.csv"
            runner.record_sweep(stage, f"s{k}", 5.0, v, prof.sample_rate_hz, path=path,
                                settle_s=0.0)
            got.append(sweepfile.read(path))
            assert got[-1].started_s == pytest.approx(stage.run_started_s)
    hold = sweepfile.holds_s(got)[1]
    assert 0.0 < hold < 1.0
    assert got[1].started_s > got[0].started_s + v.size / prof.sample_rate_hz


def test_a_drifting_frame_is_read_from_the_readings_and_planned_in() -> None:
    """A stage that moves as the model does but whose readings drift 20 nm/s (plus 5 nm of
    noise): four sweeps and every run's readings tell the twin; the third run, 60 s after the
    sweeps, planned in the frame the twin reads, is on its trajectory to the noise, where planned
    in the model's own frame it is off by the drift since (about 1.3 um)."""
    from afmctl.files.profile import default_profile
    from afmctl.planning import track

    m, rate_um_s, dt = creeping(), 0.02, 1 / RATE
    cm = tr.compile_model(m, dt)
    rng = np.random.default_rng(11)

    def read(v: np.ndarray, t0: float, state: tr.StageState) -> tuple[np.ndarray, tr.StageState]:
        u, _, end = tr.simulate(cm, v, state)
        drift = rate_um_s * (t0 + dt * np.arange(v.size))
        return u + drift + 0.005 * rng.standard_normal(v.size), end

    sweeps, state, t = [], tr.initial(m, voltage_v=0.0), 1.0
    for top in (120.0, 90.0, 120.0, 60.0):
        v = triangle(1000, top)
        y, state = read(v, t, state)
        sweeps.append(sweepfile.from_arrays(v, y, RATE, {"started_s": f"{t:.6f}"}))
        t += v.size * dt  # each sweep right after the one before
    tw = twin.from_sweeps(m, sweeps)
    assert tw is not None
    prof = default_profile()
    desired = track.triangle(2.0, 30.0, 50.0, 3.0, dt)
    errors = {}
    for frame in (True, False):
        tw_k, held = tw, 0.0
        for k in range(3):
            start = tw_k.ended_s + 20.0
            wf = track.plan(m, desired, prof.limits, held, ("inverse",), state=tw_k.at(start),
                            frame=tw_k.frame(start) if frame else fr.Frame())["inverse"]
            y, _ = read(wf.voltage_v, start, tw_k.at(start))
            tw_k, held = tw_k.after(wf.voltage_v, start, readings_um=y), float(wf.voltage_v[-1])
        np.testing.assert_array_equal(wf.desired_um[wf.tracking], desired.u_um)
        errors[frame] = float(np.sqrt(np.mean((y[wf.tracking] - desired.u_um) ** 2)))
    assert tw_k.frame(tw_k.ended_s).um_per_s == pytest.approx(rate_um_s, rel=0.05)
    assert errors[False] > 1.0
    assert errors[True] < 0.02


def test_a_held_stage_is_read_where_it_holds(tmp_path: Path) -> None:
    """:func:`runner.read_held` on an emulated stage, two minutes after its sweeps and a move to
    20 V, through a twin whose model reads 0.5 um above the plant (the rod's offset): a run that
    moves nothing (20 V held throughout, written to its run file), one more on the device's
    counter, and the twin's ``read`` at the time of the reading with the readings less the
    model, -0.5 um within the noise; the next run's frame is anchored on it. A twin whose held
    output is not the stage's is refused before anything plays."""
    import dataclasses as dc

    from afmctl.files import runfile
    from afmctl.planning import track
    prof = default_profile()
    plant = prof.emulator.plant_model  # type: ignore[union-attr]
    model = dc.replace(plant, rod=dc.replace(plant.rod, offset_um=plant.rod.offset_um + 0.5))
    clock = {"t": 100.0}

    def tick() -> float:  # the device's time runs 10 ms per call (the runs play)
        clock["t"] += 0.01
        return clock["t"]

    with InProcessStage(prof, clock=tick) as stage:
        sweeps = []
        for top in (120.0, 60.0):
            v = triangle(int(0.2 * prof.sample_rate_hz), top)
            sweeps.append(runner.record_sweep(stage, "s", 5.0, v, prof.sample_rate_hz,
                                              settle_s=0.0))
        tw = twin.from_sweeps(model, sweeps)
        assert tw is not None and len(tw.observations) == 2 and tw.read is None
        move = track.raised_cosine(0.0, 20.0, 400)
        rec = stage.play(move)
        tw = tw.after(move, rec.started_s, rec.run_count, rec.displacement_um)
        clock["t"] += 120.0
        with pytest.raises(ValueError, match="holds 20.0000 V"):
            runner.read_held(stage, dc.replace(tw, held_v=0.0), tmp_path / "no.csv", {})
        assert not (tmp_path / "no.csv").exists()
        read = runner.read_held(stage, tw, tmp_path / "read.csv", {"what": "a test"})
        assert stage.voltage() == 20.0 and stage.run_count == tw.run_count + 1
    run = runfile.read(tmp_path / "read.csv")
    assert run.complete and np.all(run.voltage_v == 20.0)
    assert read.observations == tw.observations and read.run_count == tw.run_count + 1
    ob = read.read
    assert ob is not None and ob.at_s > tw.ended_s + 120.0
    noise = prof.emulator.noise_um  # type: ignore[union-attr]
    assert ob.offset_um == pytest.approx(-0.5, abs=5 * noise / np.sqrt(1000))
    assert read.planning_frame(ob.at_s + 0.2).offset_um == pytest.approx(ob.offset_um, abs=1e-3)
    assert read.held_v == 20.0 and read.ended_s > ob.at_s


class _Clock:
    """A stage's clock that planning moves on (s)."""

    def __init__(self) -> None:
        self.t = 100.0

    def now_s(self) -> float:
        return self.t


class _Moving:
    """A twin whose frame drifts ``rate`` um/s: what each plan was given is kept."""

    def __init__(self, rate: float) -> None:
        self.rate = rate

    def at(self, when_s: float) -> float:
        return when_s

    def planning_frame(self, when_s: float) -> fr.Frame:
        return fr.Frame(self.rate * when_s, self.rate, "test")


@pytest.mark.parametrize(("rate", "plans"), [(0.01, 2), (0.0, 1), (0.001, 1)])
def test_a_plan_that_outlasts_its_time_in_a_moving_frame_is_made_again(rate: float,
                                                                        plans: int) -> None:
    """The first plan of a run is given :data:`runner.LEAD_S` and takes 2 s: in a frame moving
    10 nm/s it would start 0.019 um off, and is made again for a start 2 s after its own
    beginning (plus the start's delay), its duration then what it took; in a frame that does not
    move, or moves under :data:`runner.REPLAN_UM` meanwhile (1 nm/s), the first plan stands."""
    clock, asked = _Clock(), []

    def plan_for(name: str, state: float, frame: fr.Frame) -> str:
        asked.append((state, frame.offset_um))
        clock.t += 2.0
        return name

    wf, took = runner._planned(clock, _Moving(rate), plan_for, "inverse", 0.0, 0.3)
    assert wf == "inverse" and len(asked) == plans and took == pytest.approx(2.0)
    assert asked[0][0] == pytest.approx(100.3)
    if plans == 2:  # begun at 102 s, for a start 2 s + 0.3 s after: where the run will be
        assert asked[1] == (pytest.approx(104.3), pytest.approx(rate * 104.3))
