"""Random foreign stages (:mod:`afmctl.drivers.device.foreign.stage`) over the ranges labs meet.

Every parameter is drawn log-uniformly (or uniformly where it may change sign) between the ends
listed in ``RANGES``; each can be fixed by a keyword of :func:`random_stage`. Density parameters
are drawn relative to the largest field of the drive range ``E_max = max|V| / thickness`` so that
every stage shows hysteresis over its drive range whatever its layer thickness. Over 0-150 V
from the poled state the quasi-static loop's largest width is 0-35 % of the span (median about
12 %; the two example sets of ``shared/data/foreign-stage`` show 8 % and, semi-bipolar, 30 %).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from afmctl.drivers.device.foreign.effects import Effect
from afmctl.drivers.device.foreign.stage import (
    COERCIVE_FAMILIES,
    INTERACTION_FAMILIES,
    Coercive,
    Interaction,
    Material,
    Rod,
    Sensor,
    Stage,
)

#: name: (low, high, kind) with kind "log" (log-uniform), "lin" (uniform) or "pm" (either sign,
#: magnitude uniform).
RANGES: dict[str, tuple[float, float, str]] = {
    "layer_thickness_um": (60.0, 150.0, "log"),
    "coercive_median_rel": (0.25, 0.75, "log"),     # median E_c / E_max
    "lognormal_shape": (0.3, 1.0, "log"),           # sigma of ln E_c
    "gamma_shape": (1.5, 8.0, "log"),               # k
    "loglogistic_shape": (2.0, 7.0, "log"),         # beta
    "interaction_std_rel": (0.1, 0.3, "log"),       # std E_I / E_max
    "reversible_rel": (0.25, 0.9, "log"),           # chi E_max: reversible / remanent polarization
    "remanence_C_m2": (0.15, 0.45, "log"),
    "resonance_hz": (100.0, 1000.0, "log"),
    "damping_ratio": (0.05, 0.5, "log"),
    "mass_kg": (0.05, 0.5, "log"),
    "span_um": (40.0, 120.0, "lin"),                # quasi-static displacement span
    "a2_ratio": (0.02, 0.3, "pm"),                  # a2 P_R / a1
    "noise_um": (0.005, 0.05, "log"),
    "offset_um": (-2.0, 2.0, "lin"),
}


def _draw(rng: np.random.Generator, name: str) -> float:
    lo, hi, kind = RANGES[name]
    if kind == "log":
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    if kind == "lin":
        return float(rng.uniform(lo, hi))
    return float(rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi))


def random_stage(rng: np.random.Generator, **overrides) -> Stage:
    """Draw a foreign stage.

    Parameters
    ----------
    rng : numpy.random.Generator
    **overrides
        Any name of ``RANGES`` (a fixed value instead of a draw), plus ``coercive_family``
        (``lognormal`` default, ``gamma``, ``loglogistic``), ``interaction_family`` (``normal``
        default, ``logistic``, ``laplace``), ``coercive_shape`` (overrides the family's shape),
        ``drive_range_V`` (default (0, 150)), ``effects`` (a tuple of hidden effects),
        ``n_coercive`` (quadrature nodes, default 400).

    Returns
    -------
    Stage
        With ``a1`` scaled so that the quasi-static displacement span over a cycle of the drive
        range is ``span_um``, and the gauge zeroed at the low end of that span.
    """
    known = set(RANGES) | {"coercive_family", "interaction_family", "coercive_shape",
                           "drive_range_V", "effects", "n_coercive"}
    unknown = set(overrides) - known
    if unknown:
        raise ValueError(f"unknown override(s) {sorted(unknown)}")
    d = {name: _draw(rng, name) for name in RANGES}
    d.update({k: v for k, v in overrides.items() if k in RANGES})
    cfam = overrides.get("coercive_family", "lognormal")
    ifam = overrides.get("interaction_family", "normal")
    if cfam not in COERCIVE_FAMILIES or ifam not in INTERACTION_FAMILIES:
        raise ValueError(f"unknown density family {cfam!r} / {ifam!r}")
    shape = overrides.get("coercive_shape", d[f"{cfam}_shape"])
    drive = tuple(float(v) for v in overrides.get("drive_range_V", (0.0, 150.0)))
    e_max = max(abs(drive[0]), abs(drive[1])) / d["layer_thickness_um"]
    material = Material(
        coercive=Coercive(cfam, d["coercive_median_rel"] * e_max, shape),
        interaction=Interaction(ifam, d["interaction_std_rel"] * e_max),
        remanence_C_m2=d["remanence_C_m2"],
        eta_MVm_per_C_m2=e_max / (d["reversible_rel"] * d["remanence_C_m2"]),
        layer_thickness_um=d["layer_thickness_um"],
        n_coercive=int(overrides.get("n_coercive", 400)))
    w = 2 * math.pi * d["resonance_hz"]
    k = d["mass_kg"] * w * w
    rod = Rod(mass_kg=d["mass_kg"], damping_N_s_per_m=2 * d["damping_ratio"] * d["mass_kg"] * w,
              stiffness_N_per_m=k, a1_N_per_C_m2=1.0,
              a2_N_per_C2_m4=d["a2_ratio"] / d["remanence_C_m2"])
    stage = Stage(material, rod, Sensor(d["noise_um"], d["offset_um"]), drive)
    lo, hi = stage.static_range_um
    scale = d["span_um"] / (hi - lo)
    rod = replace(rod, a1_N_per_C_m2=scale, a2_N_per_C2_m4=scale * rod.a2_N_per_C2_m4)
    sensor = replace(stage.sensor, zero_um=scale * lo)
    return replace(stage, rod=rod, sensor=sensor, effects=tuple(overrides.get("effects", ())))


def with_effects(stage: Stage, *effects: Effect) -> Stage:
    """The stage with hidden effects added."""
    return replace(stage, effects=stage.effects + tuple(effects))
