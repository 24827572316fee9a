"""TOML model files: the versioned, unit-carrying form of a :class:`~afmctl.model.transducer.Transducer`.

``identify`` writes them, ``track`` and ``diagnose`` read them, and a profile's ``[emulator.model]``
table uses the same schema. Every key carries its unit in its name. Example::

    format = "afmctl-model"
    format_version = 2

    [transducer]
    thickness_um = 100.0

    [polarization]
    eta_MVm_per_Cm2 = 3.0
    p_r_C_per_m2 = 0.3
    n_coercive = 128
    n_interaction = 64
    kernel = "auto"

    [polarization.coercive]
    type = "lognormal"
    median_MV_per_m = 0.8
    sigma_ln = 0.5

    [polarization.interaction]
    type = "normal"
    std_MV_per_m = 0.3

    [rod]
    m_kg = 0.05
    c_Ns_per_m = 56.5
    k_N_per_m = 177653.0
    a1_N_per_C_m2 = 12.0
    a2_N_per_C2_m4 = 0.0
    offset_um = 0.0

Version 2 adds two optional tables that ``identify`` writes (version 1 files, without them, are
still read). ``[envelope]``: where the model was identified, which ``track`` keeps to (see
:class:`Envelope`)::

    [envelope]
    voltage_min_V = 0.0
    voltage_max_V = 150.0
    field_min_MV_per_m = 0.0
    field_max_MV_per_m = 1.5
    frequencies_Hz = [0.279, 5.58, 27.9]
    sample_rates_Hz = [10000.0, 10000.0, 10000.0]

``[uncertainty]``: the fit's internal parameters with their 1-sigma, correlations and the ones the
data did not determine (:mod:`afmctl.fit.uncertainty`; informational, not read back into the model)::

    [uncertainty]
    method = "Gauss-Newton s^2 (J^T J)^+ at the solution (logs for log_ parameters)"
    parameters = ["log_median_MV_per_m", ...]
    value = [...]
    stderr = [...]
    correlation = [[1.0, ...], ...]
    undetermined = []

``[fit]``: what the program that wrote the model said of its fit (:class:`FitRecord`; optional,
informational): ``track`` warns when it flagged the model::

    [fit]
    by = "identify"
    verdict = "triangle_27.9hz.csv left at 25.8x its sensor noise"
    flagged = true
    sweeps = ["triangle_0.279hz.csv", "triangle_27.9hz.csv"]
    rms_over_noise = [1.01, 25.8]

Optional ``[effects.*]`` tables (one per effect, as ``afmctl diagnose`` writes them; schema of
:mod:`afmctl.model.effects`, the same as a profile's ``[emulator.effects.*]``)::

    [effects.amplifier_lag]
    bandwidth_Hz = 800.0

    [effects.amplifier_rails]                     # the amplifier's output is clipped here
    low_V = 0.0
    high_V = 150.0

Version 3 adds a Preisach grid in place of the densities (:mod:`afmctl.model.preisach`: a general
weight matrix on the (coercive, interaction) grid, as ``identify`` may choose it) and log-time
creep (:mod:`afmctl.model.creep`)::

    [polarization]
    type = "preisach"
    coercive_MV_per_m = [0.0, 0.024, ...]        # N_i rows (play half-widths)
    interaction_MV_per_m = [-1.57, -1.53, ...]    # N_j columns
    spread_MV_per_m = 0.035
    reversible_C_per_m2_per_MV_per_m = 0.01
    weights_C_per_m2 = [[0.0, 0.0012, ...], ...]  # N_i x N_j, >= 0

    [creep]
    tau_s = [0.01, 0.0316, ...]
    weights = [0.004, 0.003, ...]
    thresholds_C_per_m2 = [0.0, 0.0, ...]       # play half-widths (optional, default 0)
    acts_on = "force"                            # optional: the elements driven by the force
                                                 # (16) and added to it; thresholds_N then

or a Bouc-Wen polarization (:mod:`afmctl.model.boucwen`, whose minor loops need not close)::

    [polarization]
    type = "bouc-wen"
    reversible_C_per_m2_per_MV_per_m = 0.21
    rate_C_per_m2_per_MV_per_m = -0.05         # A (< 0: the loop subtracted, x = d V - h)
    saturation_C_per_m2 = 0.031                # h_s
    kappa = -1.7                               # the branch toward zero
    exponent = 1.8                             # n
    poling_MV_per_m = [0.0, 1.5]               # where "negative" / "positive" saturate

    [transducer]
    initial_state = "h=-0.557000"              # also: h at the first field, share of h_s
                                               # (identify's fitted start of the last sweep)

and, on the paper's polarization, viscous relaxation of the switching (:mod:`afmctl.model.viscous`:
the hysterons see the field through a first-order lag; ``afmctl diagnose`` writes it as a form of
``thermal-relaxation``)::

    [polarization.viscous]
    relaxation_time_s = 0.0026

and a cubic term of the force that (16) does not have, ``+ a3 P^3`` (optional, 0 when absent; the
Preisach grid's fit writes it, see :attr:`afmctl.model.rod.Rod.a3`)::

    [rod]
    a3_N_per_C3_m6 = 463.4
``identify`` writes version 3 only for a model that needs it (versions 1 and 2 are still read, and
a model of the paper's form is still written as version 2).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from afmctl.errors import FileFormatError
from afmctl.files.tomlfile import Table, dumps, load
from afmctl.model import hysteresis as hy
from afmctl.model.boucwen import BoucWen
from afmctl.model.creep import ACTS_ON, Creep
from afmctl.model.effects import Effects, SecondMode
from afmctl.model.preisach import PreisachGrid
from afmctl.model.rod import Rod
from afmctl.model.transducer import Transducer
from afmctl.model.viscous import Viscous

FORMAT = "afmctl-model"
FORMAT_VERSION = 3
READABLE_VERSIONS = (1, 2, 3)
#: The version of a two-axis model file (:mod:`afmctl.files.xymodelfile`).
XY_VERSION = 4
#: A waveform may leave the envelope's voltage range by this fraction of its span.
ENVELOPE_TOLERANCE = 0.05

__all__ = ["FileFormatError", "Envelope", "FitRecord", "read", "read_envelope", "read_fit",
           "write", "to_dict", "from_table", "FORMAT_VERSION"]


@dataclass(frozen=True)
class Envelope:
    """Where a model was identified: the range of its sweeps.

    Parameters
    ----------
    voltage_min_v, voltage_max_v : float
        Lowest and highest voltage of the sweeps, V.
    field_min_mv_m, field_max_mv_m : float
        The same as field, MV/m.
    frequencies_hz : tuple of float
        Fundamental frequency of each sweep, Hz.
    sample_rates_hz : tuple of float
        Sample rate of each sweep, Hz.
    """

    voltage_min_v: float
    voltage_max_v: float
    field_min_mv_m: float
    field_max_mv_m: float
    frequencies_hz: tuple[float, ...]
    sample_rates_hz: tuple[float, ...]

    @property
    def span_v(self) -> float:
        return self.voltage_max_v - self.voltage_min_v

    def excess_v(self, v_min: float, v_max: float) -> float:
        """How far (V) the voltage range ``[v_min, v_max]`` reaches outside the envelope's."""
        return max(0.0, self.voltage_min_v - v_min, v_max - self.voltage_max_v)

    def admits(self, v_min: float, v_max: float,
               tolerance: float = ENVELOPE_TOLERANCE) -> bool:
        """True if ``[v_min, v_max]`` leaves the envelope by at most ``tolerance`` of its span."""
        return self.excess_v(v_min, v_max) <= tolerance * self.span_v

    def describe(self) -> str:
        """E.g. ``0 ... 150 V, 0.1, 0.279, 5.58, 27.9 Hz`` (4 significant digits: a sweep's
        extreme is a float32 sample; frequencies sorted, each once)."""
        return (f"{self.voltage_min_v:.4g} ... {self.voltage_max_v:.4g} V, "
                f"{', '.join(f'{f:g}' for f in sorted(set(self.frequencies_hz)))} Hz")

    def to_dict(self) -> dict[str, Any]:
        return {"voltage_min_V": self.voltage_min_v, "voltage_max_V": self.voltage_max_v,
                "field_min_MV_per_m": self.field_min_mv_m,
                "field_max_MV_per_m": self.field_max_mv_m,
                "frequencies_Hz": list(self.frequencies_hz),
                "sample_rates_Hz": list(self.sample_rates_hz)}


