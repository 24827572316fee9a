"""``afmctl sweep``: record the standard identification set (or the separating design) on a stage."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import click

from afmctl.cli.base import (
    Finite,
    check_output_dir,
    fail,
    load_profile_or_exit,
    main,
    make_dir,
    opened_stage,
    progress_printer,
    say,
)
from afmctl.errors import InputError

#: The narrowest --v-range, as a fraction of the profile's span (below it the loops are lost in
#: the sensor's noise and the amplifier's resolution).
MIN_SPAN = 0.01


def _v_range(v_range: tuple[float, float] | None, prof) -> tuple[float, float]:  # noqa: ANN001
    """The voltage range to cover: given (checked against the profile) or the profile's."""
    lim = prof.limits
    if v_range is None:
        return lim.v_min, lim.v_max
    lo, hi = v_range
    if not lo < hi:
        raise InputError(f"--v-range {lo:g} {hi:g}: VMIN must be below VMAX")
    if lo < lim.v_min or hi > lim.v_max:
        raise InputError(f"--v-range {lo:g} {hi:g} V exceeds the profile's limits "
                         f"[{lim.v_min:g}, {lim.v_max:g}] V")
    if hi - lo < MIN_SPAN * (lim.v_max - lim.v_min):
        raise InputError(f"--v-range {lo:g} {hi:g} V: too narrow to identify a model; at least "
                         f"{MIN_SPAN:.0%} of the profile's span ({lim.v_max - lim.v_min:g} V)")
    if not lo <= 0.0 <= hi:
        raise InputError(f"--v-range {lo:g} {hi:g} V must contain 0 V (every sweep starts and "
                         f"ends at the stage's safe output)")
    return lo, hi


@main.command()
@click.option("--profile", "profile_path", type=click.Path(dir_okay=False),
              help="Stage profile (default: the embedded emulated stage).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True,
              help="Folder for the sweep files.")
@click.option("--v-range", "v_range", type=(Finite(), Finite()), default=None,
              metavar="VMIN VMAX",
              help="Voltage range the sweeps cover, V (default: the profile's [v_min, v_max]; "
                   "must contain 0 V).")
@click.option("--design", type=click.Choice(["standard", "separating", "reversals", "full"]),
              default="standard",
              show_default=True,
              help="standard: the paper's set; separating: the same and one more sweep of holds, "
                   "fast steps and a multisine that tell causes apart for `afmctl diagnose`; "
                   "reversals: the same and first-order reversal curves (`reversals.csv`), for "
                   "a stage off the paper's model family (the Preisach grid's interior); with --axes "
                   "each axis's curves after its triangles; full: the set, the separating sweep "
                   "and the reversal curves (a lab stage's first calibration).")
@click.option("--only", multiple=True, metavar="NAME",
              help="Record only this sweep of the set (repeatable), e.g. triangle_27.9hz.")
@click.option("--resume", is_flag=True,
              help="Record only the sweeps missing from --out (an interrupted one again); the "
                   "files already there are kept.")
@click.option("--axes", "axes", default=None, metavar="x,y",
              help="On a two-axis stage: record the two-axis set (each axis's standard "
                   "triangles with the other held mid-range, then a multisine per axis for the "
                   "coupling's dynamics) as two-axis sweep files.")
@click.option("--band-hz", "band_hz", type=Finite(minimum=1.0), default=None,
              help="With --axes: the multisine's top frequency, Hz (default: half the lowest "
                   "resonance of the profile's emulated axes; a lab profile must give it).")
