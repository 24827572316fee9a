"""docs/how-to/calibrate-your-stage.md, run as written on a fresh clone (issue 27, "must show").

The repository at this commit is cloned and installed in a venv of its own, as a new user does
(its dependencies are taken from this checkout's venv through a ``.pth`` file instead of being
downloaded again: no network here). An emulated stage with a hidden sensor delay of 3 samples
behind a unipolar 0-150 V amplifier is served by the clone's ``afmctl emulate`` on 127.0.0.1
(serial over ``socket://``). Then every command of the guide's ``sh`` blocks runs, in order, in
the clone, as written; the only edits are the ones the guide asks for in step 1 (the profile's
URL and voltage range "for your hardware"). Step 6 diagnoses every sweep, as written.

What the guide promises is checked on the way: the link and a reading, conformance, four whole
sweeps, the separating one and the reversal curves, identify flagging the delay and reporting
the reach, diagnose naming it (the separating sweep's steps tell it from an amplifier's lag), the triangle
tracked at the reach's centre with the readings corrected (and the true position, simulated from
the voltages the stage played, as close to the trajectory as the scores say), learning, replay.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest

from tests.harness.paths import PROFILES, REPO

DELAY = 3  # samples: the stage's hidden sensor delay


def guide_commands(text: str) -> list[str]:
    """The commands of the guide's ``sh`` blocks, in order (continued lines joined)."""
    out = []
    for block in re.findall(r"```sh\n(.*?)```", text, flags=re.S):
        joined = re.sub(r"\\\n\s*", "", block)
        for line in joined.splitlines():
            line = line.split("  #")[0].strip()
            if line and not line.startswith("#"):
                out.append(line)
    return out


def hidden_profile(path: Path) -> Path:
    text = (PROFILES / "emulated.toml").read_text()
    text = (text.replace('name = "emulated"', 'name = "the-lab-stage"')
            .replace("v_min_V = -150.0", "v_min_V = 0.0")
            .replace("# [emulator.effects.sensor_delay]\n# samples = 2",
                     f"[emulator.effects.sensor_delay]\nsamples = {DELAY}"))
    assert f"samples = {DELAY}" in text and "v_min_V = 0.0" in text
    path.write_text(text)
    return path


def fresh_clone(where: Path) -> Path:
    """The repository at this commit, cloned and installed in ``where/clone/.venv``."""
    clone = where / "clone"
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], check=True,
                          capture_output=True, text=True).stdout.strip()
    subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True)
    subprocess.run(["git", "-C", str(clone), "checkout", "-q", head], check=True)
    subprocess.run([sys.executable, "-m", "venv", str(clone / ".venv")], check=True)
    site = next((clone / ".venv" / "lib").glob("python*/site-packages"))
    (site / "afmctl-test-deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([str(clone / ".venv" / "bin" / "pip"), "install", "-q", "--no-deps", "-e",
                    str(clone)], check=True, capture_output=True)
    return clone


def simulate_truth(profile: Path, run_csv: Path) -> tuple[np.ndarray, np.ndarray, slice]:
    """The stage's true position (um) over a run: the emulated plant (the profile's model, no
    sensor) driven by the voltages the run played, from a depoled start (the run's conditioning
    excursion wipes the history out), and the run's desired trajectory and tracking part."""
    import dataclasses as dc

    from afmctl.files import runfile
    from afmctl.files.profile import load_profile
    from afmctl.model import transducer as tr
    prof = load_profile(profile)
    assert prof.emulator is not None
    model = dc.replace(prof.emulator.true_model, effects=dc.replace(
        prof.emulator.true_model.effects, sensor_delay_samples=0.0))
    run = runfile.read(run_csv)
    u, _, _ = tr.simulate(tr.compile_model(model, 1 / prof.sample_rate_hz), run.voltage_v,
                          tr.initial(model))
    ok = np.flatnonzero(np.isfinite(run.desired_um))
    return u, run.desired_um, slice(int(ok[0]), int(ok[-1]) + 1)


