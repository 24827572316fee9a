"""Polarization kernels against analytic limits, the literal Algorithm 1 and slow integrations."""

from __future__ import annotations

import dataclasses as dc

import numpy as np
import pytest
from scipy import integrate, special

from afmctl.model import hysteresis as hy
from afmctl.model import thermal as th

GRID = hy.Polarization(eta=1.2, p_r=0.3, coercive=hy.Lognormal(1.0, 0.4),
                       interaction=hy.Normal(0.3), n_coercive=24, n_interaction=20, kernel="grid")


def one_hysteron(eta: float, p_r: float, p_i: float) -> hy.Polarization:
    e_c = eta * (p_r - p_i)  # (5)
    return hy.Polarization(eta, p_r, hy.Discrete((e_c,), (1.0,)), hy.Discrete((0.0,), (1.0,)),
                           kernel="grid")


@pytest.mark.parametrize("kernel", ["grid", "literal"])
def test_single_hysteron_switches_at_coercive_field_5(kernel: str) -> None:
    eta, p_r, p_i = 2.0, 0.3, 0.1
    pol = one_hysteron(eta, p_r, p_i)
    e_c = eta * (p_r - p_i)
    e = np.array([0.0, 0.39, e_c, 0.0, -0.39, -e_c, 0.0])
    if kernel == "literal":
        p, _ = hy.algorithm1(pol, e, -np.ones((1, 1)))
    else:
        p, _ = hy.run(pol, e, hy.initial_state(pol, "negative"))
    delta = np.array([-1, -1, 1, 1, 1, -1, -1])  # switches exactly at +-E_c (tie rule)
    np.testing.assert_allclose(p, e / eta + p_r * delta, atol=1e-15)


def test_saturation_is_e_over_eta_plus_remanence() -> None:
    pol = dc.replace(GRID, kernel="auto")
    for e in (6.0, 8.0):
        (p,), _ = hy.run(pol, [e], hy.initial_state(pol))
        assert p == pytest.approx(e / pol.eta + pol.p_r, abs=1e-9)
    (p_up, p_rem), _ = hy.run(pol, [8.0, 0.0], hy.initial_state(pol))
    assert 0 < p_rem < pol.p_r  # remanence after poling, Section 3


@pytest.mark.parametrize("kernel", ["auto", "grid"])
def test_symmetric_minor_loops_close(kernel: str) -> None:
    pol = dc.replace(GRID, kernel=kernel)
    cycle = np.concatenate([np.linspace(0, 0.8, 50), np.linspace(0.8, -0.8, 100),
                            np.linspace(-0.8, 0, 50)])
    p, _ = hy.run(pol, np.tile(cycle, 3), hy.initial_state(pol))
    second, third = p[200:400], p[400:600]
    np.testing.assert_allclose(second, third, atol=1e-14)
    up = np.interp(0.0, cycle[150:200], second[150:200])
    down = np.interp(0.0, cycle[50:150][::-1], second[50:150][::-1])
    assert down - up > 1e-3  # a genuine hysteresis loop, not a line


@pytest.mark.parametrize("kernel", ["auto", "grid"])
def test_wiping_out_of_inner_loops(kernel: str) -> None:
    pol = dc.replace(GRID, kernel=kernel)
    s0 = hy.initial_state(pol)
    _, s_a = hy.run(pol, [1.5, -0.5, 0.2, -0.3, 0.1, -0.2, 1.6], s0)
    _, s_b = hy.run(pol, [1.6], s0)
    np.testing.assert_array_equal(s_a.values, s_b.values)


def _adversarial(k: hy.Kernel, n: int, rng: np.random.Generator) -> np.ndarray:
    """Fields exactly at switching thresholds E = +-E_c,i - E_I,j, repeated and interleaved."""
    e = (k.ec[rng.integers(0, k.ec.size, n)] * rng.choice([-1.0, 1.0], n)
         - k.ei[rng.integers(0, k.ei.size, n)])
    return np.repeat(e, rng.integers(1, 3, n))


@pytest.mark.parametrize("start", ["depoled", "positive", "negative", "given"])
def test_fast_grid_kernel_equals_literal_algorithm1(start: str) -> None:
    rng = np.random.default_rng(7)
    k = hy.build_kernel(GRID)
    delta0 = None
    how: object = start
    if start == "given":
        bounds = rng.integers(0, k.ei.size + 1, k.ec.size)
        delta0 = np.where(np.arange(k.ei.size)[None, :] >= bounds[:, None], 1.0, -1.0)
        how = delta0
    elif start != "depoled":
        delta0 = np.full((k.ec.size, k.ei.size), 1.0 if start == "positive" else -1.0)
    smooth = 2.2 * np.sin(np.linspace(0, 25, 1500)) * np.linspace(1, 0.1, 1500)
    e = np.concatenate([smooth + rng.normal(0, 0.05, 1500), _adversarial(k, 800, rng),
                        rng.uniform(-3, 3, 300)])
    p_lit, d_lit = hy.algorithm1(GRID, e, delta0)
    p_fast, state = hy.run(GRID, e, hy.initial_state(GRID, how))  # type: ignore[arg-type]
    np.testing.assert_allclose(p_fast, p_lit, rtol=0, atol=1e-12)
    np.testing.assert_array_equal((d_lit < 0).sum(axis=1), state.values)


