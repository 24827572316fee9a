"""The general coercive density (:mod:`afmctl.fit.density`) on a foreign stage of the paper's
family: a classical Preisach operator with a separable density (a Gaussian lobe in the coercive
field, cut at 0, times a centred Gaussian in the interaction field), drawn by the independently
written stage of :mod:`afmctl.drivers.device.foreign.family_stage`. The homogenized energy model
with relay hysterons and that density is the same operator, but the lobe reaches down to zero
coercive field, where a lognormal has no weight; the lognormal alone stays several times above
the noise."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from afmctl.drivers.device.foreign import family_stage as fst
from afmctl.files import sweepfile as sw
from afmctl.fit import density as dn
from afmctl.fit import identify as idf
from afmctl.planning import sweepdesign as sd

RATE_HZ = 1000.0


def nested_loops(seed: int) -> tuple[sw.Sweep, float]:
    """The standard set's slow triangle with nested minor loops (0 -> 150 V) recorded from the
    drawn stage's power-on, with its gauge noise; and that noise (um)."""
    stage = fst.random_family_stage(np.random.default_rng(seed), "preisach",
                                    density="separable")
    name, f, v = sd.standard_set(sample_rate_hz=RATE_HZ, v_range=(0.0, 150.0))[0]
    _, reading, _ = fst.run(stage, v, RATE_HZ, fst.initial_state(stage))
    noisy = reading + stage.noise_um * np.random.default_rng(seed + 1).standard_normal(v.size)
    meta = {"layer_thickness_um": "100", "frequency_hz": f"{f:g}"}
    return sw.from_arrays(v, noisy, RATE_HZ, meta, name), float(stage.noise_um)


def test_hats_put_a_linear_density_on_the_quadrature_nodes() -> None:
    nodes = np.linspace(0.0, 2.0, 5)
    fine, t = dn.hats(nodes, 4)
    assert fine.size == 16 and np.allclose(np.diff(fine), 0.125) and fine[0] > 0
    np.testing.assert_allclose(t.sum(axis=0), [0.5, 1, 1, 1, 0.5])
    np.testing.assert_allclose(4 * t @ (3.0 + 2.0 * nodes), 3.0 + 2.0 * fine)  # exact on lines


@pytest.mark.parametrize("seed", [8])
def test_a_density_cut_at_zero_coercive_field_reaches_the_noise(seed: int) -> None:
    s, noise = nested_loops(seed)
    settings = idf.Settings(representation="hem", restarts=0)
    lognormal = idf.fit([s], replace(settings, density="parametric"))
    general = idf.fit([s], replace(settings, density="discrete"))
    over = [r.sweeps[0].rms_um / noise for r in (lognormal, general)]
    assert over[1] <= 1.5, over
    assert over[0] >= 2.0 * over[1], over


@pytest.mark.parametrize(("n_nodes", "median"), [(3, 1.0), (24, 4.5)])
def test_the_start_is_finite_for_few_nodes_and_a_lognormal_out_of_reach(n_nodes: int,
                                                                      median: float) -> None:
    """Three nodes still reach the top; a narrow lognormal wholly above the peak field (1.5
    MV/m) gives a flat start, not 0/0."""
    from afmctl.fit import parametrization as pz
    v = sd.voltage_triangle(5.58, 150.0, 1, 2000.0)
    prep = pz.prepare(sw.from_arrays(v, 0.1 * v, 2000.0), 100.0, 0.0, None)
    theta = np.array([median, 0.02 if median > 2 else 0.4, 0.3, 0.36, 250.0, 0.25])
    space, x0 = dn.DiscreteSpace.around(theta, [prep], pz.Scales(), n_nodes, 1e-6, 25.7)
    assert space.nodes.size == n_nodes and space.nodes[0] == 0.0
    assert space.nodes[-1] == pytest.approx(min(median * np.exp(3 * theta[1]),
                                                pz.extent([prep])[0]))
    assert np.all(np.isfinite(x0)) and np.all(x0[:n_nodes] >= 0) and np.any(x0[:n_nodes] > 0)
    assert np.all(np.isfinite(space.design(x0)))


def test_reach_is_the_largest_coercive_field_a_start_lets_move() -> None:
    """A 0 -> 150 V triangle on 100 um (0 .. 1.5 MV/m, sigma_I 0.1): depoled, every play the
    field passes moves ``H``; poled positive, ``y >= E_c`` throughout and only ``E_c`` below
    3 sigma_I change ``H``; poled negative, the plays follow the field up to 3 sigma_I past the
    peak; a ``previous`` start carries the one before it. Checked against the hysterons."""
    from afmctl.fit import parametrization as pz
    from afmctl.model import hysteresis as hy
    v = 0.5 * (sd.voltage_triangle(5.58, 150.0, 1, 2000.0) + 150.0)  # 0 .. 150 V
    prep = pz.prepare(sw.from_arrays(v, 0.1 * v, 2000.0), 100.0, 0.0, None)
    lo, hi = float(np.min(prep.field)), float(np.max(prep.field))
    assert lo == pytest.approx(0.0, abs=0.01)
    cases = {("depoled",): hi, ("positive", "previous"): 0.3 - lo, ("negative",): hi + 0.3}
    for starts, want in cases.items():
        got = dn.reach([prep] * len(starts), starts, 0.1)
        assert got == pytest.approx(want, rel=1e-3)
        for ec, moves in ((0.8 * got, True), (1.2 * got, False)):  # 3 sigma_I: a soft edge
            pol = hy.Polarization(1.0, 1.0, hy.Discrete((ec,), (1.0,)), hy.Normal(0.1))
            h = pz.run_from(pol, [prep.field], starts[:1])[0] - prep.field
            assert (np.ptp(h) > 0.01) == moves, (starts, ec, np.ptp(h))
