"""``afmctl diagnose``: what the model gets wrong, the cause, the extended model."""

from __future__ import annotations

import json
from pathlib import Path

import click

from afmctl.cli.base import (
    Finite,
    check_output_dir,
    fit_settings,
    load_profile_or_exit,
    main,
    make_dir,
    say,
    say_no_twin,
    timestamped,
    writing,
)
from afmctl.errors import InputError, OutputError

OUTPUTS = ("diagnosis.json", "base.toml", "extended.toml", "report.md", "residuals.png")
#: Each model's twin of the stage as the sweeps left it, beside it where the sweeps say their holds.
TWINS = ("base.twin.json", "extended.twin.json")


@main.command()
@click.argument("sweep_files", nargs=-1, required=True)
@click.option("--model", "model_path", type=click.Path(dir_okay=False), default=None,
              help="Start the fits from this model (any model identify writes; a general "
                   "coercive density starts them as its lognormal) instead of identifying one.")
@click.option("--profile", "profile", default=None,
              help="Stage profile, a file or a shipped name (emulated, lab-serial, ...): its "
                   "[stack] thickness for sweeps without one; its [identify] table sets the "
                   "fit options; a suggested separating sweep keeps to half its slew limit.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Output folder (default: ./afmctl-diagnose-<time>).")
@click.option("--noise-um", "noise_um", type=Finite(0, open_min=True), default=None,
              help="Sensor noise (1 sigma, um) of every sweep: the floor the errors are read "
                   "against (default: estimated from each sweep's data).")
@click.option("--jobs", type=click.IntRange(1, 256), default=None,
              help="Candidates fitted at once, each in its own process (default: one per core).")
@click.option("--json", "as_json", is_flag=True, help="Print diagnosis.json on stdout.")
@click.option("--force", is_flag=True, help="Overwrite an earlier diagnosis in --out.")
def diagnose(sweep_files: tuple[str, ...], model_path: str | None, profile: str | None,
             out_dir: str | None, noise_um: float | None, jobs: int | None, as_json: bool,
             force: bool) -> None:
    """Find what the model gets wrong on SWEEP_FILES, name the physical cause, extend the model
    and measure the gain on held-out data.

    Writes diagnosis.json, base.toml and extended.toml (model files for track), report.md and
    residuals.png to --out, and beside each model, where the sweeps say when they were recorded,
    its twin of the stage as the sweeps left it (base.twin.json, extended.twin.json): track plans
    a creeping stage's next run from it, as from identify's.
    """
    from afmctl.files import modelfile
    from afmctl.files import sweepfile as sweeps
    from afmctl.fit import diagnose as dg
    from afmctl.fit import identify as idf
    from afmctl.fit import parametrization

    slew = None if profile is None else load_profile_or_exit(profile).limits.slew_v_per_ms * 1e3
    settings = dg.Settings(identify=fit_settings(profile), jobs=jobs, max_slew_v_per_s=slew)
    # in the order recorded where the files say (a shell glob sorts triangle_27.9hz before
    # triangle_5.58hz): each sweep's creep and the holds between them, as identify fits them
    data = sweeps.in_recorded_order([sweeps.read_complete(f) for f in sweep_files])
    start = None if model_path is None else modelfile.read(model_path)
    if start is not None:
        equivalent = parametrization.lognormal_equivalent(start)
        if equivalent != start:  # identify's general density: the fits start from its lognormal
            c = equivalent.polarization.coercive
            say(f"--model {model_path}: its general coercive-field density starts the fits as "
                f"the lognormal of the same log-moments (median {c.median:.4g} MV/m, sigma_ln "
                f"{c.sigma:.3g}): diagnose's candidates are fitted in the lognormal family")
        start = equivalent
        try:
            parametrization.internal(start)
        except ValueError as exc:
            raise InputError(f"--model {model_path}: {exc}") from None
    idf.resolve_thickness(data, settings.identify)
    dg.check(data)
    noise = None if noise_um is None else dg.check_noise(data, [noise_um] * len(data))
    out = Path(out_dir) if out_dir else timestamped("afmctl-diagnose")
    if (out / "diagnosis.json").exists() and not force:
        raise OutputError(f"--out {out}: already holds a diagnosis; choose another folder or add "
                          f"--force to overwrite it")
    check_output_dir(out, "--out", OUTPUTS + TWINS, force)
    say(f"diagnosing {len(data)} sweep(s): "
        f"{len(dg.with_forms(dg.candidate_names(len(data), settings)))} candidates ...")
    d = dg.diagnose(data, settings, start, progress=say, noise_um=noise)
    doc = d.as_dict()
    text = json.dumps(doc, indent=2, allow_nan=False) + "\n"  # before anything is written
    with writing(out, "--out"):
        twins = _write(d, data, sweep_files, out, text)
    say(f"cause: {d.cause} (held-out RMS {d.base_rms_um:.4f} -> {d.extended_rms_um:.4f} um, "
        f"gain {d.gain:.2f}; {d.base_over_noise:.2f}x -> {d.extended_over_noise:.2f}x the noise "
        f"{d.noise_um:.4f} um); wrote {out}/" + ", ".join(OUTPUTS[1:] + OUTPUTS[:1]))
    if twins:
        say(f"wrote {', '.join(twins)} (each model's twin of the stage as the sweeps left it: "
            f"track plans a creeping stage's next run from it)")
    else:
        say_no_twin(data)
    if d.cause == "unexplained":
        say(d.closest_dict()["text"])
    if d.kept_grid:
        say(f"base.toml and extended.toml hold the Preisach grid without creep (held-out "
            f"{d.file_over_noise[0]:.2f}x the noise; the paper's model {d.base_over_noise:.2f}x): "
            f"the best model diagnose fitted, with nothing added (or track with identify's "
            f"model)")
    for s in d.suggestions() if d.cause != "unexplained" else []:  # the closest says more
        say(f"{s['reading']}: {s['measure']}")
    if as_json:
        click.echo(json.dumps(doc, allow_nan=False))


