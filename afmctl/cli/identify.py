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
    say_no_twin,
    writing,
)

#: Readable names of the fit's internal parameters (:mod:`afmctl.fit.uncertainty`).
INTERNAL_NAMES = {"log_median_MV_per_m": "coercive median", "log_sigma_ln": "coercive sigma_ln",
                  "log_std_MV_per_m": "interaction std", "log_r_MV_per_m": "eta p_r",
                  "log_natural_hz": "natural frequency", "log_damping_ratio": "damping ratio",
                  "g1_um_per_MV_per_m": "gain g1", "g2_um_per_MV2_per_m2": "gain g2"}


def _internal_name(name: str) -> str:
    if name.startswith("c@"):  # a node of the general coercive density, not the damping c
        return f"coercive density at {name[2:]} MV/m"
    return INTERNAL_NAMES.get(name, name)


def undetermined_text(result: Any) -> str:
    """The parameters the data do not fix: the fit's own list (internal parameters whose 1-sigma
    exceeds half their value, or that trade off with another along a valley), in words, and the
    physical parameters whose 1-sigma exceeds half their value."""
    from afmctl.fit.uncertainty import UNDETERMINED_REL
    out = [_internal_name(n) for n in result.uncertainty.get("undetermined", [])]
    for p in result.parameters:
        if not p.fixed and p.value and p.stderr > UNDETERMINED_REL * abs(p.value):
            out.append(f"{p.name} (+- {100 * p.stderr / abs(p.value):.0f} %)")
    if not out:
        return "undetermined by the data: none"
    return ("undetermined by the data (1-sigma above half the value, or traded off with "
            "another: the data fix a combination, not each): " + ", ".join(dict.fromkeys(out)))


def start_notes(result: Any, data: Any) -> list[str]:
    """What a start state means on sweeps that never reach the other polarity: fitted, it only
    says which way the hysterons their field cannot switch point, not that the stage was driven
    there."""
    one_sided = [s for s, d in zip(result.sweeps, data, strict=True)
                 if (s.start == "negative" and float(d.voltage_v.min()) >= 0)
                 or (s.start == "positive" and float(d.voltage_v.max()) <= 0)]
    if not one_sided or result.representation == "bouc-wen":  # poled: over the sweeps' range
        return []
    names = ", ".join(Path(s.file).name for s in one_sided)
    return [f"start: the hysteresis state each sweep is fitted to start from. On {names}, which "
            f"never change the voltage's sign, 'negative' or 'positive' only says which way the "
            f"hysterons their field cannot switch point (a constant in the polarization, which "
            f"the force's quadratic term turns into a small gain); it does not say the stage "
            f"was driven there"]


def _report(result: Any, data: Any = None, reach: str = "", loops: str = "") -> str:
    """Human-readable fit report (``result`` is an ``identify.FitResult``, ``data`` its
    sweeps, ``loops`` the minor loops' closure in words)."""
    state = "converged" if result.success else "NOT CONVERGED (its best point is kept)"
    lines = [f"fit {state}: {result.message} (status {result.status}, {result.nfev} evaluations, "
             f"{result.seconds:.2f} s)"]
    if not result.thickness_known:
        lines.append("layer thickness unknown: fitted in volts (thickness_um = 1 by convention)")
    if "chosen" in result.representations:  # a two-axis fit may hold only its mode's figures
        lines.append(f"representation: {result.representations['chosen']} "
                     f"({result.representations['why']})")
    floor = "at" if result.at_noise_floor else "NOT at"
    n_c = result.model.polarization.n_coercive
    lines.append(f"{floor} the noise floor (every sweep within 1.5x its sensor noise); "
                 + (f"N_c = {n_c}, " if n_c else "") + f"{result.restarts} restart(s)")
    lines.append(f"{'sweep':32s} {'start':>9s} {'rms um':>9s} {'noise um':>9s} {'rms/noise':>9s} "
                 f"{'max um':>9s} {'rms %':>7s}")
    for s in result.sweeps:
        lines.append(f"{Path(s.file).name:32s} {s.start:>9s} {s.rms_um:9.4f} {s.noise_um:9.4f} "
                     f"{s.rms_over_noise:9.2f} {s.max_um:9.4f} {s.rms_pct:7.3f}")
    if data is not None:
        lines += start_notes(result, data)
    if loops:
        lines.append(loops)
    lines.append("parameters (1-sigma from the Jacobian):")
    for p in result.parameters:
        err = "fixed (scale convention)" if p.fixed else f"+- {p.stderr:.4g}"
        lines.append(f"  {p.name:20s} {p.value:14.6g} {err:>26s}  {p.unit}")
    lines.append(undetermined_text(result))
    if result.envelope is not None:
        lines.append(f"validity envelope: {result.envelope.describe()}")
    if reach:
        lines.append(reach)
    return "\n".join(lines)


