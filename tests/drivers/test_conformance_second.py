"""The conformance check against a second device implementation, written from docs/reference/protocol.md
alone (``tests/harness/second_device.py``: no afmctl code, its own plant). Its conforming variants
pass ``afmctl conformance --yes`` — plain, with an amplifier lagging at 66 Hz and a 3 % gain
error, read-only, recording the command (declared), with a recorder written 4 ms after the clock —
and each deliberately broken variant fails the clause it breaks, naming the requirement."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.drivers import conformance as cf
from afmctl.drivers.serial_link import SerialStage
from afmctl.files.profile import load_profile
from tests.harness import second_device, second_server
from tests.harness.paths import PROFILES
from tests.harness.second_device import DEFECTS
from tests.harness.second_server import SecondStage


def profile_for(url: str, folder: Path) -> Path:
    """The shipped lab-serial profile pointed at ``url``, for the device's 0-150 V amplifier."""
    text = (PROFILES / "lab-serial.toml").read_text()
    text = text.replace('url = "/dev/ttyUSB0"', f'url = "{url}"')
    path = folder / "second.toml"
    path.write_text(text.replace("v_min_V = -150.0", "v_min_V = 0.0"))
    return path


@pytest.mark.parametrize("module", [second_device, second_server])
def test_the_second_device_uses_no_afmctl_code(module: object) -> None:
    tree = ast.parse(Path(module.__file__).read_text())  # type: ignore[attr-defined]
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert {n for n in names if n.split(".")[0] in ("afmctl", "drivers", "tests")} <= {
        "tests.harness.second_device"}


#: The clauses of a device of several channels: not applicable to this one-channel device of
#: serial protocol 3 (document v5), which passes the rest of the v6 check unchanged.
CHANNELS = {"§2.14", "§3.6 §3.7", "§4.4 §4.5"}

VARIANTS = {"plain": {}, "lagging 66 Hz, gain 1.03": {"lag_hz": 66.0, "gain": 1.03},
            "read-only": {"read_only": True},
            "records the command": {"records_command": True, "lag_hz": 66.0},
            "recorder 4 ms after the clock": {"latency_s": 0.004, "lag_hz": 66.0}}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_afmctl_conformance_passes_on_the_second_device(variant: str, tmp_path: Path) -> None:
    with SecondStage(**VARIANTS[variant]) as server:
        path = profile_for(server.url, tmp_path)
        res = CliRunner().invoke(main, ["conformance", "--profile", str(path), "--yes", "--json"])
    assert res.exit_code == 0, res.stdout
    (results,) = json.loads(res.stdout)["wires"].values()
    by_clause = {r["clause"]: r for r in results}
    skipped = {c for c, r in by_clause.items() if r["passed"] is None}
    if variant == "read-only":
        assert skipped == {c for c, *_ in cf.CLAUSES if c[:2] in ("§4",)} | {
            "§2.5", "§2.6", "§2.1-2.3", "§2.4", "§2.7", "§2.9 §2.11 §2.12", "errors"} | CHANNELS
        assert by_clause["§2.10"]["passed"] and by_clause["§2.8"]["passed"]
    else:
        assert skipped == {"§2.10", "§4", "§4.1", "§4.3"} | CHANNELS
    if variant.startswith("lagging"):  # the v4 check's 1.55 V bound would have failed it
        gap = float(by_clause["§2.1-2.3"]["detail"].split("recorded voltage up to ")[1].split()[0])
        assert gap > 5.0
    if variant == "records the command":
        assert "is the command (declared)" in by_clause["§2.1-2.3"]["detail"]


