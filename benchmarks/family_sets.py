"""Out-of-family stages for the benches (issue 23): which stages, how they are served, recorded,
identified and judged by their true position.

The stages are the emulated device with ``[emulator.family]``
(:mod:`afmctl.drivers.device.foreign.family_stage`: Preisach with a non-separable, off-centre
density, modified Prandtl-Ishlinskii with a cubic output map, Bouc-Wen; unipolar 0..150 V and
bipolar -150..150 V; with and without log-time creep; two with frame drift), reached through the
driver interface in-process on a device clock that advances by :data:`CLOCK_STEP_S` per call
(:class:`SteppedClock`: a 7 s sweep is recorded in about a second, and waiting a minute costs
nothing: the plant is told the time passed). :data:`OTHER_FORM_CASES` are Preisach stages of the
paper's own family (a separable, centred density) each carrying a second form of one of
diagnose's causes (:mod:`afmctl.drivers.device.foreign.family_physics`).

:func:`session` opens a stage with a :class:`Probe` that keeps each run's true position (the run
re-simulated from the device's state when it began, no gauge, no noise, in the readings' frame);
:func:`record` records the three standard triangles and the reversal curves
(``afmctl sweep --design reversals``) through it; :func:`identified` fits them
(``afmctl.fit.identify.fit``, default settings), optionally kept in a cache folder so the four
benches fit each stage once (``--family-cache DIR``). :func:`profile_toml` writes a stage as a
profile file for ``afmctl emulate --profile``.
"""

from __future__ import annotations

import argparse
import dataclasses as dc
import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from afmctl.drivers.inprocess import InProcessStage
from afmctl.experiment import calibration, twin
from afmctl.experiment.twin import Twin
from afmctl.files import modelfile
from afmctl.files.profile import FamilySpec, Profile, shipped_profile
from afmctl.model import frame as fr
from afmctl.fit import identify

#: Device time each call into the in-process device advances its clock by, s.
CLOCK_STEP_S = 0.01


@dataclass(frozen=True)
class Case:
    """One out-of-family stage: its family, drive, creep, drift, seed and (other forms) effect."""

    name: str
    family: str
    bipolar: bool = False
    creep: bool = False
    drift: bool = False
    seed: int = 0
    density: str = "random"
    effect: str | None = None
    reversals: bool = True  # identified with the reversal curves (--family-design reversals)

    @property
    def spec(self) -> FamilySpec:
        return FamilySpec(self.family, self.seed, self.creep, self.drift, self.density,
                          self.effect)

    @property
    def drive_V(self) -> tuple[float, float]:
        return (-150.0, 150.0) if self.bipolar else (0.0, 150.0)

    @property
    def cause(self) -> str:
        """What a perfect diagnosis names: the effect, ``creep``, or ``none`` (a drift stage:
        ``unexplained``, with a drift hint)."""
        if self.effect is not None:
            return self.effect
        if self.drift:
            return "unexplained"
        return "creep" if self.creep else "none"


def _family_cases() -> tuple[Case, ...]:
    out = []
    for k, (fam, short) in enumerate((("preisach", "preisach"), ("prandtl-ishlinskii", "pi"),
                                      ("bouc-wen", "bw"))):
        for j, (bipolar, creep) in enumerate(((False, False), (True, False), (False, True),
                                              (True, True))):
            name = f"{short}-{'b' if bipolar else 'u'}" + ("-creep" if creep else "")
            out.append(Case(name, fam, bipolar, creep, False, 100 * (k + 1) + j + 1))
    out.append(Case("preisach-u-drift", "preisach", drift=True, seed=105))
    out.append(Case("pi-u-creep-drift", "prandtl-ishlinskii", creep=True, drift=True, seed=205))
    return tuple(out)


#: The out-of-family stages: 4 per family (unipolar / bipolar, with / without creep) and two
#: with frame drift.
FAMILY_CASES = _family_cases()
#: Identification sets a stage can be identified from (``--family-design``).
DESIGNS = ("reversals", "standard")
#: Second forms of diagnose's causes, two stages each, on in-family (separable) Preisach stages.
OTHER_FORMS = ("amplifier-lag", "thermal-relaxation", "second-mode", "sensor-delay",
               "sensor-nonlinearity", "voltage-gain-drift")
