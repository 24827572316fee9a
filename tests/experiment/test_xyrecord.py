"""Recording a two-axis set on the emulated x/y stage (what `afmctl sweep --axes x,y` does), and
its refusals before anything moves."""

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from afmctl.cli import main
from afmctl.drivers import open_stage
from afmctl.errors import LimitError
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
    ok = sd.xy_design(XY.sample_rate_hz, {a: (v.v_min, v.v_max) for a, v in LIMITS.items()},
                      {a: v.max_rate_v_per_ms * 1e3 for a, v in LIMITS.items()}, 125.0)
    xyrecord.check_design(ok, 1.0 / XY.sample_rate_hz, LIMITS)  # the design keeps to both


@pytest.mark.parametrize("argv, words", [
    (["--profile", "emulated", "--axes", "x,y"], "not a two-axis"),
    (["--profile", "emulated-xy", "--axes", "x,y", "--v-range", "0", "10"], "without --v-range"),
    (["--profile", "emulated-xy", "--axes", "y,z"], "--axes x,y"),
])
def test_sweep_axes_refusals_exit_2(tmp_path: Path, argv: list[str], words: str) -> None:
    res = CliRunner().invoke(main, ["sweep", *argv, "--out", str(tmp_path / "out")])
    assert res.exit_code == 2 and words in res.stderr
    assert not (tmp_path / "out").exists()