def _envelope(t: Table) -> Envelope:
    env = Envelope(t.number("voltage_min_V"), t.number("voltage_max_V"),
                   t.number("field_min_MV_per_m"), t.number("field_max_MV_per_m"),
                   t.numbers("frequencies_Hz"), t.numbers("sample_rates_Hz"))
    if not env.voltage_max_v > env.voltage_min_v:
        raise t.fail("voltage_max_V", "must be above voltage_min_V")
    return env


@dataclass(frozen=True)
class FitRecord:
    """What the program that wrote a model said of its fit (the ``[fit]`` table).

    Parameters
    ----------
    by : str
        ``identify``, ``diagnose`` or ``calibration``.
    verdict : str
        One line: what the fit left unexplained, or that it reached the noise floor.
    flagged : bool
        True when the writer found the model missing something the data show (a sweep left
        above twice its sensor noise, a cause diagnose named and the model lacks).
    sweeps : tuple of str
        The sweep files it was fitted on.
    rms_over_noise : tuple of float
        Each sweep's fit RMS over its sensor noise (empty if not known).
    """

    by: str
    verdict: str
    flagged: bool
    sweeps: tuple[str, ...] = ()
    rms_over_noise: tuple[float, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"by": self.by, "verdict": self.verdict, "flagged": self.flagged}
        if self.sweeps:
            out["sweeps"] = list(self.sweeps)
        if self.rms_over_noise:
            out["rms_over_noise"] = [round(float(x), 4) for x in self.rms_over_noise]
        return out