OTHER_FORM_CASES = tuple(Case(f"other-{c}-{k}", "preisach", seed=400 + 10 * i + k,
                              density="separable", effect=c)
                         for i, c in enumerate(OTHER_FORMS) for k in range(2))


def add_arguments(ap: argparse.ArgumentParser, cache: bool = True) -> None:
    """A bench's flags for its out-of-family part: ``--family-only``, ``--family NAMES`` and
    (``cache``: the benches that identify) ``--family-cache DIR`` and ``--family-design``."""
    ap.add_argument("--family-only", action="store_true",
                    help="only the out-of-family stages (issue 23)")
    ap.add_argument("--family", default="", help="comma-separated out-of-family stages "
                                                 "(default: all; 'none': no such stage)")
    if cache:
        ap.add_argument("--family-design", choices=DESIGNS, default="reversals",
                        help="the identification set recorded on each stage: the standard "
                             "triangles, or those and the reversal curves (default)")
        ap.add_argument("--family-cache", type=Path, default=None,
                        help="reuse (or keep) each stage's fit in this folder")


def cases_named(names: str, pool: tuple[Case, ...] = FAMILY_CASES,
                design: str = "reversals") -> tuple[Case, ...]:
    """The cases of ``pool`` whose names are listed (comma-separated; empty: all), identified
    from ``design`` (one of :data:`DESIGNS`)."""
    want = names.split(",") if names else [c.name for c in pool]
    known = {c.name: c for c in pool}
    bad = [n for n in want if n not in known]
    if bad:
        raise ValueError(f"unknown stage(s) {bad} (known: {', '.join(known)})")
    return tuple(dc.replace(known[n], reversals=design == "reversals") for n in want)


def profile(case: Case) -> Profile:
    """The shipped foreign profile with ``case``'s stage in ``[emulator.family]`` and its drive."""
    base = shipped_profile("emulated-foreign")
    assert base.emulator is not None
    lo, hi = case.drive_V
    em = dc.replace(base.emulator, foreign=None, family=case.spec)
    return dc.replace(base, name=f"family-{case.name}", emulator=em,
                      limits=dc.replace(base.limits, v_min=lo, v_max=hi))


def profile_text(table: str, v_min: float = 0.0, transport: str = 'kind = "emulated"') -> str:
    """The shipped foreign profile's text with ``[emulator.family]`` (``table``: its lines)
    instead of its ``[emulator.foreign]``, over ``v_min .. 150`` V, transport ``transport``."""
    from afmctl.profiles import __file__ as where
    text = (Path(where).parent / "emulated-foreign.toml").read_text()
    head, _, rest = text.partition("\n[emulator.foreign]\n")
    _, _, model = rest.partition("[emulator.model.transducer]")
    head = head.replace("v_min_V = 0.0", f"v_min_V = {v_min}").replace('kind = "emulated"',
                                                                      transport, 1)
    return head + "\n[emulator.family]\n" + table + "\n[emulator.model.transducer]" + model


def profile_toml(case: Case, transport: str = 'kind = "emulated"') -> str:
    """``case`` as a profile file (``afmctl emulate --profile``), transport ``transport``."""
    s = case.spec
    table = (f'family = "{s.family}"\nseed = {s.seed}\ncreep = {str(s.creep).lower()}\n'
             f'drift = {str(s.drift).lower()}\ndensity = "{s.density}"\n'
             + (f'effect = "{s.effect}"\n' if s.effect else ""))
    return profile_text(table, case.drive_V[0], transport)


class SteppedClock:
    """A device clock that advances :data:`CLOCK_STEP_S` per reading, plus any :meth:`skip`."""

    def __init__(self, step_s: float = CLOCK_STEP_S) -> None:
        self.now, self.step = 0.0, step_s

    def __call__(self) -> float:
        self.now += self.step
        return self.now

    def skip(self, seconds: float) -> None:
        """Let ``seconds`` of device time pass (the stage holds its output)."""
        self.now += seconds


