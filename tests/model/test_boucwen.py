"""The Bouc-Wen polarization (afmctl.model.boucwen): its kernel against an independent ODE solver,
its open minor loops, Algorithm 3 through it, and the model file."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from afmctl.files import modelfile as mf
from afmctl.model import hysteresis as hy
from afmctl.model import inverse as inv
from afmctl.model import rod as rd
from afmctl.model import transducer as td
from afmctl.model.boucwen import BoucWen

# the classic form dh = A dE - beta |dE| |h|^(n-1) h - gamma dE |h|^n, written out for the oracle
A, BETA, GAMMA, N = 0.8, 30.0, -10.0, 1.5


def _classic(bw_sign: float = 1.0) -> BoucWen:
    """The same operator in the module's parameters: h_s^n = A / (beta + gamma), kappa =
    (gamma - beta) / (beta + gamma)."""
    hs = (A / (BETA + GAMMA)) ** (1 / N)
    r = 0.05 if bw_sign > 0 else 2.5  # monotone: r >= |A| max(1, 1 - kappa) = 2.4 for A < 0
    return BoucWen(r, bw_sign * A, hs, (GAMMA - BETA) / (BETA + GAMMA), N)


def _hem() -> hy.Polarization:
    """The paper's model (lognormal/normal densities)."""
    return hy.Polarization(1.0, 0.3, hy.Lognormal(1.35, 0.5), hy.Normal(0.4))


def _oracle(fields: list[float], sign: float = 1.0, h0: float = 0.0) -> list[float]:
    """h at each corner of a piecewise-linear field path from (h=h0, E=0), by solve_ivp on the
    classic equation in time (E moving at unit rate), tolerance 1e-11."""
    h, e0, out = h0, 0.0, []
    a, b, g = sign * A, BETA, sign * GAMMA  # A < 0: the loop of -h (subtracted)

    def rhs(_t: float, y: np.ndarray, de: float) -> list[float]:
        hh = y[0]
        return [a * de - b * abs(de) * abs(hh) ** (N - 1) * hh - g * de * abs(hh) ** N]

    for e1 in fields:
        de = 1.0 if e1 > e0 else -1.0
        sol = solve_ivp(rhs, (0.0, abs(e1 - e0)), [h], args=(de,), rtol=1e-11, atol=1e-13)
        h, e0 = float(sol.y[0, -1]), e1
        out.append(h)
    return out


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_kernel_matches_the_classic_equation(sign: float) -> None:
    """Corners of a path with a minor loop inside, against solve_ivp on the classic form."""
    corners = [1.5, 0.4, 1.1, -1.5, 0.2]
    path = np.concatenate([np.linspace(a, b, 400)[1:] for a, b in
                           zip([0.0] + corners[:-1], corners, strict=True)])
    bw = _classic(sign)
    p, _ = hy.run(bw, path, hy.initial_state(bw, "depoled"))
    h = (p - bw.reversible * path)[398::399]
    assert np.allclose(h, _oracle(corners, sign), rtol=0, atol=1e-8 * bw.saturation)


@pytest.mark.parametrize(("sign", "share"), [(1.0, -0.4), (-1.0, 0.7)])
def test_a_state_named_by_its_value_starts_the_classic_equation(sign: float, share: float
                                                                ) -> None:
    """A state named by its value (identify's fitted start of a Bouc-Wen sweep): ``h = share
    h_s`` in the sense of ``A`` at the first field, then the path's corners as the classic form
    integrated from that ``h``."""
    corners = [1.5, 0.4, 1.1, -1.5, 0.2]
    path = np.concatenate([[0.0]] + [np.linspace(a, b, 400)[1:] for a, b in
                                     zip([0.0] + corners[:-1], corners, strict=True)])
    bw = _classic(sign)
    p, _ = hy.run(bw, path, hy.initial_state(bw, hy.bouc_wen_state(share)))
    h = p - bw.reversible * path
    h0 = share * math.copysign(bw.saturation, bw.rate)
    assert h[0] == pytest.approx(h0, abs=1e-12)
    assert np.allclose(h[399::399], _oracle(corners, sign, h0), rtol=0,
                       atol=1e-8 * bw.saturation)