def _fit_record(t: Table) -> FitRecord:
    sweeps = t.data.get("sweeps", [])
    if not isinstance(sweeps, list) or not all(isinstance(x, str) for x in sweeps):
        raise t.fail("sweeps", "expected an array of file names")
    t.has("sweeps")
    ratios = t.numbers("rms_over_noise") if t.has("rms_over_noise") else ()
    return FitRecord(t.string("by"), t.string("verdict", ""), t.boolean("flagged"),
                     tuple(sweeps), ratios)


UNCERTAINTY_KEYS = ("method", "parameters", "value", "stderr", "correlation", "undetermined")


def uncertainty_table(u: Mapping[str, Any]) -> dict[str, Any]:
    """The ``[uncertainty]`` table from :func:`afmctl.fit.uncertainty.summary` (NaN for unknown)."""
    names = list(u["parameters"])

    def num(v: float | None) -> float:
        return float("nan") if v is None else float(v)

    return {"method": u["method"], "parameters": names,
            "value": [num(u["parameters"][n]["value"]) for n in names],
            "stderr": [num(u["parameters"][n]["stderr"]) for n in names],
            "correlation": [[num(v) for v in row] for row in u["correlation"]["matrix"]],
            "undetermined": list(u["undetermined"])}


def _density_dict(d: hy.Lognormal | hy.Normal | hy.Discrete) -> dict[str, Any]:
    if isinstance(d, hy.Lognormal):
        return {"type": "lognormal", "median_MV_per_m": d.median, "sigma_ln": d.sigma}
    if isinstance(d, hy.Normal):
        return {"type": "normal", "std_MV_per_m": d.std}
    return {"type": "discrete", "nodes_MV_per_m": list(d.nodes),
            "values_per_MV_per_m": list(d.values)}


