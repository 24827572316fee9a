"""Help and report texts a new user trips on (issue 27 items 6, 17 and 18): each says what it
means, in words the user has."""

from __future__ import annotations

import dataclasses as dc
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import identify as identify_cli
from afmctl.cli import main
from afmctl.files import modelfile
from afmctl.files import sweepfile as sw
from afmctl.files.profile import default_profile
from afmctl.fit import identify as idf
from afmctl.model.transducer import Transducer
from afmctl.planning import sweepdesign as sd
from tests.harness.paths import PROFILES

FAST = "\n[identify]\nrestarts = 0\ndensity = \"parametric\"\nmax_nfev = 40\nn_coercive_fit = 32\n"


def unipolar_sweep(folder: Path) -> Path:
    """3 cycles of 27.9 Hz over 0 ... 150 V on the emulated plant (never negative)."""
    from afmctl.drivers.device import plant
    v = sd.loop(27.9, 0.0, 150.0, 3, 10_000.0)
    u, _ = plant.expected_readback(dc.replace(default_profile().emulator, seed=4), 10_000.0, v)
    path = folder / "uni.csv"
    sw.write(sw.from_arrays(v, u, 10_000.0, {"frequency_hz": "27.9",
                                              "layer_thickness_um": "100"}, "uni"), path)
    return path


@pytest.fixture(scope="module")
def unipolar_fit(tmp_path_factory: pytest.TempPathFactory) -> tuple[idf.FitResult, sw.Sweep]:
    path = unipolar_sweep(tmp_path_factory.mktemp("uni"))
    data = sw.read(path)
    return idf.fit([data], idf.Settings(restarts=0, density="parametric", max_nfev=40,
                                        n_coercive_fit=32)), data


# ----------------------------------------------------------------------------------------------
# item 17: identify's uncertainty and start texts
# ----------------------------------------------------------------------------------------------


def test_undetermined_parameters_are_named_in_words_with_the_physical_ones(
        unipolar_fit: tuple[idf.FitResult, sw.Sweep]) -> None:
    """"eta 1.45 +- 18.8, a1 3.47 +- 44.8" while "undetermined" listed only "c@0.2929" (read as
    the damping c): the physical parameters beyond half their value are listed, and a density
    node says it is one."""
    result, _ = unipolar_fit
    params = tuple(dc.replace(p, stderr=13 * abs(p.value)) if p.name in ("eta", "a1") else p
                   for p in result.parameters)
    loose = dc.replace(result, parameters=params,
                       uncertainty={**result.uncertainty, "undetermined": ["c@0.2929"]})
    line = identify_cli.undetermined_text(loose)
    assert "coercive density at 0.2929 MV/m" in line and "c@" not in line
    assert "eta (+- 1300 %)" in line and "a1 (+- 1300 %)" in line
    assert identify_cli.undetermined_text(dc.replace(
        result, parameters=tuple(dc.replace(p, stderr=0.01 * abs(p.value))
                                 for p in result.parameters),
        uncertainty={**result.uncertainty, "undetermined": []})).endswith(": none")


def test_a_start_on_a_never_negative_stage_is_explained(
        unipolar_fit: tuple[idf.FitResult, sw.Sweep]) -> None:
    result, data = unipolar_fit
    negative = dc.replace(result, sweeps=tuple(dc.replace(s, start="negative")
                                               for s in result.sweeps))
    text = identify_cli._report(negative, [data])
    assert "never change the voltage's sign, 'negative' or 'positive' only says" in text
    positive = dc.replace(result, sweeps=tuple(dc.replace(s, start="positive")
                                               for s in result.sweeps))
    assert "never change the voltage's sign" not in identify_cli._report(positive, [data])


def test_identify_reports_the_reach_on_its_profile(tmp_path: Path) -> None:
    """Issue 27 item 6: the reachable displacement range of the model on the profile is part of
    identify's output (and `afmctl reach` shows it for any model)."""
    sweep = unipolar_sweep(tmp_path)
    prof = tmp_path / "uni.toml"
    prof.write_text((PROFILES / "emulated.toml").read_text().replace(
        "v_min_V = -150.0", "v_min_V = 0.0") + FAST)
    res = CliRunner().invoke(main, ["identify", str(sweep), "--profile", str(prof), "-o",
                                    str(tmp_path / "m.toml")])
    assert res.exit_code == 0, res.output
    line = next(ln for ln in res.stdout.splitlines() if ln.startswith("reach on profile"))
    again = CliRunner().invoke(main, ["reach", "--model", str(tmp_path / "m.toml"), "--profile",
                                      str(prof), "--json", "--amplitude", "27.04"])
    assert again.exit_code == 0, again.output
    doc = json.loads(again.stdout)
    lo, hi = doc["reach_um"]
    assert f"{lo:.4g} ... {hi:.4g} um on 0 ... 150 V" in line
    assert 0 < lo < hi and doc["centre_um"] == pytest.approx(0.5 * (lo + hi))
    assert doc["offset_range_um"] == pytest.approx([lo + 13.52, hi - 13.52])


