"""Viscous relaxation of the switching (:mod:`afmctl.model.viscous`) in the forward model and
through Algorithm 3: its step response in closed form, its two limits (a lag far shorter than
the sweep is the paper's model; one far longer freezes the hysterons), the inverse's round trip
and the state it keeps, and the model file."""

from __future__ import annotations

import dataclasses as dc
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import sawtooth

from afmctl.files import modelfile
from afmctl.model import hysteresis as hy
from afmctl.model import inverse as inv
from afmctl.model import rod as rd
from afmctl.model import transducer as tr
from afmctl.model import viscous as vs

DT = 1e-4


def triangle(freq: float, amp_um: float, periods: float) -> np.ndarray:
    t = np.arange(1, int(round(periods / freq / DT)) + 1) * DT
    return 0.5 * amp_um * sawtooth(2 * np.pi * freq * t + np.pi / 2, 0.5)


def test_lag_of_a_step_is_the_exponential_one_sample_late() -> None:
    """From rest at 0, a step to 1 at sample 0: the hysterons see ``1 - exp(-k dt / tau)`` at
    sample ``k`` (the continuous lag sampled at each sample's start), and the next call starts
    where this one ended."""
    tau = 2.5e-3
    e = np.ones(40)
    got, end = vs.lagged(vs.Viscous(tau), e, DT, 0.0)
    k = np.arange(40)
    np.testing.assert_allclose(got, 1 - np.exp(-k * DT / tau), rtol=1e-12, atol=1e-15)
    assert end == pytest.approx(1 - math.exp(-40 * DT / tau), rel=1e-12)
    more, _ = vs.lagged(vs.Viscous(tau), np.ones(5), DT, end)
    np.testing.assert_allclose(more, 1 - np.exp(-(40 + np.arange(5)) * DT / tau), rtol=1e-12)


def test_a_relaxation_time_must_be_positive() -> None:
    for bad in (0.0, -1e-3, math.nan, math.inf):
        with pytest.raises(ValueError, match="relaxation time"):
            vs.Viscous(bad)


def test_viscous_relaxation_needs_the_papers_polarization(nominal: tr.Transducer) -> None:
    from afmctl.model.preisach import PreisachGrid

    grid = PreisachGrid(coercive=(0.0, 0.1), interaction=(-0.1, 0.1), spread=0.01,
                        reversible=0.01, weights=((0.0, 0.1), (0.1, 0.0)))
    with pytest.raises(ValueError, match="viscous relaxation needs"):
        dc.replace(nominal, polarization=grid, viscous=vs.Viscous(1e-3))


def _polarization(model: tr.Transducer, v: np.ndarray) -> np.ndarray:
    cm = tr.compile_model(model, DT)
    return tr.polarization(cm, v, tr.initial(model, voltage_v=float(v[0])))[0]


def test_a_short_lag_is_the_papers_model_and_a_long_one_freezes_the_hysterons(
        nominal: tr.Transducer) -> None:
    """On a 0.5 Hz triangle over +-150 V: with tau = 1e-10 s the polarization is (13)'s with the
    field a sample late (equal to round-off); with tau = 1000 s the hysterons keep their start and
    ``P`` is the start's plus the reversible slope times the field's change: a line, where the
    paper's model has its loop."""
    v = 150.0 * triangle(0.5, 2.0, 1.0)
    paper = _polarization(nominal, v)
    short = _polarization(dc.replace(nominal, viscous=vs.Viscous(1e-10)), v)
    late, _ = hy.run(nominal.polarization, np.concatenate(([v[0]], v[:-1])) / nominal.thickness_um,
                     tr.initial(nominal, voltage_v=float(v[0])).polarization)
    lam = tr.reversible_slope(hy.build_kernel(nominal.polarization))
    np.testing.assert_allclose(short, late + lam * (v - np.concatenate(([v[0]], v[:-1])))
                               / nominal.thickness_um, atol=1e-12)
    assert np.max(np.abs(short - paper)) < 0.05 * np.ptp(paper)  # a sample late only
    frozen = _polarization(dc.replace(nominal, viscous=vs.Viscous(1e3)), v)
    np.testing.assert_allclose(frozen, frozen[0] + lam * (v - v[0]) / nominal.thickness_um,
                               rtol=0, atol=1e-6 * np.ptp(paper))
    line = np.polyval(np.polyfit(v, paper, 1), v)
    assert np.max(np.abs(paper - line)) > 1e3 * np.max(np.abs(frozen - frozen[0] - lam * (
        v - v[0]) / nominal.thickness_um))


def test_the_loop_depends_on_the_rate(nominal: tr.Transducer) -> None:
    """A 2.5 ms lag barely moves a 0.5 Hz loop but changes a 50 Hz one: at the middle voltage
    the two branches part by the paper's model's opening within 5 % at 0.5 Hz, and by a third
    less at 50 Hz (the hysterons see a smaller field, a phase later: a minor loop)."""
    model = dc.replace(nominal, viscous=vs.Viscous(2.5e-3))

    def opening(m: tr.Transducer, freq: float) -> float:
        t = np.arange(int(round(2 / freq / DT))) * DT
        v = 150.0 * np.sin(2 * np.pi * freq * t)
        p = _polarization(m, v)[t >= 1 / freq]  # the second period
        mid = np.abs(v[t >= 1 / freq]) < 5.0
        rising = np.gradient(v[t >= 1 / freq]) > 0
        return float(np.mean(p[mid & rising]) - np.mean(p[mid & ~rising]))

    slow = opening(model, 0.5) / opening(nominal, 0.5)
    fast = opening(model, 50.0) / opening(nominal, 50.0)
    assert abs(slow - 1) < 0.05 and fast < 0.8, (slow, fast)