def version_for(model: Transducer) -> int:
    """The lowest format version that holds ``model`` (3 for a Preisach grid, Bouc-Wen, creep,
    viscous relaxation or the force's cubic)."""
    return 3 if (isinstance(model.polarization, (PreisachGrid, BoucWen))
                 or model.creep is not None or model.viscous is not None
                 or model.rod.a3 != 0.0) else 2


def _polarization_dict(pol: hy.Polarization | PreisachGrid | BoucWen) -> dict[str, Any]:
    if isinstance(pol, BoucWen):
        return {"type": "bouc-wen", "reversible_C_per_m2_per_MV_per_m": pol.reversible,
                "rate_C_per_m2_per_MV_per_m": pol.rate, "saturation_C_per_m2": pol.saturation,
                "kappa": pol.kappa, "exponent": pol.exponent,
                **({"poling_MV_per_m": list(pol.poling_mv_m)}
                   if all(math.isfinite(f) for f in pol.poling_mv_m) else {})}
    if isinstance(pol, PreisachGrid):
        return {"type": "preisach", "coercive_MV_per_m": list(pol.coercive),
                "interaction_MV_per_m": list(pol.interaction),
                "spread_MV_per_m": pol.spread,
                "reversible_C_per_m2_per_MV_per_m": pol.reversible,
                "weights_C_per_m2": [list(row) for row in pol.weights]}
    pd: dict[str, Any] = {
        "eta_MVm_per_Cm2": pol.eta, "p_r_C_per_m2": pol.p_r, "n_coercive": pol.n_coercive,
        "n_interaction": pol.n_interaction, "kernel": pol.kernel,
        "coercive": _density_dict(pol.coercive), "interaction": _density_dict(pol.interaction)}
    if pol.thermal is not None:
        pd["thermal"] = {"field_scale_MV_per_m": pol.thermal.field_scale,
                         "attempt_rate_per_s": pol.thermal.attempt_rate}
    return pd


def to_dict(model: Transducer) -> dict[str, Any]:
    """The model as nested dicts (the TOML tables)."""
    pd = _polarization_dict(model.polarization)
    if model.viscous is not None:
        pd["viscous"] = {"relaxation_time_s": model.viscous.time_s}
    r = model.rod
    out = {
        "format": FORMAT, "format_version": version_for(model),
        "transducer": {"thickness_um": model.thickness_um, "initial_state": model.initial},
        "polarization": pd,
        "rod": {"m_kg": r.m, "c_Ns_per_m": r.c, "k_N_per_m": r.k, "a1_N_per_C_m2": r.a1,
                "a2_N_per_C2_m4": r.a2, "offset_um": r.offset_um},
    }
    if r.a3:
        out["rod"]["a3_N_per_C3_m6"] = r.a3
    if model.creep is not None:
        out["creep"] = {"tau_s": list(model.creep.tau_s), "weights": list(model.creep.weights)}
        on_force = model.creep.acts_on == "force"
        if on_force:
            out["creep"]["acts_on"] = "force"
        if any(model.creep.thresholds):
            out["creep"]["thresholds_N" if on_force else "thresholds_C_per_m2"] = list(
                model.creep.thresholds)
    fx = effects_dict(model.effects)
    return {**out, "effects": fx} if fx else out