def test_closed_form_interaction_integral_matches_a_fine_grid() -> None:
    e = 1.8 * np.sin(np.linspace(0, 20, 600)) * np.linspace(1, 0.3, 600)
    normal = dc.replace(GRID, n_coercive=16, kernel="auto")
    fine = dc.replace(GRID, n_coercive=16, n_interaction=20_000, kernel="grid")
    p_n, _ = hy.run(normal, e, hy.initial_state(normal))
    p_f, _ = hy.run(fine, e, hy.initial_state(fine))
    np.testing.assert_allclose(p_n, p_f, atol=2e-4)  # midpoint error of the E_I grid


def test_thermal_kernel_reduces_to_relay_as_kt_over_v_goes_to_zero() -> None:
    e = 2.0 * np.sin(np.linspace(0, 12, 400)) * np.linspace(1, 0.4, 400)
    p_relay, _ = hy.algorithm1(GRID, e)
    errs = []
    for scale in (1e-2, 1e-3, 1e-4, 1e-6):  # E_th -> 0 with the attempt rate ~ 1/E_th
        th = dc.replace(GRID, thermal=hy.Thermal(scale, 1e4 / scale))
        p, _ = hy.run(th, e, hy.initial_state(th), dt=1e-4)
        errs.append(np.max(np.abs(p - p_relay)))
    assert errs[0] > errs[1] > errs[2] > errs[3]
    assert errs[3] < 1e-12


def _rates_by_quadrature(e_eff: float, e_c: float, eta: float, beta: float,
                         eps: float, tau: float) -> tuple[float, float]:
    """(7)-(8) in the inflection-point form, integrated numerically from the Gibbs energy (1)."""
    p_r = 0.3
    p_i = p_r - e_c / eta
    g_plus = lambda p: 0.5 * eta * (p - p_r) ** 2 - e_eff * p  # noqa: E731
    g_minus = lambda p: 0.5 * eta * (p + p_r) ** 2 - e_eff * p  # noqa: E731
    # each well's integrand scaled by its own minimum, which cancels in the ratios (7)
    ref_p, ref_m = g_plus(max(p_r + e_eff / eta, p_i)), g_minus(min(-p_r + e_eff / eta, -p_i))
    w_p = lambda p: np.exp(-beta * (g_plus(p) - ref_p))  # noqa: E731
    w_m = lambda p: np.exp(-beta * (g_minus(p) - ref_m))  # noqa: E731
    den_p = integrate.quad(w_p, p_i, np.inf, epsabs=0, epsrel=1e-12)[0]
    den_m = integrate.quad(w_m, -np.inf, -p_i, epsabs=0, epsrel=1e-12)[0]
    r_pm = 2 * eps * w_p(p_i) / den_p
    r_mp = 2 * eps * w_m(-p_i) / den_m
    return r_pm / tau, r_mp / tau


def test_thermal_kernel_matches_slow_direct_integration() -> None:
    """x_+ of a few hysterons: closed-form rates + exact step vs quadrature rates + an ODE solver."""
    eta, beta, eps, tau = 1.2, 2 * 1.2 / 0.05**2, 1e-3, 1e-4
    th = hy.Thermal(np.sqrt(2 * eta / beta), 2 * eps * np.sqrt(2 * beta * eta / np.pi) / tau)
    e_c = np.array([0.8, 1.0, 1.2])
    pol = hy.Polarization(eta, 0.3, hy.Discrete(tuple(e_c), (1.0, 1.0, 1.0)),
                          hy.Discrete((0.0,), (1.0,)), thermal=th)
    dt = 1e-3
    field = np.concatenate([np.linspace(0, 1.1, 40), np.full(30, 1.1), np.linspace(1.1, -1.2, 60)])
    _, st = hy.run(pol, field[:0], hy.initial_state(pol, "negative"), dt)
    x = np.zeros(3)
    history = []
    for e in field:
        _, st = hy.run(pol, [e], st, dt)

        def rhs(_t: float, xp: np.ndarray, e: float = e) -> np.ndarray:
            rates = np.array([_rates_by_quadrature(e, c, eta, beta, eps, tau) for c in e_c])
            return -rates[:, 0] * xp + rates[:, 1] * (1 - xp)

        x = integrate.solve_ivp(rhs, (0, dt), x, method="LSODA", rtol=1e-10, atol=1e-12).y[:, -1]
        np.testing.assert_allclose(st.values[:-1], x, atol=2e-6)  # x_+; last: their total
        history.append(x)
    xs = np.array(history)
    peak = xs.max(axis=0)
    assert peak[0] > 0.99 and peak[1] > 0.99 and xs[-1, :2].max() < 0.01  # up, then back down
    # E_c = 1.2 is never reached (max field 1.1): thermal activation still switches part of it
    assert 0.01 < peak[2] < 0.99


