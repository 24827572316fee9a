"""Command line: ``afmctl``. Composes the library; holds no numerics and no device I/O."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import click

from afmctl import __version__

if TYPE_CHECKING:
    from afmctl import identify as identify_mod
    from afmctl.sweeps import Sweep


class InputError(Exception):
    """Bad input from the user: printed as one line ``afmctl: error: ...`` with exit code 2."""


def _fail(msg: str, code: int = 2) -> None:
    click.echo(f"afmctl: error: {msg}", err=True)
    sys.exit(code)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="afmctl")
def main() -> None:
    """Make a hysteretic piezo stage track what it is told (Hatch, Smith et al. inverse filter)."""


def _report(result: identify_mod.FitResult) -> str:
    state = "converged" if result.success else "NOT CONVERGED (fit failed)"
    lines = [f"fit {state}: {result.message} (status {result.status}, {result.nfev} evaluations, "
             f"{result.seconds:.2f} s)"]
    if not result.thickness_known:
        lines.append("layer thickness unknown: fitted in volts (thickness_um = 1 by convention)")
    lines.append(f"{'sweep':40s} {'rms um':>9s} {'max um':>9s} {'rms %':>7s} {'max %':>7s}")
    for s in result.sweeps:
        lines.append(f"{Path(s.file).name:40s} {s.rms_um:9.4f} {s.max_um:9.4f} "
                     f"{s.rms_pct:7.3f} {s.max_pct:7.3f}")
    lines.append("parameters (1-sigma from the Jacobian):")
    for p in result.parameters:
        err = "fixed (scale convention)" if p.fixed else f"+- {p.stderr:.4g}"
        lines.append(f"  {p.name:20s} {p.value:14.6g} {err:>26s}  {p.unit}")
    return "\n".join(lines)


def _load_inputs(files: tuple[str, ...],
                 profile: str | None) -> tuple[list[Sweep], identify_mod.Settings]:
    from afmctl import identify, sweeps, tomlfile

    table = None
    if profile is not None:
        table = tomlfile.load(profile).table("identify", required=False)
    settings = identify.settings_from_table(table)
    return [sweeps.read(f) for f in files], settings


@main.command()
@click.argument("sweep_files", nargs=-1, required=True)
@click.option("--profile", "profile", default=None, help="TOML profile; its [identify] table "
              "sets mass_kg, p_r_C_per_m2, thickness_um, n_coercive_fit, field_step, max_nfev.")
@click.option("-o", "--output", required=True, help="Model file to write (TOML).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@click.option("--plots", "plots_dir", default=None, help="Directory for per-sweep figures.")
def identify(sweep_files: tuple[str, ...], profile: str | None, output: str, as_json: bool,
             plots_dir: str | None) -> None:
    """Fit the stage model jointly to SWEEP_FILES and write it to the model file OUTPUT.

    Exit status: 0 converged, 1 the solver did not converge (no model written), 2 bad input.
    """
    from afmctl import identify as idf
    from afmctl import modelfile
    from afmctl.tomlfile import FileFormatError

    try:
        sweeps, settings = _load_inputs(sweep_files, profile)
        if not Path(output).resolve().parent.is_dir():
            raise InputError(f"{output}: directory does not exist")
        idf.resolve_thickness(sweeps, settings)  # validate before any progress output
        click.echo(f"fitting {len(sweeps)} sweep(s) ...", err=True)
        result = idf.fit(sweeps, settings, progress=lambda m: click.echo(m, err=True))
    except (FileFormatError, InputError, idf.FitInputError) as exc:
        _fail(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        return
    if plots_dir is not None:
        from afmctl import plots

        fitted = [idf.predict(result.model, s.voltage_v, s.dt) for s in sweeps]
        for p in plots.fit_figures(sweeps, fitted, plots_dir):
            click.echo(f"wrote {p}", err=True)
    if result.success:
        header = "afmctl identify: " + ", ".join(Path(f).name for f in sweep_files)
        header += "\nm and p_r are fixed by convention (only their ratios to c, k, a1, a2, eta"
        header += " are identifiable)"
        modelfile.write(result.model, output, header=header)
        click.echo(f"wrote {output}", err=True)
    click.echo(json.dumps(result.to_dict()) if as_json else _report(result))
    if not result.success:
        sys.exit(1)
