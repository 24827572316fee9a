"""The model's validity envelope in track (issue 11): conditioning inside the identified voltage
range, waveforms leaving it refused unless --extrapolate."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.files import modelfile
from afmctl.files.profile import default_profile
from afmctl.model.transducer import Transducer
from afmctl.planning import track

LIM = default_profile().limits  # -150 ... 150 V
UNIPOLAR = modelfile.Envelope(0.0, 150.0, 0.0, 1.5, (0.279, 5.58, 27.9), (1e3, 5e3, 1e4))


def test_conditioning_stays_inside_the_identified_range(nominal: Transducer) -> None:
    desired = track.triangle(27.9, 20.0, 0.0, 2, 1e-4)
    plain = track.plan(nominal, desired, LIM, filters=("inverse",))["inverse"]
    kept = track.plan(nominal, desired, LIM, filters=("inverse",), envelope=UNIPOLAR,
                      extrapolate=True)["inverse"]
    pre = slice(0, track.conditioning(track.conditioning_limits(LIM, UNIPOLAR), 0.0, 1e-4).size)
    assert plain.voltage_v[pre].min() == pytest.approx(LIM.v_min)
    assert kept.voltage_v[pre].min() == pytest.approx(0.0, abs=1e-9)
    assert kept.voltage_v[pre].max() == pytest.approx(150.0)


def test_waveform_outside_the_envelope_is_refused(nominal: Transducer) -> None:
    desired = track.triangle(27.9, 20.0, 0.0, 2, 1e-4)  # about -25 ... 25 V, far below 0 V
    with pytest.raises(track.EnvelopeError, match="envelope"):
        track.plan(nominal, desired, LIM, envelope=UNIPOLAR)
    inside = track.triangle(27.9, 20.0, 30.0, 2, 1e-4)
    wf = track.plan(nominal, inside, LIM, envelope=UNIPOLAR)["inverse"]
    assert np.all(wf.voltage_v[wf.tracking] >= -0.05 * UNIPOLAR.span_v)


def test_cli_refuses_with_one_line_and_extrapolate_allows(nominal: Transducer,
                                                          tmp_path: Path) -> None:
    path = tmp_path / "m.toml"
    modelfile.write(nominal, path, envelope=UNIPOLAR)
    args = ["track", "triangle", "--freq", "27.9", "--amplitude", "20", "--periods", "2",
            "--model", str(path), "--dry-run"]
    res = CliRunner().invoke(main, args + ["--out", str(tmp_path / "a")])
    assert res.exit_code == 2
    line = res.output.strip()
    assert "\n" not in line and line.startswith("afmctl: error:") and "envelope" in line
    assert not list((tmp_path / "a").glob("*.csv")) if (tmp_path / "a").exists() else True
    res = CliRunner().invoke(main, args + ["--extrapolate", "--out", str(tmp_path / "b")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "b" / "waveform_inverse.csv").exists()