def test_states_named_by_their_values_are_checked() -> None:
    """Saturation is the bound; another model's initial state cannot be one; the name says its
    value to six digits."""
    assert hy.bouc_wen_state(-0.25) == "h=-0.250000"
    assert hy.bouc_wen_share("h=-0.250000") == -0.25
    assert hy.bouc_wen_share("negative") is None
    for bad in ("h=1.5", "h=abc"):
        with pytest.raises(ValueError, match="h="):
            hy.initial_state(_classic(), bad)
    with pytest.raises(ValueError, match="unknown initial state"):
        hy.initial_state(_hem(), hy.bouc_wen_state(0.5))


def test_minor_loops_do_not_close() -> None:
    """Back and forth between the same two fields: a Preisach-type model returns to the same
    polarization each cycle (wiping out); Bouc-Wen drifts toward a limit cycle."""
    bw = _classic()
    cycle = np.concatenate([np.linspace(0.3, 0.9, 50), np.linspace(0.9, 0.3, 50)])
    path = np.concatenate([np.linspace(-2.0, 0.3, 200), np.tile(cycle, 4)])
    p, _ = hy.run(bw, path, hy.initial_state(bw, "depoled"))
    ends = p[199::100]  # at 0.3 after each cycle
    assert abs(ends[1] - ends[0]) > 1e-3 * bw.saturation
    assert abs(ends[-1] - ends[-2]) < abs(ends[1] - ends[0])  # settling, not growing


def test_saturation_and_initial_states() -> None:
    bw = _classic()
    p, st = hy.run(bw, np.linspace(0.0, 50.0, 2000), hy.initial_state(bw, "depoled"))
    assert st.values[0] == pytest.approx(bw.saturation, rel=1e-6)
    pos = hy.initial_state(bw, "positive")
    p2, _ = hy.run(bw, np.array([0.7, 0.7]), pos)  # saturated where it starts
    assert p2[0] == pytest.approx(0.7 * bw.reversible + bw.saturation)
    with pytest.raises(ValueError, match="Bouc-Wen"):
        hy.initial_state(bw, np.ones((2, 2)))
    with pytest.raises(ValueError, match="kappa"):
        BoucWen(0.1, 1.0, 0.2, 1.5, 1.0)
    with pytest.raises(ValueError, match="not monotone"):  # 0.25 < 0.1 max(1, 1 + 2) = 0.3
        BoucWen(0.25, -0.1, 0.05, -2.0, 2.0)


def test_a_monotone_subtracted_loop_is_inverted_from_saturation() -> None:
    """The reviewer's case at the edge of monotony (r = |A| (1 - kappa) + 2 %): from the poled
    state, a ramp down and up again through the steepest branch; Algorithm 2 recovers the
    field that made the polarization, sample by sample (a non-monotone model gave 15 V off)."""
    bw = BoucWen(0.1 * 1.5 * 1.02, -0.1, 0.05, -0.5, 2.0, (0.0, 1.5))
    e = np.concatenate([np.linspace(1.5, 0.2, 600), np.linspace(0.2, 1.5, 600)])
    p, _ = hy.run(bw, e, hy.initial_state(bw, "positive"))
    res = inv.algorithm2(bw, p, hy.initial_state(bw, "positive"), e_init=1.5)
    assert np.max(np.abs(res.field_mv_m - e)) < 1e-6