def effects_dict(e: Effects) -> dict[str, Any]:
    """The ``[effects.*]`` tables of the effects that are on (empty if none)."""
    out: dict[str, Any] = {}
    if e.amplifier_bandwidth_hz is not None:
        amp = {"bandwidth_Hz": e.amplifier_bandwidth_hz, "damping_ratio": e.amplifier_damping_ratio,
               "slew_V_per_s": e.amplifier_slew_v_per_s}
        out["amplifier_lag"] = {k: v for k, v in amp.items() if v is not None}
    if e.amplifier_rails_v is not None:
        out["amplifier_rails"] = {"low_V": e.amplifier_rails_v[0], "high_V": e.amplifier_rails_v[1]}
    if e.sensor_delay_samples or e.sensor_delay_s or e.sensor_window_s:
        out["sensor_delay"] = {"samples": e.sensor_delay_samples, "seconds": e.sensor_delay_s}
        if e.sensor_window_s:
            out["sensor_delay"]["window_seconds"] = e.sensor_window_s
    if e.sensor_quadratic_per_um or e.sensor_cubic_per_um2:
        out["sensor_nonlinearity"] = {"quadratic_per_um": e.sensor_quadratic_per_um,
                                      "cubic_per_um2": e.sensor_cubic_per_um2,
                                      "center_um": e.sensor_center_um,
                                      "half_range_um": e.sensor_half_range_um}
        if e.sensor_third_moment_um3 or e.sensor_fourth_moment_um4:
            out["sensor_nonlinearity"] |= {"third_moment_um3": e.sensor_third_moment_um3,
                                           "fourth_moment_um4": e.sensor_fourth_moment_um4}
    if e.second_mode is not None:
        m = e.second_mode
        out["second_mode"] = {"frequency_Hz": m.frequency_hz, "damping_ratio": m.damping_ratio,
                              "gain": m.gain}
        if m.rate_gain:
            out["second_mode"]["rate_gain"] = m.rate_gain
    if e.voltage_gain_sigma:
        out["voltage_gain_drift"] = {"sigma": e.voltage_gain_sigma}
    return out


EFFECT_TABLES = ("thermal_relaxation", "amplifier_lag", "sensor_delay", "sensor_nonlinearity",
                 "second_mode", "voltage_gain_drift", "amplifier_rails")


def _thermal(t: Table) -> hy.Thermal:
    return hy.Thermal(t.number("field_scale_MV_per_m", positive=True),
                      t.number("attempt_rate_per_s", positive=True))


def _rails(t: Table) -> tuple[float, float]:
    """``[effects.amplifier_rails]``: the amplifier's output range, V (low below high)."""
    low, high = t.number("low_V"), t.number("high_V")
    if not low < high:
        raise t.fail("high_V", f"must be above low_V ({low:g} V)")
    return low, high


def _optional(t: Table | None, key: str) -> float | None:
    """A positive number of ``t`` if the key is there, else None."""
    return t.number(key, positive=True) if t is not None and t.has(key) else None


def effects_from_table(t: Table | None) -> tuple[Effects, hy.Thermal | None]:
    """Effects (and thermal relaxation, which belongs to the polarization kernel) from an
    ``effects`` table: one sub-table per effect that is on, keys with units (see
    :mod:`afmctl.model.effects`)."""
    if t is None:
        return Effects(), None
    for key in t.data:
        if key not in EFFECT_TABLES:
            raise t.fail(key, f"unknown effect (known: {', '.join(sorted(EFFECT_TABLES))})")
    th, lag, dly, nl, sm, gd, rails = (t.table(k, required=False) for k in EFFECT_TABLES)
    mode = None if sm is None else SecondMode(sm.number("frequency_Hz", positive=True),
                                              sm.number("damping_ratio", positive=True),
                                              sm.number("gain"), sm.number("rate_gain", 0.0))
    return Effects(
        amplifier_bandwidth_hz=None if lag is None else lag.number("bandwidth_Hz", positive=True),
        amplifier_damping_ratio=_optional(lag, "damping_ratio"),
        amplifier_slew_v_per_s=_optional(lag, "slew_V_per_s"),
        amplifier_rails_v=None if rails is None else _rails(rails),
        sensor_delay_samples=0.0 if dly is None else dly.number("samples", 0.0, nonnegative=True),
        sensor_delay_s=0.0 if dly is None else dly.number("seconds", 0.0, nonnegative=True),
        sensor_window_s=0.0 if dly is None else dly.number("window_seconds", 0.0,
                                                           nonnegative=True),
        sensor_quadratic_per_um=0.0 if nl is None else nl.number("quadratic_per_um"),
        sensor_cubic_per_um2=0.0 if nl is None else nl.number("cubic_per_um2", 0.0),
        sensor_center_um=0.0 if nl is None else nl.number("center_um", 0.0),
        sensor_half_range_um=0.0 if nl is None else nl.number("half_range_um", 0.0,
                                                               nonnegative=True),
        sensor_third_moment_um3=0.0 if nl is None else nl.number("third_moment_um3", 0.0),
        sensor_fourth_moment_um4=0.0 if nl is None else nl.number("fourth_moment_um4", 0.0,
                                                                   nonnegative=True),
        second_mode=mode,
        voltage_gain_sigma=0.0 if gd is None else gd.number("sigma", nonnegative=True),
    ), None if th is None else _thermal(th)


