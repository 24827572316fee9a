"""Learning on stages written independently of afmctl's model (issue 23, items 3 and 5): a
Preisach stage whose frame drifts (a learned waveform replayed a minute later, re-learned) and
a Bouc-Wen stage (no wiping-out: the plant seen through the inverse is not what iteration 0
measured once the waveform moves).

The stages are the benches' (:mod:`benchmarks.family_sets`: the emulated device with
``[emulator.family]``, :mod:`afmctl.drivers.device.foreign.family_stage`, reached through the
driver in-process on a stepped device clock), judged by their true position. The models are
``afmctl.fit.identify.fit``'s (default settings) on each stage's standard triangles, as the
benches fit them, kept in ``data/`` (identify takes 6-16 minutes a stage on this machine):
``family-<stage>.toml``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from afmctl.experiment import learn
from afmctl.files import modelfile
from afmctl.model import frame as fr
from afmctl.model import transducer as tr
from afmctl.planning import ilc, track
from benchmarks import family_sets, learn_judge

DATA = Path(__file__).parent / "data"
#: The triangle the bench learns (27.9 Hz, 3 periods), its amplitude and centre on each stage
#: (bench_learn: 27.04 um about the middle of the fast sweep's span, um).
TRIANGLE = {"preisach-u-drift": (27.04, 46.5), "bw-b": (27.04, -0.4)}


class Timed(family_sets.Probe):
    """The benches' probe, also keeping the device time each run starts at (s)."""

    def __init__(self, probe: family_sets.Probe, clock: family_sets.SteppedClock) -> None:
        super().__init__(probe.stage)
        self.clock, self.starts = clock, []

    def play(self, waveform_v: np.ndarray, on_block: Any = None, **kw: Any) -> Any:
        self.starts.append(self.clock.now)
        return super().play(waveform_v, on_block, **kw)


def true_rms(probe: family_sets.Probe, first: int, res: learn.Result,
             desired: track.Desired) -> list[float]:
    return [learn_judge.true_rms(probe.positions[first + i], it, desired)
            for i, it in enumerate(res.iterations)]


@contextlib.contextmanager
def learned_on(name: str, model_file: str, tmp: Path) -> Iterator[tuple[Any, Timed, Any,
                                                                        track.Desired,
                                                                        learn.Result]]:
    """Stage ``name``'s session, its timed probe, the model ``data/model_file``, the bench's
    27.9 Hz triangle and learning's result there (5 iterations), inside the session."""
    model = modelfile.read(DATA / model_file)
    amp, centre = TRIANGLE[name]
    with family_sets.session(family_sets.cases_named(name)[0]) as s:
        probe = Timed(s.probe, s.clock)
        desired = track.triangle(27.9, amp, centre, 3, 1 / s.profile.sample_rate_hz)
        res = learn.run(probe, model, desired, s.profile.limits, tmp / "learn", {}, 5,
                        ilc.Law())
        yield s, probe, model, desired, res


