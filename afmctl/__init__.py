"""afmctl: make a hysteretic piezo stage go where it is told.

The model-based inverse filter of Hatch, Smith et al. (the homogenized energy model, Algorithms 1-3,
the lumped rod (16)/(17)), identified from measured sweeps and played on a stage over serial or
Modbus, or on the emulated stage that ships with it. This is the Python front door; the command
line (``afmctl --help``) composes the same functions. Names are imported when first used, so
``import afmctl`` is cheap and loads no device or plotting library.

A walk-through on the emulated stage (``docs/tutorials/python-api.md``, run in CI)::

    import afmctl
    prof = afmctl.load_profile("emulated")
    with afmctl.open_stage(prof) as stage:
        sweeps = [afmctl.record_sweep(stage, name, freq, v, prof.sample_rate_hz)
                  for name, freq, v in afmctl.standard_sweeps(prof)[:3]]
    fit = afmctl.identify(sweeps)
    desired = afmctl.triangle(27.9, 27.04, 30.0, 3, 1 / prof.sample_rate_hz)
    plans = afmctl.plan(fit.model, desired, prof.limits)
    with afmctl.open_stage(prof) as stage:
        rec = stage.play(plans["inverse"].voltage_v)
    afmctl.score(plans["inverse"], desired, rec.displacement_um).rms_um

Rooms (subpackages), for what the front door does not cover: :mod:`afmctl.model` (the physics),
:mod:`afmctl.fit` (identify, diagnose), :mod:`afmctl.planning` (what is sent),
:mod:`afmctl.files` (file formats), :mod:`afmctl.experiment` (runs on a stage, learning),
:mod:`afmctl.drivers` (the wire and the emulated device), :mod:`afmctl.cli`.
Units everywhere: um, V, s, Hz, MV/m (= V/um), C/m^2.
"""

from importlib import import_module as _import_module

from afmctl._version import __version__  # noqa: F401 (in __all__)

#: Public name -> "module:attribute" it is imported from on first use.
_EXPORTS: dict[str, str] = {
    # the stage
    "Limits": "afmctl.guard:Limits",
    "Profile": "afmctl.files.profile:Profile",
    "Recording": "afmctl.drivers.stage:Recording",
    "Stage": "afmctl.drivers.stage:StageBase",
    "Status": "afmctl.drivers.protocol:Status",
    "load_profile": "afmctl.files.profile:load_profile",
    "open_stage": "afmctl.drivers.stage:open_stage",
    # files
    "Run": "afmctl.files.runfile:Run",
    "Sweep": "afmctl.files.sweepfile:Sweep",
    "read_model": "afmctl.files.modelfile:read",
    "read_run": "afmctl.files.runfile:read",
    "read_sweep": "afmctl.files.sweepfile:read",
    "read_sweeps": "afmctl.files.sweepfile:read_all",
    "write_model": "afmctl.files.modelfile:write",
    "write_sweep": "afmctl.files.sweepfile:write",
    # the model
    "Transducer": "afmctl.model.transducer:Transducer",
    "simulate": "afmctl.model.transducer:displacement",
    # identify and diagnose
    "Diagnosis": "afmctl.fit.diagnosis:Diagnosis",
    "DiagnoseSettings": "afmctl.fit.diagnose:Settings",
    "FitResult": "afmctl.fit.identify:FitResult",
    "IdentifySettings": "afmctl.fit.identify:Settings",
    "diagnose": "afmctl.fit.diagnose:diagnose",
    "identify": "afmctl.fit.identify:fit",
    "record_sweep": "afmctl.experiment.runner:record_sweep",
    "standard_sweeps": "afmctl.planning.sweepdesign:standard_set",
    # tracking
    "Desired": "afmctl.planning.track:Desired",
    "Score": "afmctl.planning.track:Score",
    "Waveform": "afmctl.planning.track:Waveform",
    "plan": "afmctl.planning.track:plan",
    "score": "afmctl.planning.track:score",
    "sine": "afmctl.planning.track:sine",
    "trajectory": "afmctl.planning.track:from_samples",
    "triangle": "afmctl.planning.track:triangle",
    "Twin": "afmctl.experiment.twin:Twin",
    "twin_from_sweeps": "afmctl.experiment.twin:from_sweeps",
    # learning
    "LearningLaw": "afmctl.planning.ilc:Law",
    "learn": "afmctl.experiment.learn:run",
    # raster scans (two axes)
    "AxisPlan": "afmctl.planning.raster:AxisPlan",
    "RasterFrame": "afmctl.planning.raster:Frame",
    "ScanSetup": "afmctl.experiment.scan:Setup",
    "plan_raster": "afmctl.planning.raster:plan",
    "raster_images": "afmctl.planning.scanimage:images",
    "raster_merit": "afmctl.planning.scanimage:merit",
    "pixel_grid": "afmctl.planning.raster:pixel_grid",
    "scan_raster": "afmctl.experiment.scan:run",
    "write_gwy": "afmctl.files.gwy:write",
    # errors
    "AfmctlError": "afmctl.errors:AfmctlError",
    "EnvelopeError": "afmctl.errors:EnvelopeError",
    "FileFormatError": "afmctl.errors:FileFormatError",
    "FitError": "afmctl.errors:FitError",
    "FrameReachError": "afmctl.errors:FrameReachError",
    "InputError": "afmctl.errors:InputError",
    "LimitError": "afmctl.errors:LimitError",
    "ReachError": "afmctl.errors:ReachError",
    "StageError": "afmctl.errors:StageError",
}

__all__ = sorted([*_EXPORTS, "__version__"], key=str.casefold)


def __getattr__(name: str) -> object:
    """Import a public name on first use (PEP 562) and keep it in the module's namespace."""
    where = _EXPORTS.get(name)
    if where is None:
        raise AttributeError(f"module 'afmctl' has no attribute {name!r}")
    module, attr = where.split(":")
    value = getattr(_import_module(module), attr)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_EXPORTS})