@pytest.mark.slow
@pytest.mark.guide
def test_the_guide_runs_as_written_on_a_fresh_clone(tmp_path: Path) -> None:
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    clone = fresh_clone(tmp_path)
    bin_dir = clone / ".venv" / "bin"
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}"}
    env.pop("PYTHONPATH", None)
    stage = hidden_profile(tmp_path / "the-lab-stage.toml")
    server = subprocess.Popen([str(bin_dir / "afmctl"), "emulate", "--profile", str(stage),
                               "--serial", "socket://127.0.0.1:0", "--modbus-port", "0",
                               "--no-rtu"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, env=env, cwd=tmp_path)
    out: dict[str, subprocess.CompletedProcess[str]] = {}
    try:
        assert server.stdout is not None
        where = dict(server.stdout.readline().strip().split(": ", 1) for _ in range(2))
        url = where["serial"]
        commands = guide_commands((clone / "docs" / "how-to" / "calibrate-your-stage.md").read_text())
        verbs = [" ".join(c.split()[:2]) for c in commands]
        assert verbs == ["cp profiles/lab-serial.toml", "afmctl status", "afmctl set",
                         "afmctl safe", "afmctl conformance", "afmctl sweep", "afmctl identify",
                         "afmctl diagnose", "afmctl reach", "afmctl track", "afmctl track",
                         "afmctl play"], verbs
        for i, cmd in enumerate(commands):
            res = subprocess.run(["bash", "-c", cmd], cwd=clone, env=env, capture_output=True,
                                 text=True, timeout=3600)
            out[verbs[i] + ("" if verbs[i] not in out else " --learn")] = res
            assert res.returncode == 0, (cmd, res.stdout[-2000:], res.stderr[-3000:])
            assert "Traceback" not in res.stderr, (cmd, res.stderr[-3000:])
            if cmd.startswith("cp "):  # step 1: "set, for your hardware"
                prof = clone / "my-stage.toml"
                text = prof.read_text()
                assert 'url = "/dev/ttyUSB0"' in text and "v_min_V = -150.0" in text
                prof.write_text(text.replace('url = "/dev/ttyUSB0"', f'url = "{url}"')
                                .replace("v_min_V = -150.0", "v_min_V = 0.0"))
    finally:
        server.terminate()
        server.communicate(timeout=30)

    # 2: the link, a reading, the stage brought up by hand and back
    assert re.search(r"^reading_um: -?\d+\.\d+ \(mean of", out["afmctl status"].stdout, re.M)
    assert out["afmctl set"].stdout.startswith("output 10 V; reading ")
    assert out["afmctl safe"].stdout.strip() == "safe: stopped, output 0 V"
    # 4: the four standard sweeps, the separating one and the reversal curves, whole
    assert sorted(p.name for p in (clone / "sweeps").iterdir()) == [
        "minor_loops_0.1hz.csv", "reversals.csv", "separating.csv", "triangle_0.279hz.csv",
        "triangle_27.9hz.csv", "triangle_5.58hz.csv"]
    # 5: identify flags the delay and reports the reach
    from afmctl.files import modelfile
    fit = modelfile.read_fit(clone / "model.toml")
    assert fit is not None and fit.flagged and "triangle_27.9hz.csv" in fit.verdict
    assert "reach on profile 'lab-serial'" in out["afmctl identify"].stdout
    # 6: diagnose names the hidden cause
    diagnosis = json.loads((clone / "diagnose" / "diagnosis.json").read_text())
    assert diagnosis["cause"] == "sensor-delay", diagnosis["cause"]
    assert "wrote base.twin.json, extended.twin.json" in out["afmctl diagnose"].stderr
    # 7: track plans from the extended model's twin, which diagnose left beside it
    assert "the stage as the model's twin follows it" in out["afmctl track"].stderr
    # 7: the reach, the triangle tracked at its centre, the readings corrected and named
    reach = out["afmctl reach"].stdout
    centre = float(re.search(r"^centre: ([\d.]+) um", reach, re.M).group(1))  # type: ignore[union-attr]
    assert "--amplitude 27.04 fits with --offset" in reach
    summary = json.loads((clone / "tracked" / "summary.json").read_text())
    assert "sensor_delay" in summary["readings_corrected_for"]
    assert summary["between_samples_from"].startswith("not judged: a real stage")
    inverse = summary["filters"]["inverse"]
    assert inverse["rms_um"] < 0.1 and summary["ratio_linear_over_inverse"] > 10
    header = (clone / "tracked" / "run.csv").read_text().splitlines()[0]
    assert "corrected_displacement_um_inverse" in header
    u, desired, part = simulate_truth(stage, clone / "tracked" / "run_inverse.csv")
    k0 = part.start + round(1 / 27.9 * 1e4)  # the steady part: one period in
    true_rms = float(np.sqrt(np.mean((u[k0:part.stop] - desired[k0:part.stop]) ** 2)))
    middle = 0.5 * (float(np.max(desired[part])) + float(np.min(desired[part])))
    assert abs(middle - centre) < 0.01  # --offset centre: the reach's (printed to 4 digits)
    assert true_rms < max(2 * inverse["rms_um"], 0.05), (true_rms, inverse["rms_um"])
    # 8: learning and the replay
    learned = json.loads((clone / "learned" / "summary.json").read_text())
    its = learned["iterations"]
    assert len(its) >= 2 and min(i["rms_steady_um"] for i in its) <= its[0]["rms_steady_um"]
    assert "warning" not in out["afmctl play"].stderr, out["afmctl play"].stderr
    assert (clone / "replayed" / "play.png").stat().st_size > 10_000
