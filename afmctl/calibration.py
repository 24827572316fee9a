"""The default model of a stage: identified from the stage's own standard sweeps, cached.

``afmctl track`` with no ``--model`` uses it. The first use records the three standard triangle
sweeps (0.279, 5.58, 27.9 Hz; :func:`afmctl.sweeps.standard_set`) on the stage, fits them with
:func:`afmctl.identify.fit`, and keeps the sweeps and the model under the cache folder
(``$XDG_CACHE_HOME/afmctl`` or ``~/.cache/afmctl``), keyed by a hash of the profile: a changed
profile gets a new calibration. The true parameters of an emulated stage are never used.
"""

from __future__ import annotations

import hashlib
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from afmctl import modelfile
from afmctl.profile import EmulatedTransport, Profile
from afmctl.tomlfile import InputError
from afmctl.transducer import Transducer

Progress = Callable[[str, int, int], None]


def cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "afmctl"


def cache_dir(profile: Profile) -> Path:
    """Folder of this profile's calibration (name plus a hash of everything in the profile)."""
    digest = hashlib.sha256(repr(profile).encode()).hexdigest()[:12]
    return cache_root() / f"{profile.name}-{digest}"


def record_standard(stage: Any, profile: Profile, out: Path,
                    progress: Progress | None = None) -> list[Any]:
    """Record the standard identification triangles on ``stage`` and write them to ``out``."""
    from afmctl import experiment, sweeps

    meta = {"profile": profile.name, "layer_thickness_um": f"{profile.thickness_um:g}",
            "sample_rate_hz": f"{profile.sample_rate_hz:g}",
            "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    out.mkdir(parents=True, exist_ok=True)
    recorded = []
    for name, freq, v in sweeps.standard_set(150.0, profile.sample_rate_hz)[:3]:
        sweep = experiment.record_sweep(stage, name, freq, v, profile.sample_rate_hz, meta,
                                        progress)
        sweeps.write(sweep, out / f"{name}.csv")
        recorded.append(sweep)
    return recorded


def cached_model(profile: Profile, stage: Any | None,
                 progress: Progress | None = None) -> Transducer:
    """The cached identified model of ``profile``'s stage, calibrating it first if needed.

    ``stage`` may be None (``--dry-run``): an emulated profile is then calibrated on a private
    in-process emulator; a real stage needs a calibration first (InputError otherwise).
    """
    folder = cache_dir(profile)
    path = folder / "model.toml"
    if path.exists():
        return modelfile.read(path)
    if stage is None:
        if not isinstance(profile.transport, EmulatedTransport):
            raise InputError(f"no cached model for profile {profile.name!r}: run once without "
                             f"--dry-run, or pass --model")
        from drivers import open_stage
        with open_stage(profile) as private:
            return _calibrate(profile, private, folder, progress)
    return _calibrate(profile, stage, folder, progress)


def _calibrate(profile: Profile, stage: Any, folder: Path,
               progress: Progress | None) -> Transducer:
    from afmctl import identify

    if progress is not None:
        progress("calibration: recording the standard sweeps", 0, 3)
    recorded = record_standard(stage, profile, folder / "sweeps", progress)
    result = identify.fit(recorded)
    if not result.success:
        raise RuntimeError(f"calibration fit did not converge: {result.message}")
    modelfile.write(result.model, folder / "model.toml",
                    header=f"afmctl calibration of profile {profile.name}: identified from "
                           f"{', '.join(s.path for s in recorded)}",
                    envelope=result.envelope, uncertainty=result.uncertainty)
    return result.model