def _density(t: Table, allowed: tuple[str, ...]) -> hy.Lognormal | hy.Normal | hy.Discrete:
    kind = t.string("type", choices=allowed)
    if kind == "lognormal":
        return hy.Lognormal(t.number("median_MV_per_m", positive=True),
                            t.number("sigma_ln", positive=True))
    if kind == "normal":
        return hy.Normal(t.number("std_MV_per_m", positive=True))
    nodes, values = t.numbers("nodes_MV_per_m"), t.numbers("values_per_MV_per_m")
    try:
        return hy.Discrete(nodes, values)
    except ValueError as exc:
        raise t.fail("values_per_MV_per_m", str(exc)) from None


def _matrix(t: Table, key: str) -> tuple[tuple[float, ...], ...]:
    """A non-empty array of equally long, non-empty arrays of finite numbers."""
    t.has(key)
    rows = t.data.get(key)
    if not isinstance(rows, list) or not rows or not all(isinstance(r, list) and r for r in rows):
        raise t.fail(key, "expected a non-empty array of non-empty arrays of numbers")
    if len({len(r) for r in rows}) != 1:
        raise t.fail(key, "rows of different lengths")
    for i, r in enumerate(rows):
        for j, x in enumerate(r):
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                raise t.fail(key, f"element [{i}][{j}] is not a finite number: {x!r}")
    return tuple(tuple(float(x) for x in r) for r in rows)


def _preisach(p: Table) -> PreisachGrid:
    try:
        return PreisachGrid(p.numbers("coercive_MV_per_m"), p.numbers("interaction_MV_per_m"),
                            p.number("spread_MV_per_m", positive=True),
                            _matrix(p, "weights_C_per_m2"),
                            p.number("reversible_C_per_m2_per_MV_per_m", nonnegative=True))
    except ValueError as exc:
        if isinstance(exc, FileFormatError):
            raise
        raise p.fail("weights_C_per_m2", str(exc)) from None


def _bouc_wen(p: Table) -> BoucWen:
    try:
        return BoucWen(p.number("reversible_C_per_m2_per_MV_per_m", nonnegative=True),
                       p.number("rate_C_per_m2_per_MV_per_m"),
                       p.number("saturation_C_per_m2", positive=True), p.number("kappa"),
                       p.number("exponent", positive=True),
                       p.numbers("poling_MV_per_m") if p.has("poling_MV_per_m")  # type: ignore[arg-type]
                       else (math.nan, math.nan))
    except ValueError as exc:
        if isinstance(exc, FileFormatError):
            raise
        raise p.fail("rate_C_per_m2_per_MV_per_m", str(exc)) from None


def _creep(t: Table | None) -> Creep | None:
    if t is None:
        return None
    on = t.string("acts_on", "polarization", choices=ACTS_ON)
    key = "thresholds_N" if on == "force" else "thresholds_C_per_m2"
    try:
        return Creep(t.numbers("tau_s"), t.numbers("weights"),
                     t.numbers(key) if t.has(key) else (), acts_on=on)
    except ValueError as exc:
        if isinstance(exc, FileFormatError):
            raise
        raise t.fail("weights", str(exc)) from None


