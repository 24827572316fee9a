import numpy as np
import pytest

from afmctl.files import sweepfile as sw
from afmctl.fit import density as dn
from afmctl.fit import identify as idf
from afmctl.fit import parametrization as pz
from afmctl.model.transducer import Transducer
from afmctl.planning import sweepdesign as sd
from tests.harness.emulated import NOISE_UM, SAMPLE_RATE_HZ


def test_fit_approximations_are_well_below_noise(true_model: Transducer) -> None:
    """Decimated hysteresis (turning points kept) and the fit's coercive nodes vs the exact model."""
    v = sd.voltage_triangle(0.279, 150.0, 1, SAMPLE_RATE_HZ)
    theta = np.array([1.0, 0.4, 0.3, 0.36])
    s = sw.from_arrays(v, np.zeros_like(v), SAMPLE_RATE_HZ)
    coarse = pz.prepare(s, 100.0, idf.Settings().field_step, None)
    exact = pz.prepare(s, 100.0, 0.0, None)
    (q_fit,) = pz.hysteresis(theta, [coarse.field[coarse.keep]], idf.Settings().n_coercive_fit)
    q_fit = np.interp(np.arange(v.size), coarse.keep, q_fit)
    (q_ref,) = pz.hysteresis(theta, [exact.field], 256)
    g1 = 1e6 * true_model.rod.a1 / (true_model.rod.k * true_model.polarization.eta)
    assert g1 * np.max(np.abs(q_fit - q_ref)) < NOISE_UM / 3


def test_turning_points() -> None:
    x = np.array([0.0, 1, 2, 2, 1, 0, 1, 1])
    assert pz.turning_points(x).tolist() == [0, 3, 5, 7]  # a plateau counts at its end


def test_to_model_static_gain() -> None:
    theta = np.array([1.0, 0.4, 0.3, 0.36, 250.0, 0.25])
    m = pz.to_model(theta, np.array([10.0, 0.5, 1.0]), pz.Scales(), 100.0)
    q = 2.0
    p = q / m.polarization.eta
    u = 1e6 * (m.rod.a1 * p + m.rod.a2 * p * p) / m.rod.k
    assert u == pytest.approx(10.0 * q + 0.5 * q * q)
    assert m.rod.natural_hz == pytest.approx(250.0) and m.rod.damping_ratio == pytest.approx(0.25)


def test_decimation_keeps_turning_points_and_field_steps() -> None:
    e = np.concatenate((np.linspace(0, 1, 101), np.linspace(1, -1, 201)[1:]))
    keep = pz.decimation(e, 0.1)
    assert 100 in keep and 0 in keep and e.size - 1 in keep
    assert np.all(np.abs(np.diff(e[keep])) <= 0.1 + 0.01 + 1e-12)  # step + one sample


def test_discrete_space_reproduces_its_lognormal_start(true_model: Transducer) -> None:
    v = sd.voltage_triangle(5.58, 150.0, 1, 2000.0)
    s = sw.from_arrays(v, idf.predict(true_model, v, 5e-4), 2000.0)
    # a 40 um layer: the sweep's peak field (3.75 MV/m) reaches past the lognormal's +3 sigma_ln,
    # so the nodes (which stop at the peak field) hold all of its mass and the model's
    # hysteretic weight r, the mass on the nodes, is the lognormal's (on 100 um it is 84 % of it:
    # the hysterons that never switch are left out)
    prep = pz.prepare(s, 40.0, 0.0, None)
    theta = np.array([1.0, 0.4, 0.3, 0.36, 250.0, 0.25])
    space, x0 = dn.DiscreteSpace.around(theta, [prep], pz.Scales(), 48, 0.0, 25.7)
    lognormal = pz.LognormalSpace([prep], pz.Scales(), 256)
    a_d, a_l = space.design(x0), lognormal.design(np.log(theta))
    assert np.max(np.abs(a_d[:, 0] - a_l[:, 0])) < 0.01 * np.ptp(a_l[:, 0])
    model = space.model(x0, np.array([25.7, 0.4, 0.0]), 100.0)
    assert sum(w for w in model.polarization.coercive.nodes_weights()[1]) == pytest.approx(1.0)
    assert model.polarization.eta == pytest.approx(0.36 / 0.3, rel=2e-3)  # the quadrature's


@pytest.mark.parametrize(("fn", "zeta", "dt"), [(250.0, 0.25, 1e-4), (100.0, 1.0, 1e-3),
                                                (1000.0, 3.0, 1e-4), (5.0, 0.003, 1e-3)])