#: Each broken behaviour: the clause that must fail and the requirement it must name.
BROKEN = {
    "limits-not-float32": ("§1 §2.6(a)", "§2.6(a)"),
    "dc-no-slew-check": ("§2.5", "§2.5(a)"),
    "output-is-measured": ("§2.5", "§2.2(f)"),
    "limits-exclusive": ("§2.6", "§2.6(c)"),
    "chunk-steps-unchecked": ("§2.6", "§2.6(d)"),
    "start-wrap-unchecked": ("§2.6", "§2.6(e)"),
    "refused-chunk-stores-some": ("§2.6", "§2.6(f)"),
    "incomplete-table-starts": ("§2.1-2.3", "§2.1(d)"),
    "clock-fast": ("§2.1-2.3", "§2.2(a)"),
    "position-lags": ("§2.1-2.3", "§2.2(c)"),
    "recorder-loses-entries": ("§2.1-2.3", "§2.3(a)"),
    "declares-command-records-output": ("§2.1-2.3", "§2.3(e)"),
    "recorder-not-cleared": ("§2.1-2.3", "§2.3(f)"),
    "fill-counts-held": ("§2.1-2.3", "§2.3(g)"),
    "wgo-plays-stale-slots": ("§2.4", "§2.1(d)"),
    "stream-window-lenient": ("§2.4", "§2.4(b)"),
    "stream-plays-stale": ("§2.4", "§2.4(d)"),
    "stream-slew-unchecked": ("§2.4", "§2.4(e)"),
    "wgs-start-slew-unchecked": ("§2.4", "§2.4(f)"),
    "complete-after-stream": ("§2.4", "§2.4(h)"),
    "fault-no-ramp": ("§2.4", "§2.7(b)"),
    "safe-no-ramp": ("§2.7", "§2.7(d)"),
    "wdt-keeps-expired": ("§2.8", "§2.8(b)"),
    "watchdog-fed-by-queries": ("§2.8", "§2.8(d)"),
    "watchdog-rearm-needs-wdt": ("§2.8", "§2.8(g)"),
    "watchdog-late": ("§2.8", "§5(g)"),
    "stop-ignored": ("§2.9 §2.11 §2.12", "§2.2(e)"),
    "stop-reverts-output": ("§2.9 §2.11 §2.12", "§2.2(e)"),
    "busy-sva-accepted": ("§2.9 §2.11 §2.12", "§2.9(a)"),
    "busy-before-bad-argument": ("§2.9 §2.11 §2.12", "§2.12(a)"),
    "read-only-refuses-safe": ("§2.10", "§2.10(b)"),
    "wtl-range-error-2": ("errors", "§2.12(a)"),
    "cr-ends-line": ("§3.1", "§3.1(a)"),
    "overlong-accepted": ("§3.1", "§3.1(b)"),
    "non-ascii-accepted": ("§3.1", "§3.1(c)"),
    "tab-not-separator": ("§3.1", "§3.1(d)"),
    "blank-line-answered": ("§3.1", "§3.1(e)"),
    "crc-upper-refused": ("§3.2", "§3.2(a)"),
    "bad-crc-answered": ("§3.2", "§3.2(c)"),
    "tag-normalised": ("§3.2", "§3.2(d)"),
    "reply-crc-upper": ("§3.2", "§3.2(d)"),
    "nan-accepted": ("§3.3", "§3.3(a)"),
    "int-takes-float": ("§3.3", "§3.3(b)"),
    "status-out-of-order": ("§3.4", "§3.4(a)"),
    "idn-three-fields": ("§3.4", "§3.4(b)"),
    "hb-takes-args": ("§3.4", "§3.4(c)"),
    "rate-as-double": ("§3.5", "§2.6(b)"),
    "error-cleared-by-success": ("§3.5", "§2.11(a)"),
    "slow-replies": ("§5(e)", "§5(e)"),
}


def test_every_defect_is_tried_and_every_serial_clause_is_broken_once() -> None:
    assert set(BROKEN) == set(DEFECTS)
    # Modbus: test_conformance.py; channels: test_xy_conformance.py
    serial = {c for c, *_ in cf.CLAUSES} - {"§4", "§4.1", "§4.3"} - CHANNELS
    assert {clause for clause, _ in BROKEN.values()} == serial


@pytest.mark.parametrize("defect", list(BROKEN))
def test_a_broken_second_device_fails_the_clause_it_breaks(defect: str, tmp_path: Path) -> None:
    """One broken behaviour: the clause it belongs to fails and names the requirement (the check
    runs that clause only; ``test_a_broken_device_fails_nothing_else`` runs them all)."""
    clause, label = BROKEN[defect]
    with SecondStage(defect=defect, read_only=defect == "read-only-refuses-safe") as server:
        profile = load_profile(profile_for(server.url, tmp_path))
        with SerialStage(profile) as stage:
            (result,) = cf.run(stage, profile, only={clause})
    assert result.passed is False and label in result.label.split(", "), result
    assert result.detail.startswith(result.label)


@pytest.mark.slow
@pytest.mark.parametrize("defect", ["stop-reverts-output", "watchdog-fed-by-queries",
                                    "nan-accepted", "stream-plays-stale"])
def test_a_broken_device_fails_nothing_else(defect: str, tmp_path: Path) -> None:
    """The whole check on a device with one of the issue's defects: only its clause fails."""
    with SecondStage(defect=defect) as server:
        profile = load_profile(profile_for(server.url, tmp_path))
        with SerialStage(profile) as stage:
            results = cf.run(stage, profile)
    failed = {r.clause for r in results if r.passed is False or r.host_late}
    assert failed == {BROKEN[defect][0]}, [(r.clause, r.detail) for r in results if not r.passed]
