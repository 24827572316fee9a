"""``afmctl sweep``: record the standard identification set on a stage."""

from __future__ import annotations

import time
from pathlib import Path

import click

from afmctl.cli.base import load_profile_or_exit, main, progress_printer
from afmctl.tomlfile import InputError


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