def from_table(t: Table) -> Transducer:
    """Build a model from the tables of a model file (or a profile's ``emulator.model``)."""
    p = t.table("polarization")
    assert p is not None
    kind = p.string("type", "hem", choices=("hem", "preisach", "bouc-wen"))
    if kind != "hem":
        if p.table("viscous", required=False) is not None:
            raise p.fail("viscous", "viscous relaxation needs the paper's polarization "
                                    f"(type = \"hem\"), not type = \"{kind}\"")
        return _transducer(t, _preisach(p) if kind == "preisach" else _bouc_wen(p), None)
    coercive = _density(p.table("coercive"), ("lognormal", "discrete"))  # type: ignore[arg-type]
    if isinstance(coercive, hy.Discrete) and min(coercive.nodes) <= 0:
        raise p.fail("coercive.nodes_MV_per_m", "coercive-field nodes must be > 0")
    th = p.table("thermal", required=False)
    effects, thermal = effects_from_table(t.table("effects", required=False))
    if thermal is not None and th is not None:
        raise t.fail("effects.thermal_relaxation", "thermal relaxation given twice (also as "
                     "[polarization.thermal])")
    thermal = thermal if th is None else _thermal(th)
    pol = hy.Polarization(
        eta=p.number("eta_MVm_per_Cm2", positive=True), p_r=p.number("p_r_C_per_m2", positive=True),
        coercive=coercive,  # type: ignore[arg-type]
        interaction=_density(p.table("interaction"), ("normal", "discrete")),  # type: ignore[arg-type,union-attr]
        n_coercive=p.integer("n_coercive", 128, minimum=1),
        n_interaction=p.integer("n_interaction", 64, minimum=1),
        kernel=p.string("kernel", "auto", choices=("auto", "normal", "grid")),  # type: ignore[arg-type]
        thermal=thermal)
    visc = p.table("viscous", required=False)
    return _transducer(t, pol, effects, None if visc is None else
                       Viscous(visc.number("relaxation_time_s", positive=True)))


def _transducer(t: Table, pol: hy.Polarization | PreisachGrid | BoucWen,
                effects: Effects | None, viscous: Viscous | None = None) -> Transducer:
    """The rest of the model around its polarization: rod, thickness, effects, creep."""
    if effects is None:
        effects, thermal = effects_from_table(t.table("effects", required=False))
        if thermal is not None:
            raise t.fail("effects.thermal_relaxation", "a Preisach grid or Bouc-Wen model has no "
                         "thermal kernel")
    r = t.table("rod")
    assert r is not None
    rod = Rod(m=r.number("m_kg", positive=True), c=r.number("c_Ns_per_m", nonnegative=True),
              k=r.number("k_N_per_m", positive=True), a1=r.number("a1_N_per_C_m2"),
              a2=r.number("a2_N_per_C2_m4", 0.0), a3=r.number("a3_N_per_C3_m6", 0.0),
              offset_um=r.number("offset_um", 0.0))
    tt = t.table("transducer")
    assert tt is not None
    return Transducer(pol, rod, tt.number("thickness_um", positive=True), effects,  # type: ignore[arg-type]
                      _initial_state(tt, pol), _creep(t.table("creep", required=False)), viscous)


def _initial_state(tt: Table, pol: object) -> str:
    """``[transducer] initial_state``: a named state, or for a Bouc-Wen polarization also one
    named by its value (:func:`afmctl.model.hysteresis.bouc_wen_state`)."""
    named = ("depoled", "positive", "negative")
    val = tt.string("initial_state", "depoled")
    if val in named:
        return val
    if isinstance(pol, BoucWen):
        try:
            if hy.bouc_wen_share(val) is not None:
                return val
        except ValueError as exc:
            raise tt.fail("initial_state", str(exc)) from None
        named += (f"{hy.BW_STATE}<share of the saturation, -1 ... 1>",)
    raise tt.fail("initial_state", f"must be one of {', '.join(named)}, got {val!r}")


