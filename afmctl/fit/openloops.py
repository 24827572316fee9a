"""Sweeps of minor loops that do not close, left out of the fit that they would only spoil.

Reversal curves (``afmctl sweep --design reversals``) and nested minor loops are what a
Preisach-type model learns its interior from. A stage without return-point memory (Bouc-Wen)
leaves those loops open (:mod:`afmctl.fit.closure`), and no Preisach-type model fits them: the
fit then trades the triangles for them and is worse everywhere. On the out-of-family stage bw-u
the curves stayed at 42.7x the noise against 3.3-4.0x on the triangles; on foreign-xy-2's
Bouc-Wen y axis at 270x against 5-9x, and the raster's slow axis landed 8.8 pixels off.

A sweep is left out when it traces reversal curves from inside its range
(:func:`afmctl.fit.representation.interior_reversals`: it carries minor loops), its loops are
open, and the fit's error on it is the worst of all and more than :data:`SPOILS` times the median
of the other sweeps'. The model is then fitted again without it, and it is judged (held out) by
that model, recorded in sequence with the rest (:func:`judged`); the result says so under
``representations["left_out"]``. Pure numerics: no I/O.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from afmctl.files.sweepfile import Sweep
from afmctl.fit import closure
from afmctl.fit import identify as idf
from afmctl.fit import representation as rep
from afmctl.model import transducer as td

#: A sweep of open minor loops is left out when its error is more than this many times the median
#: of the other sweeps' (each over its noise; the median: the sweep spoils the others' fit too,
#: foreign-xy-2's Bouc-Wen y axis had its fast triangle at 76x beside the curves' 229x).
SPOILS = 4.0

Fitter = Callable[[Sequence[Sweep], idf.Settings, Callable[[str], None] | None], idf.FitResult]


def spoiling(sweeps: Sequence[Sweep], result: idf.FitResult) -> list[int]:
    """Indices of the sweeps to leave out (see the module docstring); none if that would leave
    no sweep, or if the model is Bouc-Wen (open loops are its physics: leaving them out would
    take away what it was chosen for)."""
    if result.representation == "bouc-wen":
        return []
    ratios = [s.rms_over_noise for s in result.sweeps]
    out = []
    for i, (s, e) in enumerate(zip(sweeps, result.sweeps, strict=True)):
        others = [r for j, r in enumerate(ratios) if j != i]
        if (others and ratios[i] >= max(others) and ratios[i] > SPOILS * float(np.median(others))
                and rep.interior_reversals([s]) >= rep.REVERSALS_NEEDED
                and closure.check([s], [e.noise_um])["close"] is False):  # the cheap tests first
            out.append(i)
    return out if len(out) < len(sweeps) else []


def without_spoilers(result: idf.FitResult, sweeps: Sequence[Sweep], settings: idf.Settings,
                     fitter: Fitter, progress: Callable[[str], None] | None = None
                     ) -> idf.FitResult:
    """``result``, or the model fitted again without the :func:`spoiling` sweeps, every sweep
    judged by it (the left-out ones held out, from where the sweep before left the stage, each
    with the sensor zero that fits it best)."""
    out = spoiling(sweeps, result)
    if not out:
        return result
    say = progress or (lambda _msg: None)
    names = [sweeps[i].path or sweeps[i].name for i in out]
    say(f"minor loops of {', '.join(names)} do not close and its fit is "
        f"{max(result.sweeps[i].rms_over_noise for i in out):.1f}x the noise: fitting again "
        f"without it")
    kept = [s for i, s in enumerate(sweeps) if i not in out]
    inner = fitter(kept, settings, progress)
    left: dict[str, Any] = {
        "files": names, "why": f"minor loops open and fitted at more than {SPOILS:g}x the "
        "median of the other sweeps (no return-point memory: no Preisach-type model fits them)",
        "per_sweep_over_noise_with_them": [s.rms_over_noise for s in result.sweeps]}
    return replace(inner, sweeps=judged(inner.model, sweeps, out, [e.start for e in inner.sweeps],
                                        [e.offset_um for e in inner.sweeps], settings.window_s),
                   representations={**inner.representations, "left_out": left},
                   held_out=tuple(out))


def judged(model: td.Transducer, sweeps: Sequence[Sweep], held_out: Sequence[int],
           starts: Sequence[str], offsets_um: Sequence[float], window_s: idf.Window
           ) -> tuple[idf.SweepError, ...]:
    """Every sweep's error under ``model``: the fitted ones (all but ``held_out``, whose
    ``starts`` and ``offsets_um`` these are, in order) with theirs, the held-out ones from where
    the sweep before left the stage, each with the sensor zero that fits it best."""
    fitted = iter(zip(starts, offsets_um, strict=True))
    pairs = [("previous", 0.0) if i in held_out else next(fitted) for i in range(len(sweeps))]
    all_starts, offsets = [p[0] for p in pairs], [p[1] for p in pairs]
    predicted = idf.predict_set(model, sweeps, all_starts, offsets)
    for i in held_out:  # the held-out sweep's own sensor zero
        m = sweeps[i].mask(window_s)
        offsets[i] = float(np.mean((sweeps[i].displacement_um - predicted[i])[m]))
        predicted[i] = predicted[i] + offsets[i]
    return idf.judge_set(sweeps, predicted, all_starts, offsets, window_s)
