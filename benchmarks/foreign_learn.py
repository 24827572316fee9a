"""Learning on a foreign stage (:mod:`drivers.device.foreign`) behind the serial protocol.

The stage is the emulated device of the shipped ``emulated-foreign`` profile with its
``[emulator.foreign]`` table set to a seed (and a hidden plant effect at strength 0.5), served on a
pty (:class:`~drivers.device.serial_server.SerialServer`) and reached through the driver
(``open_stage``, real pyserial), as a lab reaches its stage. Its three standard triangles are
recorded through the driver (:func:`afmctl.calibration.record_standard`), the model comes from
``afmctl identify`` on them (with its validity envelope), and ``learn.run`` plays the 27.9 Hz
triangle (27.04 um, or 60 % of the span the fast sweep covered if that is less).

Judged by the stage's true position in the readings' frame: the reading minus the device's own
sensor noise draw for that run (exact for the plant-side effects used here, whose gauge is linear;
sensor-side causes would need ``diagnose`` and are refused).
"""

from __future__ import annotations

import dataclasses as dc
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from click.testing import CliRunner

from afmctl import calibration, ilc, learn, modelfile, track
from afmctl.cli import main as afmctl_main
from afmctl.profile import Profile, SerialTransport, shipped_profile
from drivers import open_stage
from drivers.device import foreign as fp
from drivers.device.emulated import EmulatedDevice
from drivers.device.serial_server import SerialServer

#: Causes whose readings are the true position plus noise (linear gauge, no latency).
PLANT_CAUSES = ("none", "amplifier-lag", "second-mode", "thermal-relaxation",
                "voltage-gain-drift")
STRENGTH = 0.5


#: The clean stage the in-process bench used before (``random_stage`` of ``default_rng([1, 13])``:
#: rod at 116 Hz, damping 0.055; its identify then put the resonance at 1.96 kHz), as the
#: parameters ``[emulator.foreign]`` fixes.
EARLIER_CLEAN = (("layer_thickness_um", 142.684502), ("coercive_median_rel", 0.684287),
                 ("coercive_shape", 0.342828), ("interaction_std_rel", 0.216091),
                 ("reversible_rel", 0.250022), ("remanence_C_m2", 0.214156),
                 ("resonance_hz", 115.910768), ("damping_ratio", 0.054747),
                 ("mass_kg", 0.148293), ("span_um", 84.607148), ("a2_ratio", -0.204942),
                 ("noise_um", 0.01521), ("offset_um", -0.452971))


def foreign_profile(cause: str, seed: int, overrides: tuple[tuple[str, float], ...] = ()
                    ) -> Profile:
    """The shipped 0-150 V foreign profile, its stage drawn from ``seed`` with ``cause`` (and the
    parameters ``overrides`` fixes instead of the profile's)."""
    if cause not in PLANT_CAUSES:
        raise ValueError(f"{cause!r}: only plant-side causes {PLANT_CAUSES} are judged here")
    base = shipped_profile("emulated-foreign")
    assert base.emulator is not None and base.emulator.foreign is not None
    spec = dc.replace(base.emulator.foreign, seed=seed,
                      effect=None if cause == "none" else cause,
                      strength=None if cause == "none" else STRENGTH,
                      overrides=overrides or base.emulator.foreign.overrides)
    return dc.replace(base, name=f"foreign-{seed}-{cause}",
                      emulator=dc.replace(base.emulator, foreign=spec))


class TruthProbe:
    """A driver stage that also keeps the device's true position of every run it plays (um)."""

    def __init__(self, stage: Any, device: EmulatedDevice) -> None:
        self.stage, self.device = stage, device
        self.positions: list[np.ndarray] = []

    def voltage(self) -> float:
        return self.stage.voltage()

    def play(self, waveform_v: np.ndarray, on_block: Any = None, **kw: Any) -> Any:
        rec = self.stage.play(waveform_v, on_block, **kw)
        with self.device.lock:
            dev = self.device.emulator
            noise = dev.physics.noise(dev.run_count - 1, 0, len(waveform_v))
        self.positions.append(rec.displacement_um - noise)
        return rec


def identified(profile: Profile, stage: Any, folder: Path) -> tuple[Any, Any, Any]:
    """Standard triangles recorded through ``stage``, then ``afmctl identify`` on them: the
    model, its envelope and the fastest sweep."""
    sweeps = calibration.record_standard(stage, profile, folder / "sweeps")
    files = sorted(str(p) for p in (folder / "sweeps").glob("*.csv"))
    out = folder / "model.toml"
    res = CliRunner().invoke(afmctl_main, ["identify", "-o", str(out), "--json", *files])
    if res.exit_code != 0:
        raise RuntimeError(f"afmctl identify failed ({res.exit_code}): {res.output[-300:]}")
    fit = json.loads(res.stdout)
    fast = max(sweeps, key=lambda s: s.frequency_hz or 0.0)
    return (modelfile.read(out), modelfile.read_envelope(out),
            (fast, fit["at_noise_floor"], fit["parameters"]["natural_frequency"]["value"]))


def learn_foreign(cause: str, seed: int, out: Path, iterations: int = 5,
                  overrides: tuple[tuple[str, float], ...] = ()) -> dict[str, Any]:
    """One foreign stage over a pty: identify, then learn, judged by its true position."""
    prof = foreign_profile(cause, seed, overrides)
    t0 = time.perf_counter()
    with EmulatedDevice(prof) as dev, SerialServer(dev, "pty") as ser:
        truth = dev.emulator.physics.stage  # type: ignore[attr-defined]
        wired = dc.replace(prof, transport=SerialTransport(ser.url))
        with open_stage(wired) as stage:
            model, envelope, (fast, at_floor, natural_hz) = identified(wired, stage, out)
            steady = fast.displacement_um[fast.displacement_um.size // 2:]
            lo, hi = float(np.min(steady)), float(np.max(steady))
            amp = min(27.04, 0.6 * (hi - lo))
            desired = track.triangle(27.9, amp, 0.5 * (lo + hi), 3, 1 / prof.sample_rate_hz)
            probe = TruthProbe(stage, dev)
            res = learn.run(probe, model, desired, prof.limits, out, {}, iterations, ilc.Law(),
                            envelope=envelope)
    part = ilc.steady_part(desired)
    rms = [float(np.sqrt(np.mean((p[it.outcome.waveform.tracking] - desired.u_um)[part] ** 2)))
           for p, it in zip(probe.positions, res.iterations, strict=False)]
    noise = truth.sensor.noise_um
    described = fp.describe(truth)
    return {"effect": cause, "plant": "foreign", "wire": "serial protocol on a pty",
            "seed": seed, "truth": described["effects"],
            "true_resonance_Hz": described["derived"]["resonance_hz"],
            "identified_resonance_Hz": natural_hz, "identify_at_noise_floor": at_floor,
            "model": "afmctl identify (3 standard triangles through the driver, 0..150 V)",
            "amplitude_um": amp, "noise_um": noise, "rms_um_by_iteration": rms,
            "readings_rms_um_by_iteration": [it.steady_um for it in res.iterations],
            "kept_iteration": res.best, "stop": res.stop,
            "final_over_noise": rms[res.best] / noise, "ok": rms[res.best] / noise <= 2,
            "target": "final_over_noise <= 2 within 5 iterations",
            "seconds_per_iteration_compute": float(np.mean(res.compute_s)),
            "seconds": time.perf_counter() - t0}
