"""Bad input files: each one exits 2 with one line naming the problem, and writes nothing.

The command reference's table of bad inputs (``docs/reference/cli.md``) is generated from
:data:`CASES` by this module (``python -m tests.files.test_bad_inputs`` prints it) and a test
checks that the page holds
exactly that table, so every message in it is what afmctl really prints.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.files import modelfile
from afmctl.files.profile import default_profile
from tests.harness.paths import PROFILES, REPO

ROOT = REPO
PROFILE_TEXT = (PROFILES / "emulated.toml").read_text()
SWEEP_TEXT = ("# frequency_hz: 5\n# layer_thickness_um: 100\ntime_s,voltage_V,displacement_um\n"
              + "".join(f"{k / 1e4:.4f},{k * 0.5:.1f},{k * 0.01:.3f}\n" for k in range(6)))
TRAJECTORY_TEXT = "time_s,desired_um\n0,0\n0.1,1\n0.2,2\n"


def model_text() -> str:
    """The emulated stage's true model, as a model file."""
    import tempfile
    model = default_profile().emulator.model  # type: ignore[union-attr]
    with tempfile.TemporaryDirectory() as tmp:
        modelfile.write(model, Path(tmp) / "m.toml")
        return (Path(tmp) / "m.toml").read_text()


def sub(old: str, new: str) -> Callable[[str], str]:
    def edit(text: str) -> str:
        assert old in text, old
        return text.replace(old, new, 1)
    return edit


def add(extra: str) -> Callable[[str], str]:
    return lambda text: text + extra


@dataclass(frozen=True)
class Case:
    """A bad input: which file, what is wrong with it, how to make it from a good one."""

    file: str  # profile | model | sweep | trajectory
    problem: str
    edit: Callable[[str], str] | None  # None: the file does not exist


CASES = [
    Case("profile", "NaN in TOML", sub("v_max_V = 150.0", "v_max_V = nan")),
    Case("profile", "inf in TOML", sub("slew_V_per_ms = 50.0", "slew_V_per_ms = inf")),
    Case("profile", "missing key", sub("v_min_V = -150.0\n", "")),
    Case("profile", "missing table", sub("[sensor]", "[sensors]")),
    Case("profile", "negative limit", sub("current_mA = 100.0", "current_mA = -100.0")),
    Case("profile", "inverted limits", lambda t: t.replace("v_min_V = -150.0", "v_min_V = X")
         .replace("v_max_V = 150.0", "v_max_V = -150.0").replace("v_min_V = X", "v_min_V = 150.0")),
    Case("profile", "range without 0 V (the safe state)", sub("v_min_V = -150.0", "v_min_V = 10.0")),
    Case("profile", "slew beyond current / capacitance",
         sub("slew_V_per_ms = 50.0", "slew_V_per_ms = 80.0")),
    Case("profile", "wrong type (string for a number)",
         sub("sample_rate_Hz = 10000.0", 'sample_rate_Hz = "10 kHz"')),
    Case("profile", "wrong type (string for a boolean)", sub("read_only = false", 'read_only = "no"')),
    Case("profile", "wrong type (number for a table)",
         lambda t: sub('name = "emulated"', 'name = "emulated"\nstack = 100.0')(
             sub("[stack]", "[stack_old]")(t))),
    Case("profile", "unknown transport", sub('kind = "emulated"', 'kind = "usb"')),
    Case("profile", "fault probability above 1", add("\n[emulator.faults]\ndrop = 1.5\n")),
    Case("profile", "unknown fault", add("\n[emulator.faults]\ndorp = 0.1\n")),
    Case("profile", "misspelt key", sub("noise_um = 0.02", "noise = 0.02")),
    Case("profile", "other format version", sub("format_version = 1", "format_version = 2")),
    Case("profile", "not TOML", add("\nthis is = = not toml\n")),
    Case("profile", "no such file", None),
    Case("model", "NaN in TOML", sub("k_N_per_m = 123370.0", "k_N_per_m = nan")),
    Case("model", "inf in TOML", sub("eta_MVm_per_Cm2 = 1.2", "eta_MVm_per_Cm2 = inf")),
    Case("model", "missing key", sub("m_kg = 0.05\n", "")),
    Case("model", "misspelt key", sub("sigma_ln = 0.4", "sigma_log = 0.4\nsigma_ln = 0.4")),
    Case("model", "negative value", sub("median_MV_per_m = 1.0", "median_MV_per_m = -1.0")),
    Case("model", "wrong type (string for an integer)",
         sub("n_coercive = 256", 'n_coercive = "many"')),
    Case("model", "wrong type (float for an integer)", sub("n_coercive = 256", "n_coercive = 256.5")),
    Case("model", "not a model file", sub('format = "afmctl-model"', 'format = "afmctl-profile"')),
    Case("sweep", "empty file", lambda t: ""),
    Case("sweep", "missing column", sub("displacement_um", "disp")),
    Case("sweep", "NaN value", sub("0.0002,1.0,0.020", "0.0002,nan,0.020")),
    Case("sweep", "inf value", sub("0.0002,1.0,0.020", "0.0002,1.0,inf")),
    Case("sweep", "text for a number", sub("0.0002,1.0,0.020", "0.0002,one,0.020")),
    Case("sweep", "time not increasing", sub("0.0003,", "0.0001,")),
    Case("sweep", "not uniformly sampled", sub("0.0005,", "0.0009,")),
    Case("sweep", "one sample only", lambda t: "\n".join(t.splitlines()[:4]) + "\n"),
    Case("sweep", "bad metadata", sub("layer_thickness_um: 100", "layer_thickness_um: -1")),
    Case("trajectory", "missing column", sub("desired_um", "wanted_um")),
    Case("trajectory", "NaN value", sub("0.1,1", "0.1,nan")),
]

