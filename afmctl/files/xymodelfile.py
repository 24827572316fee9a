"""Two-axis model files: both axes' models and the coupling both ways (model format version 4).

``identify`` writes one for a two-axis sweep set. Each axis's tables are exactly those of a
one-axis model file (:mod:`afmctl.files.modelfile`, versions 2 and 3: model, ``envelope``,
``uncertainty``, ``fit``) under ``[axis.<name>]``; the coupling of each direction
(:class:`afmctl.model.coupling.Coupling`, ``yx`` = y motion caused by x) under
``[coupling.<direction>]``::

    format = "afmctl-model"
    format_version = 4

    [axes]
    names = ["x", "y"]

    [axis.x.transducer]
    thickness_um = 100.0
    ...                                  # every table of a one-axis model file

    [axis.y.transducer]
    ...

    [coupling.yx]
    static_um_per_um = -0.0112           # um of y per um of x, signed
    mode_Hz = 412.0                      # 0: static only
    damping_ratio = 0.05
    gain_hp_um_per_um = 0.021
    gain_bp_um_per_um = 0.004
    reference_um = 48.3                  # x displacement at which y's model was identified
    quadratic_um_per_um2 = -1.6e-5       # optional (0): a flexure's arc, about centre_um
    centre_um = 53.1                     # optional (0): x where static_um_per_um is the slope
    stderr = [1e-5, 0.02, 0.1, 0.001, 0.0005]   # optional, informational: 1-sigma of static,
                                                # ln mode, ln damping, gain_hp, gain_bp

One-axis model files are read as before; :func:`read` reads either kind (a one-axis file as a
model of its one axis, ``None`` for the coupling).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from afmctl.files import modelfile as mf
from afmctl.files.tomlfile import Table, load
from afmctl.model.coupling import Coupling
from afmctl.model.transducer import Transducer
from afmctl.model.xy import AXES, DIRECTIONS, XYModel

__all__ = ["write", "read", "read_axis", "coupling_dict"]


def coupling_dict(c: Coupling, stderr: Sequence[float] | None = None) -> dict[str, Any]:
    """The ``[coupling.<direction>]`` table of ``c`` (with the fit's 1-sigma if given)."""
    out: dict[str, Any] = {"static_um_per_um": c.static, "mode_Hz": c.mode_hz,
                           "damping_ratio": c.damping, "gain_hp_um_per_um": c.gain_hp,
                           "gain_bp_um_per_um": c.gain_bp, "reference_um": c.reference_um,
                           "quadratic_um_per_um2": c.quadratic, "centre_um": c.centre_um}
    if stderr is not None:
        out["stderr"] = [float(x) for x in stderr]
    return out


def _coupling(t: Table) -> Coupling:
    if t.has("stderr"):
        t.numbers("stderr")
    try:
        return Coupling(t.number("static_um_per_um"), t.number("mode_Hz", 0.0, nonnegative=True),
                        t.number("damping_ratio", 0.05, positive=True),
                        t.number("gain_hp_um_per_um", 0.0), t.number("gain_bp_um_per_um", 0.0),
                        t.number("reference_um", 0.0), t.number("quadratic_um_per_um2", 0.0),
                        t.number("centre_um", 0.0))
    except ValueError as exc:
        if isinstance(exc, mf.FileFormatError):
            raise
        raise t.fail("mode_Hz", str(exc)) from None


def write(model: XYModel, path: str | Path, header: str = "",
          envelopes: Mapping[str, mf.Envelope | None] | None = None,
          uncertainties: Mapping[str, Mapping[str, Any]] | None = None,
          fits: Mapping[str, mf.FitRecord] | None = None,
          stderr: Mapping[str, Sequence[float]] | None = None) -> None:
    """Write a two-axis model atomically, each axis with its envelope, uncertainty and fit record
    and each coupling with its 1-sigma, where given."""
    axis = {a: mf.full_dict(model.axes[a], (envelopes or {}).get(a),
                            (uncertainties or {}).get(a), (fits or {}).get(a)) for a in AXES}
    for tables in axis.values():
        del tables["format"], tables["format_version"]
    data = {"format": mf.FORMAT, "format_version": mf.XY_VERSION, "axes": {"names": list(AXES)},
            "axis": axis,
            "coupling": {d: coupling_dict(model.coupling[d], (stderr or {}).get(d))
                         for d in DIRECTIONS}}
    mf.write_text(path, header, data)


def _axes(t: Table) -> tuple[Table, dict[str, Table]]:
    names = t.table("axes")
    assert names is not None
    got = names.data.get("names")
    names.has("names")
    if got != list(AXES):
        raise names.fail("names", f"expected {list(AXES)}, got {got!r}")
    axis = t.table("axis")
    assert axis is not None
    return axis, {a: axis.table(a) for a in AXES}  # type: ignore[misc]


def _load(path: str | Path) -> tuple[dict[str, tuple[Transducer, mf.Envelope | None,
                                                     mf.FitRecord | None]],
                                     dict[str, Coupling] | None]:
    t = load(path)
    ver = mf.file_version(t)
    if ver != mf.XY_VERSION:
        parts = mf.load_tables(t, ver)
        t.reject_unknown()
        return {"x": parts}, None
    _, tables = _axes(t)
    axes = {a: mf.load_tables(tt, 3) for a, tt in tables.items()}
    ct = t.table("coupling")
    assert ct is not None
    coupling = {d: _coupling(ct.table(d)) for d in DIRECTIONS}  # type: ignore[arg-type]
    t.reject_unknown()
    return axes, coupling


def read(path: str | Path) -> XYModel:
    """Read a two-axis model file; FileFormatError (naming the file and key) on anything
    malformed, or for a one-axis model file."""
    axes, coupling = _load(path)
    if coupling is None:
        raise mf.FileFormatError(f"{path}: a one-axis model file (version "
                                 f"{mf.FORMAT_VERSION} or lower): a two-axis model is version "
                                 f"{mf.XY_VERSION}")
    return XYModel({a: v[0] for a, v in axes.items()}, coupling)


def read_axis(path: str | Path, axis: str | None
              ) -> tuple[Transducer, mf.Envelope | None, mf.FitRecord | None]:
    """One axis's model, envelope and fit record from a model file of either kind: a two-axis
    file needs ``axis``; a one-axis file is the model of whichever axis is named."""
    axes, coupling = _load(path)
    if coupling is None:
        return axes["x"]
    if axis is None:
        raise mf.FileFormatError(f"{path}: a two-axis model file: name the axis (--axis x|y)")
    return axes[axis]
