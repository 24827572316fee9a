"""Model files round-trip with units and a version; malformed ones fail naming the key."""

from __future__ import annotations

import dataclasses as dc
from pathlib import Path

import pytest

from afmctl.files import modelfile
from afmctl.model import hysteresis as hy
from afmctl.model.effects import Effects, SecondMode
from afmctl.model.transducer import Transducer


def test_round_trip(nominal: Transducer, tmp_path: Path) -> None:
    thermal = dc.replace(nominal, polarization=dc.replace(
        nominal.polarization, thermal=hy.Thermal(0.05, 100.0),
        coercive=hy.Discrete((0.5, 1.0, 1.5), (0.2, 0.6, 0.2))))
    effects = dc.replace(nominal, effects=Effects(
        amplifier_bandwidth_hz=400.0, sensor_delay_samples=2.5, sensor_delay_s=1e-4,
        sensor_window_s=3e-4, sensor_quadratic_per_um=-1e-3, sensor_cubic_per_um2=2e-5,
        sensor_center_um=-73.5,
        second_mode=SecondMode(600.0, 0.03, 0.4, -0.04), voltage_gain_sigma=0.02))
    amp2 = dc.replace(nominal, effects=Effects(amplifier_bandwidth_hz=120.0,
                                               amplifier_damping_ratio=0.6,
                                               amplifier_slew_v_per_s=2e4,
                                               amplifier_rails_v=(-20.0, 150.0)))
    for m in (nominal, thermal, effects, amp2):
        modelfile.write(m, tmp_path / "m.toml", header="test")
        assert modelfile.read(tmp_path / "m.toml") == m
    assert not list(tmp_path.glob("*.partial"))


def test_rails_must_be_in_order(nominal: Transducer, tmp_path: Path) -> None:
    modelfile.write(dc.replace(nominal, effects=Effects(amplifier_rails_v=(0.0, 150.0))),
                    tmp_path / "m.toml", header="test")
    text = (tmp_path / "m.toml").read_text()
    assert "[effects.amplifier_rails]" in text
    (tmp_path / "m.toml").write_text(text.replace("high_V = 150.0", "high_V = -1.0"))
    with pytest.raises(modelfile.FileFormatError, match="high_V.*above low_V"):
        modelfile.read(tmp_path / "m.toml")


@pytest.mark.parametrize(("old", "new", "key"), [
    ("eta_MVm_per_Cm2 = 1.2", "eta_MVm_per_Cm2 = nan", "eta_MVm_per_Cm2"),
    ("k_N_per_m = 123370.0", "k_N_per_m = inf", "k_N_per_m"),
    ("m_kg = 0.05", "m_kg = -0.05", "m_kg"),
    ("m_kg = 0.05", "", "m_kg"),
    ("sigma_ln = 0.4", 'sigma_ln = "wide"', "sigma_ln"),
    ('type = "lognormal"', 'type = "cauchy"', "type"),
    ("format_version = 2", "format_version = 9", "format_version"),
    ("[rod]", "[rodd]", "rod"),
    ("sigma_ln = 0.4", "sigma_ln = 0.4\nsigma = 0.9", "coercive.sigma"),  # misspelt, not ignored
    ("[rod]", "[effects.amplifier_lag]\nbandwidth_Hz = 4e2\nbandwith_Hz = 3e2\n[rod]",
     "amplifier_lag.bandwith_Hz"),
])
def test_malformed_files_name_the_key(nominal: Transducer, tmp_path: Path, old: str, new: str,
                                      key: str) -> None:
    path = tmp_path / "m.toml"
    modelfile.write(nominal, path)
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(modelfile.FileFormatError, match=key):
        modelfile.read(path)


def test_not_toml_or_missing(tmp_path: Path) -> None:
    (tmp_path / "bin.toml").write_bytes(b"\xff\xfe\x00junk")
    with pytest.raises(modelfile.FileFormatError, match="UTF-8"):
        modelfile.read(tmp_path / "bin.toml")
    with pytest.raises(modelfile.FileFormatError, match="no such file"):
        modelfile.read(tmp_path / "absent.toml")


ENVELOPE = modelfile.Envelope(-40.0, 150.0, -0.4, 1.5, (0.279, 5.58, 27.9), (2000.0, 5000.0, 1e4))


def test_envelope_and_uncertainty_round_trip(nominal: Transducer, tmp_path: Path) -> None:
    unc = {"method": "m", "parameters": {"a": {"value": 1.0, "stderr": 0.1},
                                         "b": {"value": 2.0, "stderr": None}},
           "correlation": {"names": ["a", "b"], "matrix": [[1.0, -0.5], [-0.5, 1.0]]},
           "undetermined": ["b"]}
    modelfile.write(nominal, tmp_path / "m.toml", envelope=ENVELOPE, uncertainty=unc)
    assert modelfile.read(tmp_path / "m.toml") == nominal
    assert modelfile.read_envelope(tmp_path / "m.toml") == ENVELOPE
    text = (tmp_path / "m.toml").read_text()
    assert "[envelope]" in text and "[uncertainty]" in text and "format_version = 2" in text


