"""Recording a two-axis set on the emulated x/y stage (what `afmctl sweep --axes x,y` does), and
its refusals before anything moves."""

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.drivers import open_stage
from afmctl.errors import LimitError, SweepFormatError
from afmctl.experiment import xyrecord
from afmctl.files import xysweepfile as xs
from afmctl.files.profile import shipped_profile
from afmctl.planning import sweepdesign as sd

XY = shipped_profile("emulated-xy")
LIMITS = {a: XY.axis(a).limits for a in ("x", "y")}


def _file(name: str, axis: int, v: np.ndarray, held_v: float) -> tuple:
    both = np.full((v.size, 2), held_v)
    both[:, axis] = v
    return (name, 5.58, both, {"swept_axis": "xy"[axis]})


def test_a_short_set_is_recorded_with_the_other_axis_held(tmp_path: Path) -> None:
    rate = XY.sample_rate_hz
    tri = sd.loop(5.58, -100.0, 100.0, 1, rate)
    design = [_file("x_tri", 0, tri, 30.0), _file("y_tri", 1, tri, -40.0)]
    with open_stage(XY) as stage:
        paths = xyrecord.record(stage, design, rate, LIMITS, tmp_path, {"profile": XY.name})
    x, y = (xs.read(p) for p in paths)
    assert x.moving == ("x",) and y.moving == ("y",)
    np.testing.assert_allclose(x.voltage_v[:, 1], 30.0)
    np.testing.assert_allclose(y.voltage_v[:, 0], -40.0)
    assert x.meta["frequency_hz"] == "5.58" and x.meta["profile"] == "emulated-xy"
    # the held axis's sensor follows the driven one by the profile's static coupling (the shared
    # mode at 420 Hz adds little at 5.58 Hz), so the coupling is there to identify
    for s, i, c in ((x, 0, 0.012), (y, 1, -0.008)):
        slope = np.polyfit(s.displacement_um[:, i], s.displacement_um[:, 1 - i], 1)[0]
        assert slope == pytest.approx(c, rel=0.15)


def test_a_sample_outside_an_axis_limits_is_refused_before_anything_moves(tmp_path: Path) -> None:
    bad = [_file("y_too_far", 1, np.linspace(0.0, 130.0, 2000), 0.0)]  # y's range is +-120 V
    with pytest.raises(LimitError, match="axis y"):
        xyrecord.check_design(bad, 1.0 / XY.sample_rate_hz, LIMITS)
    for design in ("standard", "reversals"):
        ok = sd.xy_design(XY.sample_rate_hz, {a: (v.v_min, v.v_max) for a, v in LIMITS.items()},
                          {a: v.max_rate_v_per_ms * 1e3 for a, v in LIMITS.items()}, 125.0,
                          design)
        xyrecord.check_design(ok, 1.0 / XY.sample_rate_hz, LIMITS)  # the design keeps to both


def test_the_reversals_design_adds_each_axis_reversal_curves_the_other_held() -> None:
    """``--design reversals``: each axis's first-order reversal curves after its triangles, over
    its whole range, reversing inside it; the other axis held where its triangles held it."""
    ranges = {a: (v.v_min, v.v_max) for a, v in LIMITS.items()}
    design = sd.xy_design(XY.sample_rate_hz, ranges,
                          {a: v.max_rate_v_per_ms * 1e3 for a, v in LIMITS.items()}, 125.0,
                          "reversals")
    names = [d[0] for d in design]
    assert names.index("x_reversals") == names.index("x_triangle_27.9hz") + 1
    assert names.index("y_reversals") == names.index("y_triangle_27.9hz") + 1
    for i, a in enumerate(("x", "y")):
        v = design[names.index(f"{a}_reversals")][2]
        held = design[names.index(f"{a}_triangle_0.279hz")][2][0, 1 - i]
        assert np.all(v[:, 1 - i] == held)
        lo, hi = ranges[a]
        assert v[:, i].min() == pytest.approx(lo) and v[:, i].max() == pytest.approx(hi)
        turns = np.flatnonzero(np.diff(np.sign(np.diff(v[:, i]))) != 0)
        inside = v[turns + 1, i]
        assert np.sum((inside > lo + 0.05 * (hi - lo)) & (inside < hi - 0.05 * (hi - lo))) >= 4


@pytest.mark.parametrize("argv, words", [
    (["--profile", "emulated", "--axes", "x,y"], "not a two-axis"),
    (["--profile", "emulated-xy", "--axes", "x,y", "--v-range", "0", "10"], "no --v-range"),
    (["--profile", "emulated-xy", "--axes", "x,y", "--design", "full"],
     "--design standard or reversals only"),
    (["--profile", "emulated-xy", "--axes", "y,z"], "--axes x,y"),
])
def test_sweep_axes_refusals_exit_2(tmp_path: Path, argv: list[str], words: str) -> None:
    res = CliRunner().invoke(main, ["sweep", *argv, "--out", str(tmp_path / "out")])
    assert res.exit_code == 2 and words in res.stderr
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------------------------
# issue 25 leftover: a two-axis sweep streams as it records; an interrupt keeps what arrived
# ----------------------------------------------------------------------------------------------


