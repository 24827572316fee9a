"""``afmctl conformance``: the emulated device meets docs/protocol.md over every wire; devices that
break a clause fail exactly that clause (the check can fail)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import stage_on

from afmctl.profile import Profile
from drivers.device import conformance as cf
from drivers.device.emulator import Emulator

WIRES = ["serial-pty", "serial-socket", "modbus-tcp", "modbus-rtu"]
SERIAL_ONLY = {"§3.4", "§3.1", "§3.2", "§3.3"}
MODBUS_ONLY = {"§4.1", "§4"}


def verdicts(results: list[cf.Result]) -> dict[str, bool | None]:
    return {r.clause: r.passed for r in results}


@pytest.mark.parametrize("kind", WIRES)
def test_the_emulated_device_passes_every_clause(kind: str, profile: Profile) -> None:
    with stage_on(kind, profile) as (stage, _):
        results = cf.run(stage, profile)
    failed = [(r.clause, r.detail) for r in results if r.passed is False]
    assert not failed
    wire_only = MODBUS_ONLY if kind.startswith("serial") else SERIAL_ONLY
    assert {r.clause for r in results if r.passed is None} == wire_only | {"§2.10"}
    assert len(results) == len(cf.CLAUSES)


def test_a_read_only_device_passes_what_applies(profile: Profile) -> None:
    with stage_on("serial-socket", profile, read_only=True) as (stage, _):
        v = verdicts(cf.run(stage, profile))
    assert v["§2.10"] is True and v["§3.2"] is True and v["§2.5"] is None
    assert False not in v.values()


def _break(monkeypatch: pytest.MonkeyPatch, name: str, replacement) -> None:  # noqa: ANN001
    monkeypatch.setattr(Emulator, name, replacement)


@pytest.mark.parametrize(("defect", "clause"), [
    ("watchdog fed by queries", "§2.8"),
    ("no slew check on DC sets", "§2.5"),
    ("stop ignored", "§2.9 §2.11 §2.12"),
])
def test_a_defective_device_fails_its_clause(defect: str, clause: str, profile: Profile,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """Devices with one defect each (the emulator's logic patched): the check names the clause."""
    if defect == "watchdog fed by queries":
        real = Emulator.status

        def status(self: Emulator, now: float):  # noqa: ANN202
            self.last_heartbeat = now
            return real(self, now)
        _break(monkeypatch, "status", status)
    elif defect == "no slew check on DC sets":
        def set_voltage(self: Emulator, v: float, now: float) -> None:
            self.tick(now)
            self._hold(np.array([float(v)]), now)
        _break(monkeypatch, "set_voltage", set_voltage)
    else:
        _break(monkeypatch, "stop", lambda self, now: self.tick(now))
    with stage_on("serial-socket", profile) as (stage, _):
        v = verdicts(cf.run(stage, profile))
    assert v[clause] is False


def test_bounds_default_to_a_tenth_of_the_span(profile: Profile) -> None:
    assert cf.bounds(profile, None) == (-30.0, 30.0)
    assert cf.bounds(profile, 5.0) == (-5.0, 5.0)
    with pytest.raises(ValueError):
        cf.bounds(profile, 0.0)
