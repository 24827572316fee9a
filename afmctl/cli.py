"""Command line: ``afmctl``. Composes the library; holds no numerics and no device I/O.

Exit codes: 0 success; 1 the stage failed or a fit did not converge; 2 bad input (one line on
stderr, nothing written); 130 interrupted (the stage was put in its safe state).
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn

import click

from afmctl import __version__
from afmctl.tomlfile import FileFormatError, InputError


def fail(message: str, code: int = 2) -> NoReturn:
    click.echo(f"afmctl: error: {message}", err=True)
    sys.exit(code)


class Group(click.Group):
    """Turns known failures into one line and an exit code instead of a traceback."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except InputError as exc:
            fail(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        except KeyboardInterrupt:
            fail("interrupted; the stage was sent to its safe state", 130)
        except Exception as exc:
            if type(exc).__name__ == "StageError" or isinstance(exc, TimeoutError | OSError):
                fail(f"stage: {exc}", 1)
            if isinstance(exc, RuntimeError):  # a failed calibration fit, a sweep that lost data
                fail(str(exc), 1)
            raise


@click.group(cls=Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="afmctl")
def main() -> None:
    """Make a hysteretic piezo stage track what it is told (Hatch, Smith et al. inverse filter)."""


def load_profile_or_exit(path: str | None):  # noqa: ANN201 (Profile)
    """The profile at ``path`` (the shipped emulated one if None); one line and exit 2 if bad."""
    from afmctl.profile import default_profile, load_profile
    try:
        return default_profile() if path is None else load_profile(path)
    except FileFormatError as exc:
        fail(f"bad profile: {exc}")


def fit_settings(path: str | None):  # noqa: ANN201 (identify.Settings)
    """Identification settings from a profile: its ``[identify]`` table, and its ``[stack]``
    thickness for sweeps whose metadata gives none (defaults without a profile)."""
    from afmctl import identify as idf
    from afmctl import tomlfile
    if path is None:
        return idf.Settings()
    prof = load_profile_or_exit(path)
    base = idf.Settings(fallback_thickness_um=prof.thickness_um)
    return idf.settings_from_table(tomlfile.load(path).table("identify", required=False), base)


def progress_printer(quiet: bool) -> Callable[[str, int, int], None]:
    """Progress on stderr: a line per 10 % (and the last sample) of each run."""
    last: dict[str, int] = {}

    def show(what: str, done: int, total: int) -> None:
        step = 10 * done // max(total, 1)
        if quiet or last.get(what) == step:
            return
        last[what] = step
        click.echo(f"  {what}: {done}/{total} samples ({100 * done // max(total, 1)} %)",
                   err=True)

    return show


@main.command()
@click.option("--profile", "profile_path", type=click.Path(dir_okay=False),
              help="Stage profile with an [emulator] section (default: the shipped emulated one).")
@click.option("--modbus-port", type=click.IntRange(0, 65535), default=5020, show_default=True,
              help="Modbus TCP port (0: any free port).")
@click.option("--serial", "serial_where", default="pty", show_default=True,
              help="Serial protocol on 'pty' or 'socket://HOST:PORT'.")
@click.option("--no-rtu", is_flag=True, help="Do not serve Modbus RTU on a pty.")
@click.option("--host", default=None, help="Address to bind (default 127.0.0.1).")
@click.option("--bind-any", is_flag=True, help="Bind 0.0.0.0 (reachable from other machines).")
@click.option("--read-only", is_flag=True, help="Refuse every command that changes the output.")
def emulate(profile_path: str | None, modbus_port: int, serial_where: str, no_rtu: bool,
            host: str | None, bind_any: bool, read_only: bool) -> None:
    """Serve an emulated stage (Modbus TCP, Modbus RTU on a pty, serial protocol) until Ctrl-C."""
    prof = load_profile_or_exit(profile_path)
    if prof.emulator is None:
        fail(f"bad profile: {prof.name}: missing table [emulator]")
    if bind_any and host is not None:
        raise click.UsageError("give --host or --bind-any, not both")
    bind = "0.0.0.0" if bind_any else (host or "127.0.0.1")
    if serial_where.startswith("socket://") and not (host or bind_any):
        serial_where = serial_where.replace("socket://:", f"socket://{bind}:")
    from drivers.servers import serve_all
    try:
        with serve_all(prof, host=bind, modbus_port=modbus_port, serial=serial_where,
                       rtu=not no_rtu, read_only=read_only or None) as where:
            for name, addr in where.items():
                click.echo(f"{name}: {addr}")
            click.echo("serving; Ctrl-C to stop", err=True)
            sys.stdout.flush()
            while True:
                time.sleep(3600)
    except KeyboardInterrupt:
        click.echo("stopped", err=True)
    except (OSError, ValueError) as exc:
        fail(f"cannot serve: {exc}", 1)


# ----------------------------------------------------------------------------------------------
# sweep and identify
# ----------------------------------------------------------------------------------------------


@main.command()
@click.option("--profile", "profile_path", type=click.Path(dir_okay=False),
              help="Stage profile (default: the embedded emulated stage).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True,
              help="Folder for the sweep files.")
@click.option("--amplitude", type=click.FloatRange(min=0, min_open=True), default=150.0,
              show_default=True, help="Voltage amplitude of the sweeps, V.")
@click.option("--only", multiple=True, metavar="NAME",
              help="Record only this sweep of the set (repeatable), e.g. triangle_27.9hz.")
def sweep(profile_path: str | None, out_dir: str, amplitude: float, only: tuple[str, ...]) -> None:
    """Record the standard identification set: triangles at 0.279, 5.58 and 27.9 Hz (Fig. 2) and
    nested minor loops at 0.1 Hz (Fig. 1(b))."""
    from afmctl import experiment, sweeps
    prof = load_profile_or_exit(profile_path)
    if not (prof.limits.v_min <= -amplitude and amplitude <= prof.limits.v_max):
        raise InputError(f"--amplitude {amplitude} V exceeds the profile's limits "
                         f"[{prof.limits.v_min}, {prof.limits.v_max}] V")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta = {"profile": prof.name, "layer_thickness_um": f"{prof.thickness_um:g}",
            "sample_rate_hz": f"{prof.sample_rate_hz:g}",
            "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    chosen = [w for w in sweeps.standard_set(amplitude, prof.sample_rate_hz)
              if not only or w[0] in only]
    unknown = set(only) - {w[0] for w in chosen}
    if unknown:
        names = ", ".join(w[0] for w in sweeps.standard_set(amplitude, prof.sample_rate_hz))
        raise InputError(f"--only {sorted(unknown)[0]}: not in the standard set ({names})")
    say = progress_printer(False)
    from drivers import open_stage
    with open_stage(prof) as stage:
        for name, freq, v in chosen:
            path = out / f"{name}.csv"
            if path.exists():
                raise InputError(f"{path} exists; measured data is never overwritten")
            s = experiment.record_sweep(stage, name, freq, v, prof.sample_rate_hz, meta, say)
            sweeps.write(s, path)
            click.echo(str(path))


# ----------------------------------------------------------------------------------------------
# identify
# ----------------------------------------------------------------------------------------------


def _report(result: Any) -> str:
    """Human-readable fit report (``result`` is an ``identify.FitResult``)."""
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


@main.command()
@click.argument("sweep_files", nargs=-1, required=True)
@click.option("--profile", "profile", default=None, help="Stage profile: its [stack] thickness "
              "for sweeps without layer_thickness_um; its [identify] table sets mass_kg, "
              "p_r_C_per_m2, thickness_um, n_coercive_fit, field_step, max_nfev.")
@click.option("-o", "--output", required=True, help="Model file to write (TOML).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@click.option("--plots", "plots_dir", default=None, help="Directory for per-sweep figures.")
def identify(sweep_files: tuple[str, ...], profile: str | None, output: str, as_json: bool,
             plots_dir: str | None) -> None:
    """Fit the stage model jointly to SWEEP_FILES and write it to the model file OUTPUT.

    Exit status: 0 converged, 1 the solver did not converge (no model written), 2 bad input.
    """
    from afmctl import identify as idf
    from afmctl import modelfile, sweeps

    settings = fit_settings(profile)
    data = [sweeps.read(f) for f in sweep_files]
    if not Path(output).resolve().parent.is_dir():
        raise InputError(f"{output}: directory does not exist")
    idf.resolve_thickness(data, settings)  # validate before any progress output
    click.echo(f"fitting {len(data)} sweep(s) ...", err=True)
    result = idf.fit(data, settings, progress=lambda m: click.echo(m, err=True))
    if plots_dir is not None:
        from afmctl import plots

        fitted = [idf.predict(result.model, s.voltage_v, s.dt) for s in data]
        for p in plots.fit_figures(data, fitted, plots_dir):
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


# ----------------------------------------------------------------------------------------------
# diagnose
# ----------------------------------------------------------------------------------------------


@main.command()
@click.argument("sweep_files", nargs=-1, required=True)
@click.option("--model", "model_path", type=click.Path(dir_okay=False), default=None,
              help="Start the fits from this model (lognormal/normal densities) instead of "
                   "identifying one.")
@click.option("--profile", "profile", default=None,
              help="Stage profile: its [stack] thickness for sweeps without one; its [identify] "
                   "table sets the fit options.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Output folder (default: ./afmctl-diagnose-<time>).")
@click.option("--json", "as_json", is_flag=True, help="Print diagnosis.json on stdout.")
def diagnose(sweep_files: tuple[str, ...], model_path: str | None, profile: str | None,
             out_dir: str | None, as_json: bool) -> None:
    """Find what the model gets wrong on SWEEP_FILES, name the physical cause, extend the model
    and measure the gain on held-out data.

    Writes diagnosis.json, base.toml and extended.toml (model files for track), report.md and
    residuals.png to --out.
    """
    from afmctl import diagnose as dg
    from afmctl import identify as idf
    from afmctl import modelfile, parametrization, plots, sweeps
    from afmctl.experiment import atomic_write

    settings = dg.Settings(identify=fit_settings(profile))
    data = [sweeps.read(f) for f in sweep_files]
    start = None if model_path is None else modelfile.read(model_path)
    if start is not None:
        try:
            parametrization.internal(start)
        except ValueError as exc:
            raise InputError(f"--model {model_path}: {exc}") from None
    idf.resolve_thickness(data, settings.identify)
    dg.check(data)
    out = Path(out_dir) if out_dir else Path(f"afmctl-diagnose-{time.strftime('%Y%m%d-%H%M%S')}")
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: exists and is not a folder")
    if (out / "diagnosis.json").exists():
        fail(f"{out} already holds a diagnosis; choose another --out")
    click.echo(f"diagnosing {len(data)} sweep(s): "
               f"{len(dg.candidate_names(len(data), settings))} candidates ...", err=True)
    d = dg.diagnose(data, settings, start, progress=lambda m: click.echo(m, err=True))
    doc = d.as_dict()
    text = json.dumps(doc, indent=2, allow_nan=False) + "\n"  # before anything is written
    out.mkdir(parents=True, exist_ok=True)
    header = "afmctl diagnose: " + ", ".join(Path(f).name for f in sweep_files)
    modelfile.write(d.base_model, out / "base.toml", header=header + "\nthe paper's model")
    modelfile.write(d.extended_model, out / "extended.toml",
                    header=header + f"\nextended with: {d.cause}")
    before = [idf.predict(d.base_model, s.voltage_v, s.dt) for s in data]
    after = [idf.predict(d.extended_model, s.voltage_v, s.dt, g)
             for s, g in zip(data, d.extended_gains, strict=True)]
    partial = out / "residuals.partial.png"
    plots.diagnosis_figure(data, before, after, d.base_model.thickness_um,
                           ("paper's model", f"extended: {d.cause}"), partial)
    partial.replace(out / "residuals.png")
    atomic_write(out / "report.md", dg.report(d, "residuals.png"))
    atomic_write(out / "diagnosis.json", text)  # last: marks the folder complete
    click.echo(f"cause: {d.cause} (held-out RMS {d.base_rms_um:.4f} -> {d.extended_rms_um:.4f} um, "
               f"gain {d.gain:.2f}); wrote {out}/diagnosis.json, extended.toml, report.md, "
               f"residuals.png", err=True)
    if as_json:
        click.echo(json.dumps(doc, allow_nan=False))


# ----------------------------------------------------------------------------------------------
# track
# ----------------------------------------------------------------------------------------------


@main.group(cls=Group)
def track() -> None:
    """Open-loop tracking with the model-based inverse filter (and the linear one to compare)."""


def track_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    opts = [
        click.option("--profile", "profile_path", type=click.Path(dir_okay=False),
                     help="Stage profile (default: the embedded emulated stage)."),
        click.option("--model", "model_path", type=click.Path(dir_okay=False),
                     help="Model file (default: identified from the stage's own sweeps, cached)."),
        click.option("--filter", "filters", type=click.Choice(["inverse", "linear", "both"]),
                     default="both", show_default=True),
        click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
                     help="Output folder (default: ./afmctl-track-<time>)."),
        click.option("--dry-run", is_flag=True,
                     help="Send nothing; write DIR/waveform_<filter>.csv."),
        click.option("--json", "as_json", is_flag=True, help="Print the summary JSON on stdout."),
        click.option("--condition/--no-condition", default=True, show_default=True,
                     help="Start with one slow full-range excursion (to the profile's voltage "
                          "limits) that wipes out the stage's hysteresis memory; --no-condition "
                          "skips it and assumes a depoled stage (less accurate)."),
    ]
    for opt in reversed(opts):
        fn = opt(fn)
    return fn


def periodic_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    opts = [
        click.option("--freq", type=click.FloatRange(min=0, min_open=True), required=True,
                     help="Frequency, Hz."),
        click.option("--amplitude", type=click.FloatRange(min=0, min_open=True), required=True,
                     help="Peak-to-peak amplitude, um."),
        click.option("--offset", type=float, default=0.0, show_default=True,
                     help="Centre of the trajectory, um."),
        click.option("--periods", type=click.FloatRange(min=0, min_open=True), default=3.0,
                     show_default=True),
    ]
    for opt in reversed(opts):
        fn = opt(fn)
    return fn


@track.command("triangle")
@periodic_options
@track_options
def track_triangle(freq: float, amplitude: float, offset: float, periods: float,
                   **kw: Any) -> None:
    """Track a triangle wave (the paper's Figs. 9-11)."""
    from afmctl import track as trk
    _track(lambda dt: trk.triangle(freq, amplitude, offset, periods, dt), **kw)


@track.command("sine")
@periodic_options
@track_options
def track_sine(freq: float, amplitude: float, offset: float, periods: float, **kw: Any) -> None:
    """Track a sine wave."""
    from afmctl import track as trk
    _track(lambda dt: trk.sine(freq, amplitude, offset, periods, dt), **kw)


@track.command("file")
@click.argument("wave", type=click.Path(dir_okay=False))
@track_options
def track_file(wave: str, **kw: Any) -> None:
    """Track any trajectory: a CSV with columns time_s,desired_um."""
    from afmctl import sweeps
    from afmctl import track as trk
    t, u = sweeps.read_trajectory(wave)
    _track(lambda dt: trk.from_samples(t, u, dt, f"file {Path(wave).name}"), **kw)


def _out_dir(out_dir: str | None) -> Path:
    path = Path(out_dir) if out_dir else Path(f"afmctl-track-{time.strftime('%Y%m%d-%H%M%S')}")
    if path.exists() and any(path.glob("run_*.csv")):
        fail(f"{path} already holds run data; choose another --out (measured data is never "
             f"overwritten)")
    path.mkdir(parents=True, exist_ok=True)
    return path


def _track(make_desired: Callable[[float], Any], profile_path: str | None,
           model_path: str | None, filters: str, out_dir: str | None, dry_run: bool,
           as_json: bool, condition: bool) -> None:
    from afmctl import calibration, experiment, modelfile
    from afmctl import effects as fx
    from afmctl import track as trk
    prof = load_profile_or_exit(profile_path)
    desired = make_desired(1.0 / prof.sample_rate_hz)
    wanted = ("inverse", "linear") if filters == "both" else (filters,)
    say = progress_printer(False)
    if dry_run:
        model = (modelfile.read(model_path) if model_path
                 else calibration.cached_model(prof, None, say))
        plans = trk.plan(model, desired, prof.limits, 0.0, wanted, condition=condition)
        out = _out_dir(out_dir)
        for name in wanted:
            experiment.write_waveform_csv(plans[name], out / f"waveform_{name}.csv")
            click.echo(f"wrote {out / f'waveform_{name}.csv'}", err=True)
        return
    from drivers import open_stage
    with open_stage(prof) as stage:
        model = (modelfile.read(model_path) if model_path
                 else calibration.cached_model(prof, stage, say))
        start_v = stage.voltage()
        click.echo(f"planning {desired.label} from {start_v:.3f} V ...", err=True)
        plans = trk.plan(model, desired, prof.limits, start_v, wanted, condition=condition)
        out = _out_dir(out_dir)
        meta = {"profile": prof.name, "model": model_path or "identified (cached)",
                "trajectory": desired.label, "sample_rate_Hz": prof.sample_rate_hz}
        truth = prof.emulator.true_model if prof.emulator is not None else model
        outcomes = experiment.run_all(stage, {k: plans[k] for k in wanted}, desired, out, meta,
                                      truth, say, sensor=model.effects)
    data = experiment.summary(outcomes, desired, {
        **meta, "between_samples_model": "emulator truth" if prof.emulator else "model estimate",
        "readings_corrected_for": modelfile.effects_dict(fx.sensor_part(model.effects))})
    experiment.write_combined_csv(outcomes, desired, out / "run.csv")
    experiment.write_summary(data, out / "summary.json")
    experiment.plot(outcomes, desired, model.thickness_um, out / "track.png")
    for name, o in outcomes.items():
        click.echo(f"{name:8s} RMS {o.score.rms_um:.4f} um ({o.score.rms_pct:.3f} %), max "
                   f"{o.score.max_um:.4f} um; between samples {o.score.rms_between_um:.4f} um; "
                   f"max slew {o.waveform.max_slew_v_per_ms:.1f} V/ms", err=True)
    click.echo(f"wrote {out}/run.csv, summary.json, track.png", err=True)
    if as_json:
        click.echo(json.dumps(data))