def test_an_interrupted_two_axis_sweep_keeps_its_rows_and_a_rerun_supersedes_them(
        tmp_path: Path) -> None:
    """Ctrl-C (a KeyboardInterrupt where it lands: between blocks, in the progress callback) in
    the middle of a two-axis file: its NAME.incomplete.csv holds the rows received on both
    channels, readable with the header's units and marked interrupted; both outputs are at 0 V;
    recording the file again replaces it with the whole file."""
    rate = XY.sample_rate_hz
    entry = _file("y_tri", 1, sd.loop(5.58, -100.0, 100.0, 2, rate), 30.0)
    n = entry[2].shape[0]
    path = tmp_path / "y_tri.csv"

    def interrupt(what: str, done: int, total: int) -> None:
        if done >= 0.4 * total:
            raise KeyboardInterrupt

    with open_stage(XY) as stage:
        with pytest.raises(KeyboardInterrupt):
            xyrecord.record_one(stage, entry, rate, LIMITS, path, {"profile": XY.name}, interrupt)
        np.testing.assert_array_equal(stage.voltages(), [0.0, 0.0])  # every channel safe
        partial = tmp_path / "y_tri.incomplete.csv"
        assert sorted(p.name for p in tmp_path.iterdir()) == [partial.name]
        text = partial.read_text()
        assert ",".join(xs.COLUMNS) in text.splitlines()  # the header, units in every name
        assert text.rstrip().splitlines()[-1].startswith("# end: interrupted (KeyboardInterrupt")
        with pytest.raises(SweepFormatError, match="--resume"):
            xs.read(partial)  # identify refuses it ...
        kept = xs.parse(text, str(partial))  # ... but every row that arrived is there
        assert 0.4 * n <= kept.time_s.size < n and kept.meta["frequency_hz"] == "5.58"
        np.testing.assert_allclose(kept.voltage_v, entry[2][:kept.time_s.size], atol=1e-6)
        assert np.ptp(kept.displacement_um[:, 1]) > 20 and np.isfinite(kept.displacement_um).all()
        whole = xyrecord.record_one(stage, entry, rate, LIMITS, path, {"profile": XY.name})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["y_tri.csv"]  # superseded, removed
    again = xs.read(path)
    assert again.time_s.size == n and again.moving == ("y",)
    np.testing.assert_allclose(again.displacement_um, whole.displacement_um, atol=1e-6)


@pytest.mark.slow
def test_ctrl_c_in_sweep_axes_keeps_the_file_in_progress_and_resume_completes_the_set(
        tmp_path: Path) -> None:
    """A real SIGINT to a real `afmctl sweep --axes x,y --resume` (six files of the set already
    there, kept untouched; x_multisine and y_triangle_27.9hz missing): exit 130, one line naming
    the kept x_multisine.incomplete.csv; `--resume` then records the two missing files, removes
    the incomplete one and leaves the set complete."""
    import os
    import subprocess
    import sys

    from afmctl.cli.xysweep import first_resonance_hz
    from tests.harness.paths import REPO
    from tests.harness.sigint import interrupt_when

    out = tmp_path / "s"
    out.mkdir()
    design = sd.xy_design(XY.sample_rate_hz, {a: (v.v_min, v.v_max) for a, v in LIMITS.items()},
                          {a: v.max_rate_v_per_ms * 1e3 for a, v in LIMITS.items()},
                          0.5 * first_resonance_hz(XY))  # the band sweep --axes takes
    missing = {"x_multisine", "y_triangle_27.9hz"}
    there = {}
    for name, _, v, _ in design:
        if name not in missing:  # a short stand-in for the file recorded earlier
            xs.write(xs.from_arrays(v[:50], 0.1 * v[:50], XY.sample_rate_hz), out / f"{name}.csv")
            there[name] = (out / f"{name}.csv").read_bytes()
    argv = [sys.executable, "-m", "afmctl", "sweep", "--axes", "x,y", "--profile", "emulated-xy",
            "--out", str(out), "--resume"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(REPO)})
    partial = out / "x_multisine.incomplete.csv"
    err = interrupt_when(proc, lambda: partial.exists()
                         and partial.read_text().count("\n") >= 3000)
    assert proc.returncode == 130, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("afmctl: error: interrupted; the stage was sent to its safe state")
    assert str(partial) in last and "--resume" in last
    assert err.count("already recorded, kept") == 6
    kept = xs.parse(partial.read_text(), str(partial))
    assert 2000 < kept.time_s.size < 40_001 and kept.moving == ("x",)
    assert kept.meta["profile"] == "emulated-xy" and kept.meta["layer_thickness_y_um"]
    res = CliRunner().invoke(main, ["sweep", "--axes", "x,y", "--profile", "emulated-xy",
                                    "--out", str(out), "--resume"])
    assert res.exit_code == 0, res.output
    assert res.stdout.split() == [str(out / "x_multisine.csv"), str(out / "y_triangle_27.9hz.csv")]
    assert f"{partial}: the interrupted attempt, superseded" in res.stderr
    assert sorted(p.name for p in out.iterdir()) == sorted(f"{d[0]}.csv" for d in design)
    assert all((out / f"{n}.csv").read_bytes() == b for n, b in there.items())
    full = xs.read(out / "x_multisine.csv")
    assert full.time_s.size == 40_001 and full.meta["swept_axis"] == "x"
    np.testing.assert_allclose(full.voltage_v[:kept.time_s.size], kept.voltage_v, atol=1e-6)


def test_ctrl_c_between_runs_sends_every_channel_to_0_v() -> None:
    """A Ctrl-C while no run plays (a sweep's rest, with y held at 30 V) inside a command's
    stage: the stage is sent to its safe state all the same (``play`` only makes its own runs
    safe)."""
    from afmctl.cli.base import opened_stage
    from afmctl.experiment import runner

    with pytest.raises(KeyboardInterrupt), opened_stage(XY) as stage:
        runner.move_and_read(stage, 30.0, LIMITS["y"], XY.sample_rate_hz, 0.01, 1)
        np.testing.assert_allclose(stage.voltages(), [0.0, 30.0], atol=1e-4)
        raise KeyboardInterrupt
    np.testing.assert_array_equal(stage.voltages(), [0.0, 0.0])