@pytest.mark.parametrize("tau", [3e-4, 2.5e-3, 1e-2])
def test_algorithm3_inverts_through_the_lag(nominal: tr.Transducer, tau: float) -> None:
    """Round trip: the fields Algorithm 3 finds through the lag drive the forward model onto a
    0.279 Hz triangle to 1e-6 um, and onto a 27.9 Hz one (with the smooth horizon) to 0.5 % of
    its amplitude without chatter; the same fields on the model without the lag miss more."""
    model = dc.replace(nominal, viscous=vs.Viscous(tau))
    cm = tr.compile_model(model, DT)
    for freq, amp, horizon in ((0.279, 40.56, 1), (27.9, 27.04, rd.smooth_horizon(cm.disc))):
        ud = triangle(freq, amp, 2)
        res = inv.algorithm3(cm, ud, tr.initial(model), horizon=horizon, e_max=1.5)
        u, _, _ = tr.simulate(cm, res.voltage(model.thickness_um), tr.initial(model))
        np.testing.assert_allclose(u, res.predicted, atol=1e-9)
        period = int(1 / freq / DT)
        err = (u[1:] - ud[:-1])[period:]
        v = res.voltage(model.thickness_um)[period:]
        if freq < 1:
            assert np.max(np.abs(err)) < 1e-6
        else:
            assert np.sqrt(np.mean(err ** 2)) < 0.005 * amp
            assert np.mean(np.diff(np.sign(np.diff(v))) != 0) < 0.2
        u0, _, _ = tr.simulate(tr.compile_model(nominal, DT), res.voltage(model.thickness_um),
                               tr.initial(nominal))
        assert np.sqrt(np.mean(((u0[1:] - ud[:-1])[period:]) ** 2)) > 2 * np.sqrt(
            np.mean(err ** 2)) + 1e-3


def test_algorithm3_keeps_the_lag_simulate_reaches(nominal: tr.Transducer) -> None:
    model = dc.replace(nominal, viscous=vs.Viscous(2.5e-3))
    cm = tr.compile_model(model, DT)
    ud = triangle(27.9, 27.04, 1.5)
    st0 = tr.initial(model)
    res = inv.algorithm3(cm, ud, st0, horizon=2, e_max=1.5, keep=400)
    _, _, want = tr.simulate(cm, res.voltage(model.thickness_um)[:400], st0)
    np.testing.assert_allclose(res.kept.lag, want.lag, atol=1e-12)
    np.testing.assert_allclose(res.kept.polarization.values, want.polarization.values,
                               atol=1e-12)
    np.testing.assert_allclose(res.kept.rod, want.rod, rtol=1e-9, atol=1e-18)
    assert res.kept.lag.size == 1 and st0.lag.size == 1


def test_model_file_round_trip(nominal: tr.Transducer, tmp_path: Path) -> None:
    model = dc.replace(nominal, viscous=vs.Viscous(2.57e-3))
    path = tmp_path / "model.toml"
    modelfile.write(model, path)
    text = path.read_text()
    assert "[polarization.viscous]" in text and "relaxation_time_s" in text
    assert "format_version = 3" in text
    assert modelfile.read(path) == model
    path.write_text(text.replace("format_version = 3", "format_version = 2"))
    with pytest.raises(Exception, match="viscous relaxation needs version 3"):
        modelfile.read(path)
    path.write_text(text.replace("relaxation_time_s = 0.00257", "relaxation_time_s = -1.0"))
    with pytest.raises(Exception, match="relaxation_time_s"):
        modelfile.read(path)


def test_every_state_at_rest_carries_the_lag(nominal: tr.Transducer) -> None:
    """A stage at rest under a field has its hysterons there too, however the state was made
    (the model's initial state, the one a sweep that carries on from the last starts in), so
    the forward model and the inverse start the lag at the same field."""
    from afmctl.fit import prediction

    model = dc.replace(nominal, viscous=vs.Viscous(2.5e-3))
    st = tr.initial(model, voltage_v=60.0)
    assert st.lag.tolist() == [60.0 / model.thickness_um]
    after = prediction.start_state(model, "previous", 90.0, st.polarization)
    assert after.lag.tolist() == [90.0 / model.thickness_um]
    assert tr.initial(nominal, voltage_v=60.0).lag.size == 0
    cm = tr.compile_model(model, DT)
    ud = 20.0 + triangle(27.9, 10.0, 1.0)
    res = inv.algorithm3(cm, ud, after, e_init=90.0 / model.thickness_um, horizon=2, e_max=1.5)
    u, _, _ = tr.simulate(cm, res.voltage(model.thickness_um), after)
    np.testing.assert_allclose(u, res.predicted, atol=1e-9)