class Probe:
    """A driver stage that keeps the true position (um, readings' frame) of every run it plays."""

    def __init__(self, stage: InProcessStage) -> None:
        self.stage = stage
        self.positions: list[np.ndarray] = []

    @property
    def plant(self) -> Any:
        return self.stage.emulator.physics

    def voltage(self) -> float:
        return self.stage.voltage()

    def now_s(self) -> float:
        return self.stage.now_s()

    @property
    def run_started_s(self) -> float | None:
        """When the last run started (s, the device's clock)."""
        return self.stage.run_started_s

    def play(self, waveform_v: np.ndarray, on_block: Any = None, **kw: Any) -> Any:
        rec = self.stage.play(waveform_v, on_block, **kw)
        dev = self.stage.emulator
        applied = dev.rec_v[np.arange(len(waveform_v)) % dev.rec_v.size].astype(float)
        true_um = self.plant.true_um(applied, dev.run_state)
        self.positions.append(true_um - self.plant.stage.zero_um)
        return rec


@dataclass
class Session:
    """An open out-of-family stage: the probe to play through, its clock, its truth, and (once
    set, :func:`follow`) the model's twin of it with the last start's latency (s); ``frame``:
    runs planned in the frame the twin reads from the readings (:meth:`Twin.planning_frame`,
    as ``afmctl track`` plans them), each run's in ``frames`` (off unless set: the bench sets
    it)."""

    case: Case
    profile: Profile
    probe: Probe
    clock: SteppedClock
    twin: Twin | None = None
    lead_s: float = 0.1
    frame: bool = False
    frames: list[dict[str, Any]] = dc.field(default_factory=list)

    @property
    def truth(self) -> Any:
        return self.probe.plant.stage

    @property
    def noise_um(self) -> float:
        return float(self.truth.noise_um)


@contextmanager
def session(case: Case) -> Iterator[Session]:
    """``case``'s stage, powered on, in-process on a :class:`SteppedClock`."""
    prof = profile(case)
    clock = SteppedClock()
    with InProcessStage(prof, clock=clock) as stage:
        yield Session(case, prof, Probe(stage), clock)


def record(s: Session, folder: Path, reversals: bool | None = None, separating: bool = False
           ) -> list[Any]:
    """The three standard triangles over the drive range and (``reversals``, default the case's)
    the reversal curves of ``afmctl sweep --design reversals``, recorded through the driver: what
    identify asks for on a stage off the paper's model family (without them the grid's interior,
    every minor loop a tracking triangle makes, is the smoothing's guess); or (``separating``)
    the separating sweep of ``afmctl sweep --design separating``."""
    from afmctl.experiment import runner
    from afmctl.files import sweepfile
    from afmctl.planning import sweepdesign

    sweeps = calibration.record_standard(s.probe, s.profile, folder)
    lim = s.profile.limits
    rate = lim.max_rate_v_per_ms * 1e3
    extra = None
    if s.case.reversals if reversals is None else reversals:
        extra = sweepdesign.reversals_sweep((lim.v_min, lim.v_max), s.profile.sample_rate_hz,
                                            rate)
    elif separating:
        extra = sweepdesign.design_set("separating", s.profile.sample_rate_hz, rate,
                                       (lim.v_min, lim.v_max))[-1]
    if extra is not None:
        name, freq, v, meta = extra
        path = folder / f"{name}.csv"  # written once complete, read back as a lab's file
        runner.record_sweep(s.probe, name, freq, v, s.profile.sample_rate_hz,
                            {"layer_thickness_um": f"{s.profile.thickness_um:g}", **meta},
                            path=path)
        sweeps.append(sweepfile.read(path))
    return sweeps


