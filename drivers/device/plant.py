"""The emulated stage's plant: afmctl's true model and the effects a real stage adds, in device time.

Physics of one run (:meth:`Physics.respond`), sample by sample at the device's sample rate:

1. commanded voltage ``v_cmd`` (float32 as on the wire);
2. applied-voltage gain ``1 + N(0, sigma)`` drawn once per run (effect ``voltage_gain_drift``);
3. first-order amplifier lag (``amplifier_lag``) -> the voltage actually on the stack, recorded;
4. the true model: polarization (13) and rod (16) via :func:`afmctl.model.transducer.simulate`, with the
   thermal kernel (10) if ``thermal_relaxation`` is on;
5. a second mechanical mode driven by that displacement (``second_mode``), added;
6. gauge nonlinearity ``u + c u^2`` (``sensor_nonlinearity``), pure latency (``sensor_delay``);
7. Gaussian sensor noise.

Each run ``r`` draws its gain from ``numpy.random.default_rng((seed, r, 1))`` and its noise by
global sample index (blocks keyed ``(seed, r, 0, block)``), so :func:`expected_readback` reproduces
a run exactly, whether it was played from the table or streamed.

Hidden effects (``afmctl diagnose``'s catalogue): :func:`hidden_effect`, :func:`with_hidden_effect`,
:func:`hidden_cases`, :data:`HIDDEN_RANGES`. :class:`~afmctl.files.profile.EmulatorConfig` (the plant's
configuration, parsed from a profile's ``[emulator]`` table) is re-exported here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from afmctl.files.profile import EmulatorConfig, Profile
from afmctl.model import effects as fx
from afmctl.model import hysteresis as hy
from afmctl.model import transducer as td

__all__ = ["EmulatorConfig", "Physics", "PhysicsState", "NOISE_BLOCK", "block_noise", "HIDDEN_RANGES",
           "HIDDEN_SEED", "hidden_effect", "hidden_cases", "with_hidden_effect",
           "expected_readback"]

FloatArray = NDArray[np.float64]

#: Sensor noise is drawn in blocks of this many samples, keyed by (seed, run, 0, block).
NOISE_BLOCK = 4096

def block_noise(key: tuple[int, ...], first: int, n: int) -> FloatArray:
    """Unit Gaussian noise of samples ``first .. first+n-1``, shape (n,): blocks of
    :data:`NOISE_BLOCK` drawn from ``numpy.random.default_rng((*key, block))``, so a function of the
    global sample index only (a run played in pieces draws what one long run draws)."""
    if n <= 0:
        return np.zeros(0)
    b0, b1 = first // NOISE_BLOCK, (first + n - 1) // NOISE_BLOCK
    z = np.concatenate([np.random.default_rng((*key, b)).standard_normal(NOISE_BLOCK)
                        for b in range(b0, b1 + 1)])
    off = first - b0 * NOISE_BLOCK
    return z[off:off + n]


@dataclass(frozen=True)
class PhysicsState:
    """Everything the device remembers between samples: model, amplifier, second mode, sensor."""

    stage: td.StageState
    amp_v: float
    mode_zi: FloatArray
    delay_um: FloatArray


class Physics:
    """The true model and effects, compiled for one sample rate (immutable after construction)."""

    def __init__(self, config: EmulatorConfig, sample_rate_hz: float) -> None:
        self.config = config
        self.dt = 1.0 / sample_rate_hz
        self.compiled = td.compile_model(config.model, self.dt)
        self.chain = fx.compile_chain(config.effects, self.dt)

    def initial(self) -> PhysicsState:
        """Power-on state: depoled, 0 V, at rest."""
        stage = td.initial(self.config.model)
        u0, _, _ = td.simulate(self.compiled, np.zeros(1), stage)
        return PhysicsState(stage, 0.0, *fx.rest(self.chain, float(u0[0])))

    def gain(self, run_index: int) -> float:
        """Applied-voltage gain of run ``run_index`` (1 unless ``voltage_gain_drift``)."""
        sigma = self.config.effects.voltage_gain_sigma
        if sigma <= 0:
            return 1.0
        return 1.0 + sigma * float(np.random.default_rng((self.config.seed, run_index, 1))
                                    .standard_normal())

    def noise(self, run_index: int, first: int, n: int) -> FloatArray:
        """Sensor noise of samples ``first .. first+n-1`` of run ``run_index``, um, shape (n,).

        A function of the global sample index only (blocks of :data:`NOISE_BLOCK` keyed by
        ``(seed, run, 0, block)``), so a run played in pieces draws what one long run draws.
        """
        return self.config.noise_um * block_noise((self.config.seed, run_index, 0), first, n)

    def draws(self, run_index: int, n: int) -> tuple[float, FloatArray]:
        """Applied-voltage gain and sensor noise (um, shape (n,)) of the first ``n`` samples of run
        ``run_index``."""
        return self.gain(run_index), self.noise(run_index, 0, n)

    def respond(self, v_cmd: FloatArray, state: PhysicsState, gain: float = 1.0,
                noise_um: FloatArray | None = None
                ) -> tuple[FloatArray, FloatArray, PhysicsState]:
        """Run commanded samples through amplifier, model, mode and sensor.

        Parameters
        ----------
        v_cmd : ndarray, shape (N,)
            Commanded voltage held over each sample, V.
        state : PhysicsState
        gain : float
            Applied-voltage gain of this run.
        noise_um : ndarray, shape (N,), optional
            Sensor noise to add, um.

        Returns
        -------
        u_um : ndarray, shape (N,)
            Measured displacement at each sample instant (before that sample acts), um.
        v_applied : ndarray, shape (N,)
            Voltage on the stack during each sample, V.
        state : PhysicsState
        """
        v_app, amp_v = fx.lag(self.chain, gain * np.asarray(v_cmd, dtype=float), state.amp_v)
        u, _, stage = td.simulate(self.compiled, v_app, state.stage)
        u, zi, delay = fx.measure(self.chain, u, state.mode_zi, state.delay_um)
        if noise_um is not None:
            u = u + noise_um
        return u, v_app, PhysicsState(stage, amp_v, zi, delay)


#: Strength ranges (low, high) of the effects :func:`hidden_effect` draws: each clearly above
#: 20 nm of sensor noise on the standard triangle sweeps, yet physical (a 200-600 Hz amplifier,
#: 0.2-0.8 ms latency, a 0.1-0.3 %/um gauge error, a 400-800 Hz mode, 1.5-3 % gain spread).
HIDDEN_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "thermal-relaxation": {"field_scale_MV_per_m": (0.02, 0.05), "attempt_rate_per_s": (30, 300)},
    "amplifier-lag": {"bandwidth_Hz": (200.0, 600.0)},
    "sensor-delay": {"samples": (2, 8)},
    "sensor-nonlinearity": {"abs_quadratic_per_um": (1e-3, 3e-3)},
    "second-mode": {"frequency_Hz": (400.0, 800.0), "damping_ratio": (0.02, 0.04),
                    "gain": (0.3, 0.5)},
    "voltage-gain-drift": {"sigma": (0.015, 0.03)},
}


def hidden_effect(cause: str, rng: np.random.Generator, config: EmulatorConfig) -> EmulatorConfig:
    """``config`` carrying one effect of ``afmctl diagnose``'s catalogue (``none``: unchanged) with
    a strength drawn from :data:`HIDDEN_RANGES`: uniform, except log-uniform rates and bandwidths,
    whole delays and either sign of the gauge error. The thermal stage runs on a 48 x 16 grid."""
    if cause == "none":
        return config
    if cause not in HIDDEN_RANGES:
        raise ValueError(f"unknown cause {cause!r}")
    r = HIDDEN_RANGES[cause]

    def log_uniform(lo: float, hi: float) -> float:
        return math.exp(rng.uniform(math.log(lo), math.log(hi)))

    if cause == "thermal-relaxation":
        th = hy.Thermal(rng.uniform(*r["field_scale_MV_per_m"]),
                        log_uniform(*r["attempt_rate_per_s"]))
        pol = replace(config.model.polarization, n_coercive=48, n_interaction=16, thermal=th)
        return replace(config, model=replace(config.model, polarization=pol))
    if cause == "amplifier-lag":
        e = fx.Effects(amplifier_bandwidth_hz=log_uniform(*r["bandwidth_Hz"]))
    elif cause == "sensor-delay":
        lo, hi = r["samples"]
        e = fx.Effects(sensor_delay_samples=int(rng.integers(lo, hi + 1)))
    elif cause == "sensor-nonlinearity":
        sign = float(rng.choice([-1, 1]))
        e = fx.Effects(sensor_quadratic_per_um=sign * rng.uniform(*r["abs_quadratic_per_um"]))
    elif cause == "second-mode":
        e = fx.Effects(second_mode=fx.SecondMode(rng.uniform(*r["frequency_Hz"]),
                                                 rng.uniform(*r["damping_ratio"]),
                                                 rng.uniform(*r["gain"])))
    else:
        e = fx.Effects(voltage_gain_sigma=rng.uniform(*r["sigma"]))
    return replace(config, effects=e)


#: Seed of the batch of hidden-effect stages (tests and ``benchmarks/bench_diagnose.py``).
HIDDEN_SEED = 20261122


def hidden_cases(causes: tuple[str, ...], per_cause: int = 2) -> list[tuple[str, int]]:
    """The batch: ``per_cause`` cases of each cause as (cause, case index)."""
    return [(c, per_cause * i + k) for i, c in enumerate(causes) for k in range(per_cause)]


def with_hidden_effect(profile: Profile, cause: str, index: int) -> Profile:
    """``profile``'s emulated stage carrying ``cause`` at the strength drawn for case ``index``."""
    if profile.emulator is None:
        raise ValueError(f"profile {profile.name!r} has no [emulator] section")
    rng = np.random.default_rng((HIDDEN_SEED, index))
    config = replace(profile.emulator, seed=profile.emulator.seed + index)  # own noise and gains
    return replace(profile, emulator=hidden_effect(cause, rng, config))


def expected_readback(config: EmulatorConfig, sample_rate_hz: float, waveform_v: FloatArray,
                      cycles: int = 1, run_index: int = 0,
                      state: PhysicsState | None = None) -> tuple[FloatArray, FloatArray]:
    """The model's own simulation of one run: what the recorder should hold.

    Parameters
    ----------
    config : EmulatorConfig
    sample_rate_hz : float
    waveform_v : ndarray, shape (N,)
        The waveform table, V (rounded to float32, as on the wire).
    cycles : int
    run_index : int
        Index of the run since power-on (selects noise and gain draws).
    state : PhysicsState, optional
        Device state before the run; the power-on state if omitted.

    Returns
    -------
    u_um : ndarray, shape (N * cycles,)
        Displacement as the sensor reports it, um.
    v_applied : ndarray, shape (N * cycles,)
        Voltage on the stack, V.
    """
    ph = Physics(config, sample_rate_hz)
    v = np.tile(np.asarray(waveform_v, dtype=np.float32).astype(float), cycles)
    gain, noise = ph.draws(run_index, v.size)
    u, va, _ = ph.respond(v, ph.initial() if state is None else state, gain, noise)
    return u, va

