"""Independent fits side by side on threads (:mod:`afmctl.fit.cores`): the results are those of
the fits one after another, to the last bit."""

from __future__ import annotations

import multiprocessing as mp
import signal
import threading
import time

import numpy as np
import pytest

from afmctl.files import sweepfile as sw
from afmctl.fit import cores
from afmctl.fit import identify as idf
from afmctl.fit import noise as ns
from afmctl.fit import preisach as pf
from afmctl.model import preisach as pr
from tests.harness.preisach_plant import PreisachStage, standard_sweeps


def cores_here(monkeypatch: pytest.MonkeyPatch, n: int) -> None:
    """This process may use ``n`` cores, whatever the machine's (threads run side by side on one
    core too): what :func:`cores.workers` reads."""
    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda _pid: set(range(n)))


@pytest.fixture
def two(monkeypatch: pytest.MonkeyPatch) -> None:
    cores_here(monkeypatch, 2)


def test_together_returns_every_result_in_the_calls_order(two: None) -> None:
    seen: list[str] = []

    def call(i: int) -> int:
        time.sleep(0.02 * (5 - i))  # the first calls end last
        seen.append(threading.current_thread().name)
        return i * i

    assert cores.together([lambda i=i: call(i) for i in range(5)]) == [0, 1, 4, 9, 16]
    assert len(set(seen)) == 2  # the caller's thread and one other


def test_at_most_two_run_at_once_and_one_core_runs_them_in_turn(
        monkeypatch: pytest.MonkeyPatch) -> None:
    cores_here(monkeypatch, 8)
    assert cores.workers() == cores.MAX_WORKERS == 2
    cores_here(monkeypatch, 1)
    names = cores.together([lambda: threading.current_thread().name] * 3)
    assert cores.workers() == 1 and set(names) == {threading.current_thread().name}


def test_an_error_is_raised_after_every_other_call_has_ended(two: None) -> None:
    ended: list[int] = []

    def fails(what: str) -> int:
        time.sleep(0.02 if what == "first" else 0.0)  # the first in order fails last
        raise ValueError(f"bad sweep: {what}")

    def slow(i: int) -> int:
        time.sleep(0.05)
        ended.append(i)
        return i

    with pytest.raises(ValueError, match="bad sweep: first"):
        cores.together([lambda: slow(0), lambda: fails("first"), lambda: slow(2),
                        lambda: fails("second"), lambda: slow(4)])
    assert sorted(ended) == [0, 2, 4]


def test_calls_inside_a_call_run_one_after_another(two: None) -> None:
    inner = cores.together([lambda: cores.workers(), lambda: cores.workers()])
    assert inner == [1, 1] and cores.workers() == 2


def test_a_pool_worker_ignores_ctrl_c_and_runs_its_calls_alone() -> None:
    with mp.get_context("fork").Pool(1, cores.pool_worker) as pool:
        handler, workers = pool.apply(_worker_state)
    assert handler == signal.SIG_IGN and workers == 1


def _worker_state() -> tuple[object, int]:
    return signal.getsignal(signal.SIGINT), cores.workers()


def _fit(monkeypatch: pytest.MonkeyPatch, workers: int) -> pf.PreisachFit:
    cores_here(monkeypatch, workers)
    sweeps = standard_sweeps(PreisachStage(seed=3, creep_per_element=0.0075))
    data = pf.Data([s.voltage_v / 100.0 for s in sweeps], [s.mask(None) for s in sweeps],
                   [s.displacement_um[s.mask(None)] for s in sweeps], [s.dt for s in sweeps],
                   np.array([ns.sensor_noise_um(s.displacement_um) for s in sweeps]))
    return pf.fit(data, [("positive",) * 3, ("depoled", "previous", "previous")],
                  (1000.0, 0.3), 100.0, 0.05)


@pytest.mark.slow
def test_the_grid_fitted_side_by_side_is_the_grid_fitted_alone(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A creeping stage of the independently written plant; the creep fit is retried from the
    runner-up start assignment (its threshold lowered so the retry runs), whose first steps were
    taken side by side with the best's; the held-out errors of three runs are judged side by
    side."""
    monkeypatch.setattr(pf, "RETRY_ABOVE", 0.5)
    retried: list[bool] = []
    real = pf._retried

    def spy(*args: object, **kwargs: object) -> object:
        retried.append(True)
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(pf, "_retried", spy)
    want, got = _fit(monkeypatch, 1), _fit(monkeypatch, 2)
    assert retried == [True, True]  # the retry runs on one core and on two
    assert got.starts == want.starts and got.creep == want.creep
    assert got.candidates == want.candidates  # every run's held-out score
    np.testing.assert_array_equal(got.heldout_rms_um, want.heldout_rms_um)
    np.testing.assert_array_equal(got.offsets, want.offsets)
    g, w = got.model.polarization, want.model.polarization
    assert isinstance(g, pr.PreisachGrid) and isinstance(w, pr.PreisachGrid)
    np.testing.assert_array_equal(g.matrix, w.matrix)
    assert got.model.creep == want.model.creep and got.model.rod == want.model.rod


@pytest.mark.slow
def test_a_runner_up_is_fitted_only_when_its_retry_is_asked_for(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Without a retry, the runner-up start assignment's fits are not run at all, on two cores
    either (beside the best's they slowed it by about a fifth): every fit without creep is the
    best's."""
    cores_here(monkeypatch, 2)
    starts: list[tuple[str, ...]] = []
    real = pf._plain

    def spy(prob: object, *args: object) -> object:
        starts.append(prob.starts)  # type: ignore[attr-defined]
        return real(prob, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(pf, "_plain", spy)
    monkeypatch.setattr(pf, "RETRY_ABOVE", 1e9)
    got = _fit(monkeypatch, 2)
    assert len(set(starts)) == 1 and got.starts == starts[0]


def test_the_papers_model_fitted_with_its_differences_side_by_side_is_the_same(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """identify's least-squares solve evaluates its finite differences side by side: the same
    solution, to the last bit."""
    from afmctl.planning.sweepdesign import voltage_triangle

    true = idf.pz.to_model(np.array([1.0, 0.4, 0.3, 0.36, 250.0, 0.25]),
                           np.array([10.0, 0.5, 0.0]), idf.pz.Scales(), 100.0)
    v = voltage_triangle(27.9, 150.0, 3, 5000.0)
    rng = np.random.default_rng(4)
    s = sw.from_arrays(v, idf.predict(true, v, 2e-4) + rng.normal(0, 0.01, v.size), 5000.0,
                       {"layer_thickness_um": "100"})
    fits = []
    for workers in (1, 2):
        cores_here(monkeypatch, workers)
        fits.append(idf.fit([s]))
    np.testing.assert_array_equal(fits[0].x, fits[1].x)
    assert fits[0].nfev == fits[1].nfev