def test_reach_says_when_an_amplitude_does_not_fit(nominal: Transducer, tmp_path: Path) -> None:
    modelfile.write(nominal, tmp_path / "m.toml")
    res = CliRunner().invoke(main, ["reach", "--model", str(tmp_path / "m.toml"), "--profile",
                                    "emulated-foreign", "--amplitude", "60"])
    assert res.exit_code == 0, res.output
    assert res.stdout.splitlines()[0].startswith("reach: 6.519 ... 53.6 um (span 47.08 um) on "
                                                 "0 ... 150 V")
    assert "--amplitude 60 does not fit: at most 47.08 um" in res.stdout


# ----------------------------------------------------------------------------------------------
# item 18: help and text
# ----------------------------------------------------------------------------------------------


def test_envelope_text_rounds_float32_extremes_and_sorts_frequencies() -> None:
    env = modelfile.Envelope(0.0, 99.99920654, 0.0, 0.9999920654, (0.1, 0.279, 27.9, 5.58, 27.9),
                             (1e4,) * 5)
    assert env.describe() == "0 ... 100 V, 0.1, 0.279, 5.58, 27.9 Hz"


def test_track_help_names_every_option_and_the_triangle_whole() -> None:
    out = CliRunner().invoke(main, ["track", "--help"]).stdout
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("triangle"))
    assert line.split(None, 1)[1] == "Track a triangle wave, as in the paper's Figs 9-11."
    help_ = CliRunner().invoke(main, ["track", "triangle", "--help"]).stdout
    flat = " ".join(help_.split())
    assert "--filter [inverse|linear|both] Which waveforms to play" in flat
    assert "in the sensor's frame" in flat and "`centre`" in flat  # --offset: from what


def test_identify_and_diagnose_take_a_shipped_profile_by_name(tmp_path: Path) -> None:
    sweep = unipolar_sweep(tmp_path)
    res = CliRunner().invoke(main, ["identify", str(sweep), "--profile", "emulated-foreign",
                                    "-o", str(tmp_path / "m.toml")])
    assert "no such file" not in res.stderr and res.exit_code == 0, res.output
    assert "reach on profile 'emulated-foreign'" in res.stdout
    res = CliRunner().invoke(main, ["diagnose", str(sweep), "--profile", "lab-serial", "--out",
                                    str(tmp_path / "d"), "--noise-um", "nan"])
    assert "no such file" not in res.stderr and res.exit_code == 2  # only --noise-um refused
    assert "--noise-um" in res.stderr


def test_track_file_says_it_resamples(nominal: Transducer, tmp_path: Path) -> None:
    modelfile.write(nominal, tmp_path / "m.toml")
    t = np.arange(0, 0.2, 1e-3)  # a 1 kHz file for a 10 kHz stage
    (tmp_path / "w.csv").write_text("time_s,desired_um\n" + "".join(
        f"{a:.4f},{5 * np.sin(2 * np.pi * 10 * a):.5f}\n" for a in t))
    res = CliRunner().invoke(main, ["track", "file", str(tmp_path / "w.csv"), "--model",
                                    str(tmp_path / "m.toml"), "--dry-run", "--out",
                                    str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    assert ("w.csv: 200 samples every 1 ms (median), resampled linearly onto the stage's clock "
            "(every 0.1 ms)") in res.stderr
    res = CliRunner().invoke(main, ["track", "file", str(tmp_path / "w.csv"), "--model",
                                    str(tmp_path / "m.toml"), "--out", str(tmp_path / "r"),
                                    "--filter", "inverse"])
    assert res.exit_code == 0, res.output
    assert "(whole run)" in res.stderr and "no full period after the first" not in res.stderr


@pytest.mark.parametrize("where", ["socket://nonsense", "socket://127.0.0.1:99999", "tty"])
def test_emulate_refuses_a_bad_serial_address_in_one_line(where: str) -> None:
    res = CliRunner().invoke(main, ["emulate", "--serial", where, "--no-rtu", "--modbus-port",
                                    "0"])
    assert res.exit_code == 2 and res.stderr.count("\n") == 1, res.output
    assert "'pty' or 'socket://HOST:PORT'" in res.stderr and "int()" not in res.stderr


def test_the_mean_against_field_is_drawn_over_both_clouds() -> None:
    """Issue 27 item 18: the base model's binned mean against field, red on its red cloud, could
    not be seen; the means are drawn dark and outlined, above both clouds."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_rgb

    from afmctl import plots
    fig, ax = plt.subplots()
    field = np.linspace(-1.5, 1.5, 3000)
    rng = np.random.default_rng(0)
    residuals = [0.2 * field + rng.normal(0, 0.3, field.size), rng.normal(0, 0.05, field.size)]
    plots.field_panel(ax, field, residuals, ("paper's model", "extended"))
    clouds = [ln for ln in ax.lines if ln.get_linestyle() == "None"]
    means = [ln for ln in ax.lines if ln.get_linestyle() != "None"]
    assert len(clouds) == 2 and len(means) == 2
    assert min(m.get_zorder() for m in means) > max(c.get_zorder() for c in clouds)
    for m, c in zip(means, clouds, strict=True):
        assert np.abs(np.subtract(to_rgb(m.get_color()), to_rgb(c.get_color()))).sum() > 0.5
        assert m.get_path_effects()  # outlined
    assert means[0].get_label() == "mean: paper's model"
    plt.close(fig)
