"""The two-axis parts of a profile (:mod:`afmctl.files.profile`): ``[axes]``, the ``[axis.<name>]``
overrides of the per-channel sections, a stage's cross-coupling (``[emulator.coupling.*]``) and
its foreign x/y plant (``[emulator.xy_foreign]``). Every problem raises
:class:`~afmctl.errors.FileFormatError` naming the file and key (the CLI: one line, exit 2).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

from afmctl.errors import FileFormatError
from afmctl.files.tomlfile import Table
from afmctl.model.coupling import Coupling

if TYPE_CHECKING:
    from afmctl.files.profile import Profile

#: Axis names a profile may declare (``[axes] names``), in channel order.
AXIS_NAMES = ("x", "y")
#: The sections an ``[axis.<name>]`` table may override (the per-channel ones).
AXIS_SECTIONS = ("amplifier", "sensor", "stack", "emulator")
#: Keys of an ``[emulator.coupling.<direction>]`` table and the :class:`Coupling` field of each.
COUPLING_KEYS = {"static_um_per_um": "static", "mode_Hz": "mode_hz", "damping_ratio": "damping",
                 "gain_hp_um_per_um": "gain_hp", "gain_bp_um_per_um": "gain_bp",
                 "reference_um": "reference_um"}


@dataclass(frozen=True)
class XYForeignSpec:
    """An independently written foreign x/y stage as a two-axis emulated device's plant
    (``[emulator.xy_foreign]``, :mod:`afmctl.drivers.device.foreign.xy_stage`): both axes and
    their coupling from formulas of its own, drawn from ``seed`` (optionally with its static
    coupling y from x, dB, and its shared mode, Hz), or one of the fixed benchmark stages
    (``bench``, 1 ... 8). Its drive range is the profile's: 0 ... 150 V (unipolar) or -150 ...
    150 V on both axes."""

    seed: int = 0
    coupling_db: float | None = None
    mode_hz: float | None = None
    bench: int | None = None


def merged(base: dict[str, object], over: dict[str, object]) -> dict[str, object]:
    """``base`` with ``over``'s keys put over it, table by table (deep)."""
    out = dict(base)
    for key, value in over.items():
        old = out.get(key)
        out[key] = (merged(old, value) if isinstance(old, dict) and isinstance(value, dict)
                    else value)
    return out


def axes_of(t: Table) -> tuple[str, ...]:
    """``[axes] names``: ``("x",)`` without the table; else ``["x"]`` or ``["x", "y"]``."""
    at = t.table("axes", required=False)
    if at is None:
        if t.has("axis"):
            raise t.fail("axis", "per-axis tables need [axes] names = [\"x\", \"y\"]")
        return ("x",)
    for key in at.data:
        if key != "names":
            raise at.fail(key, "unknown key (known: names)")
    at.has("names")
    names = at.data.get("names")
    if not isinstance(names, list) or tuple(names) not in (AXIS_NAMES[:1], AXIS_NAMES):
        raise at.fail("names", f'must be ["x", "y"] (channel 0 is x, channel 1 is y) or ["x"], '
                               f"got {names!r}")
    return tuple(names)


def other_axes(t: Table, axes: tuple[str, ...], build: Callable[[Table, str], Profile]
               ) -> tuple[Profile, ...]:
    """The one-axis profiles of ``axes[1:]``: each ``[axis.<name>]`` over the top level, built by
    ``build(table, axis name)`` from the merged per-channel sections."""
    per = t.table("axis", required=len(axes) > 1)
    if per is None:
        return ()
    for key in per.data:
        if key not in axes[1:]:
            raise per.fail(key, f"no such axis in [axes] names (per-axis tables: "
                                f"{', '.join(axes[1:]) or 'none'})")
    out = []
    for axis in axes[1:]:
        over = per.table(axis)
        assert over is not None
        for key in over.data:
            if key not in AXIS_SECTIONS:
                raise over.fail(key, f"not a per-axis section (an axis overrides "
                                     f"{', '.join(AXIS_SECTIONS)}; the rest is the stage's)")
        base = {k: v for k, v in t.data.items() if k in AXIS_SECTIONS}
        if isinstance(base.get("emulator"), dict):  # the stage's, not an axis's
            base["emulator"] = {k: v for k, v in base["emulator"].items()
                                if k not in ("coupling", "xy_foreign")}
        if "emulator" in over.data and "emulator" not in base:
            raise over.fail("emulator", "the top level has no [emulator] for it to override")
        table = Table(merged(base, dict(over.data)), over.where)
        prof = build(table, axis)
        table.reject_unknown()
        for key in over.data:  # every override was read where the axis was built
            over.has(key)
        out.append(replace(prof, axes=(axis,)))
    return tuple(out)


