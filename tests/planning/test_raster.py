"""Raster planning: the frame's geometry against its definition, the reach refusal, the coupling
fed forward (the y the model's x causes cancels), and the per-axis plans' alignment and guard."""

from __future__ import annotations

import dataclasses as dc
import math

import numpy as np
import pytest

from afmctl import guard
from afmctl.errors import FrameReachError, InputError
from afmctl.files.profile import default_profile
from afmctl.model import coupling as cp
from afmctl.model import transducer as tr
from afmctl.planning import raster as rs

DT = 1e-4


def frame(**kw: object) -> rs.Frame:
    base = dict(width_um=20.0, height_um=10.0, pixels=64, lines=8, line_rate_hz=50.0,
                centre_um=(8.0, 5.0))
    return rs.Frame(**{**base, **kw})  # type: ignore[arg-type]


def test_fast_axis_is_the_overscanned_triangle() -> None:
    fr = frame(overscan=0.25)
    t = np.arange(rs.samples(fr, DT)) * DT
    f = rs.fast_coordinate(fr, t)
    n = int(round(fr.line_s / DT))
    assert fr.span_um == pytest.approx(30.0)
    assert f[::n] == pytest.approx(np.full(f[::n].size, -15.0))  # every line starts at -span/2
    assert f[n // 2::n] == pytest.approx(np.full(f[n // 2::n].size, 15.0))
    assert np.diff(f[:n // 2]) == pytest.approx(np.full(n // 2 - 1, 30.0 / (n // 2)))


@pytest.mark.parametrize("slow", ["ramp", "staircase"])
@pytest.mark.parametrize("angle", [0.0, 30.0, 90.0])
def test_pixel_grid_lies_on_the_trajectory_inside_the_image(slow: str, angle: float) -> None:
    fr = frame(slow=slow, angle_deg=angle)
    traj = rs.trajectories(fr, DT)
    g = rs.pixel_grid(fr, DT)
    k = np.arange(traj.x_um.size)
    assert np.interp(g.sample, k, traj.x_um) == pytest.approx(g.x_um, abs=1e-9)
    assert np.interp(g.sample, k, traj.y_um) == pytest.approx(g.y_um, abs=1e-9)
    # the pixels' fast coordinates are the nominal ones, trace and retrace alike
    nominal = -10.0 + 20.0 / 64 * (np.arange(64) + 0.5)
    assert g.fast_um[0, 3] == pytest.approx(nominal)
    assert g.fast_um[1, 5] == pytest.approx(nominal)
    # rotation: the fast direction is (cos a, sin a)
    a = math.radians(angle)
    dx, dy = g.x_um[0, 2, -1] - g.x_um[0, 2, 0], g.y_um[0, 2, -1] - g.y_um[0, 2, 0]
    if slow == "staircase":
        assert (dx, dy) == pytest.approx((63 / 64 * 20 * math.cos(a), 63 / 64 * 20 * math.sin(a)),
                                         abs=1e-9)
    # every pixel is passed inside the image (the turnarounds are in the overscan)
    f = rs.fast_coordinate(fr, g.sample * DT)
    assert np.all(np.abs(f) <= 10.0 + 1e-9)
    assert np.all(g.sample >= rs.LEAD_LINES * fr.line_s / DT)


def test_staircase_holds_each_row_over_its_image_and_steps_in_the_turnaround() -> None:
    fr = frame(slow="staircase")
    traj = rs.trajectories(fr, DT)
    s = traj.y_um - 5.0  # angle 0: y is the slow coordinate
    inside = rs.image_mask(fr, DT)
    n = int(round(fr.line_s / DT))
    for j in range(fr.lines):
        line = slice((j + 1) * n, (j + 2) * n)
        rows = s[line][inside[line]]
        assert rows == pytest.approx(np.full(rows.size, -5.0 + 10.0 / 8 * (j + 0.5)), abs=1e-12)
    step_samples = rs.STEP_FRACTION * 0.1 / 1.2 * n  # the overscan: 0.1 W of a 1.2 W half line, x2
    assert np.max(np.abs(np.diff(s))) < 10.0 / 8 * math.pi / 2 / step_samples * 1.01


def test_directions_order_rows_by_slow_coordinate() -> None:
    up, down = frame(direction="up"), frame(direction="down")
    g_up, g_down = rs.pixel_grid(up, DT), rs.pixel_grid(down, DT)
    assert np.all(np.diff(g_up.y_um[0, :, 0]) > 0) and np.all(np.diff(g_down.y_um[0, :, 0]) > 0)
    assert g_up.sample[0, 0, 0] < g_up.sample[0, -1, 0]
    assert g_down.sample[0, 0, 0] > g_down.sample[0, -1, 0]  # down scans the top row first
    bounce = frame(direction="bounce")
    assert bounce.upward(0) and not bounce.upward(1) and bounce.upward(2)


def test_bad_frames_are_input_errors() -> None:
    for kw in ({"overscan": 1.5}, {"slow": "zigzag"}, {"pixels": 1}, {"width_um": -1.0},
               {"direction": "left"}, {"line_rate_hz": math.nan}):
        with pytest.raises(InputError):
            frame(**kw)


def test_reach_refusal_names_the_largest_frame_that_fits() -> None:
    reach = {"x": (-30.0, 50.0), "y": (-20.0, 40.0)}
    fr = frame(width_um=100.0, height_um=50.0, centre_um=(10.0, 10.0))
    with pytest.raises(FrameReachError, match="largest that fits at this centre is") as err:
        rs.check_reach(fr, reach)
    w, h = (float(v) for v in str(err.value).split("is ")[-1].replace(" um", "").split(" x "))
    assert h / w == pytest.approx(0.5, rel=0.01)
    rs.check_reach(dc.replace(fr, width_um=w, height_um=h), reach)  # the named one fits
    with pytest.raises(FrameReachError):
        rs.check_reach(dc.replace(fr, width_um=1.02 * w, height_um=1.02 * h), reach)
    with pytest.raises(FrameReachError, match="outside the stage's reach"):
        rs.check_reach(dc.replace(fr, centre_um=(60.0, 0.0)), reach)


def test_feedforward_cancels_the_coupling_through_the_models() -> None:
    """Planned through each axis's model, the motion each model axis causes on the other is what
    the other's target left out: with the feed-forward each axis is within 5 % of the coupling's
    effect of what its inverse does on an uncoupled stage."""
    prof = default_profile()
    m = prof.emulator.model
    fr = frame(line_rate_hz=30.0, lines=3)
    c = {"yx": cp.Coupling(0.02, 400.0, 0.05, 0.03, 0.05),
         "xy": cp.Coupling(-0.01, reference_um=2.0)}
    axes = {n: rs.AxisPlan(m, prof.limits) for n in rs.AXES}
    res = {}
    for case, fed, plant in (("ff", c, c), ("without", None, c), ("uncoupled", None, None)):
        wf = rs.plan(fr, axes, DT, fed, ("inverse",))["inverse"]
        u = [tr.simulate(tr.compile_model(m, DT), wf.voltage_v[:, k], tr.initial(m))[0]
             for k in range(2)]
        if plant is not None:
            u = [u[0] + cp.caused(plant["xy"], u[1], DT), u[1] + cp.caused(plant["yx"], u[0], DT)]
        err = (np.column_stack(u)[wf.tracking] - wf.desired_um[wf.tracking])[
            rs.image_mask(fr, DT)]
        res[case] = np.sqrt(np.mean(err**2, axis=0))
    assert np.all(res["without"] > 10 * res["uncoupled"])  # the coupling: tens of nm
    assert np.all(res["ff"] < res["uncoupled"] + res["without"] / 20)


def test_plans_align_both_axes_and_guard_each_channel() -> None:
    prof = default_profile()
    m = prof.emulator.model
    fr = frame()
    narrow = dc.replace(prof.limits, slew_v_per_ms=20.0)
    axes = {"x": rs.AxisPlan(m, prof.limits), "y": rs.AxisPlan(m, narrow, start_v=5.0)}
    plans = rs.plan(fr, axes, DT)
    for wf in plans.values():
        assert wf.voltage_v.shape == wf.desired_um.shape and wf.voltage_v.shape[1] == 2
        tracked = wf.desired_um[wf.tracking]
        assert np.isfinite(tracked).all() and np.isnan(wf.desired_um[:wf.tracking.start]).all()
        assert abs(wf.voltage_v[0, 1] - 5.0) < narrow.slew_v_per_ms * 1e3 * DT
        for k, name in enumerate(rs.AXES):
            guard.check(wf.voltage_v[:, k], DT, axes[name].limits, axes[name].start_v, name)
    tight = {"x": rs.AxisPlan(m, prof.limits), "y": rs.AxisPlan(m, dc.replace(prof.limits,
                                                                             v_max=5.0))}
    with pytest.raises(guard.LimitError):
        rs.plan(fr, tight, DT, filters=("inverse",))


def test_targets_aim_each_axis_as_its_model_was_identified() -> None:
    """A linear x/y plant coupled statically both ways (x = xa + 0.06 y, y = ya - 0.05 x, the
    loop solved exactly): each axis's model taken the way the two-axis fit takes it
    (:func:`afmctl.fit.xyidentify.axis_sweeps` on files where one axis moves and the other is
    held), then a raster's targets through those models: the stage lands on the frame to the
    coupling's third order (0.008 um). Aiming at the other axis's desired motion instead of its
    own left the loop ``c_xy c_yx`` (0.3 %) as a gain error: 0.13 um."""
    from afmctl.files import xysweepfile as xsf
    from afmctl.fit import xyidentify as xi

    cxy, cyx = 0.06, -0.05

    def plant(xa: np.ndarray, ya: np.ndarray) -> np.ndarray:
        det = 1 - cxy * cyx
        return np.column_stack(((xa + cxy * ya) / det, (ya + cyx * xa) / det))

    ramp, n = np.linspace(0.0, 80.0, 2000), 2000
    files = [np.column_stack((ramp, np.full(n, 30.0))), np.column_stack((np.full(n, 40.0), ramp))]
    sweeps = [xsf.from_arrays(v, plant(v[:, 0], v[:, 1]), 1000.0, {}, f"f{i}")
              for i, v in enumerate(files)]
    found = {"xy": cp.Coupling(cxy, reference_um=xi.reference_um(sweeps, "x")),
             "yx": cp.Coupling(cyx, reference_um=xi.reference_um(sweeps, "y"))}
    maps = {}
    for a in ("x", "y"):
        (s,) = xi.axis_sweeps(sweeps, a, found)
        maps[a] = np.polyfit(s.voltage_v, s.displacement_um, 1)  # the axis's (linear) model
    t = np.linspace(0.0, 1.0, 3000)
    traj = rs.Trajectories(t[1] - t[0], 10 + 70 * np.abs(2 * ((5 * t) % 1) - 1), 10 + 60 * t)
    for aims, tol in ((rs.targets(traj, found), 0.02), (_first_order(traj, found), None)):
        v = {a: (aims[a] - maps[a][1]) / maps[a][0] for a in ("x", "y")}
        miss = np.abs(plant(v["x"], v["y"]) - np.column_stack((traj.x_um, traj.y_um))).max()
        assert miss < tol if tol else miss > 0.08, miss


def _first_order(traj: rs.Trajectories, c: dict[str, cp.Coupling]) -> dict[str, np.ndarray]:
    """The targets before: each axis's desired less what the other's *desired* causes."""
    return {"x": traj.x_um - cp.caused(c["xy"], traj.y_um, traj.dt_s),
            "y": traj.y_um - cp.caused(c["yx"], traj.x_um, traj.dt_s)}