def sweep(profile_path: str | None, out_dir: str, v_range: tuple[float, float] | None,
          design: str, only: tuple[str, ...], resume: bool, axes: str | None,
          band_hz: float | None) -> None:
    """Record the standard identification set over the stage's voltage range: triangles at
    0.279, 5.58 and 27.9 Hz (Fig. 2) and nested minor loops at 0.1 Hz (Fig. 1(b)); with
    `--design separating` also a sweep of holds, fast steps and a multisine (`separating.csv`);
    with `--design reversals` also first-order reversal curves (`reversals.csv`); with
    `--design full` both.

    Each sweep is written to --out as it arrives (NAME.incomplete.csv); an interrupted one stays
    there, marked, until `--resume` records what is missing (the whole sweep then replaces it).
    Sweep files are never overwritten.
    """
    from afmctl import guard
    from afmctl.experiment import runner as experiment
    from afmctl.planning import sweepdesign
    prof = load_profile_or_exit(profile_path)
    if axes is not None:
        from afmctl.cli.xysweep import sweep_xy
        if v_range is not None or only or design in ("separating", "full"):
            raise InputError("--axes records the whole two-axis set over each axis's range: "
                             "no --v-range or --only, and --design standard or reversals only")
        sweep_xy(prof, axes, Path(out_dir), band_hz, resume, design)
        return
    lo, hi = _v_range(v_range, prof)
    designed = sweepdesign.design_set(design, prof.sample_rate_hz,
                                 prof.limits.max_rate_v_per_ms * 1e3, (lo, hi))
    unknown = set(only) - {w[0] for w in designed}
    if unknown:
        names = ", ".join(w[0] for w in designed)
        raise InputError(f"--only {sorted(unknown)[0]}: not in the {design} set ({names})")
    chosen = [w for w in designed if not only or w[0] in only]
    for name, _, v, _ in chosen:  # the stage refuses too; fail before anything is written
        guard.check(v, 1.0 / prof.sample_rate_hz, prof.limits, what=name)
    out = Path(out_dir)
    todo = to_record([w[0] for w in chosen], out, resume)
    chosen = [w for w in chosen if w[0] in todo]
    meta = {"profile": prof.name, "layer_thickness_um": f"{prof.thickness_um:g}",
            "sample_rate_hz": f"{prof.sample_rate_hz:g}", "v_range_V": f"{lo:g} {hi:g}",
            "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    show = progress_printer(False)
    with opened_stage(prof) as stage:
        if chosen:
            say(f"recording {len(chosen)} sweep(s) over [{lo:g}, {hi:g}] V ...")
            make_dir(out, "--out")
            start_v = stage.voltage()
            if chosen[0][2][0] != start_v:  # left elsewhere by hand (`afmctl set`)
                say(f"the output is at {start_v:g} V: ramping it to {chosen[0][2][0]:g} V, where "
                    f"every sweep starts")
                experiment.move_and_read(stage, float(chosen[0][2][0]), prof.limits,
                                         prof.sample_rate_hz, 0.01)
        entries = {w[0]: w for w in chosen}

        def one(name: str, path: Path) -> None:
            _, freq, v, kinds = entries[name]
            experiment.record_sweep(stage, name, freq, v, prof.sample_rate_hz,
                                    {**meta, **kinds}, show, path)

        record_each(list(entries), out, one)


def to_record(names: list[str], out: Path, resume: bool) -> list[str]:
    """The sweeps of ``names`` still to record into ``out``: those without a complete
    ``<name>.csv`` there. One there without ``resume`` is refused (measured data is never
    overwritten); with it, each is said kept. ``out`` is checked writable for the rest."""
    done = [n for n in names if (out / f"{n}.csv").exists()]
    if done and not resume:
        raise InputError(f"--out {out}: {done[0]}.csv exists (measured data is never "
                         f"overwritten): add --resume to record only what is missing, or choose "
                         f"another folder")
    todo = [n for n in names if n not in done]
    check_output_dir(out, "--out", [f"{n}.csv" for n in todo], force=False)
    for name in done:
        say(f"{out / (name + '.csv')}: already recorded, kept")
    return todo


def record_each(names: list[str], out: Path, record: Callable[[str, Path], object]) -> None:
    """``record(name, out/<name>.csv)`` for each sweep in turn, its path on stdout once complete.

    ``record`` streams into ``<name>.incomplete.csv``
    (:func:`afmctl.experiment.runner.record_sweep`); on Ctrl-C (the stage sent to its safe state
    by ``play`` and :func:`afmctl.cli.base.opened_stage`) one line says what was kept and exit
    130; an earlier interrupted attempt superseded is said removed."""
    from afmctl.experiment.runner import incomplete_path
    for name in names:
        path = out / f"{name}.csv"
        partial = incomplete_path(path)
        earlier = partial.exists()
        try:
            record(name, path)
        except KeyboardInterrupt:
            kept = (f"the sweep in progress is kept in {partial}, marked incomplete"
                    if partial.exists() else "no sample of the sweep in progress had arrived")
            fail(f"interrupted; the stage was sent to its safe state; {kept}; rerun with "
                 f"--resume to record what is missing", 130)
        if earlier:
            say(f"{partial}: the interrupted attempt, superseded by {path}: removed")
        click.echo(str(path))