def _stage(sign: float) -> td.Transducer:
    k = 1e-3 * (2 * math.pi * 900.0) ** 2
    rod = rd.Rod(m=1e-3, c=2 * 0.15 * math.sqrt(k * 1e-3), k=k, a1=0.4, a2=0.05)
    bw = _classic(sign)
    if sign < 0:  # the subtracted loop must leave dP/dE > 0: r > |A| max(1, 1 - kappa) = 3 |A|
        bw = BoucWen(4.0 * abs(bw.rate), bw.rate, bw.saturation, bw.kappa, bw.exponent)
    assert bw.least_slope > 0
    return td.Transducer(bw, rod, 100.0)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_algorithm3_inverts_it(sign: float) -> None:
    """A target the model reached (a sine with a minor loop) is recovered by Algorithm 3 to
    round-off, with the field the model was driven by."""
    model = _stage(sign)
    dt = 1e-4
    t = np.arange(4000) * dt
    v = 70 + 60 * np.sin(2 * np.pi * 5 * t) + 15 * np.sin(2 * np.pi * 23 * t)
    cm = td.compile_model(model, dt)
    u, _, _ = td.simulate(cm, v, td.initial(model, "depoled", v[0]))
    ud = u[1:]  # what the model did, one sample ahead (the paper's Algorithm 3, d = 1)
    res = inv.algorithm3(cm, ud, td.initial(model, "depoled", v[0]), tol_um=1e-9)
    again, _, _ = td.simulate(cm, res.voltage(model.thickness_um),
                              td.initial(model, "depoled", v[0]))
    assert np.max(np.abs(again[1:] - ud[:-1])) < 1e-7 * np.ptp(u)
    assert np.max(np.abs(res.voltage(model.thickness_um)[1:] - v[1:-1])) < 1e-3  # volts


def test_model_file_round_trip(tmp_path: Path) -> None:
    model = _stage(-1.0)
    mf.write(model, tmp_path / "m.toml")
    back = mf.read(tmp_path / "m.toml")
    assert back.polarization == model.polarization
    assert mf.file_version(mf.load(tmp_path / "m.toml")) == 3
    text = (tmp_path / "m.toml").read_text().replace("kappa = ", "kappa = 7.0 #")
    (tmp_path / "bad.toml").write_text(text)
    with pytest.raises(mf.FileFormatError, match="kappa"):
        mf.read(tmp_path / "bad.toml")


def test_model_file_keeps_a_fitted_initial_state(tmp_path: Path) -> None:
    """A Bouc-Wen model's initial state named by its value is written and read back (and the
    model runs from it); a value beyond saturation, or such a state on the paper's model, is a
    file error naming the key."""
    model = replace(_stage(-1.0), initial=hy.bouc_wen_state(-0.3125))
    mf.write(model, tmp_path / "m.toml")
    back = mf.read(tmp_path / "m.toml")
    assert back.initial == "h=-0.312500"
    assert td.initial(back).polarization.values[0] == pytest.approx(
        -0.3125 * math.copysign(back.polarization.saturation, back.polarization.rate))
    text = (tmp_path / "m.toml").read_text()
    (tmp_path / "over.toml").write_text(text.replace("h=-0.312500", "h=-1.5"))
    with pytest.raises(mf.FileFormatError, match="initial_state"):
        mf.read(tmp_path / "over.toml")
    hem = td.Transducer(_hem(), model.rod, model.thickness_um)
    mf.write(hem, tmp_path / "hem.toml")
    text = (tmp_path / "hem.toml").read_text()
    (tmp_path / "hem_bad.toml").write_text(text.replace('initial_state = "depoled"',
                                                        'initial_state = "h=+0.500000"'))
    with pytest.raises(mf.FileFormatError, match="initial_state"):
        mf.read(tmp_path / "hem_bad.toml")


def test_diagnose_says_it_needs_the_papers_model(tmp_path: Path) -> None:
    """``afmctl diagnose --model`` on a Bouc-Wen model: exit 2 and a sentence, no traceback."""
    from click.testing import CliRunner

    from afmctl.cli import main
    from afmctl.files import sweepfile as sw

    model = _stage(-1.0)
    mf.write(model, tmp_path / "m.toml")
    v = np.interp(np.arange(2000), [0, 1000, 2000], [0.0, 150.0, 0.0])
    u, _, _ = td.simulate(td.compile_model(model, 1e-3), v, td.initial(model, "depoled", 0.0))
    sw.write(sw.from_arrays(v, u, 1000.0, {"layer_thickness_um": "100"}), tmp_path / "s.csv")
    res = CliRunner().invoke(main, ["diagnose", str(tmp_path / "s.csv"), "--model",
                                    str(tmp_path / "m.toml")])
    assert res.exit_code == 2 and "is a Bouc-Wen model" in res.output, res.output
