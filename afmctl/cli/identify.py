"""``afmctl identify``: fit the model to measured sweeps."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import click

from afmctl.cli.base import (
    check_output_dir,
    check_output_file,
    fit_settings,
    main,
    make_dir,
    say,
    writing,
)


def _report(result: Any) -> str:
    """Human-readable fit report (``result`` is an ``identify.FitResult``)."""
    state = "converged" if result.success else "NOT CONVERGED (its best point is kept)"
    lines = [f"fit {state}: {result.message} (status {result.status}, {result.nfev} evaluations, "
             f"{result.seconds:.2f} s)"]
    if not result.thickness_known:
        lines.append("layer thickness unknown: fitted in volts (thickness_um = 1 by convention)")
    if result.representations:
        lines.append(f"representation: {result.representations['chosen']} "
                     f"({result.representations['why']})")
    floor = "at" if result.at_noise_floor else "NOT at"
    lines.append(f"{floor} the noise floor (every sweep within 1.5x its sensor noise); "
                 f"N_c = {result.model.polarization.n_coercive}, {result.restarts} restart(s)")
    lines.append(f"{'sweep':32s} {'start':>9s} {'rms um':>9s} {'noise um':>9s} {'rms/noise':>9s} "
                 f"{'max um':>9s} {'rms %':>7s}")
    for s in result.sweeps:
        lines.append(f"{Path(s.file).name:32s} {s.start:>9s} {s.rms_um:9.4f} {s.noise_um:9.4f} "
                     f"{s.rms_over_noise:9.2f} {s.max_um:9.4f} {s.rms_pct:7.3f}")
    lines.append("parameters (1-sigma from the Jacobian):")
    for p in result.parameters:
        err = "fixed (scale convention)" if p.fixed else f"+- {p.stderr:.4g}"
        lines.append(f"  {p.name:20s} {p.value:14.6g} {err:>26s}  {p.unit}")
    und = result.uncertainty.get("undetermined", [])
    lines.append("undetermined by the data: " + (", ".join(und) if und else "none"))
    if result.envelope is not None:
        lines.append(f"validity envelope: {result.envelope.describe()}")
    return "\n".join(lines)


def _warn_above_floor(result: Any) -> None:
    """Name on stderr every sweep the best fit leaves above 2x its sensor noise."""
    for s in result.above_floor():
        click.echo(f"warning: {Path(s.file).name}: fit RMS {s.rms_um:.4f} um is "
                   f"{s.rms_over_noise:.1f}x its sensor noise ({s.noise_um:.4f} um); the model "
                   f"misses something there: run `afmctl diagnose` on these sweeps", err=True)


@main.command()
@click.argument("sweep_files", nargs=-1, required=True)
@click.option("--profile", "profile", default=None, help="Stage profile: its [stack] thickness "
              "for sweeps without layer_thickness_um; its [identify] table sets mass_kg, "
              "p_r_C_per_m2, thickness_um, n_coercive_fit, field_step, max_nfev, restarts.")
@click.option("-o", "--output", required=True,
              help="Model file to write (TOML); an existing file only with --force, a measured "
                   "file (sweep, run) never.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@click.option("--plots", "plots_dir", default=None, help="Directory for per-sweep figures.")
@click.option("--force", is_flag=True, help="Overwrite an existing model file or figures.")
def identify(sweep_files: tuple[str, ...], profile: str | None, output: str, as_json: bool,
             plots_dir: str | None, force: bool) -> None:
    """Fit the stage model jointly to SWEEP_FILES and write it to the model file OUTPUT.

    Sweeps in the order they were recorded. Exit status: 0 a model was written, 1 the fit gave
    no finite model (nothing written), 2 bad input. The model written is the best the fit found,
    converged or not (``success``) and at its sensor noise or not (``at_noise_floor``): each
    sweep's fit RMS is reported against its sensor noise (estimated from the data), and a fit
    that stopped early or sweeps left above 2x are named on stderr.
    """
    from afmctl.files import modelfile
    from afmctl.files import sweepfile as sweeps
    from afmctl.fit import identify as idf

    settings = fit_settings(profile)
    data = [sweeps.read_complete(f) for f in sweep_files]
    check_output_file(output, "-o", force)
    if plots_dir is not None:
        from afmctl import plots
        check_output_dir(plots_dir, "--plots", plots.fit_names(data), force)
    idf.resolve_thickness(data, settings)  # validate before any progress output
    say(f"fitting {len(data)} sweep(s) ...")
    result = idf.fit(data, settings, progress=say)
    if result.finite:  # the model first: a figure that fails must not cost the fit
        header = "afmctl identify: " + ", ".join(Path(f).name for f in sweep_files)
        header += "\nm and p_r are fixed by convention (only their ratios to c, k, a1, a2, eta"
        header += " are identifiable)"
        with writing(output, "-o"):
            modelfile.write(result.model, output, header=header, envelope=result.envelope,
                            uncertainty=result.uncertainty)
        say(f"wrote {output}")
    if plots_dir is not None:
        fitted = idf.predict_set(result.model, data, [s.start for s in result.sweeps],
                                 [s.offset_um for s in result.sweeps])
        with writing(plots_dir, "--plots"):
            for p in plots.fit_figures(data, fitted, make_dir(Path(plots_dir), "--plots"),
                                       settings.window_s):
                say(f"wrote {p}")
    _warn_above_floor(result)
    if result.finite and not result.success:
        click.echo(f"warning: the solver stopped before converging ({result.message}); the "
                   f"model written is its best point (at_noise_floor: "
                   f"{str(result.at_noise_floor).lower()})", err=True)
    click.echo(json.dumps(result.to_dict()) if as_json else _report(result))
    if not result.finite:
        sys.exit(1)