def _warn_few_reversals(result: Any) -> None:
    """The Preisach grid kept on sweeps that trace reversal curves from few voltages inside their
    range: its interior (every minor loop a tracking waveform makes) is the smoothing's guess."""
    from afmctl.fit import representation as rep

    n = result.representations.get("preisach", {}).get("interior_reversals")
    if result.representation == "preisach" and n is not None and n < rep.REVERSALS_NEEDED:
        click.echo(f"warning: the Preisach grid was fitted to sweeps that trace reversal curves "
                   f"from {n} voltage(s) inside their range (a triangle over the whole range "
                   f"traces none, and steps and a fast multisine jump over theirs): minor loops "
                   f"inside it are the smoothing's guess; record the reversal curves with the "
                   f"standard set and the separating sweep, back to back (`afmctl sweep --design "
                   f"full --out NEW_FOLDER`, about a minute, so that a creeping stage's twin "
                   f"follows them) and identify on those", err=True)
    grid = result.representations.get("preisach", {})
    if result.representation == "preisach" and grid.get("force_cubic_fitted") is False:
        click.echo(f"note: the force's cubic a3 P^3 is held at 0: the sweeps run "
                   f"{grid['interior_loops']} loop(s) with both ends inside their range, and "
                   f"first-order reversal curves alone fit as well with any cubic; a stage whose "
                   f"displacement is not quadratic in its hysteresis (a modified Prandtl-"
                   f"Ishlinskii stage) needs `afmctl sweep --design full` (interior loops)",
                   err=True)


def _warn_above_floor(result: Any) -> None:
    """Name on stderr every sweep the best fit leaves above 2x its sensor noise."""
    for s in result.above_floor():
        click.echo(f"warning: {Path(s.file).name}: fit RMS {s.rms_um:.4f} um is "
                   f"{s.rms_over_noise:.1f}x its sensor noise ({s.noise_um:.4f} um); the model "
                   f"misses something there: run `afmctl diagnose` on these sweeps", err=True)


def _warn_offsets(result: Any) -> None:
    """Name on stderr every sweep whose sensor zero disagrees with the model's."""
    z = result.sweeps[result.zero_index]
    for s in result.offsets_disagreeing():
        click.echo(f"warning: {Path(s.file).name}: sensor zero {s.offset_um:.4g} um (start "
                   f"{s.start}) is {abs(s.offset_um - z.offset_um):.4g} um from the model's, "
                   f"{z.offset_um:.4g} um of {Path(z.file).name} (start {z.start}): the sensor "
                   f"was re-zeroed between them, or that start does not fit the sweep and its "
                   f"offset absorbed the misfit; positions planned from the model are in "
                   f"{Path(z.file).name}'s frame", err=True)


@main.command()
@click.argument("sweep_files", nargs=-1, required=True)
@click.option("--profile", "profile", default=None, help="Stage profile, a file or a shipped "
              "name (emulated, lab-serial, ...): its [stack] thickness for sweeps without "
              "layer_thickness_um; its [identify] table sets mass_kg, p_r_C_per_m2, "
              "thickness_um, n_coercive_fit, field_step, max_nfev, restarts; and the model's "
              "reach within its voltage limits is reported.")
