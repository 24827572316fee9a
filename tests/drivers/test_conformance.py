"""``afmctl conformance``: the emulated device meets docs/protocol.md over every wire; devices that
break a clause fail exactly that clause (the check can fail)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.drivers import conformance as cf
from afmctl.drivers.device.emulated import serve_all
from afmctl.drivers.device.emulator import Emulator
from afmctl.files.profile import Profile
from tests.harness.emulated import stage_on
from tests.harness.paths import PROFILES, REPO

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


ROOT = REPO


def lab_profile(tmp_path: Path, wire: str, address: str) -> Path:
    """A shipped lab profile pointed at a served emulated device."""
    if wire.startswith("serial"):
        text = (PROFILES / "lab-serial.toml").read_text()
        text = text.replace('url = "/dev/ttyUSB0"', f'url = "{address}"')
    else:
        text = (PROFILES / "lab-modbus.toml").read_text()
        if wire == "modbus-tcp":
            host, port = address.rsplit(":", 1)
            text = text.replace('host = "192.168.1.50"', f'host = "{host}"')
            text = text.replace("port = 502", f"port = {port}")
        else:
            text = text.replace('kind = "modbus-tcp"', 'kind = "modbus-rtu"')
            text = text.replace('host = "192.168.1.50"\n', "")
            text = text.replace("port = 502", f'port = "{address}"')
    path = tmp_path / f"{wire}.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("wire", WIRES)
def test_cli_conformance_passes_on_a_lab_profile(wire: str, profile: Profile,
                                                 tmp_path: Path) -> None:
    serial = "socket://127.0.0.1:0" if wire == "serial-socket" else "pty"
    with serve_all(profile, serial=serial, rtu=wire == "modbus-rtu") as where:
        address = where["serial" if wire.startswith("serial") else wire]
        path = lab_profile(tmp_path, wire, address)
        refused = CliRunner().invoke(main, ["conformance", "--profile", str(path)])
        res = CliRunner().invoke(main, ["conformance", "--profile", str(path), "--yes", "--json"])
    assert refused.exit_code == 2 and "pass --yes" in refused.stderr
    assert res.exit_code == 0, res.output
    report = json.loads(res.stdout)
    assert report["passed"] and report["max_voltage_V"] == 30.0
    (rows,) = report["wires"].values()
    assert sum(r["passed"] is True for r in rows) >= 11


def test_cli_conformance_fails_with_exit_1_on_a_defective_device(
        profile: Profile, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(Emulator, "stop", lambda self, now: self.tick(now))
    with serve_all(profile, serial="socket://127.0.0.1:0", rtu=False) as where:
        path = lab_profile(tmp_path, "serial-socket", where["serial"])
        res = CliRunner().invoke(main, ["conformance", "--profile", str(path), "--yes"])
    assert res.exit_code == 1
    assert "FAIL  §2.9 §2.11 §2.12" in res.stdout and "WGO 0 did not stop the run" in res.stdout


def test_cli_conformance_refuses_a_zero_voltage_bound(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["conformance", "--max-voltage", "0"])
    assert res.exit_code == 2
    assert res.stderr.strip() == "afmctl: error: --max-voltage must be > 0 V, got 0"


def test_status_and_safe_by_shipped_profile_name(profile: Profile, tmp_path: Path) -> None:
    with serve_all(profile, serial="socket://127.0.0.1:0", rtu=False) as where:
        path = lab_profile(tmp_path, "serial-socket", where["serial"])
        from afmctl.drivers.serial_link import SerialStage
        with SerialStage(profile, where["serial"]) as stage:
            stage.set_voltage(3.0)
        before = CliRunner().invoke(main, ["status", "--profile", str(path), "--json"])
        safe = CliRunner().invoke(main, ["safe", "--profile", str(path)])
        after = CliRunner().invoke(main, ["status", "--profile", str(path), "--json"])
    assert before.exit_code == 0 and json.loads(before.stdout)["output_V"] == 3.0
    assert safe.exit_code == 0 and safe.stdout.strip() == "safe: stopped, output 0 V"
    st = json.loads(after.stdout)
    assert st["output_V"] == 0.0 and not st["running"] and st["v_max_V"] == 150.0
    named = CliRunner().invoke(main, ["status", "--profile", "emulated", "--json"])
    assert named.exit_code == 0 and json.loads(named.stdout)["profile"] == "emulated"
    missing = CliRunner().invoke(main, ["status", "--profile", "lab-modbuss"])
    assert missing.exit_code == 2
    assert "shipped: emulated, emulated-foreign, lab-modbus, lab-serial" in missing.stderr


def test_the_limits_clause_leaves_no_sample_beyond_the_bound_in_the_table(
        profile: Profile) -> None:
    """The limits clause writes v_max into a table slot (never played); it overwrites it
    afterwards, so a device that keeps stale slots cannot later play a sample beyond the bound."""
    with stage_on("serial-socket", profile) as (stage, em):
        bench = cf.Bench(stage, profile, -5.0, 5.0)
        cf.check_limits(bench)
        assert np.max(np.abs(em.table)) <= 5.0
        assert stage.status().last_error == 0


def test_the_dc_set_clause_stays_within_the_bound_on_a_device_without_slew_check(
        profile: Profile, monkeypatch: pytest.MonkeyPatch) -> None:
    """A device that takes any DC step is never sent one beyond ``--max-voltage``: with a bound
    too tight for a step over the slew limit, the clause says that part was not checked."""
    def set_voltage(self: Emulator, v: float, now: float) -> None:  # range checked, not slew
        self.tick(now)
        self._check(np.array([float(np.float32(v))]))
        self._hold(np.array([float(np.float32(v))]), now)
    _break(monkeypatch, "set_voltage", set_voltage)
    with stage_on("serial-socket", profile) as (stage, em):
        detail = cf.check_dc_set(cf.Bench(stage, profile, -2.0, 2.0))
        assert np.max(np.abs(em.applied_log(time.monotonic()))) <= 2.0
    assert "NOT checked" in detail