GOOD = {"profile": PROFILE_TEXT, "sweep": SWEEP_TEXT, "trajectory": TRAJECTORY_TEXT}
NAMES = {"profile": "stage.toml", "model": "model.toml", "sweep": "sweep.csv",
         "trajectory": "wave.csv"}


def command(case: Case) -> list[str]:
    """The afmctl command that reads the bad file (run in a folder holding it and a good model)."""
    track = ["--freq", "5", "--amplitude", "10", "--dry-run", "--out", "out"]
    if case.file == "profile":
        return ["track", "triangle", *track, "--profile", "stage.toml", "--model", "good.toml"]
    if case.file == "model":
        return ["track", "triangle", *track, "--model", "model.toml"]
    if case.file == "trajectory":
        return ["track", "file", "wave.csv", "--dry-run", "--out", "out", "--model", "good.toml"]
    return ["identify", "sweep.csv", "-o", "out/model.toml"]


def run(case: Case, folder: Path) -> tuple[int, str, str, list[str]]:
    """(exit code, stdout, stderr, files written) of the case's command run in ``folder``."""
    good_model = model_text()
    (folder / "good.toml").write_text(good_model)
    if case.edit is not None:
        text = good_model if case.file == "model" else GOOD[case.file]
        (folder / NAMES[case.file]).write_text(case.edit(text))
    if case.file == "sweep":
        (folder / "out").mkdir()
    before = set(folder.rglob("*"))
    cwd = Path.cwd()
    os.chdir(folder)
    try:
        res = CliRunner().invoke(main, command(case))
    finally:
        os.chdir(cwd)
    written = sorted(str(p.relative_to(folder)) for p in set(folder.rglob("*")) - before)
    return res.exit_code, res.stdout, res.stderr, written


def table(folder: Path) -> str:
    """The command reference's markdown table: every case with the one line afmctl prints."""
    rows = ["| file | problem | what afmctl prints (exit 2, nothing written) |", "|---|---|---|"]
    for i, case in enumerate(CASES):
        (folder / str(i)).mkdir()
        _, _, err, _ = run(case, folder / str(i))
        msg = err.strip().replace("|", "\\|")
        rows.append(f"| {case.file} | {case.problem} | `{msg}` |")
    return "\n".join(rows) + "\n"


@pytest.mark.parametrize("case", CASES, ids=[f"{c.file}-{c.problem}" for c in CASES])
def test_bad_input_exits_2_with_one_line_and_writes_nothing(case: Case, tmp_path: Path) -> None:
    code, out, err, written = run(case, tmp_path)
    assert code == 2, err
    assert out == "" and err.count("\n") == 1 and err.startswith("afmctl: error: ")
    assert NAMES[case.file] in err  # it names the file
    assert written == []


def reference_section(tag: str) -> str:
    """The command reference's text between ``<!-- TAG:begin -->`` and ``<!-- TAG:end -->``."""
    readme = (ROOT / "docs" / "reference" / "cli.md").read_text()
    begin, end = f"<!-- {tag}:begin -->\n", f"<!-- {tag}:end -->"
    assert begin in readme and end in readme
    return readme[readme.index(begin) + len(begin):readme.index(end)]


def test_reference_table_is_what_afmctl_prints(tmp_path: Path) -> None:
    assert reference_section("bad-inputs") == table(tmp_path)


if __name__ == "__main__":
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        print(table(Path(tmp)), end="")