def test_a_drifting_stage_replayed_a_minute_later_is_relearned_in_two_iterations(
        tmp_path: Path) -> None:
    """A Preisach stage (non-separable density) whose frame drifts 18.5 nm/s (noise 15 nm).
    Learning reaches the noise (the slow offset of each run measured on the conditioning and
    its trend predicted: it neither chases nor diverges; measured: 0.85 -> 0.060 -> 0.014 ->
    0.009 um, 0.6 x the noise; before this change learning chased the drift and stayed one
    run's drift, 16 nm, off: 1.25-1.33 x from iteration 2 on). A minute later the kept waveform, replayed as it was, is 1.13 um off (73 x the
    noise: the frame moved, and no waveform learned before can know where to): the replay says
    how far the stage moved (its offset against the kept run's conditioning: 1.127 um, within
    5 % of the drift rate times the device time between the two runs), and two re-learned
    iterations bring it back within 2 x the noise (1.130 -> 0.055 -> 0.027 um). Before this
    change there was no re-learning replay (the bench replayed the waveform as it was: 75 x);
    a first version, which let the replay's offset-free error count as its best, halved its
    step from there and ended at 3.3 x."""
    with learned_on("preisach-u-drift", "family-preisach-u-drift.toml", tmp_path) as (
            s, probe, model, desired, res):
        learned = true_rms(probe, 0, res, desired)
        kept_at = probe.starts[res.best]
        s.clock.skip(60.0)
        first = len(probe.positions)
        rep = learn.run(probe, model, desired, s.profile.limits, tmp_path / "replay", {}, 2,
                        ilc.Law(), resume=learn.Resume.kept(res))
        again = true_rms(probe, first, rep, desired)
        moved = s.truth.drift_um_per_s * (probe.starts[first] - kept_at)
    noise = s.noise_um
    assert not res.stop.startswith("diverging"), res.stop
    assert learned[res.best] <= noise, learned  # not a run's drift off
    assert again[0] > 20 * noise  # the stage had moved on: the replay as it was is far off
    assert rep.iterations[0].offset_um == pytest.approx(moved, rel=0.05)
    assert len(again) <= 3 and again[rep.best] <= 2 * noise, again


def test_a_drift_read_before_learning_is_followed_from_iteration_1(tmp_path: Path) -> None:
    """The drifting stage (18.5 nm/s) learning in a frame that knows the drift rate (as the
    twin's read before learning gives it): iteration 1 is planned for the drift over the
    device time between the two runs' starts (before this change for none: one run's drift,
    whatever the frame said), and learning still ends at the noise."""
    model = modelfile.read(DATA / "family-preisach-u-drift.toml")
    amp, centre = TRIANGLE["preisach-u-drift"]
    with family_sets.session(family_sets.cases_named("preisach-u-drift")[0]) as s:
        probe = Timed(s.probe, s.clock)
        desired = track.triangle(27.9, amp, centre, 3, 1 / s.profile.sample_rate_hz)
        rate = s.truth.drift_um_per_s
        res = learn.run(probe, model, desired, s.profile.limits, tmp_path, {}, 3, ilc.Law(),
                        start=(tr.initial(model), fr.Frame(0.0, rate, "test")))
        learned = true_rms(probe, 0, res, desired)
    between = probe.starts[1] - probe.starts[0]
    assert res.iterations[1].predicted_offset_um == pytest.approx(rate * between, rel=0.1)
    assert min(learned) <= s.noise_um, learned


def test_a_stage_that_does_not_forget_has_its_offset_measured_on_the_tracking_part(
        tmp_path: Path) -> None:
    """The bipolar Bouc-Wen stage ``bw-b`` (no wiping-out; its model ``family-bw-b.toml`` is
    identify's Bouc-Wen on its reversal set). The conditioning excursion does not erase what came
    before, so two runs read differently on it: their difference left 0.37 um unexplained by a
    gain and an offset (the noise of two runs is 0.017 um), and the "offset" it gave, -1.21 um
    where the tracking parts were 0.03 um apart, shifted the next run for a drift that was not
    there (0.029 -> 1.89 um). The run's offset is now the tracking part's, and learning does
    not jump."""
    case = family_sets.cases_named("bw-b")[0]
    model = modelfile.read(DATA / f"family-{case.name}.toml")
    amp, centre = TRIANGLE[case.name]
    with family_sets.session(case) as s:
        desired = track.triangle(27.9, amp, centre, 3, 1 / s.profile.sample_rate_hz)
        res = learn.run(s.probe, model, desired, s.profile.limits, tmp_path, {}, 2, ilc.Law())
        rms = true_rms(s.probe, 0, res, desired)
    later = res.iterations[1:]
    assert later and all(it.offset_from == "tracking" for it in later)
    assert all(abs(it.offset_um) < 5 * s.noise_um for it in later)
    assert max(rms) < 2 * rms[0], rms  # measured before: 0.021 -> 0.029 -> 1.89 um