def test_closed_form_oscillator_discretization_equals_the_matrix_exponential(
        fn: float, zeta: float, dt: float) -> None:
    """Under-, critically and over-damped: the closed form against rod.discretize (expm)."""
    from afmctl.model import rod as rd
    w = 2 * np.pi * fn
    ref = rd.discretize(rd.Rod(1.0, 2 * zeta * w, w * w, 1.0), dt)
    new = pz.unit_oscillator_zoh(fn, zeta, dt)
    np.testing.assert_allclose(new.phi, ref.phi, rtol=1e-12, atol=1e-14 * np.abs(ref.phi).max())
    np.testing.assert_allclose(new.gamma, ref.gamma, rtol=1e-12)


@pytest.mark.parametrize(("starts", "initial"), [(("positive", "previous"), "positive"),
                                                 (("negative",), "negative"),
                                                 (("previous",), "depoled"), ((), "depoled")])
def test_every_space_gives_its_model_the_first_sweeps_start(starts: tuple[str, ...],
                                                             initial: str) -> None:
    """identify and diagnose build models through the spaces: each model starts where its
    sweeps did (track and learning start from Transducer.initial)."""
    v = sd.voltage_triangle(5.58, 150.0, 1, 2000.0)
    prep = pz.prepare(sw.from_arrays(v, 0.1 * v, 2000.0), 100.0, 0.0, None)
    preps = [prep] * max(len(starts), 1)
    theta = np.array([1.0, 0.4, 0.3, 0.36, 250.0, 0.25])
    beta = np.array([25.7, 0.4, 0.0])
    lognormal = pz.LognormalSpace(preps, pz.Scales(), 64, starts or None)
    discrete, x0 = dn.DiscreteSpace.around(theta, preps, pz.Scales(), 16, 0.0, 25.7,
                                           starts or None)
    assert lognormal.model(np.log(theta), beta, 100.0).initial == initial
    assert discrete.model(x0, beta, 100.0).initial == initial


def test_a_general_density_model_starts_the_lognormal_fits_where_it_is(
        true_model: Transducer, tmp_path) -> None:  # noqa: ANN001
    """Issue 27 item 5: diagnose --model refused the model identify wrote whenever it chose the
    general coercive density ("needs a lognormal coercive-field ..."), exactly when diagnose is
    needed. The discrete model of a lognormal start (identify's own refinement space) maps back to
    that lognormal's parameters, and the CLI takes the file."""
    from click.testing import CliRunner

    from afmctl.cli import main
    from afmctl.files import modelfile
    v = sd.voltage_triangle(5.58, 150.0, 1, 2000.0)
    s = sw.from_arrays(v, idf.predict(true_model, v, 5e-4), 2000.0)
    # a 40 um layer: the sweep's peak field (3.75 MV/m) reaches past the lognormal's +3 sigma_ln,
    # so every node of it can switch (the space stops its nodes at the peak field)
    prep = pz.prepare(s, 40.0, 0.0, None)
    theta = np.array([1.0, 0.4, 0.3, 0.36, 250.0, 0.25])
    space, x0 = dn.DiscreteSpace.around(theta, [prep], pz.Scales(), 24, 0.0, 25.7)
    general = space.model(x0, np.array([25.7, 0.4, 0.0]), 100.0)
    with pytest.raises(ValueError, match="lognormal"):
        pz.internal(general)
    x = pz.internal(pz.lognormal_equivalent(general))
    np.testing.assert_allclose(np.exp(x), theta, rtol=0.03)  # +-3 sigma nodes: 1-2 % low sigma
    modelfile.write(general, tmp_path / "general.toml")
    sweep = tmp_path / "short.csv"
    sw.write(sw.from_arrays(v[:50], 0.1 * v[:50], 2000.0, {"layer_thickness_um": "100"}), sweep)
    res = CliRunner().invoke(main, ["diagnose", str(sweep), "--model",
                                    str(tmp_path / "general.toml"), "--out", str(tmp_path / "d")])
    assert "needs a lognormal" not in res.stderr, res.stderr
    assert "starts the fits as the lognormal" in res.stderr  # and then: the sweep is too short
    assert res.exit_code == 2 and "record a longer sweep" in res.stderr


def test_thinned_sums_the_misfit_over_every_kth_sample_of_a_long_sweep() -> None:
    """Issue 27: a sweep longer than ``rows`` keeps every k-th of its residual samples (the
    readings at exactly those samples); the field and the samples the model runs on stay."""
    n = 250_003
    mask = np.ones(n, dtype=bool)
    mask[:1000] = False  # before the first full excursion
    prep = pz.Prepared(np.linspace(0, 1, n), np.arange(0, n, 7), mask,
                       np.flatnonzero(mask).astype(float), 1e-4)
    thin = pz.thinned(prep, 20_000)
    rows = np.flatnonzero(thin.mask)
    assert 10_000 < rows.size <= 20_000
    assert np.all(np.diff(rows) == rows[1] - rows[0]) and rows[0] == 1000
    np.testing.assert_array_equal(thin.y, rows.astype(float))  # the readings of those samples
    assert thin.field is prep.field and thin.keep is prep.keep and thin.dt == prep.dt
    assert pz.thinned(prep, n) is prep
