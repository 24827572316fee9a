import json
from collections.abc import Callable
from pathlib import Path

import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.files import modelfile
from afmctl.files import sweepfile as sw
from afmctl.planning import sweepdesign as sd
from tests.harness.emulated import NOISE_UM, SAMPLE_RATE_HZ
from tests.harness.paths import PROFILES

EMULATED = PROFILES / "emulated.toml"

MALFORMED = {
    "missing_column": b"time_s,voltage_V\n0,0\n0.001,1\n",
    "nan": b"time_s,voltage_V,displacement_um\n0,0,0\n0.001,NaN,1\n0.002,1,1\n",
    "non_increasing_time": b"time_s,voltage_V,displacement_um\n0,0,0\n0.002,1,1\n0.001,2,1\n",
    "empty": b"",
    "not_text": b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe",
}


@pytest.fixture(scope="module")
def good_file(tmp_path_factory: pytest.TempPathFactory,
              emulate: Callable[..., sw.Sweep]) -> Path:
    """A foreign-tool sweep: no metadata at all (so the fit is in volts)."""
    s = emulate(sd.voltage_triangle(27.9, 150.0, 6, SAMPLE_RATE_HZ), 27.9, seed=11, meta=False)
    p = tmp_path_factory.mktemp("sweeps") / "foreign.csv"
    sw.write(s, p)
    return p


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_sweep_exits_2_with_one_line_and_writes_nothing(
        case: str, tmp_path: Path, good_file: Path) -> None:
    bad = tmp_path / f"{case}.csv"
    bad.write_bytes(MALFORMED[case])
    out, plots = tmp_path / "model.toml", tmp_path / "plots"
    res = CliRunner().invoke(main, ["identify", str(good_file), str(bad), "-o", str(out),
                                    "--plots", str(plots), "--json"])
    assert res.exit_code == 2, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("afmctl: error: ") and str(bad) in lines[0]
    assert res.stdout == ""
    assert not out.exists() and not plots.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [bad.name]


def test_missing_file_exits_2(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["identify", str(tmp_path / "nope.csv"), "-o",
                                    str(tmp_path / "m.toml")])
    assert res.exit_code == 2 and res.stderr.startswith("afmctl: error: ")
    assert not (tmp_path / "m.toml").exists()


def test_identify_json_model_and_plots(tmp_path: Path, good_file: Path) -> None:
    out, plots = tmp_path / "model.toml", tmp_path / "plots"
    res = CliRunner().invoke(main, ["identify", str(good_file), "-o", str(out),
                                    "--plots", str(plots), "--json"])
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["success"] is True and doc["seconds"] > 0
    assert doc["thickness_known"] is False
    (s,) = doc["sweeps"]
    assert set(s) >= {"file", "rms_um", "max_um", "range_um"}
    assert s["file"] == str(good_file) and s["rms_um"] <= 1.5 * NOISE_UM
    assert doc["parameters"]["m"]["fixed"] is True
    assert doc["minor_loops"]["close"] is not False, doc["minor_loops"]  # the paper's model: Preisach
    model = modelfile.read(out)
    assert model.thickness_um == 1.0 and model.polarization.n_coercive == doc["n_coercive"] >= 64
    assert len(list(plots.glob("*.png"))) == 1


def test_identify_human_report(tmp_path: Path, good_file: Path) -> None:
    res = CliRunner().invoke(main, ["identify", str(good_file), "-o", str(tmp_path / "m.toml")])
    assert res.exit_code == 0
    assert "fit converged" in res.stdout and "fixed (scale convention)" in res.stdout
    assert "foreign.csv" in res.stdout and "minor loops" in res.stdout


def test_non_converged_fit_writes_its_best_model_with_a_warning(tmp_path: Path,
                                                                good_file: Path) -> None:
    """No dead end (issue 23): a fit stopped by its budget writes its best point, says so on
    stderr and in the JSON (success false), and exits 0."""
    prof = tmp_path / "p.toml"
    prof.write_text(EMULATED.read_text() + "\n[identify]\nmax_nfev = 1\nrepresentation = \"hem\"\n")
    out = tmp_path / "m.toml"
    res = CliRunner().invoke(main, ["identify", str(good_file), "-o", str(out), "--json",
                                    "--profile", str(prof)])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["success"] is False and isinstance(doc["at_noise_floor"], bool)
    assert "stopped before converging" in res.stderr
    assert modelfile.read(out).thickness_um > 0


def test_profile_gives_the_thickness_of_sweeps_without_one(tmp_path: Path,
                                                          good_file: Path) -> None:
    """A foreign sweep (no metadata) is fitted in volts alone, in MV/m with the stage's profile."""
    out = tmp_path / "m.toml"
    res = CliRunner().invoke(main, ["identify", str(good_file), "-o", str(out), "--json",
                                    "--profile", str(EMULATED)])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["thickness_known"] is True
    assert modelfile.read(out).thickness_um == 100.0


def test_conflicting_thickness_exits_2(tmp_path: Path, emulate: Callable[..., sw.Sweep]) -> None:
    a = emulate(sd.voltage_triangle(27.9, 150.0, 1, SAMPLE_RATE_HZ), 27.9, seed=3)
    b = sw.Sweep(a.time_s, a.voltage_v, a.displacement_um, {"layer_thickness_um": "50"})
    sw.write(a, tmp_path / "a.csv")
    sw.write(b, tmp_path / "b.csv")
    out = tmp_path / "m.toml"
    res = CliRunner().invoke(main, ["identify", str(tmp_path / "a.csv"), str(tmp_path / "b.csv"),
                                    "-o", str(out)])
    assert res.exit_code == 2 and "disagree" in res.stderr and len(res.stderr.splitlines()) == 1
    assert not out.exists()