def test_version_1_files_are_still_read(nominal: Transducer, tmp_path: Path) -> None:
    modelfile.write(nominal, tmp_path / "m.toml")
    path = tmp_path / "m.toml"
    path.write_text(path.read_text().replace("format_version = 2", "format_version = 1"))
    assert modelfile.read(path) == nominal and modelfile.read_envelope(path) is None


def test_envelope_admits_within_five_percent_of_its_span() -> None:
    assert ENVELOPE.span_v == 190.0
    assert ENVELOPE.admits(-40.0 - 9.4, 150.0) and ENVELOPE.admits(0.0, 159.4)
    assert not ENVELOPE.admits(-150.0, 150.0) and not ENVELOPE.admits(0.0, 160.0)
    assert ENVELOPE.excess_v(-150.0, 100.0) == pytest.approx(110.0)


def test_malformed_envelope_names_the_key(nominal: Transducer, tmp_path: Path) -> None:
    modelfile.write(nominal, tmp_path / "m.toml", envelope=ENVELOPE)
    path = tmp_path / "m.toml"
    path.write_text(path.read_text().replace("voltage_max_V = 150.0", "voltage_max_V = -50.0"))
    with pytest.raises(modelfile.FileFormatError, match="voltage_max_V"):
        modelfile.read_envelope(path)


def preisach_model(nominal: Transducer) -> Transducer:
    from afmctl.model.creep import Creep
    from afmctl.model.preisach import PreisachGrid
    grid = PreisachGrid((0.0, 0.3, 0.6), (-1.0, -0.5, 0.0, 0.5), 0.2,
                        ((0.01, 0.02, 0.0, 0.0), (0.0, 0.03, 0.05, 0.01), (0.0, 0.0, 0.02, 0.04)),
                        0.05)
    return dc.replace(nominal, polarization=grid, creep=Creep((0.01, 1.0, 100.0),
                                                              (0.01, 0.005, 0.0), (0.0, 0.0, 0.02)))


def test_preisach_grid_and_creep_round_trip_as_version_3(nominal: Transducer,
                                                          tmp_path: Path) -> None:
    m = preisach_model(nominal)
    path = tmp_path / "m.toml"
    modelfile.write(m, path)
    assert "format_version = 3" in path.read_text() and modelfile.read(path) == m
    modelfile.write(nominal, path)  # the paper's model is still written as version 2
    assert "format_version = 2" in path.read_text() and "a3_N" not in path.read_text()
    cubic = dc.replace(m, rod=dc.replace(m.rod, a3=463.4))  # the force's cubic, written and read
    modelfile.write(cubic, path)
    assert "a3_N_per_C3_m6 = 463.4" in path.read_text() and modelfile.read(path) == cubic
    on_force = dc.replace(m, creep=dc.replace(m.creep, thresholds=(0.0, 0.0, 3.5),
                                              acts_on="force"))  # creep of the force, N
    modelfile.write(on_force, path)
    text = path.read_text()
    assert 'acts_on = "force"' in text and "thresholds_N = [0.0, 0.0, 3.5]" in text
    assert modelfile.read(path) == on_force
    path.write_text(text.replace('acts_on = "force"', 'acts_on = "field"'))
    with pytest.raises(modelfile.FileFormatError, match="acts_on"):
        modelfile.read(path)


@pytest.mark.parametrize(("old", "new", "match"), [
    ("format_version = 3", "format_version = 2", "needs version 3"),
    ("weights_C_per_m2 = [[0.01, 0.02, 0.0, 0.0], ", "weights_C_per_m2 = [[0.01, 0.02, 0.0], ",
     "weights_C_per_m2: rows of different lengths"),
    ("[0.0, 0.03, 0.05, 0.01]", "[0.0, -0.03, 0.05, 0.01]", "weights_C_per_m2: .*>= 0"),
    ("weights = [0.01, 0.005, 0.0]", "weights = [0.01, 0.005]", "creep.weights: .*equally long"),
    ("thresholds_C_per_m2 = [0.0, 0.0, 0.02]", "thresholds_C_per_m2 = [0.0, 0.0, -0.02]",
     "creep.weights: .*thresholds >= 0"),
])
def test_malformed_preisach_file_names_the_key(nominal: Transducer, tmp_path: Path, old: str,
                                               new: str, match: str) -> None:
    path = tmp_path / "m.toml"
    modelfile.write(preisach_model(nominal), path)
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))
    with pytest.raises(modelfile.FileFormatError, match=match):
        modelfile.read(path)