def test_thermal_kernel_creeps_toward_equilibrium_at_constant_field() -> None:
    th = dc.replace(GRID, thermal=hy.Thermal(0.05, 30.0))
    _, st = hy.run(th, np.linspace(0, 0.9, 50), hy.initial_state(th), dt=1e-3)
    p, _ = hy.run(th, np.full(3000, 0.9), st, dt=1e-3)
    steps = np.diff(p)
    assert np.all(steps >= -1e-15)  # creep is monotone at constant field
    assert p[-1] - p[0] > 1e-3  # and visible
    assert steps[-100:].max() < steps[:100].max() / 5  # and slowing toward equilibrium


def test_switching_rates_closed_form_matches_quadrature() -> None:
    eta, beta, eps, tau = 1.2, 2 * 1.2 / 0.05**2, 1e-3, 1e-4
    th = hy.Thermal(np.sqrt(2 * eta / beta), 2 * eps * np.sqrt(2 * beta * eta / np.pi) / tau)
    for e_eff in (-1.05, -0.9, 0.0, 0.95, 1.0, 1.1):
        pm, pp = hy.switching_rates(np.array([e_eff]), np.array([1.0]), th)
        qm, qp = _rates_by_quadrature(e_eff, 1.0, eta, beta, eps, tau)
        assert pm[0] == pytest.approx(qm, rel=1e-7)
        assert pp[0] == pytest.approx(qp, rel=1e-7)


def test_state_is_not_mutated_and_must_match_the_model() -> None:
    s0 = hy.initial_state(GRID)
    before = s0.values.copy()
    hy.run(GRID, [2.0, -2.0], s0)
    np.testing.assert_array_equal(s0.values, before)
    with pytest.raises(ValueError, match="state does not belong"):
        hy.run(dc.replace(GRID, kernel="auto"), [0.0], s0)


def test_discrete_density_validation() -> None:
    with pytest.raises(ValueError, match="increasing"):
        hy.Discrete((1.0, 0.5), (1.0, 1.0))
    with pytest.raises(ValueError, match="nonnegative"):
        hy.Discrete((0.5, 1.0), (1.0, -1.0))


def test_rate_table_matches_erfcx() -> None:
    """The thermal kernel's ``1 / erfcx`` table: within its stated relative error over its span
    (far tighter where the rates matter, z >= 0), the formula outside it."""
    z = np.concatenate((np.linspace(th.RATE_Z_LO, th.RATE_Z_HI, 200_001)[:-1],
                        np.random.default_rng(5).uniform(th.RATE_Z_LO, th.RATE_Z_HI, 100_000)))
    got = np.array([th.rate(v, 1.0, th.RATE_TABLE) for v in z])
    rel = np.abs(got * special.erfcx(z) - 1.0)
    assert rel.max() < th.RATE_REL_ERROR
    assert rel[z >= 0].max() < 1e-12
    for v in (th.RATE_Z_LO - 1.0, th.RATE_Z_HI + 3.0, -30.0):  # the formula (asymptotic z >= 25)
        assert th.rate(v, 7.0, th.RATE_TABLE) == pytest.approx(7.0 / special.erfcx(v), rel=1e-10)


def _rates_and_means(ee: np.ndarray, p_i: np.ndarray, eta: float, p_r: float, beta: float,
                     eps: float, tau: float) -> tuple[np.ndarray, ...]:
    """Per hysteron at effective field ``ee`` (inflection points ``p_i``): the likelihoods
    p_+-, p_-+ (1/s) of (7)-(8) in the inflection-point form, each well's integral by adaptive
    quadrature of the Gibbs energy (1) on its quadratic branch of psi from the inflection point
    out, and the averages <P_+>, <P_-> of (9) by quadrature over each branch."""
    quad = lambda f, a, b: integrate.quad_vec(f, a, b, epsabs=0, epsrel=1e-12)[0]  # noqa: E731
    out = []
    for sign, edge in ((1.0, p_i), (-1.0, -p_i)):  # the positive well, then the negative
        g = lambda p, sign=sign: 0.5 * eta * (p - sign * p_r) ** 2 - ee * p  # noqa: E731
        mode = sign * p_r + ee / eta  # the branch's minimum
        low = g(np.maximum(mode, edge) if sign > 0 else np.minimum(mode, edge))  # cancels
        well = quad(lambda s, g=g, low=low, edge=edge, sign=sign:
                    np.exp(-beta * (g(edge + sign * s) - low)), 0.0, np.inf)
        rate = 2 * eps * np.exp(-beta * (g(edge) - low)) / well / tau
        mass = quad(lambda s, g=g, m=mode: np.exp(-beta * (g(m + s) - g(m))), -np.inf, np.inf)
        first = quad(lambda s, g=g, m=mode: (m + s) * np.exp(-beta * (g(m + s) - g(m))),
                     -np.inf, np.inf)
        out += [rate, first / mass]
    return out[0], out[2], out[1], out[3]


