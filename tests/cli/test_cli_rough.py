"""Rough hands: every command's help, rough numbers on the command line, rough output paths, and
sweep files as DAQs and spreadsheets write them.

The command reference's table of rough inputs (``docs/reference/cli.md``) is generated from
:data:`CASES` by this module (``python -m tests.cli.test_cli_rough`` prints it) and a test checks
that the page holds exactly that table:
every exit code and line in it is what afmctl really prints. A refused input exits 2 with one
line and writes nothing.
"""

from __future__ import annotations

import dataclasses as dc
import functools
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.drivers.device import plant
from afmctl.files import modelfile
from afmctl.files.profile import default_profile
from afmctl.planning import sweepdesign as sd

RATE_HZ = 10_000.0
TRACK = ["track", "triangle", "--model", "good.toml", "--dry-run"]


def command_paths(group: click.Group, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Every command and subcommand of ``group`` as its argv prefix."""
    out = [prefix]
    for name, cmd in sorted(group.commands.items()):
        if isinstance(cmd, click.Group):
            out += command_paths(cmd, (*prefix, name))
        else:
            out.append((*prefix, name))
    return out


@pytest.mark.parametrize("path", command_paths(main), ids=lambda p: " ".join(p) or "afmctl")
@pytest.mark.parametrize("flag", ["--help", "-h"])
def test_help_exits_0_with_nothing_on_stderr(path: tuple[str, ...], flag: str) -> None:
    res = CliRunner().invoke(main, [*path, flag])
    assert res.exit_code == 0, res.output
    assert res.stderr == "" and res.stdout.startswith("Usage: ")


def test_version_exits_0() -> None:
    res = CliRunner().invoke(main, ["--version"])
    assert res.exit_code == 0 and res.stderr == "" and "afmctl, version" in res.stdout


@functools.cache
def base_sweep() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """3 cycles of the 27.9 Hz triangle (0.11 s at 10 kHz) on the emulated stage."""
    cfg = default_profile().emulator
    assert cfg is not None
    v = sd.voltage_triangle(27.9, 150.0, 3, RATE_HZ)
    u, _ = plant.expected_readback(dc.replace(cfg, seed=5), RATE_HZ, v)
    return np.arange(v.size) / RATE_HZ, v, u


def sweep_text(header: str, rows: Callable[[np.ndarray, np.ndarray, np.ndarray], list[str]],
               meta: str = "# layer_thickness_um: 100\n") -> str:
    t, v, u = base_sweep()
    return meta + header + "\n" + "\n".join(rows(t, v, u)) + "\n"


def jitter(fraction: float) -> Callable[..., list[str]]:
    def rows(t: np.ndarray, v: np.ndarray, u: np.ndarray) -> list[str]:
        j = np.random.default_rng(1).uniform(-fraction, fraction, t.size) / RATE_HZ
        return [f"{a:.8f},{b:.6f},{c:.6f}" for a, b, c in zip(t + j, v, u, strict=True)]
    return rows


ROUGH_FILES = {
    "float32 time column (a DAQ clock at 100 s, 10 kHz)": lambda: sweep_text(
        "time_s,voltage_V,displacement_um",
        lambda t, v, u: [f"{np.float32(100 + a)},{b:.6f},{c:.6f}"
                         for a, b, c in zip(t, v, u, strict=True)]),
    "timestamps with +-5 % jitter": lambda: sweep_text("time_s,voltage_V,displacement_um",
                                                       jitter(0.05)),
    "timestamps with +-30 % jitter": lambda: sweep_text("time_s,voltage_V,displacement_um",
                                                        jitter(0.3)),
    "time_ms, Voltage (V), displacement_nm": lambda: sweep_text(
        "time_ms,Voltage (V),displacement_nm",
        lambda t, v, u: [f"{1e3 * a:.4f},{b:.6f},{1e3 * c:.3f}" for a, b, c in zip(t, v, u, strict=True)]),
    "`;` between columns, decimal commas": lambda: sweep_text(
        "time_s;voltage_V;displacement_um",
        lambda t, v, u: [f"{a:.7f};{b:.6f};{c:.6f}".replace(".", ",")
                         for a, b, c in zip(t, v, u, strict=True)]),
    "decimal commas in a comma-separated file": lambda: sweep_text(
        "time_s,voltage_V,displacement_um",
        lambda t, v, u: [f"{a:.7f},{b:.6f},{c:.6f}".replace(".", ",")
                         for a, b, c in zip(t, v, u, strict=True)]),
    "no time column, `sample_rate_hz: 10000` metadata": lambda: sweep_text(
        "voltage_V,displacement_um",
        lambda t, v, u: [f"{b:.6f},{c:.6f}" for b, c in zip(v, u, strict=True)],
        "# layer_thickness_um: 100\n# sample_rate_hz: 10000\n"),
    "`sample_rate_hz: 5000` metadata, time column at 10 kHz": lambda: sweep_text(
        "time_s,voltage_V,displacement_um",
        lambda t, v, u: [f"{a:.7f},{b:.6f},{c:.6f}" for a, b, c in zip(t, v, u, strict=True)],
        "# layer_thickness_um: 100\n# sample_rate_hz: 5000\n"),
}


@dataclass(frozen=True)
class Case:
    """A rough input: what it is, the command (run in a folder holding ``good.toml``, a good
    ``sweep.csv`` and ``rough.csv``), and files to put there first."""

    what: str
    argv: tuple[str, ...]
    setup: tuple[tuple[str, str], ...] = ()


def track(*args: str) -> tuple[str, ...]:
    base = {"--freq": "27.9", "--amplitude": "27.04", "--out": "out"}
    base.update(dict(zip(args[::2], args[1::2], strict=True)))
    return (*TRACK, *sum(([k, v] for k, v in base.items()), []))


def _flag(*args: str) -> tuple[str, ...]:
    return (*TRACK, "--freq", "27.9", "--amplitude", "27.04", "--out", "out", *args)


RUN_FILE = "# afmctl-run: 1\nseq,time_s,desired_um,voltage_V,displacement_um,status\n"
CASES = [
    Case("`--freq nan`", track("--freq", "nan")),
    Case("`--freq inf`", track("--freq", "inf")),
    Case("`--freq 0`", track("--freq", "0")),
    Case("`--freq 1e-6` (days long)", track("--freq", "1e-6")),
    Case("`--freq 5000` (2 samples a period)", track("--freq", "5000")),
    Case("`--amplitude inf`", track("--amplitude", "inf")),
    Case("`--amplitude -3`", track("--amplitude", "-3")),
    Case("`--amplitude 1e30`", track("--amplitude", "1e30")),
    Case("`--amplitude 400` (beyond the stage)", track("--amplitude", "400")),
    Case("`--offset nan`", track("--offset", "nan")),
    Case("`--periods inf`", track("--periods", "inf")),
    Case("`--periods nan`", track("--periods", "nan")),
    Case("`--periods 0.001`", track("--periods", "0.001")),
    Case("`--periods 0`", track("--periods", "0")),
    Case("`--out` is a file", track("--out", "good.toml")),
    Case("`--out` where nothing can be written", track("--out", "/proc/afmctl-out")),
    Case("`--out` holding run files, even with `--force`", _flag("--force"),
         (("out/run_inverse.csv", RUN_FILE),)),
    Case("`--out` holding earlier outputs", track(), (("out/waveform_inverse.csv", "x\n"),)),
    Case("`identify -o` a sweep file, even with `--force`",
         ("identify", "sweep.csv", "-o", "sweep.csv", "--force")),
    Case("`identify -o` an existing model", ("identify", "sweep.csv", "-o", "good.toml")),
    Case("`identify -o` in a missing folder", ("identify", "sweep.csv", "-o", "no/model.toml")),
    Case("`identify --plots` where nothing can be written",
         ("identify", "sweep.csv", "-o", "m.toml", "--plots", "/proc/afmctl-plots")),
    Case("`diagnose --out` holding a diagnosis", ("diagnose", "sweep.csv", "--out", "d"),
         (("d/diagnosis.json", "{}\n"),)),
    Case("`sweep --v-range 20 150` (0 V outside)", ("sweep", "--out", "s", "--v-range", "20", "150")),
    Case("`sweep --v-range -200 150`", ("sweep", "--out", "s", "--v-range", "-200", "150")),
    Case("`sweep --v-range nan 150`", ("sweep", "--out", "s", "--v-range", "nan", "150")),
    Case("`sweep --amplitude 150` (gone: `--v-range`)", ("sweep", "--out", "s", "--amplitude", "150")),
    *(Case(f"sweep file: {what}", ("identify", "rough.csv", "-o", "m.toml"), (("rough.csv", ""),))
      for what in ROUGH_FILES),
]


def run(case: Case, folder: Path) -> tuple[int, str, str, list[str]]:
    """(exit code, stdout, stderr, files written) of the case's command run in ``folder``."""
    cfg = default_profile().emulator
    assert cfg is not None
    modelfile.write(cfg.model, folder / "good.toml")
    (folder / "sweep.csv").write_text(ROUGH_FILES["timestamps with +-5 % jitter"]())
    for name, text in case.setup:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        if name == "rough.csv":
            text = ROUGH_FILES[case.what.removeprefix("sweep file: ")]()
        (folder / name).write_text(text)
    before = {p: p.stat().st_mtime_ns for p in folder.rglob("*")}
    cwd = Path.cwd()
    os.chdir(folder)
    try:
        res = CliRunner().invoke(main, list(case.argv))
    finally:
        os.chdir(cwd)
    changed = sorted(str(p.relative_to(folder)) for p in folder.rglob("*")
                     if before.get(p) != p.stat().st_mtime_ns)
    return res.exit_code, res.stdout, res.stderr, changed


def table(folder: Path) -> str:
    """The command reference's markdown table: every case, its exit code and the last line on
    stderr."""
    rows = ["| rough input | exit | what afmctl prints (last line on stderr) |", "|---|---|---|"]
    for i, case in enumerate(CASES):
        (folder / str(i)).mkdir()
        code, _, err, _ = run(case, folder / str(i))
        line = err.strip().splitlines()[-1].replace("|", "\\|") if err.strip() else ""
        rows.append(f"| {case.what} | {code} | `{line}` |")
    return "\n".join(rows) + "\n"


@pytest.mark.parametrize("case", CASES, ids=[c.what for c in CASES])
def test_rough_input(case: Case, tmp_path: Path) -> None:
    code, out, err, written = run(case, tmp_path)
    if code == 0:  # accepted sweep files: the fit ran and the model was written
        assert case.what.startswith("sweep file: ") and written == ["m.toml"]
        return
    assert code == 2, err
    assert out == "" and err.count("\n") == 1 and err.startswith("afmctl: error: "), err
    assert written == [], written


@pytest.mark.slow
def test_reference_table_is_what_afmctl_prints(tmp_path: Path) -> None:
    from tests.files.test_bad_inputs import reference_section
    assert reference_section("rough-inputs") == table(tmp_path)


if __name__ == "__main__":
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        print(table(Path(tmp)), end="")


@pytest.mark.parametrize("path", [(), ("track",)], ids=["afmctl", "track"])
def test_bare_group_shows_its_help(path: tuple[str, ...]) -> None:
    res = CliRunner().invoke(main, list(path))
    assert res.exit_code == 2 and res.stderr.startswith("Usage: ") and "afmctl: error" not in res.stderr
