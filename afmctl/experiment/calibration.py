"""The default model of a stage: identified from the stage's own standard sweeps, cached.

``afmctl track`` with no ``--model`` uses it. A calibration records the three standard triangle
sweeps (0.279, 5.58, 27.9 Hz; :func:`afmctl.planning.sweepdesign.standard_set`) over the profile's
voltage range [v_min, v_max] (unipolar, semi-bipolar or bipolar amplifiers alike), fits them with
:func:`afmctl.fit.identify.fit`, and keeps the sweeps, the model and ``calibration.json`` (when, on
which sweeps, over which range) in a folder of its own under the cache (``$XDG_CACHE_HOME/afmctl``
or ``~/.cache/afmctl``), keyed by a hash of the profile: a changed profile gets a new calibration.
A recalibration adds a new folder; earlier sweeps are never overwritten. The true parameters of an
emulated stage are never used.

A calibration moves the stage over its whole voltage range. On an emulated stage it happens on
first use; on any other stage only when asked (:func:`for_track` with ``calibrate`` or
``recalibrate``), since a tip may be near the sample.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from afmctl.errors import FitError, InputError
from afmctl.files import modelfile
from afmctl.files.profile import EmulatedTransport, Profile
from afmctl.model.transducer import Transducer

Progress = Callable[[str, int, int], None]
#: The sweeps of a calibration: the first three of the standard set (the triangles).
N_SWEEPS = 3


@dataclass(frozen=True)
class Calibration:
    """A model and where it came from (printed by ``track`` and kept in ``summary.json``).

    Attributes
    ----------
    model : Transducer
    path : Path
        The model file.
    identified : str
        When the model was identified (ISO 8601; the file's time if it does not say).
    sweeps : tuple of str
        The sweep files it was identified from (empty if unknown).
    new : bool
        True if the sweeps were recorded by this command.
    fit : FitRecord or None
        What identify or diagnose said of the fit (the model file's ``[fit]``), if it says.
    """

    model: Transducer
    path: Path
    identified: str
    sweeps: tuple[str, ...] = ()
    new: bool = False
    fit: modelfile.FitRecord | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"file": str(self.path), "identified": self.identified,
                "sweeps": list(self.sweeps), "calibrated_now": self.new,
                "fit": None if self.fit is None else self.fit.to_dict()}

    def warning(self, learning: bool = False) -> str | None:
        """What a flagged model means for the figures track (or learning) shows; None if the
        model's writer did not flag it.

        The readings are scored corrected for the sensor effects the model knows; an effect it
        misses can make them better than the stage is, a sensor effect above all (a delay, a gauge
        error): learning then drives the readings, not the stage, to the trajectory."""
        if self.fit is None or not self.fit.flagged:
            return None
        from afmctl.model import effects as fx
        known = ", ".join(modelfile.effects_dict(fx.sensor_part(self.model.effects))) or "nothing"
        what = ("learning optimises the readings" if learning else "track scores the readings")
        return (f"warning: {self.fit.by} flagged model {self.path}: {self.fit.verdict}. Here "
                f"{what}, corrected for what the model knows ({known}); an effect it misses, a "
                f"sensor effect above all, can make them look better than the stage is: readings "
                f"that improve need not mean the stage does. Run `afmctl diagnose` on its sweeps "
                f"and track with the extended model it writes")

    def describe(self) -> str:
        """One line: which model, identified when, on which sweeps."""
        on = f" on {len(self.sweeps)} sweeps in {Path(self.sweeps[0]).parent}" if self.sweeps else ""
        return f"model {self.path} (identified {self.identified}{on})"


def cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "afmctl"


def cache_dir(profile: Profile) -> Path:
    """Folder of this profile's calibrations (name plus a hash of everything in the profile)."""
    digest = hashlib.sha256(repr(profile).encode()).hexdigest()[:12]
    return cache_root() / f"{profile.name}-{digest}"


def _stamp(path: Path) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(path.stat().st_mtime))


def from_file(path: str | Path) -> Calibration:
    """A model file given by the user, with its ``calibration.json`` beside it if there is one."""
    p = Path(path)
    model, fit = modelfile.read(p), modelfile.read_fit(p)
    info = p.with_name("calibration.json")
    if info.exists():
        doc = json.loads(info.read_text(encoding="utf-8"))
        return Calibration(model, p, doc.get("identified", _stamp(p)),
                           tuple(doc.get("sweeps", ())), fit=fit)
    return Calibration(model, p, _stamp(p), fit=fit)


def find(profile: Profile) -> Calibration | None:
    """The latest calibration of ``profile``'s stage in the cache, or None."""
    root = cache_dir(profile)
    if not root.is_dir():
        return None
    found = sorted(root.glob("calibration-*/model.toml"))
    if found:
        return from_file(found[-1])
    legacy = root / "model.toml"  # layout before calibration folders
    return from_file(legacy) if legacy.exists() else None


def record_standard(stage: Any, profile: Profile, out: Path, progress: Progress | None = None,
                    v_range: tuple[float, float] | None = None) -> list[Any]:
    """Record the standard identification triangles on ``stage`` over ``v_range`` (default: the
    profile's [v_min, v_max]) and write them to ``out``."""
    from afmctl.experiment import runner as experiment
    from afmctl.files import sweepfile as sweeps
    from afmctl.planning import sweepdesign as sd

    lo, hi = v_range if v_range is not None else (profile.limits.v_min, profile.limits.v_max)
    meta = {"profile": profile.name, "layer_thickness_um": f"{profile.thickness_um:g}",
            "sample_rate_hz": f"{profile.sample_rate_hz:g}", "v_range_V": f"{lo:g} {hi:g}",
            "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    out.mkdir(parents=True, exist_ok=True)
    recorded = []
    for name, freq, v in sd.standard_set(sample_rate_hz=profile.sample_rate_hz,
                                             v_range=(lo, hi))[:N_SWEEPS]:
        sweep = experiment.record_sweep(stage, name, freq, v, profile.sample_rate_hz, meta,
                                        progress)
        path = out / f"{name}.csv"
        sweeps.write(sweep, path)
        recorded.append(sweeps.read(path))
    return recorded


def calibrate(profile: Profile, stage: Any, progress: Progress | None = None) -> Calibration:
    """Record the standard sweeps on ``stage`` within the profile's range, identify, and keep
    both in a new folder of the cache: the fit's best model, converged or not (its verdict is
    identify's to report). FitError if the fit gives no finite model."""
    from afmctl.experiment import twin
    from afmctl.fit import identify

    when = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    folder = cache_dir(profile) / f"calibration-{time.strftime('%Y%m%d-%H%M%S')}"
    while folder.exists():  # two calibrations within a second: never overwrite the first
        folder = folder.with_name(folder.name + "b")
    recorded = record_standard(stage, profile, folder / "sweeps", progress)
    result = identify.fit(recorded)
    if not result.finite:
        raise FitError(f"calibration fit gave no finite model: {result.message} (sweeps kept in "
                       f"{folder / 'sweeps'})")
    names = tuple(s.path for s in recorded)
    path = folder / "model.toml"
    modelfile.write(result.model, path,
                    header=f"afmctl calibration of profile {profile.name}: identified {when} from "
                           f"{', '.join(Path(n).name for n in names)}",
                    envelope=result.envelope, uncertainty=result.uncertainty,
                    fit=result.record("calibration"))
    twin.keep_beside(result.model, recorded, path)
    (folder / "calibration.json").write_text(json.dumps(
        {"identified": when, "sweeps": list(names), "profile": profile.name,
         "v_range_V": [profile.limits.v_min, profile.limits.v_max]}, indent=2) + "\n",
        encoding="utf-8")
    return Calibration(result.model, path, when, names, new=True,
                       fit=result.record("calibration"))


def for_track(profile: Profile, stage: Any | None, progress: Progress | None = None,
              calibrate_ok: bool = False, recalibrate: bool = False, *,
              open_stage: Callable[[Profile], AbstractContextManager[Any]] | None = None,
              how_to_calibrate: str = "") -> Calibration:
    """The model ``track`` uses when given none.

    The cached calibration if there is one (unless ``recalibrate``); otherwise a new one: on an
    emulated stage always, on any other only with ``calibrate_ok`` or ``recalibrate``
    (:class:`InputError` otherwise, with ``how_to_calibrate`` appended: the caller's words for
    what to run). ``stage`` None (``--dry-run``) calibrates an emulated profile on a private
    stage from ``open_stage`` (e.g. :func:`afmctl.drivers.open_stage`: an in-process emulator).
    """
    emulated = isinstance(profile.transport, EmulatedTransport)
    if not recalibrate:
        found = find(profile)
        if found is not None:
            return found
        if not (emulated or calibrate_ok):
            lo, hi = profile.limits.v_min, profile.limits.v_max
            raise InputError(f"no calibration for profile {profile.name!r}, and calibrating "
                             f"moves the stage over its whole range [{lo:g}, {hi:g}] V"
                             + (f": {how_to_calibrate}" if how_to_calibrate else ""))
    if stage is not None:
        return calibrate(profile, stage, progress)
    if not emulated or open_stage is None:
        raise InputError(f"--dry-run sends nothing, so it cannot calibrate profile "
                         f"{profile.name!r}: run once without --dry-run, or pass --model")
    with open_stage(profile) as private:
        return calibrate(profile, private, progress)