def identified(case: Case, sweeps: list[Any], noise_um: float, cache: Path | None
               ) -> dict[str, Any]:
    """``identify.fit`` on ``sweeps`` (default settings): ``model``, ``seconds``,
    ``rms_over_noise`` (per sweep, against the true noise), ``success``; read from
    ``cache/<case>/`` (``cache/<case>-standard/`` for the triangles alone) when it holds them,
    written there otherwise."""
    folder = None if cache is None else cache / (case.name if case.reversals
                                                 else f"{case.name}-standard")
    if folder is not None and (folder / "fit.json").is_file():
        info = json.loads((folder / "fit.json").read_text())
        return {**info, "model": modelfile.read(folder / "model.toml"), "cached": True}
    t0 = time.perf_counter()
    res = identify.fit(sweeps)
    info = {"seconds": time.perf_counter() - t0, "success": bool(res.success),
            "rms_over_noise": [s.rms_um / noise_um for s in res.sweeps],
            "noise_estimated_um": [s.noise_um for s in res.sweeps]}
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
        modelfile.write(res.model, folder / "model.toml", envelope=res.envelope)
        (folder / "fit.json").write_text(json.dumps(info))
    return {**info, "model": res.model, "cached": False}


def follow(s: Session, model: Any, sweeps: list[Any]) -> bool:
    """Plan ``s``'s runs from ``model``'s twin of the stage after ``sweeps``
    (:func:`afmctl.experiment.twin.from_sweeps`; False, and from rest, where the sweeps do not
    say their holds)."""
    s.twin = twin.from_sweeps(model, sweeps)
    return s.twin is not None


def span_of(sweeps: list[Any]) -> tuple[float, float]:
    """(low, high) of the fast sweep's steady half, um (the readings' frame)."""
    fast = max(sweeps, key=lambda s: s.frequency_hz or 0.0)
    steady = fast.displacement_um[fast.displacement_um.size // 2:]
    return float(np.min(steady)), float(np.max(steady))


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.asarray(x) ** 2)))


#: The out-of-family tracking triangles: (Hz, fraction of the span), centred in it.
TRIANGLES = ((0.279, 0.45), (27.9, 0.3))


def tracked(s: Session, model: Any, freq: float, frac: float, span: tuple[float, float],
            periods: float, filters: tuple[str, ...] = ("inverse", "linear")) -> dict[str, float]:
    """A triangle at ``freq`` over ``frac`` of ``span`` (um, low and high) around its middle,
    planned through ``model`` and played open loop with each of ``filters`` in turn: each one's
    TRUE RMS after the first period (um; the stage re-simulated, no gauge, no noise).
    ``afmctl.guard.LimitError`` if the plan is refused."""
    return {name: rms(e) for name, e in tracked_errors(s, model, freq, frac, span, periods,
                                                       filters).items()}


def tracked_errors(s: Session, model: Any, freq: float, frac: float, span: tuple[float, float],
                   periods: float, filters: tuple[str, ...] = ("inverse", "linear")
                   ) -> dict[str, np.ndarray]:
    """:func:`tracked`'s true errors themselves (um, after the first period), per filter."""
    from afmctl.planning import track

    lo, hi = span
    desired = track.triangle(freq, frac * (hi - lo), 0.5 * (lo + hi), periods,
                             1 / s.profile.sample_rate_hz)
    assert desired.period_s is not None
    skip = int(round(desired.period_s / desired.dt_s))
    out = {}
    for name in filters:  # each planned from the twin as the run before left it
        asked = s.probe.now_s() + s.lead_s
        state = None if s.twin is None else s.twin.at(asked)
        frame = fr.Frame() if s.twin is None or not s.frame else s.twin.planning_frame(asked)
        wf = track.plan(model, desired, s.profile.limits, s.probe.voltage(),
                        tuple(dict.fromkeys(("inverse", name))), state=state, frame=frame)[name]
        rec = s.probe.play(wf.voltage_v)
        s.frames.append(frame.as_dict())
        if s.twin is not None and rec.started_s is not None:
            s.twin = s.twin.after(wf.voltage_v, rec.started_s, readings_um=rec.displacement_um)
            s.lead_s = rec.started_s - asked + s.lead_s
        out[name] = (s.probe.positions[-1][wf.tracking] - desired.u_um)[skip:]
    return out


def detrended_rms(e: np.ndarray) -> float:
    """RMS of ``e`` less its straight-line fit over the samples (um): what is left of a tracking
    error once an offset and a steady slope, all that a slow creep or drift makes over one run,
    are taken out."""
    t = np.arange(e.size, dtype=float)
    return rms(e - np.polyval(np.polyfit(t, e, 1), t))
