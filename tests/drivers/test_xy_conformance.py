"""The conformance check's channel clauses (docs/reference/protocol.md §2.14, §3.6-§3.7, §4.4-§4.5):
the emulated x/y device passes them over the serial protocol and Modbus, and an x/y device with a
defect of its channels fails the clause it breaks, naming the requirement. (The whole check on
every wire is the CLI's, ``afmctl conformance --profile emulated-xy --yes``: a minute, so CI runs
the channel clauses here; the one-axis device of protocol 3 passes the whole v6 check in
``test_conformance.py`` and ``test_conformance_second.py``.)"""

from __future__ import annotations

import numpy as np
import pytest

from afmctl.drivers import conformance as cf
from afmctl.drivers.device import emulator as em
from afmctl.files.profile import shipped_profile

XY = shipped_profile("emulated-xy")
CHANNELS = ("§2.14", "§3.6 §3.7", "§4.4 §4.5")


@pytest.mark.parametrize("wire", ["serial-socket", "modbus-tcp"])
def test_the_xy_device_passes_the_channel_clauses(wire: str) -> None:
    with cf.emulated_stage(XY, wire) as stage:
        results = {r.clause: r for r in cf.run(stage, XY, only=CHANNELS)}
    rows, n = ("§3.6 §3.7", 29) if wire.startswith("serial") else ("§4.4 §4.5", 13)
    assert results[rows].passed and f"{n} rows of §" in results[rows].detail, results[rows]
    # On a machine too loaded to refill the stream in time the check says so (no verdict on the
    # device), never that the device failed.
    assert results["§2.14"].passed or results["§2.14"].host_late, results["§2.14"]
    assert all(r.passed is None and not r.host_late for c, r in results.items()
               if c not in (rows, "§2.14"))


def _ramp_channel_0_only(self: em.Emulator, now: float) -> None:
    v = np.zeros((0, self.channels))
    r = em.ramp_to_zero(float(self.outputs[0]), self.channel_limits[0], self.sample_rate_hz)
    if r.size:
        v = np.tile(self.outputs, (r.size, 1))
        v[:, 0] = r
    self._hold(v, now)


_SAMPLES = em.Emulator._samples


def _held_plays_zero(self: em.Emulator, run: em._Run, g: np.ndarray
                     ) -> tuple[np.ndarray, int, int]:
    v, n, fault = _SAMPLES(self, run, g)
    v[:, run.held] = 0.0
    return v, n, fault


@pytest.mark.parametrize(("defect", "patch", "label"), [
    ("SAFE ramps channel 0 only", ("_ramp", _ramp_channel_0_only), "§2.14(e)"),
    ("a channel without a table plays 0 V", ("_samples", _held_plays_zero), "§2.14(c)"),
])
def test_an_xy_device_with_a_channel_defect_fails_the_clause(
        defect: str, patch: tuple[str, object], label: str,
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(em.Emulator, *patch)
    with cf.emulated_stage(XY, "serial-pty") as stage:
        (result,) = cf.run(stage, XY, only=("§2.14",))
    assert result.passed is False and label in result.label, (defect, result)
