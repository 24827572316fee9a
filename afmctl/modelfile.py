"""TOML model files: the versioned, unit-carrying form of a :class:`~afmctl.transducer.Transducer`.

``identify`` writes them, ``track`` and ``diagnose`` read them, and a profile's ``[emulator.model]``
table uses the same schema. Every key carries its unit in its name. Example::

    format = "afmctl-model"
    format_version = 1

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

Optional ``[effects.*]`` tables (one per effect, as ``afmctl diagnose`` writes them; schema of
:mod:`afmctl.effects`, the same as a profile's ``[emulator.effects.*]``)::

    [effects.amplifier_lag]
    bandwidth_Hz = 800.0
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from afmctl import hysteresis as hy
from afmctl.effects import Effects, SecondMode
from afmctl.rod import Rod
from afmctl.tomlfile import FileFormatError, Table, dumps, load
from afmctl.transducer import Transducer

FORMAT = "afmctl-model"
FORMAT_VERSION = 1

__all__ = ["FileFormatError", "read", "write", "to_dict", "from_table", "FORMAT_VERSION"]


def _density_dict(d: hy.Lognormal | hy.Normal | hy.Discrete) -> dict[str, Any]:
    if isinstance(d, hy.Lognormal):
        return {"type": "lognormal", "median_MV_per_m": d.median, "sigma_ln": d.sigma}
    if isinstance(d, hy.Normal):
        return {"type": "normal", "std_MV_per_m": d.std}
    return {"type": "discrete", "nodes_MV_per_m": list(d.nodes),
            "values_per_MV_per_m": list(d.values)}


def to_dict(model: Transducer) -> dict[str, Any]:
    """The model as nested dicts (the TOML tables)."""
    pol = model.polarization
    pd: dict[str, Any] = {
        "eta_MVm_per_Cm2": pol.eta, "p_r_C_per_m2": pol.p_r, "n_coercive": pol.n_coercive,
        "n_interaction": pol.n_interaction, "kernel": pol.kernel,
        "coercive": _density_dict(pol.coercive), "interaction": _density_dict(pol.interaction)}
    if pol.thermal is not None:
        pd["thermal"] = {"field_scale_MV_per_m": pol.thermal.field_scale,
                         "attempt_rate_per_s": pol.thermal.attempt_rate}
    r = model.rod
    out = {
        "format": FORMAT, "format_version": FORMAT_VERSION,
        "transducer": {"thickness_um": model.thickness_um},
        "polarization": pd,
        "rod": {"m_kg": r.m, "c_Ns_per_m": r.c, "k_N_per_m": r.k, "a1_N_per_C_m2": r.a1,
                "a2_N_per_C2_m4": r.a2, "offset_um": r.offset_um},
    }
    fx = effects_dict(model.effects)
    return {**out, "effects": fx} if fx else out


def effects_dict(e: Effects) -> dict[str, Any]:
    """The ``[effects.*]`` tables of the effects that are on (empty if none)."""
    out: dict[str, Any] = {}
    if e.amplifier_bandwidth_hz is not None:
        amp = {"bandwidth_Hz": e.amplifier_bandwidth_hz, "damping_ratio": e.amplifier_damping_ratio,
               "slew_V_per_s": e.amplifier_slew_v_per_s}
        out["amplifier_lag"] = {k: v for k, v in amp.items() if v is not None}
    if e.sensor_delay_samples or e.sensor_delay_s:
        out["sensor_delay"] = {"samples": e.sensor_delay_samples, "seconds": e.sensor_delay_s}
    if e.sensor_quadratic_per_um or e.sensor_cubic_per_um2:
        out["sensor_nonlinearity"] = {"quadratic_per_um": e.sensor_quadratic_per_um,
                                      "cubic_per_um2": e.sensor_cubic_per_um2}
    if e.second_mode is not None:
        m = e.second_mode
        out["second_mode"] = {"frequency_Hz": m.frequency_hz, "damping_ratio": m.damping_ratio,
                              "gain": m.gain}
    if e.voltage_gain_sigma:
        out["voltage_gain_drift"] = {"sigma": e.voltage_gain_sigma}
    return out


EFFECT_TABLES = ("thermal_relaxation", "amplifier_lag", "sensor_delay", "sensor_nonlinearity",
                 "second_mode", "voltage_gain_drift")


def _thermal(t: Table) -> hy.Thermal:
    return hy.Thermal(t.number("field_scale_MV_per_m", positive=True),
                      t.number("attempt_rate_per_s", positive=True))


def _optional(t: Table | None, key: str) -> float | None:
    """A positive number of ``t`` if the key is there, else None."""
    return t.number(key, positive=True) if t is not None and t.has(key) else None


def effects_from_table(t: Table | None) -> tuple[Effects, hy.Thermal | None]:
    """Effects (and thermal relaxation, which belongs to the polarization kernel) from an
    ``effects`` table: one sub-table per effect that is on, keys with units (see
    :mod:`afmctl.effects`)."""
    if t is None:
        return Effects(), None
    for key in t.data:
        if key not in EFFECT_TABLES:
            raise t.fail(key, f"unknown effect (known: {', '.join(sorted(EFFECT_TABLES))})")
    th, lag, dly, nl, sm, gd = (t.table(k, required=False) for k in EFFECT_TABLES)
    mode = None if sm is None else SecondMode(sm.number("frequency_Hz", positive=True),
                                              sm.number("damping_ratio", positive=True),
                                              sm.number("gain"))
    return Effects(
        amplifier_bandwidth_hz=None if lag is None else lag.number("bandwidth_Hz", positive=True),
        amplifier_damping_ratio=_optional(lag, "damping_ratio"),
        amplifier_slew_v_per_s=_optional(lag, "slew_V_per_s"),
        sensor_delay_samples=0.0 if dly is None else dly.number("samples", 0.0, nonnegative=True),
        sensor_delay_s=0.0 if dly is None else dly.number("seconds", 0.0, nonnegative=True),
        sensor_quadratic_per_um=0.0 if nl is None else nl.number("quadratic_per_um"),
        sensor_cubic_per_um2=0.0 if nl is None else nl.number("cubic_per_um2", 0.0),
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


def from_table(t: Table) -> Transducer:
    """Build a model from the tables of a model file (or a profile's ``emulator.model``)."""
    p = t.table("polarization")
    assert p is not None
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
    r = t.table("rod")
    assert r is not None
    rod = Rod(m=r.number("m_kg", positive=True), c=r.number("c_Ns_per_m", nonnegative=True),
              k=r.number("k_N_per_m", positive=True), a1=r.number("a1_N_per_C_m2"),
              a2=r.number("a2_N_per_C2_m4", 0.0), offset_um=r.number("offset_um", 0.0))
    tt = t.table("transducer")
    assert tt is not None
    return Transducer(pol, rod, tt.number("thickness_um", positive=True), effects)


def read(path: str | Path) -> Transducer:
    """Read a model file; FileFormatError (naming file and key) on anything malformed."""
    t = load(path)
    t.check_format(FORMAT, FORMAT_VERSION)
    model = from_table(t)
    t.reject_unknown()
    return model


def write(model: Transducer, path: str | Path, header: str = "") -> None:
    """Write ``model`` atomically (temporary file then rename: never a half-written model)."""
    p = Path(path)
    text = "".join(f"# {line}\n" for line in header.splitlines()) + dumps(to_dict(model))
    tmp = p.with_name(p.name + ".partial")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(p)