@pytest.mark.parametrize("idle_s", [60.0, 300.0])
def test_a_drifting_stage_replayed_a_minute_later_is_moved_for_the_drift_in_one_run(
        tmp_path: Path, idle_s: float) -> None:
    """The drifting Preisach stage again (18.5 nm/s, noise 15 nm), its kept waveform played a
    minute later as ``afmctl play --model`` plays it (:func:`afmctl.experiment.replay.
    moved_replay`): the conditioning first, whose last 0.1 s against the kept run's tell how far
    the stage has moved; then the rest, the voltages that move the model by as much added. The
    move read is the drift since the kept run (within 3 %), and the trajectory is within 2x the
    noise, where the kept voltages played as they were are 73x off (the test above). The model
    is identify's on the stage's reversal set (as bench_identify fits it): the
    move goes through its minor loops, and the fit on the triangles alone misses 3.4 % of it
    (0.052 um, 3.3x the noise). Five minutes later (a 5.6 um move) too: 1.29x, where the move's
    voltages scaled from a plan at 1 um made it 7.4x, and from plans at 1 and 4 um 2.2x."""
    with learned_on("preisach-u-drift", "family-preisach-u-drift-reversals.toml", tmp_path) as (
            s, probe, model, desired, res):
        s.clock.skip(idle_s)
        got = learn.replayed_moved(probe, model, desired, s.profile.limits, res,
                                   (tmp_path / "a.csv", tmp_path / "b.csv"))
        true = probe.positions[-1][got.waveform.tracking] - desired.u_um
        drifted = s.truth.drift_um_per_s * (probe.starts[-2] - probe.starts[res.best])
    rms = float(np.sqrt(np.mean(true[ilc.steady_part(desired)] ** 2)))
    assert got.moved and got.move_um is not None
    assert got.move_um == pytest.approx(drifted, rel=0.03), (got.move_um, drifted)
    assert rms <= 2 * s.noise_um, (rms, s.noise_um, float(np.mean(true)))


def test_a_stage_that_does_not_forget_is_replayed_as_learned_after_another_history(
        tmp_path: Path) -> None:
    """``bw-b`` (Bouc-Wen: no wiping-out) swung to its lower rail and back between learning and
    the replay: the conditioning's readings then differ from the learned run's by its history
    (0.70 um RMS beyond an offset and a trend, against the noise's 0.012 um), the move they
    would give (-0.10 um) is not a move, and the rest plays as learned (1.79x the noise; moved
    for it: 6.9x, a reviewer's measurement). With nothing played between, it is moved."""
    from afmctl.experiment import replay
    from afmctl.experiment import runner as experiment

    case = family_sets.cases_named("bw-b")[0]
    model = modelfile.read(DATA / f"family-{case.name}.toml")
    amp, centre = TRIANGLE[case.name]
    with family_sets.session(case) as s:
        dt, lim = 1 / s.profile.sample_rate_hz, s.profile.limits
        desired = track.triangle(27.9, amp, centre, 3, dt)
        res = learn.run(s.probe, model, desired, lim, tmp_path / "learn", {}, 5, ilc.Law())

        def replayed(k: int) -> replay.Moved:
            return learn.replayed_moved(s.probe, model, desired, lim, res,
                                        (tmp_path / f"c{k}.csv", tmp_path / f"r{k}.csv"))

        same = replayed(0)
        swing = np.concatenate([np.linspace(0.0, lim.v_min, 4000), np.full(2000, lim.v_min),
                                np.linspace(lim.v_min, 0.0, 4000), np.zeros(2000)])
        experiment.stream(s.probe, track.Waveform("swing", dt, swing, np.full(swing.size, np.nan),
                                                  slice(0, 0)), tmp_path / "swing.csv", {})
        other = replayed(1)
    assert same.moved
    assert not other.moved and "past differs" in other.why, other.why