def file_version(t: Table) -> int:
    """The ``format_version`` of a model file's root table (checking ``format``); one of
    :data:`READABLE_VERSIONS` or :data:`XY_VERSION` (a two-axis file)."""
    fmt = t.string("format")
    if fmt != FORMAT:
        raise t.fail("format", f"expected {FORMAT!r}, got {fmt!r}")
    ver = t.integer("format_version")
    if ver not in (*READABLE_VERSIONS, XY_VERSION):
        raise t.fail("format_version", f"this afmctl reads versions "
                     f"{', '.join(map(str, (*READABLE_VERSIONS, XY_VERSION)))}, got {ver}")
    return ver


def _load(path: str | Path) -> tuple[Transducer, Envelope | None, FitRecord | None]:
    t = load(path)
    ver = file_version(t)
    if ver == XY_VERSION:
        raise t.fail("format_version", "a two-axis model file (version 4): name the axis "
                     "(afmctl track --axis x|y)")
    model, env, fit = load_tables(t, ver)
    t.reject_unknown()
    return model, env, fit


def load_tables(t: Table, ver: int) -> tuple[Transducer, Envelope | None, FitRecord | None]:
    """Model, envelope and fit record from the tables of a one-axis model (a file's root, or
    one axis's table of a two-axis file, read as version ``ver``)."""
    model = from_table(t)
    if ver < 3 <= version_for(model):
        raise t.fail("format_version", "a Preisach grid, creep or viscous relaxation needs "
                                       f"version 3, got {ver}")
    env_t = t.table("envelope", required=False) if ver >= 2 else None
    env = None if env_t is None else _envelope(env_t)
    unc = t.table("uncertainty", required=False) if ver >= 2 else None
    if unc is not None:
        for key in UNCERTAINTY_KEYS:
            unc.has(key)
    fit_t = t.table("fit", required=False) if ver >= 2 else None
    fit = None if fit_t is None else _fit_record(fit_t)
    return model, env, fit


def read(path: str | Path) -> Transducer:
    """Read a model file (format version 1, 2 or 3); FileFormatError (naming file and key) on
    anything malformed."""
    return _load(path)[0]


def read_envelope(path: str | Path) -> Envelope | None:
    """The ``[envelope]`` of a model file (None for version 1 files and models without one)."""
    return _load(path)[1]


def read_fit(path: str | Path) -> FitRecord | None:
    """The ``[fit]`` record of a model file (None if it has none)."""
    return _load(path)[2]


def write(model: Transducer, path: str | Path, header: str = "",
          envelope: Envelope | None = None,
          uncertainty: Mapping[str, Any] | None = None, fit: FitRecord | None = None) -> None:
    """Write ``model`` atomically (temporary file then rename: never a half-written model), with
    its validity ``envelope``, the fit's ``uncertainty`` (:func:`afmctl.fit.uncertainty.summary`)
    and its writer's ``fit`` record if given."""
    write_text(path, header, full_dict(model, envelope, uncertainty, fit))


def full_dict(model: Transducer, envelope: Envelope | None = None,
              uncertainty: Mapping[str, Any] | None = None,
              fit: FitRecord | None = None) -> dict[str, Any]:
    """The tables of a one-axis model file: the model and what its fit said of it."""
    data = to_dict(model)
    if envelope is not None:
        data["envelope"] = envelope.to_dict()
    if uncertainty:
        data["uncertainty"] = uncertainty_table(uncertainty)
    if fit is not None:
        data["fit"] = fit.to_dict()
    return data


def write_text(path: str | Path, header: str, data: Mapping[str, Any]) -> None:
    """Write the tables ``data`` atomically (temporary file then rename), ``header`` as comments."""
    p = Path(path)
    text = "".join(f"# {line}\n" for line in header.splitlines()) + dumps(data)
    tmp = p.with_name(p.name + ".partial")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(p)
