"""``afmctl sweep --axes x,y``: record a two-axis identification set."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

from afmctl.cli.base import make_dir, opened_stage, progress_printer, say
from afmctl.cli.sweep import record_each, to_record
from afmctl.errors import InputError


def first_resonance_hz(prof: Any) -> float | None:
    """The lowest natural frequency ``sqrt(k / m) / 2 pi`` of the emulated axes' rods, Hz (None
    for a profile without an emulated model)."""
    freqs = []
    for a in prof.axis_names:
        em = prof.axis(a).emulator
        if em is None or em.plant_model is None:
            return None
        rod = em.model.rod
        freqs.append(math.sqrt(rod.k / rod.m) / (2 * math.pi))
    return min(freqs)


def sweep_xy(prof: Any, axes: str, out: Path, band_hz: float | None, resume: bool,
             design: str = "standard") -> None:
    """Design, check and record the two-axis set (:func:`afmctl.planning.sweepdesign.xy_design`;
    ``design`` "standard" or "reversals"),
    each file streamed as it records and, with ``resume``, only the files missing from ``out``
    (as the one-axis set: :func:`afmctl.cli.sweep.to_record`, :func:`afmctl.cli.sweep.record_each`)."""
    from afmctl.experiment import xyrecord
    from afmctl.planning import sweepdesign
    if tuple(a.strip() for a in axes.split(",")) != ("x", "y"):
        raise InputError(f"--axes {axes}: the two-axis set is --axes x,y")
    if prof.axis_names != ("x", "y"):
        raise InputError(f"--axes x,y: profile {prof.name!r} is not a two-axis profile (axes "
                         f"{', '.join(prof.axis_names)}; a two-axis profile declares [axes])")
    if band_hz is None:
        first = first_resonance_hz(prof)
        if first is None:
            raise InputError("--axes x,y: give --band-hz (about half the stage's first "
                             "resonance): the profile does not model its axes")
        band_hz = 0.5 * first
    limits = {a: prof.axis(a).limits for a in ("x", "y")}
    design = sweepdesign.xy_design(
        prof.sample_rate_hz, {a: (lim.v_min, lim.v_max) for a, lim in limits.items()},
        {a: lim.max_rate_v_per_ms * 1e3 for a, lim in limits.items()}, band_hz, design)
    xyrecord.check_design(design, 1.0 / prof.sample_rate_hz, limits)
    todo = to_record([d[0] for d in design], out, resume)
    entries = {d[0]: d for d in design if d[0] in todo}
    meta = {"profile": prof.name, "sample_rate_hz": f"{prof.sample_rate_hz:g}",
            "layer_thickness_x_um": f"{prof.axis('x').thickness_um:g}",
            "layer_thickness_y_um": f"{prof.axis('y').thickness_um:g}",
            "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    show = progress_printer(False)
    with opened_stage(prof) as stage:
        if stage.channels != 2:
            raise InputError(f"--axes x,y: the stage reports {stage.channels} channel(s)")
        if entries:
            say(f"recording {len(entries)} two-axis sweep(s), coupling band {band_hz:g} Hz ...")
            make_dir(out, "--out")

        def one(name: str, path: Path) -> None:
            xyrecord.record_one(stage, entries[name], prof.sample_rate_hz, limits, path, meta,
                                show)

        record_each(list(entries), out, one)