def _write(d, data, sweep_files: tuple[str, ...], out: Path, text: str  # noqa: ANN001
           ) -> list[str]:
    """Every file of a diagnosis, each atomic, ``diagnosis.json`` last (marks it complete); the
    names of the twins written."""
    from afmctl import plots
    from afmctl.experiment import twin
    from afmctl.experiment.runner import atomic_write
    from afmctl.files import modelfile, twinfile
    from afmctl.fit import diagnosis_report
    make_dir(out, "--out")
    header = "afmctl diagnose: " + ", ".join(Path(f).name for f in sweep_files)
    names = tuple(Path(f).name for f in sweep_files)
    base, extended = d.file_models
    kept = " (kept: the best model diagnose fitted)" if d.kept_grid else ""
    modelfile.write(base, out / "base.toml",
                    header=header + f"\n{d.files_name}",
                    fit=_record(d, names, extended=False))
    modelfile.write(extended, out / "extended.toml",
                    header=header + f"\nextended with: {d.cause}{kept}",
                    fit=_record(d, names, extended=True))
    twins = []
    for model, path in ((base, out / "base.toml"), (extended, out / "extended.toml")):
        twinfile.path_for(path).unlink(missing_ok=True)  # an earlier diagnosis's (--force)
        kept = twin.keep_beside(model, data, path)  # data: in the order recorded
        twins += [] if kept is None else [kept.name]
    before, after = d.predictions(data)
    partial = out / "residuals.partial.png"
    plots.diagnosis_figure(data, before, after, d.base_model.thickness_um,
                           (d.base_name, f"extended: {d.cause}"), partial)
    partial.replace(out / "residuals.png")
    atomic_write(out / "report.md", diagnosis_report.report(d, "residuals.png"))
    atomic_write(out / "diagnosis.json", text)  # last: marks the folder complete
    return twins



def _record(d, names: tuple[str, ...], extended: bool):  # noqa: ANN001, ANN202 (Diagnosis -> FitRecord)
    """The ``[fit]`` record of diagnose's base or extended model: flagged when it misses what the
    held-out data show (a named cause the base lacks; no cause found; above 2x the noise)."""
    from afmctl.files.modelfile import FitRecord
    from afmctl.fit.identify import WARN
    over = d.file_over_noise[1 if extended else 0]
    held = f"held-out RMS {over:.1f}x the noise"
    if d.kept_grid:
        return FitRecord("diagnose", f"no candidate cause explains the residual: the Preisach "
                                     f"grid without creep kept ({held}; the paper's model "
                                     f"{d.base_over_noise:.1f}x)", not over <= WARN, names)
    if d.cause == "unexplained":
        return FitRecord("diagnose", f"no candidate cause explains the residual ({held})", True,
                         names)
    if d.separating is not None:  # indistinguishable: both files are the paper's model
        s = d.separating
        return FitRecord("diagnose", f"{s['sensor']} or {s['actuator']}, not separated by these "
                                     f"sweeps ({held}): readings kept uncorrected", not over <= WARN,
                         names)
    if not extended and d.cause != "none":
        return FitRecord("diagnose", f"misses {d.cause}, which diagnose named ({held}): track "
                                     f"with extended.toml", True, names)
    what = f"extended with {d.cause}" if extended and d.cause != "none" else "no cause named"
    return FitRecord("diagnose", f"{what}, {held}", not over <= WARN, names)
