"""Images and figures of merit of a raster frame, against measurements whose errors are known
analytically: a perfect stage, a sensor delay (registration), a coupling proportional to the fast
coordinate (line-synchronous slow motion), missing samples."""

from __future__ import annotations

import numpy as np
import pytest

from afmctl.planning import raster as rs
from afmctl.planning import scanimage as si

DT = 1e-4
FRAME = rs.Frame(20.0, 8.0, 50, 8, 25.0, centre_um=(3.0, -2.0), slow="staircase")


def measured(frame: rs.Frame = FRAME, delay: int = 0) -> np.ndarray:
    traj = rs.trajectories(frame, DT)
    xy = np.column_stack([traj.x_um, traj.y_um])
    if delay:
        xy = np.concatenate([np.repeat(xy[:1], delay, axis=0), xy[:-delay]])
    return xy


def test_sample_at_interpolates_and_leaves_missing_pixels_missing() -> None:
    v = np.array([0.0, 1.0, 4.0, np.nan, 2.0])
    got = si.sample_at(v, np.array([0.5, 1.25, 2.5, 3.5, 4.0, -0.1]))
    assert got[:2] == pytest.approx([0.5, 1.75])
    assert np.isnan(got[2:]).all()


def test_a_perfect_stage_has_no_error_and_registers() -> None:
    g = rs.pixel_grid(FRAME, DT)
    img = si.images(FRAME, g, measured())
    m = si.merit(FRAME, img)
    assert m["fast_rms_um"] < 1e-9 and m["registration_px"] < 1e-9
    assert m["slow_deviation_px"] < 1e-9 and m["missing_pixels"] == 0
    assert img.x_um[0] == pytest.approx(g.x_um[0])


def test_a_delay_shows_as_registration_of_twice_the_lag() -> None:
    """A reading ``d`` samples late lags the fast axis by ``v d dt`` on the trace and leads it on
    the retrace: trace and retrace land ``2 v d dt`` apart, v the fast speed."""
    d = 3
    img = si.images(FRAME, rs.pixel_grid(FRAME, DT), measured(delay=d))
    speed = FRAME.span_um / (0.5 * FRAME.line_s)  # um/s
    lag = speed * d * DT
    assert img.error_fast_um[0] == pytest.approx(np.full((8, 50), -lag), abs=1e-9)
    assert img.error_fast_um[1] == pytest.approx(np.full((8, 50), lag), abs=1e-9)
    m = si.merit(FRAME, img)
    assert m["registration_px"] == pytest.approx(2 * lag / FRAME.pixel_um)
    assert m["fast_rms_pct"] == pytest.approx(100 * lag / 20.0)
    assert m["fast_rms_um_by_line"] == pytest.approx([lag] * 8)


def test_line_synchronous_slow_motion_is_what_repeats_with_the_fast_axis() -> None:
    """y = desired + c f + a per-line offset: the line-synchronous part is c f (RMS c times the
    pixels' fast coordinates' RMS), the offsets are not."""
    g = rs.pixel_grid(FRAME, DT)
    meas = measured()
    t = np.arange(meas.shape[0]) * DT
    f = rs.fast_coordinate(FRAME, t)
    c = 0.01
    meas[:, 1] += c * f + 0.3 * np.floor(t / FRAME.line_s)
    m = si.merit(FRAME, si.images(FRAME, g, meas))
    nominal = g.fast_um[0, 0]
    assert m["slow_line_synchronous_um"] == pytest.approx(
        c * np.sqrt(np.mean((nominal - nominal.mean()) ** 2)), rel=1e-6)
    assert si.decoupling_db(10.0, 1.0) == pytest.approx(20.0)


def test_rotated_frames_split_the_error_along_fast_and_slow() -> None:
    fr = rs.Frame(20.0, 8.0, 50, 8, 25.0, angle_deg=90.0)
    meas = measured(fr)
    meas[:, 0] += 0.1  # x is the slow direction at 90 degrees (slow = -x)
    img = si.images(fr, rs.pixel_grid(fr, DT), meas)
    assert img.error_fast_um == pytest.approx(np.zeros_like(img.error_fast_um), abs=1e-9)
    assert img.error_slow_um == pytest.approx(np.full_like(img.error_slow_um, -0.1), abs=1e-9)
