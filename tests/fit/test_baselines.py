import numpy as np
import pytest

from afmctl.fit import baselines as bl


def test_play_operator_backlash() -> None:
    v = np.array([0.0, 1.0, 3.0, 2.0, 0.0, -3.0, 0.0])
    y = bl.plays(v, np.array([0.0, 1.0]))
    np.testing.assert_allclose(y[:, 0], v)  # r = 0 is the identity
    np.testing.assert_allclose(y[:, 1], [0, 0, 2, 2, 1, -2, -1])


def test_pi_recovers_its_own_weights_and_offset() -> None:
    t = np.linspace(0, 3, 3001)
    v = 100 * np.sin(2 * np.pi * t) * np.minimum(1, t)
    r = np.arange(6) * 100 / 6
    w = np.array([0.1, 0.0, 0.05, 0.02, 0.0, 0.03])
    u = bl.plays(v, r) @ w - 1.5
    pi = bl.fit_pi(v, u, n_plays=6)
    np.testing.assert_allclose(pi.weights, w, atol=1e-8)
    assert pi.offset_um == pytest.approx(-1.5)
    assert min(pi.weights) >= 0


def test_linear_fit_on_mask() -> None:
    v = np.linspace(-1, 1, 11)
    u = 2 * v + 3
    u[:3] = 100.0  # outside the mask
    lin = bl.fit_linear(v, u, np.arange(11) >= 3)
    assert lin.gain_um_per_v == pytest.approx(2) and lin.offset_um == pytest.approx(3)
