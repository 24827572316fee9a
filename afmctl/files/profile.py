"""Stage profiles: TOML files that describe one stage, read into frozen dataclasses.

A profile says how to reach the stage (``[transport]``), what the amplifier may do
(``[amplifier]``: gain, voltage limits, slew limit, current and stack capacitance), how the
sensor's raw reading maps to displacement (``[sensor]``), the layer thickness (``[stack]``) and the
sample rate. An emulated stage also carries ``[emulator]``: its true model (``[emulator.model]``,
exactly the model-file schema of :mod:`afmctl.files.modelfile`), noise, seed, watchdog and optional
effects that the base model lacks (``[emulator.effects.*]``, each off unless present) and wire
faults its servers inject (``[emulator.faults]``, off unless present). ``[emulator.foreign]``
(off unless present, :class:`ForeignStage`) replaces the plant by an independently written
foreign stage (:mod:`afmctl.drivers.device.foreign.stage`) drawn from its ``seed``:
``[emulator.model]`` is then only what ``track``/``play`` take as the truth between samples, not what
the device does. ``[emulator.family]`` (:class:`FamilySpec`) likewise replaces it by an
out-of-family stage (Preisach, modified Prandtl-Ishlinskii or Bouc-Wen hysteresis, creep, drift:
:mod:`afmctl.drivers.device.foreign.family_stage`); a profile carries at most one of the two.
Every key carries its unit.
A wire's ``[transport]`` also gives ``timeout_s`` (per reply) and ``watchdog_s``, the device
watchdog's period the host arms for every run (default twice ``timeout_s``, which it must exceed;
0: never armed).

Every problem raises :class:`~afmctl.errors.FileFormatError` naming the file and key, which the
CLI prints as one line with exit status 2. Shipped profiles live in ``profiles/`` at the top of the
checkout, installed as the package data of ``afmctl.profiles``, and are reachable by name
(``--profile lab-modbus``) wherever a profile path is taken.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import ClassVar

from afmctl.errors import FileFormatError
from afmctl.files import modelfile
from afmctl.files import profile_axes as pa
from afmctl.files.profile_axes import XYForeignSpec
from afmctl.files.tomlfile import Table, load
from afmctl.guard import Limits
from afmctl.model.coupling import Coupling
from afmctl.model.effects import Effects, SecondMode
from afmctl.model.transducer import Transducer

FORMAT = "afmctl-profile"
FORMAT_VERSION = 1

__all__ = ["Effects", "SecondMode", "FileFormatError", "FamilySpec", "ForeignStage", "Profile",
           "XYForeignSpec",
           "load_profile",
           "default_profile", "shipped_profile", "shipped_names"]


@dataclass(frozen=True)
class EmulatedTransport:
    """The emulated device, run in-process (no wire)."""


#: Watchdog period a host arms for every run over a wire, in per-reply timeouts, when the profile
#: gives none (2: one lost reply and its retry fit in a period).
WATCHDOG_TIMEOUTS = 2.0
#: The longest watchdog period a device takes, s (``WDT`` outside 0 ... 3600 s is error 2).
WATCHDOG_MAX_S = 3600.0


@dataclass(frozen=True)
class SerialTransport:
    """ASCII protocol over any pyserial URL (a port, ``socket://host:port``, a pty path).

    ``timeout_s`` is the per-reply timeout; ``watchdog_s`` the device watchdog's period the host
    arms for every run (0: never armed), which must exceed ``timeout_s`` (one lost reply must not
    end a run; default twice ``timeout_s``). The same two keys, in seconds, for every wire."""

    url: str
    baudrate: int = 115200
    timeout_s: float = 2.0
    watchdog_s: float = WATCHDOG_TIMEOUTS * 2.0


@dataclass(frozen=True)
class ModbusTcpTransport:
    host: str
    port: int = 502
    unit: int = 1
    timeout_s: float = 2.0
    watchdog_s: float = WATCHDOG_TIMEOUTS * 2.0


@dataclass(frozen=True)
class ModbusRtuTransport:
    """Modbus RTU over a serial port (or ``socket://host:port`` for RTU framing over TCP)."""

    port: str
    baudrate: int = 115200
    unit: int = 1
    timeout_s: float = 2.0
    watchdog_s: float = WATCHDOG_TIMEOUTS * 2.0


Transport = EmulatedTransport | SerialTransport | ModbusTcpTransport | ModbusRtuTransport


@dataclass(frozen=True)
class WireFaults:
    """Faults the emulated device's servers inject into their replies (all off by default).

    Each reply (a line of the serial protocol, or a chunk of bytes the device sends on Modbus TCP
    or RTU) suffers at most one fault, drawn from a generator seeded with ``seed``.

    Parameters
    ----------
    drop, corrupt, delay, disconnect, garbage : float
        Probability per reply of: never sending it; flipping one of its bytes (on RTU: a bad CRC);
        sending it ``delay_s`` late; dropping the connection instead (a socket is closed, a pty
        loses what it had buffered); sending random bytes before it. Their sum must be <= 1.
    delay_s : float
        How late a delayed reply is, s.
    seed : int
    """

    drop: float = 0.0
    corrupt: float = 0.0
    delay: float = 0.0
    disconnect: float = 0.0
    garbage: float = 0.0
    delay_s: float = 0.05
    seed: int = 0

    KINDS: ClassVar[tuple[str, ...]] = ("drop", "corrupt", "delay", "disconnect", "garbage")

    def probabilities(self) -> tuple[float, ...]:
        """Probabilities of :attr:`KINDS`, in that order."""
        return tuple(getattr(self, k) for k in self.KINDS)

    @property
    def active(self) -> bool:
        return any(p > 0 for p in self.probabilities())


#: Parameters of a random foreign stage a profile may fix (``[emulator.foreign]``), with the name
#: :func:`afmctl.drivers.device.foreign.stages.random_stage` knows each by (units in the names).
FOREIGN_NUMBERS: dict[str, str] = {
    "layer_thickness_um": "layer_thickness_um", "coercive_median_rel": "coercive_median_rel",
    "coercive_shape": "coercive_shape", "interaction_std_rel": "interaction_std_rel",
    "reversible_rel": "reversible_rel", "remanence_C_m2": "remanence_C_m2",
    "resonance_Hz": "resonance_hz", "damping_ratio": "damping_ratio", "mass_kg": "mass_kg",
    "span_um": "span_um", "a2_ratio": "a2_ratio", "noise_um": "noise_um",
    "offset_um": "offset_um"}
FOREIGN_FAMILIES = {"coercive_family": ("lognormal", "gamma", "loglogistic"),
                    "interaction_family": ("normal", "logistic", "laplace")}
#: Hidden causes a foreign stage may carry (:func:`afmctl.drivers.device.foreign.effects.random_effect`).
FOREIGN_CAUSES = ("amplifier-lag", "sensor-delay", "thermal-relaxation", "second-mode",
                  "sensor-nonlinearity", "voltage-gain-drift", "backlash", "gauge-saturation",
                  "interference")


@dataclass(frozen=True)
class ForeignStage:
    """A foreign stage as the emulated device's plant (``[emulator.foreign]``).

    Parameters
    ----------
    seed : int
        Draws the stage (and its effect) and seeds its sensor noise.
    start : str or float
        State at power-on: ``"poled+"``, ``"poled-"``, ``"depoled"`` or a voltage, V (poled+,
        then brought to it).
    effect : str or None
        One hidden cause of :data:`FOREIGN_CAUSES` (None: a clean stage).
    strength : float or None
        The effect's strength, 0 (barely detectable) .. 1 (strong); None: drawn.
    overrides : tuple of (str, float or str)
        Fixed stage parameters, by :func:`~afmctl.drivers.device.foreign.stages.random_stage`'s names
        (the profile's keys are :data:`FOREIGN_NUMBERS` and :data:`FOREIGN_FAMILIES`).
    """

    seed: int = 0
    start: str | float = "poled+"
    effect: str | None = None
    strength: float | None = None
    overrides: tuple[tuple[str, float | str], ...] = ()


#: Out-of-family stages (``[emulator.family]``, :mod:`afmctl.drivers.device.foreign.family_stage`):
#: hysteresis families, Preisach densities, second forms of diagnose's causes, and the stage
#: parameters a profile may fix (profile key: the name ``random_family_stage`` knows it by).
FAMILY_NAMES = ("preisach", "prandtl-ishlinskii", "bouc-wen")
FAMILY_DENSITIES = ("random", "separable")
FAMILY_EFFECTS = ("amplifier-lag", "thermal-relaxation", "second-mode", "sensor-delay",
                  "sensor-nonlinearity", "voltage-gain-drift")
FAMILY_NUMBERS: dict[str, str] = {
    "span_um": "span_um", "hysteresis": "hysteresis", "resonance_Hz": "resonance_hz",
    "damping_ratio": "damping", "noise_um": "noise_um", "creep_per_decade": "creep_per_decade",
    "drift_um_per_s": "drift_um_per_s"}


@dataclass(frozen=True)
class FamilySpec:
    """An out-of-family stage as the emulated device's plant (``[emulator.family]``).

    Parameters
    ----------
    family : str
        ``preisach``, ``prandtl-ishlinskii`` (modified: cubic output map) or ``bouc-wen``.
    seed : int
        Draws the stage (and its effect) and seeds its sensor noise.
    creep, drift : bool
        Log-time creep (1-2 % per decade), frame drift linear in time.
    density : str
        A Preisach density: ``random`` (non-separable, off-centre) or ``separable``.
    effect : str or None
        A second form of one of diagnose's causes (:data:`FAMILY_EFFECTS`).
    overrides : tuple of (str, float)
        Fixed stage parameters (profile keys :data:`FAMILY_NUMBERS`).
    """

    family: str
    seed: int = 0
    creep: bool = False
    drift: bool = False
    density: str = "random"
    effect: str | None = None
    overrides: tuple[tuple[str, float], ...] = ()


@dataclass(frozen=True)
class EmulatorConfig:
    """The emulated device's truth: model, effects, noise (um, 1 sigma), seed, watchdog (s), and
    the wire faults its servers inject."""

    model: Transducer
    effects: Effects = field(default_factory=Effects)
    noise_um: float = 0.0
    seed: int = 0
    watchdog_s: float = 0.0
    read_only: bool = False
    recorder_capacity: int = 262144
    table_capacity: int = 65536
    faults: WireFaults = field(default_factory=WireFaults)
    foreign: ForeignStage | None = None
    family: FamilySpec | None = None
    #: A two-axis stage's cross-coupling by direction (``"yx"``: y motion caused by x), from
    #: ``[emulator.coupling.yx]`` and ``[emulator.coupling.xy]`` of the profile's top level.
    coupling: tuple[tuple[str, Coupling], ...] = ()
    #: A two-axis stage whose plant is the foreign x/y stage (both axes and the coupling).
    xy_foreign: XYForeignSpec | None = None

    @property
    def true_model(self) -> Transducer:
        """The device's truth as one model: the transducer with the effects it carries."""
        return replace(self.model, effects=self.effects)

    @property
    def plant_model(self) -> Transducer | None:
        """The model the device simulates (:attr:`true_model`), the truth between its samples;
        None when its plant is a foreign stage: ``[emulator.model]`` is then not what it does."""
        return None if self.foreign is not None or self.xy_foreign is not None else self.true_model


@dataclass(frozen=True)
class Profile:
    """One stage. ``displacement_um = sensor_scale_um * raw + sensor_offset_um``."""

    name: str
    transport: Transport
    sample_rate_hz: float
    limits: Limits
    amplifier_gain: float
    sensor_scale_um: float
    sensor_offset_um: float
    thickness_um: float
    emulator: EmulatorConfig | None = None
    #: Names of the stage's axes, channel 0 first (``("x",)``, or ``("x", "y")`` from ``[axes]``).
    axes: tuple[str, ...] = ("x",)
    #: The one-axis profiles of the axes after the first (``[axis.y]`` over the top level).
    other_axes: tuple[Profile, ...] = ()

    @property
    def axis_names(self) -> tuple[str, ...]:
        """The axes, channel 0 first: ``("x",)`` for a one-axis profile."""
        return self.axes

    def axis(self, name: str) -> Profile:
        """The complete one-axis profile of axis ``name`` (its channel's limits, sensor, stack and
        emulated plant; transport and sample rate the stage's). KeyError for an unknown axis."""
        if name not in self.axes:
            raise KeyError(f"profile {self.name!r} has no axis {name!r} (axes: "
                           f"{', '.join(self.axes)})")
        if len(self.axes) == 1:
            return self
        if name != self.axes[0]:
            return self.other_axes[self.axes.index(name) - 1]
        em = (None if self.emulator is None
              else replace(self.emulator, coupling=(), xy_foreign=None))
        return replace(self, name=f"{self.name}, axis {name}", emulator=em, axes=(name,),
                       other_axes=())


def _transport(t: Table) -> Transport:
    kind = t.string("kind", choices=("emulated", "serial", "modbus-tcp", "modbus-rtu"))
    if kind == "emulated":
        return EmulatedTransport()
    timeout = t.number("timeout_s", 2.0, positive=True)
    watchdog = t.number("watchdog_s", WATCHDOG_TIMEOUTS * timeout, nonnegative=True)
    if 0 < watchdog <= timeout:
        raise t.fail("watchdog_s", f"must exceed timeout_s ({timeout:g} s), or be 0 (never armed)")
    if watchdog > WATCHDOG_MAX_S:
        raise t.fail("watchdog_s", f"at most {WATCHDOG_MAX_S:g} s (docs/reference/protocol.md, WDT), "
                                   f"got {watchdog:g}")
    if kind == "serial":
        return SerialTransport(t.string("url"), t.integer("baudrate", 115200, minimum=1), timeout,
                               watchdog)
    unit = t.integer("unit", 1, minimum=1)
    if unit > 247:
        raise t.fail("unit", f"must be <= 247, got {unit}")
    if kind == "modbus-tcp":
        port = t.integer("port", 502, minimum=1)
        if port > 65535:
            raise t.fail("port", f"must be <= 65535, got {port}")
        return ModbusTcpTransport(t.string("host"), port, unit, timeout, watchdog)
    return ModbusRtuTransport(t.string("port"), t.integer("baudrate", 115200, minimum=1), unit,
                              timeout, watchdog)


def _limits(t: Table, sample_rate_hz: float) -> Limits:
    v_min, v_max = t.number("v_min_V"), t.number("v_max_V")
    slew = t.number("slew_V_per_ms", positive=True)
    current, cap = t.number("current_mA", positive=True), t.number("capacitance_uF", positive=True)
    if v_min >= v_max:
        raise t.fail("v_max_V", f"must exceed v_min_V ({v_min})")
    if not v_min <= 0.0 <= v_max:
        raise t.fail("v_min_V", "the range must contain 0 V (the safe state)")
    if slew > current / cap * (1 + 1e-12):
        raise t.fail("slew_V_per_ms", f"exceeds current / capacitance = {current / cap:g} V/ms")
    return Limits(v_min, v_max, slew, current, cap)


def _faults(t: Table | None) -> WireFaults:
    if t is None:
        return WireFaults()
    known = {*WireFaults.KINDS, "delay_s", "seed"}
    for key in t.data:
        if key not in known:
            raise t.fail(key, f"unknown key (known: {', '.join(sorted(known))})")
    probs = {k: t.number(k, 0.0, nonnegative=True) for k in WireFaults.KINDS}
    for k, p in probs.items():
        if p > 1:
            raise t.fail(k, f"a probability must be <= 1, got {p}")
    if sum(probs.values()) > 1:
        raise t.fail("drop", "the fault probabilities must sum to <= 1")
    return WireFaults(**probs, delay_s=t.number("delay_s", 0.05, nonnegative=True),
                      seed=t.integer("seed", 0))


def _foreign(t: Table | None) -> ForeignStage | None:
    if t is None:
        return None
    known = {"seed", "start", "effect", "strength", *FOREIGN_NUMBERS, *FOREIGN_FAMILIES}
    for key in t.data:
        if key not in known:
            raise t.fail(key, f"unknown key (known: {', '.join(sorted(known))})")
    start: str | float = "poled+"
    if isinstance(t.data.get("start"), (int, float)) and not isinstance(t.data["start"], bool):
        start = t.number("start")
    elif t.has("start"):
        start = t.string("start", choices=("poled+", "poled-", "depoled"))
    effect = t.string("effect", choices=FOREIGN_CAUSES) if t.has("effect") else None
    strength = t.number("strength", nonnegative=True) if t.has("strength") else None
    if strength is not None and strength > 1:
        raise t.fail("strength", f"must be in [0, 1], got {strength}")
    if strength is not None and effect is None:
        raise t.fail("strength", "needs an effect")
    over: list[tuple[str, float | str]] = []
    for key, name in FOREIGN_NUMBERS.items():
        if t.has(key):
            signed = key in ("a2_ratio", "offset_um")
            over.append((name, t.number(key) if signed else t.number(key, positive=True)))
    over += [(k, t.string(k, choices=c)) for k, c in FOREIGN_FAMILIES.items() if t.has(k)]
    return ForeignStage(t.integer("seed", 0), start, effect, strength, tuple(over))


def _family(t: Table | None) -> FamilySpec | None:
    if t is None:
        return None
    known = {"family", "seed", "creep", "drift", "density", "effect", *FAMILY_NUMBERS}
    for key in t.data:
        if key not in known:
            raise t.fail(key, f"unknown key (known: {', '.join(sorted(known))})")
    signed = ("drift_um_per_s",)
    over = tuple((name, t.number(key) if key in signed else t.number(key, positive=True))
                 for key, name in FAMILY_NUMBERS.items() if t.has(key))
    return FamilySpec(t.string("family", choices=FAMILY_NAMES), t.integer("seed", 0),
                      t.boolean("creep"), t.boolean("drift"),
                      t.string("density", "random", choices=FAMILY_DENSITIES),
                      t.string("effect", choices=FAMILY_EFFECTS) if t.has("effect") else None,
                      over)


def _emulator(t: Table) -> EmulatorConfig:
    mt = t.table("model")
    assert mt is not None
    t.has("coupling")  # the stage's, read by from_table
    t.has("xy_foreign")
    model = modelfile.from_table(mt)
    if mt.has("effects"):
        raise mt.fail("effects", "put the emulator's effects in [emulator.effects]")
    effects, thermal = modelfile.effects_from_table(t.table("effects", required=False))
    foreign = _foreign(t.table("foreign", required=False))
    family = _family(t.table("family", required=False))
    if foreign is not None and family is not None:
        raise t.fail("family", "a stage is either [emulator.foreign] or [emulator.family], "
                               "not both")
    if thermal is not None:
        model = replace(model, polarization=replace(model.polarization, thermal=thermal))
    return EmulatorConfig(
        model=model, effects=effects, noise_um=t.number("noise_um", 0.0, nonnegative=True),
        seed=t.integer("seed", 0), watchdog_s=t.number("watchdog_s", 0.0, nonnegative=True),
        read_only=t.boolean("read_only"),
        recorder_capacity=t.integer("recorder_capacity", 262144, minimum=1),
        table_capacity=t.integer("table_capacity", 65536, minimum=1),
        faults=_faults(t.table("faults", required=False)),
        foreign=foreign, family=family)


def _channel(t: Table, name: str, rate: float, transport: Transport) -> Profile:
    """The one-axis profile of the per-channel sections of ``t`` (amplifier, sensor, stack,
    emulator) with the stage's name, sample rate and transport."""
    amp, sensor, stack = t.table("amplifier"), t.table("sensor"), t.table("stack")
    assert amp is not None and sensor is not None and stack is not None
    em = t.table("emulator", required=False)
    if isinstance(transport, EmulatedTransport) and em is None:
        raise t.fail("emulator", "missing table (transport kind 'emulated' needs it)")
    return Profile(
        name=name, transport=transport, sample_rate_hz=rate,
        limits=_limits(amp, rate), amplifier_gain=amp.number("gain_V_per_V", 1.0, positive=True),
        sensor_scale_um=sensor.number("scale_um_per_unit"),
        sensor_offset_um=sensor.number("offset_um", 0.0),
        thickness_um=stack.number("thickness_um", positive=True),
        emulator=None if em is None else _emulator(em))


def from_table(t: Table) -> Profile:
    """Build a profile from its parsed TOML (see the module docstring for the schema)."""
    t.check_format(FORMAT, FORMAT_VERSION)
    rate = t.number("sample_rate_Hz", positive=True)
    transport = _transport(t.table("transport"))  # type: ignore[arg-type]
    name = t.string("name")
    axes = pa.axes_of(t)
    first = _channel(t, name, rate, transport)
    others = pa.other_axes(t, axes, lambda table, axis: _channel(table, f"{name}, axis {axis}",
                                                                   rate, transport))
    coupling, xy_foreign = pa.stage_plant(t, axes, first, others)
    emulator = None if first.emulator is None else replace(first.emulator, coupling=coupling,
                                                           xy_foreign=xy_foreign)
    return replace(first, emulator=emulator, axes=axes, other_axes=others)


def shipped_names() -> list[str]:
    """Names of the profiles shipped with afmctl (``emulated``, ``lab-serial``, ...)."""
    return sorted(f.name[:-len(".toml")] for f in resources.files("afmctl.profiles").iterdir()
                  if f.name.endswith(".toml"))


def load_profile(path: str | Path) -> Profile:
    """Read and validate a profile; FileFormatError (naming file and key) on anything wrong,
    including a key no reader knows (``[identify]`` is :mod:`afmctl.fit.identify`'s).

    ``path`` may also name a shipped profile (``--profile lab-modbus``) when no such file exists
    (a file of that name in the working directory wins)."""
    if not Path(path).exists():
        names = shipped_names()
        if str(path) in names:
            return shipped_profile(str(path))
        if not Path(path).suffix:
            raise FileFormatError(f"{path}: no such file, and no shipped profile of that name "
                                  f"(shipped: {', '.join(names)})")
    t = load(path)
    profile = from_table(t)
    t.reject_unknown(ignore=("identify",))
    return profile


def profile_table(path: str | Path) -> Table:
    """The TOML tables of the profile ``path`` (a file, or a shipped profile's name as
    :func:`load_profile` takes it), e.g. for its ``[identify]`` table."""
    if not Path(path).exists() and str(path) in shipped_names():
        ref = resources.files("afmctl.profiles").joinpath(f"{path}.toml")
        with resources.as_file(ref) as shipped:
            return load(Path(shipped))
    return load(path)


def shipped_profile(name: str) -> Profile:
    """A profile shipped with afmctl, by name (``emulated``, ``lab-serial``, ``lab-modbus``)."""
    ref = resources.files("afmctl.profiles").joinpath(f"{name}.toml")
    with resources.as_file(ref) as path:
        return load_profile(Path(path))


def default_profile() -> Profile:
    """The no-hardware default: the shipped ``emulated`` profile."""
    return shipped_profile("emulated")