def coupling_of(t: Table | None, axes: tuple[str, ...]) -> tuple[tuple[str, Coupling], ...]:
    """``[emulator.coupling.yx]`` and ``.xy`` (each direction optional) of a two-axis stage."""
    if t is None:
        return ()
    if len(axes) < 2:
        raise t.fail("yx", "a coupling needs two axes ([axes] names = [\"x\", \"y\"])")
    out = []
    for direction in t.data:
        if direction not in ("yx", "xy"):
            raise t.fail(direction, "unknown direction (yx: y caused by x; xy: x caused by y)")
        d = t.table(direction)
        assert d is not None
        for key in d.data:
            if key not in COUPLING_KEYS:
                raise d.fail(key, f"unknown key (known: {', '.join(COUPLING_KEYS)})")
        fields = {f: d.number(k, 0.05 if f == "damping" else 0.0 if k != "static_um_per_um"
                              else None, nonnegative=f in ("mode_hz", "damping"))
                  for k, f in COUPLING_KEYS.items()}
        try:
            out.append((direction, Coupling(**fields)))
        except ValueError as exc:
            raise d.fail("damping_ratio", str(exc)) from None
    return tuple(out)


#: The drive ranges of a foreign x/y stage (unipolar, bipolar), V.
XY_FOREIGN_RANGES = ((0.0, 150.0), (-150.0, 150.0))


def xy_foreign_of(t: Table, first: Profile, others: tuple[Profile, ...]) -> XYForeignSpec:
    """``[emulator.xy_foreign]``: needs two axes, each amplifier over the foreign stage's range."""
    known = ("seed", "coupling_dB", "mode_Hz", "bench")
    for key in t.data:
        if key not in known:
            raise t.fail(key, f"unknown key (known: {', '.join(known)})")
    if len(others) != 1:
        raise t.fail("seed", 'a foreign x/y stage needs [axes] names = ["x", "y"]')
    for axis in (first, *others):
        if (axis.limits.v_min, axis.limits.v_max) not in XY_FOREIGN_RANGES:
            raise t.fail("seed", f"{axis.name}: the foreign x/y stage drives 0 ... 150 V or "
                                 f"-150 ... 150 V, the amplifier says {axis.limits.v_min:g} ... "
                                 f"{axis.limits.v_max:g} V")
    spec = XYForeignSpec(
        t.integer("seed", 0),
        t.number("coupling_dB") if t.has("coupling_dB") else None,
        t.number("mode_Hz", positive=True) if t.has("mode_Hz") else None,
        t.integer("bench", minimum=1) if t.has("bench") else None)
    if spec.coupling_db is not None and not -45.0 <= spec.coupling_db <= -25.0:
        raise t.fail("coupling_dB", f"must be in [-45, -25] dB, got {spec.coupling_db:g}")
    if spec.bench is not None and spec.bench > 8:
        raise t.fail("bench", f"the benchmark stages are 1 ... 8, got {spec.bench}")
    return spec


def stage_plant(t: Table, axes: tuple[str, ...], first: Profile, others: tuple[Profile, ...]
                ) -> tuple[tuple[tuple[str, Coupling], ...], XYForeignSpec | None]:
    """The stage's ``[emulator.coupling]`` and ``[emulator.xy_foreign]`` (of the top level only)."""
    em = t.data.get("emulator")
    em = em if isinstance(em, dict) else {}
    found = {}
    for key in ("coupling", "xy_foreign"):
        if key in em and not isinstance(em[key], dict):
            raise FileFormatError(f"{t.where} emulator.{key}: expected a table")
        found[key] = None if key not in em else Table(em[key], f"{t.where} emulator.{key}")
    xy = found["xy_foreign"]
    return (coupling_of(found["coupling"], axes),
            None if xy is None else xy_foreign_of(xy, first, others))