@click.option("-o", "--output", required=True,
              help="Model file to write (TOML); an existing file only with --force, a measured "
                   "file (sweep, run) never.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@click.option("--plots", "plots_dir", default=None, help="Directory for per-sweep figures.")
@click.option("--force", is_flag=True, help="Overwrite an existing model file or figures.")
def identify(sweep_files: tuple[str, ...], profile: str | None, output: str, as_json: bool,
             plots_dir: str | None, force: bool) -> None:
    """Fit the stage model jointly to SWEEP_FILES and write it to the model file OUTPUT.

    Sweeps in the order they were recorded. Two-axis sweep files (voltage_x_V, voltage_y_V, ...)
    give a two-axis model: each axis and the coupling both ways (--json adds ``axes`` and
    ``coupling``). Exit status: 0 a model was written, 1 the fit gave
    no finite model (nothing written), 2 bad input. The model written is the best the fit found,
    converged or not (``success``) and at its sensor noise or not (``at_noise_floor``): each
    sweep's fit RMS is reported against its sensor noise (estimated from the data), and a fit
    that stopped early or sweeps left above 2x are named on stderr.
    """
    from afmctl.experiment import twin
    from afmctl.files import modelfile
    from afmctl.files import sweepfile as sweeps
    from afmctl.files import xysweepfile
    from afmctl.fit import closure
    from afmctl.fit import identify as idf

    settings = fit_settings(profile)
    xy = xysweepfile.read_set(sweep_files)
    if xy is not None:
        from afmctl.cli.xyidentify import identify_xy
        identify_xy(xy, sweep_files, settings, output, as_json, plots_dir, force)
        return
    data = sweeps.in_recorded_order([sweeps.read_complete(f) for f in sweep_files])
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
                            uncertainty=result.uncertainty, fit=result.record())
            kept = twin.keep_beside(result.model, data, output)
        say(f"wrote {output}")
        if kept is not None:
            say(f"wrote {kept} (the model's twin of the stage as the sweeps left it: track plans "
                f"a creeping stage's next run from it)")
        else:
            say_no_twin(data)
    if plots_dir is not None:
        fitted = idf.predict_set(result.model, data, [s.start for s in result.sweeps],
                                 [s.offset_um for s in result.sweeps])
        with writing(plots_dir, "--plots"):
            for p in plots.fit_figures(data, fitted, make_dir(Path(plots_dir), "--plots"),
                                       settings.window_s):
                say(f"wrote {p}")
    _warn_above_floor(result)
    _warn_offsets(result)
    _warn_few_reversals(result)
    loops = closure.check(data, [s.noise_um for s in result.sweeps])
    if loops["close"] is False:
        click.echo(f"warning: {loops['text']}", err=True)
    if result.finite and not result.success:
        click.echo(f"warning: the solver stopped before converging ({result.message}); the "
                   f"model written is its best point (at_noise_floor: "
                   f"{str(result.at_noise_floor).lower()})", err=True)
    reach = _reach(result, profile) if result.finite and profile is not None else None
    if as_json:
        doc = result.to_dict()
        doc["twin"] = str(kept) if result.finite and kept is not None else None
        if reach is not None:
            doc["reach_um"] = list(reach[:2])
        doc["minor_loops"] = loops
        click.echo(json.dumps(doc))
    else:
        click.echo(_report(result, data, "" if reach is None else reach[2], loops["text"]))
    if not result.finite:
        sys.exit(1)



def _reach(result: Any, profile: str) -> tuple[float, float, str]:
    """The identified model's reach on ``profile`` (um) and its report line."""
    from afmctl.cli.base import load_profile_or_exit
    from afmctl.planning import track
    prof = load_profile_or_exit(profile)
    lo, hi = track.reach(result.model, prof.limits, result.envelope)
    lim = track.conditioning_limits(prof.limits, result.envelope)
    return lo, hi, (f"reach on profile {prof.name!r}: {lo:.4g} ... {hi:.4g} um on {lim.v_min:.4g} "
                    f"... {lim.v_max:.4g} V (quasi-static; a trajectory's centre, `track --offset`,"
                    f" and amplitude must keep inside it: `afmctl reach`)")
