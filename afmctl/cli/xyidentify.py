"""``afmctl identify`` on two-axis sweeps: both axes and the coupling both ways."""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import click

from afmctl.cli.base import check_output_file, say, writing


def _report(result: Any) -> str:
    """Human-readable: each axis's fit (as for one axis) and each direction's coupling."""
    from afmctl.cli.identify import _report as one_axis
    from afmctl.fit import coupling as fc
    lines = [f"two-axis fit ({result.seconds:.1f} s)"]
    for a, r in result.axes.items():
        lines += [f"--- axis {a}", one_axis(r)]
    freq = fc.report_frequencies()
    for d, c in result.coupling.items():
        doc = c.to_dict(freq)
        k = c.coupling
        lines.append(f"--- coupling {d} ({d[0]} caused by {d[1]}), um/um, 1-sigma:")
        lines.append(f"  static  {k.static:+.5g} +- {doc['static_stderr']:.2g} "
                     f"({k.static_db:.1f} dB; low-passed regression {c.static:+.5g} "
                     f"+- {c.static_stderr:.2g})")
        if k.quadratic:
            lines.append(f"  arc     {k.quadratic:+.3g} +- {c.quadratic_stderr:.2g} um/um^2 about "
                         f"{k.centre_um:.4g} um")
        lines.append(f"  mode    {k.mode_hz:.4g} Hz (+- {100 * doc['mode_hz_stderr_rel']:.0f} %),"
                     f" damping {k.damping:.3g} (+- {100 * doc['damping_stderr_rel']:.0f} %), "
                     f"gain_hp {k.gain_hp:+.3g}, gain_bp {k.gain_bp:+.3g}")
        lines.append(f"  estimates {c.band_hz[0]:.3g} ... {c.band_hz[1]:.4g} Hz from "
                     f"{len(c.files)} file(s); fit RMS {c.rms_over_sigma:.2f}x their scatter")
        for p in doc["frf"][::6]:
            lines.append(f"  {p['freq_hz']:8.3g} Hz  gain {p['gain']:.4g} +- {p['gain_stderr']:.2g}"
                         f"  phase {p['phase_deg']:+7.2f} +- {p['phase_stderr_deg']:.2g} deg"
                         + ("" if p["measured"] else "  (extrapolated)"))
    return "\n".join(lines)


def identify_xy(data: Sequence[Any], files: Sequence[str], settings: Any, output: str,
                as_json: bool, plots_dir: str | None, force: bool) -> None:
    """Fit a two-axis set and write its model file (version 4); exit 1 with no finite model."""
    from afmctl.cli.identify import _warn_above_floor
    from afmctl.files import xymodelfile
    from afmctl.fit import xyidentify as xi

    if plots_dir is not None:
        raise click.UsageError("--plots is not available for two-axis sweeps yet")
    check_output_file(output, "-o", force)
    say(f"fitting {len(data)} two-axis sweep(s) ...")
    result = xi.fit(data, settings, progress=say)
    if result.finite:
        header = "afmctl identify (two axes): " + ", ".join(Path(f).name for f in files)
        header += "\nm and p_r are fixed by convention (only their ratios to c, k, a1, a2, eta"
        header += " are identifiable)"
        with writing(output, "-o"):
            xymodelfile.write(result.model, output, header,
                              {a: r.envelope for a, r in result.axes.items()},
                              {a: r.uncertainty for a, r in result.axes.items()},
                              {a: r.record() for a, r in result.axes.items()},
                              {d: c.stderr for d, c in result.coupling.items()})
        say(f"wrote {output}")
    for r in result.axes.values():
        _warn_above_floor(r)
    if as_json:
        click.echo(json.dumps(result.to_dict()))
    else:
        click.echo(_report(result))
    if not result.finite:
        sys.exit(1)