def _kernel10_by_quadrature(pol: hy.Polarization, field: np.ndarray, holds: np.ndarray,
                            up: np.ndarray) -> np.ndarray:
    """P (C/m^2) of the grid model (13) with kernel (10), written from the paper alone
    (:func:`_rates_and_means`), the fractions x_+ of (8) advanced exactly at the frozen rates
    over each hold; every hysteron at every sample, no cut-off, no table, no snap. Nodes: the
    quantile midpoints of nu_1 and nu_2 (the module's quadrature); ``up``: the initial x_+."""
    eta, p_r, th_ = pol.eta, pol.p_r, pol.thermal
    assert th_ is not None and isinstance(pol.coercive, hy.Lognormal)
    assert isinstance(pol.interaction, hy.Normal)
    beta = 2 * eta / th_.field_scale ** 2  # V / kT, from E_th = sqrt(2 eta kT / V)
    eps = 1e-6  # half the separation 2 eps of (7); the relaxation time T follows from nu0
    tau = 2 * eps * np.sqrt(2 * beta * eta / np.pi) / th_.attempt_rate
    qc = (np.arange(pol.n_coercive) + 0.5) / pol.n_coercive
    qi = (np.arange(pol.n_interaction) + 0.5) / pol.n_interaction
    ec = np.repeat(pol.coercive.median * np.exp(pol.coercive.sigma * special.ndtri(qc)), qi.size)
    ei = np.tile(pol.interaction.std * special.ndtri(qi), qc.size)
    p_i = p_r - ec / eta  # inflection points, from (5)
    x = np.asarray(up, dtype=float).ravel().copy()
    out = np.empty(field.size)
    for k, (e, dt) in enumerate(zip(field, holds, strict=True)):
        p_pm, p_mp, mean_p, mean_m = _rates_and_means(e + ei, p_i, eta, p_r, beta, eps, tau)
        lam = p_pm + p_mp
        moving = lam > 0
        x_eq = np.divide(p_mp, lam, out=np.zeros_like(lam), where=moving)
        x = np.where(moving, x_eq + (x - x_eq) * np.exp(-lam * dt), x)
        out[k] = float(np.mean(x * mean_p + (1 - x) * mean_m))  # (10), weights 1 / (N_i N_j)
    return out


@pytest.mark.parametrize("start", ["positive", "depoled"])
def test_thermal_kernel_equals_quadrature_of_7_to_9_on_a_grid(start: str) -> None:
    """The compiled kernel (band walk, rate table, skips of fully switched hysterons) against
    :func:`_kernel10_by_quadrature` on a whole grid: fast ramps that switch many hysterons within
    a sample, slow creep over long holds (rate x hold up to ~1e3), reversals, and coercive rows
    narrower than the thermal band (both rates at once). Agreement to 1e-9 C/m^2 (P_R = 0.3)."""
    th_ = hy.Thermal(0.05, 2e3)
    pol = hy.Polarization(eta=1.2, p_r=0.3, coercive=hy.Lognormal(0.6, 0.9),
                          interaction=hy.Normal(0.3), n_coercive=5, n_interaction=8,
                          kernel="grid", thermal=th_)
    rng = np.random.default_rng(11)
    field = np.concatenate((np.linspace(0, 1.8, 12), np.full(4, 1.8), np.linspace(1.7, -0.4, 25),
                            np.linspace(-0.4, 0.7, 15), -1.5 + 0.2 * rng.standard_normal(10),
                            np.linspace(-1.2, 2.5, 9)))
    holds = rng.choice([1e-4, 1e-3, 2e-2, 0.5], field.size)
    state = hy.initial_state(pol, start)  # type: ignore[arg-type]
    fast, _ = hy.run(pol, field, state, holds)
    slow = _kernel10_by_quadrature(pol, field, holds, state.values[:-1])
    assert np.ptp(slow) > 0.3  # the loops switch most of the grid
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-9)
