"""Raster scans of a two-axis stage: the frame, the desired x/y trajectories, their plans.

An AFM images by scanning: the **fast** axis goes back and forth (trace, then retrace: one
*line* per period of a triangle), the **slow** axis steps (``staircase``) or ramps (``ramp``)
across the frame, and the frame may be rotated by an angle. This module turns a frame's settings
(those every scan interface carries: centre, size, angle, pixels, lines, line rate, slow axis
mode, direction) into

* the desired displacement of each axis, sampled on the stage's clock (:func:`trajectories`):
  one lead line (the slow axis held at the first row, not imaged: the ramp in settles) then
  ``lines`` image lines. The fast axis's triangle spans the width plus ``overscan`` of it on each
  side, so its turnarounds (and a staircase's steps, which happen in them) stay outside the
  image;
* the pixel grid (:func:`pixel_grid`): when each pixel of the trace and retrace images is
  passed, and where it should be;
* the voltage of each axis (:func:`plan`), planned through that axis's own model with the one-axis
  planner of :mod:`afmctl.planning.track` (Algorithm 3 and its effects, or the paper's linear
  filter), after the **coupling is fed forward**: the y target is the desired y minus the y
  motion the x trajectory causes (:func:`afmctl.model.coupling.caused`), and likewise x, so the
  stage's own cross-coupling adds it back. Each axis's waveform passes the guard against its own
  limits and the model's envelope; the two are padded (held at the start voltage before the
  conditioning, at the end voltage after) so their tracking parts start on the same sample.

A frame beyond the stage's reach is refused before anything is planned
(:class:`~afmctl.errors.FrameReachError`), naming the largest frame of the same shape that fits.

Coordinates: the fast coordinate ``f`` and the slow ``s`` are relative to the centre; the stage's
``x = cx + f cos(a) - s sin(a)``, ``y = cy + f sin(a) + s cos(a)`` (``a`` the angle). Image
rows go by increasing ``s`` (row 0 at ``s = -H/2``) whatever the direction.
"""

from __future__ import annotations

import dataclasses as dc
import math
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import sawtooth

from afmctl import guard
from afmctl.errors import FrameReachError, InputError, ReachError
from afmctl.files.modelfile import Envelope
from afmctl.model import coupling as cp
from afmctl.model import transducer as tr
from afmctl.model.xy import AXES
from afmctl.planning import track

FloatArray = NDArray[np.float64]
#: Fraction of each axis's quasi-static reach kept free for the rod's dynamics at the corners.
REACH_MARGIN = 0.02
#: Lead lines before the image (slow axis at the first row; not imaged).
LEAD_LINES = 1
SLOW_MODES = ("ramp", "staircase")
#: A staircase's step takes this fraction of the overscan's time (centred on the turnaround).
STEP_FRACTION = 0.75
DIRECTIONS = ("up", "down", "bounce")


@dataclass(frozen=True)
class Frame:
    """The settings of a raster frame.

    Parameters
    ----------
    width_um, height_um : float
        Frame size along the fast and the slow axis, um.
    pixels, lines : int
        Pixels per line, lines per frame.
    line_rate_hz : float
        Lines per second (one line: a trace and its retrace, one period of the fast triangle).
    centre_um : tuple of float
        Frame centre (x, y), um, in the sensors' frame.
    angle_deg : float
        Rotation of the fast axis from x towards y, degrees.
    slow : str
        ``ramp`` (the slow axis moves continuously) or ``staircase`` (it steps between lines,
        in the turnaround outside the image).
    direction : str
        ``up`` (slow coordinate increasing), ``down``, or ``bounce`` (up, then down, ...).
    overscan : float
        Fast-axis travel added at each side, as a fraction of the width.
    frames : int
        Frames to scan.
    """

    width_um: float
    height_um: float
    pixels: int
    lines: int
    line_rate_hz: float
    centre_um: tuple[float, float] = (0.0, 0.0)
    angle_deg: float = 0.0
    slow: str = "ramp"
    direction: str = "up"
    overscan: float = 0.1
    frames: int = 1

    def __post_init__(self) -> None:
        numbers = (self.width_um, self.height_um, self.line_rate_hz, *self.centre_um,
                   self.angle_deg, self.overscan)
        if not all(math.isfinite(v) for v in numbers):
            raise InputError("raster frame: every number must be finite")
        if self.width_um <= 0 or self.height_um < 0 or self.line_rate_hz <= 0:
            raise InputError("raster frame: need width > 0 um, height >= 0 um, line rate > 0 Hz")
        if self.pixels < 2 or self.lines < 1 or self.frames < 1:
            raise InputError("raster frame: need >= 2 pixels, >= 1 line, >= 1 frame")
        if not 0 <= self.overscan <= 1:
            raise InputError(f"raster overscan {self.overscan:g}: between 0 and 1 (a fraction "
                             f"of the width, at each side)")
        if self.slow not in SLOW_MODES:
            raise InputError(f"raster slow axis {self.slow!r}: one of {', '.join(SLOW_MODES)}")
        if self.direction not in DIRECTIONS:
            raise InputError(f"raster direction {self.direction!r}: one of "
                             f"{', '.join(DIRECTIONS)}")

    @property
    def span_um(self) -> float:
        """Fast-axis travel, um: the width and the overscan at both sides."""
        return self.width_um * (1 + 2 * self.overscan)

    @property
    def line_s(self) -> float:
        return 1.0 / self.line_rate_hz

    @property
    def pixel_um(self) -> float:
        """Pixel pitch along the fast axis, um."""
        return self.width_um / self.pixels

    @property
    def line_pitch_um(self) -> float:
        """Line pitch along the slow axis, um (the pixel pitch for a one-line frame)."""
        return self.height_um / self.lines if self.height_um > 0 else self.pixel_um

    def upward(self, index: int) -> bool:
        """Whether frame ``index`` (from 0) scans with the slow coordinate increasing."""
        return self.direction == "up" or (self.direction == "bounce" and index % 2 == 0)

    def duration_s(self) -> float:
        """Tracking time of one frame (lead line included), s."""
        return (self.lines + LEAD_LINES) * self.line_s

    def label(self) -> str:
        return (f"raster {self.width_um:g} x {self.height_um:g} um, {self.pixels} x {self.lines} "
                f"px, {self.line_rate_hz:g} lines/s")


def _rotate(frame: Frame, f: FloatArray, s: FloatArray) -> tuple[FloatArray, FloatArray]:
    a = math.radians(frame.angle_deg)
    cx, cy = frame.centre_um
    return cx + f * math.cos(a) - s * math.sin(a), cy + f * math.sin(a) + s * math.cos(a)


def _slow_ramp(frame: Frame, t: FloatArray) -> FloatArray:
    """Slow coordinate of an upward ramp (um): held at -H/2 over the lead line, then -H/2 to
    +H/2 over the image lines."""
    lines = np.clip(t / frame.line_s - LEAD_LINES, 0.0, frame.lines)
    return frame.height_um * (lines / frame.lines - 0.5)


def _slow_staircase(frame: Frame, t: FloatArray) -> FloatArray:
    """Slow coordinate of an upward staircase (um): row j's centre during its line, a
    raised-cosine step to the next in the turnaround about the start of each line, over the
    central :data:`STEP_FRACTION` of the overscan's time (the row is settled a little before
    the image starts)."""
    pos = t / frame.line_s - LEAD_LINES  # lines from the first image line
    # the overscan lasts overscan W / span of a half line at each side of a line start
    half_step = STEP_FRACTION * 0.5 * frame.overscan * frame.width_um / frame.span_um
    row = np.round(pos)  # the nearest line start: the step from row - 1 to row is about it
    frac = np.clip((pos - row + half_step) / max(2 * half_step, 1e-12), 0.0, 1.0)
    level = np.clip(row - 1 + 0.5 * (1 - np.cos(np.pi * frac)), 0, frame.lines - 1)
    return frame.line_pitch_um * (level + 0.5) - 0.5 * frame.height_um


def fast_coordinate(frame: Frame, t: FloatArray) -> FloatArray:
    """The fast axis's triangle (um about the centre): from ``-span/2`` at every line start."""
    return 0.5 * frame.span_um * sawtooth(2 * np.pi * t / frame.line_s, 0.5)


def slow_coordinate(frame: Frame, t: FloatArray, index: int = 0) -> FloatArray:
    """The slow axis (um about the centre) of frame ``index`` at times ``t`` (s)."""
    s = _slow_ramp(frame, t) if frame.slow == "ramp" else _slow_staircase(frame, t)
    return s if frame.upward(index) else -s


@dataclass(frozen=True)
class Trajectories:
    """The desired x and y of one frame's tracking part, um, sampled every ``dt_s``."""

    dt_s: float
    x_um: FloatArray
    y_um: FloatArray

    def axis(self, name: str) -> FloatArray:
        return {"x": self.x_um, "y": self.y_um}[name]


def samples(frame: Frame, dt_s: float) -> int:
    """Samples of one frame's tracking part (both ends included)."""
    return int(round(frame.duration_s() / dt_s)) + 1


def trajectories(frame: Frame, dt_s: float, index: int = 0) -> Trajectories:
    """Desired x and y (um) of frame ``index``: the lead line and the image lines."""
    t = np.arange(samples(frame, dt_s)) * dt_s
    x, y = _rotate(frame, fast_coordinate(frame, t), slow_coordinate(frame, t, index))
    return Trajectories(dt_s, x, y)


def image_mask(frame: Frame, dt_s: float) -> NDArray[np.bool_]:
    """The samples of the tracking part inside the image: on an image line (not the lead line)
    with the fast coordinate within the width (the overscan excluded)."""
    t = np.arange(samples(frame, dt_s)) * dt_s
    inside = np.abs(fast_coordinate(frame, t)) <= 0.5 * frame.width_um
    return inside & (t >= LEAD_LINES * frame.line_s)


@dataclass(frozen=True)
class PixelGrid:
    """Where and when every pixel of the trace (index 0) and retrace (1) images is passed.

    ``sample`` is the (fractional) sample index on the tracking part, shape (2, lines, pixels);
    ``x_um``, ``y_um`` the desired position there; ``fast_um`` and ``slow_um`` the pixel's
    nominal coordinates about the centre (rows by increasing slow coordinate).
    """

    sample: FloatArray
    x_um: FloatArray
    y_um: FloatArray
    fast_um: FloatArray
    slow_um: FloatArray


def pixel_grid(frame: Frame, dt_s: float, index: int = 0) -> PixelGrid:
    """The pixel grid of frame ``index`` (pixel ``i`` at ``f = -W/2 + (i + 1/2) W / P``)."""
    f = frame.pixel_um * (np.arange(frame.pixels) + 0.5) - 0.5 * frame.width_um
    half = 0.5 * frame.line_s
    t_in = (f + 0.5 * frame.span_um) / frame.span_um * half  # time into the trace
    line = np.arange(frame.lines) + LEAD_LINES
    if not frame.upward(index):
        line = line[::-1]  # rows by increasing slow coordinate
    start = (line * frame.line_s)[:, None]
    t = np.stack([start + t_in[None, :], start + 2 * half - t_in[None, :]])
    fast = np.broadcast_to(f, t.shape)
    slow = slow_coordinate(frame, t, index)
    x, y = _rotate(frame, fast, slow)
    return PixelGrid(t / dt_s, x, y, np.array(fast), slow)


# ----------------------------------------------------------------------------------------------
# reach
# ----------------------------------------------------------------------------------------------


def extent(frame: Frame) -> dict[str, tuple[float, float]]:
    """The lowest and highest x and y (um) the frame asks for, overscan included."""
    a = math.radians(frame.angle_deg)
    half_f, half_s = 0.5 * frame.span_um, 0.5 * frame.height_um
    hx = half_f * abs(math.cos(a)) + half_s * abs(math.sin(a))
    hy = half_f * abs(math.sin(a)) + half_s * abs(math.cos(a))
    (cx, cy) = frame.centre_um
    return {"x": (cx - hx, cx + hx), "y": (cy - hy, cy + hy)}


def largest_scale(frame: Frame, reach: Mapping[str, tuple[float, float]]) -> float:
    """The largest factor the frame's size may be scaled by about its centre and stay within
    ``reach`` (um per axis, narrowed by :data:`REACH_MARGIN`): 1 or more if it fits."""
    scale = math.inf
    for name, (lo, hi) in extent(frame).items():
        r_lo, r_hi = reach[name]
        m = REACH_MARGIN * (r_hi - r_lo)
        c = 0.5 * (lo + hi)
        half = 0.5 * (hi - lo)
        room = min(c - (r_lo + m), (r_hi - m) - c)
        if room <= 0:
            return 0.0
        if half > 0:
            scale = min(scale, room / half)
    return scale


def check_reach(frame: Frame, reach: Mapping[str, tuple[float, float]]) -> None:
    """FrameReachError, naming the largest frame of the same shape that fits at this centre,
    if the frame (overscan included) leaves either axis's reach."""
    k = largest_scale(frame, reach)
    if k >= 1:
        return
    where = "; ".join(f"{n} {lo:.4g} ... {hi:.4g} um" for n, (lo, hi) in reach.items())
    asked = "; ".join(f"{n} {lo:.4g} ... {hi:.4g} um" for n, (lo, hi) in extent(frame).items())
    if k <= 0:
        centre = ", ".join(f"{0.5 * (lo + hi):.4g}" for lo, hi in reach.values())
        raise FrameReachError(
            f"raster frame centred at {frame.centre_um[0]:g}, {frame.centre_um[1]:g} um is "
            f"outside the stage's reach ({where}); centre it within, e.g. --centre {centre}")
    raise FrameReachError(
        f"raster frame {frame.width_um:g} x {frame.height_um:g} um (with {frame.overscan:g} "
        f"overscan: {asked}) is beyond the stage's reach ({where}, less {100 * REACH_MARGIN:g} % "
        f"for the dynamics): the largest that fits at this centre is "
        f"{math.floor(100 * k * frame.width_um) / 100:g} x "
        f"{math.floor(100 * k * frame.height_um) / 100:g} um")


# ----------------------------------------------------------------------------------------------
# plans
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AxisPlan:
    """What one axis is planned from: its model, limits, validity envelope (None: unknown) and
    present output voltage."""

    model: tr.Transducer
    limits: guard.Limits
    envelope: Envelope | None = None
    start_v: float = 0.0


@dataclass(frozen=True)
class XYWaveform:
    """A guard-checked two-axis waveform for one filter: ``voltage_v`` and ``desired_um`` of shape
    (N, 2) (column 0 x, 1 y; desired NaN outside the tracking part), the tracking part's
    samples, and the inverse's horizons per axis (empty for the linear filter)."""

    filter: str
    dt_s: float
    voltage_v: FloatArray
    desired_um: FloatArray
    tracking: slice
    horizons: dict[str, tuple[int, ...]]
    feedforward: bool

    @property
    def time_s(self) -> FloatArray:
        return np.arange(self.voltage_v.shape[0]) * self.dt_s


def targets(traj: Trajectories, coupling: Mapping[str, cp.Coupling] | None
            ) -> dict[str, FloatArray]:
    """The targets each axis's inverse aims at (um): the desired trajectory less the motion the
    other axis's *own* motion causes through the coupling (``"yx"``: y caused by x).

    Each axis's model was identified (:func:`afmctl.fit.xyidentify.axis_sweeps`) on its own
    motion (:func:`afmctl.model.coupling.own_motion`: its readings less what the other axis's
    own motion causes); the same here, with the desired trajectories for the readings. Aiming
    at the other's *desired* motion instead leaves the loop ``c_xy c_yx`` out: on foreign-xy-1
    (5.6 % each way) a 0.32 % gain error of the fast axis, 0.22 um across a 60 um frame.
    """
    x, y = traj.x_um, traj.y_um
    if not coupling:
        return {"x": x, "y": y}
    dt = traj.dt_s

    none = cp.Coupling(0.0)
    here, back = coupling.get("xy", none), coupling.get("yx", none)
    return {"x": cp.own_motion(here, back, x, y, dt), "y": cp.own_motion(back, here, y, x, dt)}


def _pad(w: track.Waveform, before: int, total: int, start_v: float) -> FloatArray:
    after = total - before - w.voltage_v.size
    return np.concatenate([np.full(before, start_v), w.voltage_v,
                           np.full(after, w.voltage_v[-1])])


def plan(frame: Frame, axes: Mapping[str, AxisPlan], dt_s: float,
         coupling: Mapping[str, cp.Coupling] | None = None,
         filters: tuple[str, ...] = ("inverse", "linear"), index: int = 0,
         extrapolate: bool = False, aims: Mapping[str, FloatArray] | None = None
         ) -> dict[str, XYWaveform]:
    """Guard-checked two-axis waveforms of frame ``index`` for each filter.

    Each axis is planned by :func:`afmctl.planning.track.plan` (conditioning, Algorithm 3 with
    its effects, the paper's linear filter over the same voltage range) on its target
    (:func:`targets`: the coupling fed forward unless ``coupling`` is None), within its own
    limits and envelope. The frame must fit the reach (:func:`check_reach`, call it first with
    :func:`reach` for a clear refusal); a plan that still falls short at the voltage limits (the
    dynamics at the corners) is refused the same way. ``aims`` (um per axis, the tracking part)
    replaces the targets: a learned reference (:mod:`afmctl.experiment.scanlearn`). The two axes
    are planned at once, one thread each (the model's compiled kernels release the GIL); a
    refusal names x's first, as one after the other would.
    """
    traj = trajectories(frame, dt_s, index)
    aims = targets(traj, coupling) if aims is None else aims
    wanted = tuple(dict.fromkeys(("inverse", *filters)))

    def planned(name: str) -> dict[str, track.Waveform]:
        ax = axes[name]
        desired = track.Desired(dt_s, aims[name], frame.line_s, float(np.ptp(traj.axis(name))),
                                f"{frame.label()}, axis {name}")
        try:
            return track.plan(ax.model, desired, ax.limits, ax.start_v, wanted,
                              envelope=ax.envelope, extrapolate=extrapolate)
        except ReachError as exc:
            raise FrameReachError(f"axis {name}: {exc}; scan a smaller frame") from None
        except guard.LimitError as exc:
            hint = ("; the paper's linear filter needs more voltage than the inverse at the "
                    "frame's extremes: scan a smaller frame, or --filter inverse"
                    if str(exc).startswith("linear") else "")
            raise guard.LimitError(f"axis {name}: {exc}{hint}") from None

    with ThreadPoolExecutor(len(AXES)) as pool:
        futures = {n: pool.submit(planned, n) for n in AXES}
    per_axis = {n: futures[n].result() for n in AXES}
    out = {}
    for f in filters:
        ws = {n: per_axis[n][f] for n in AXES}
        start = max(w.tracking.start for w in ws.values())
        total = max(start - w.tracking.start + w.voltage_v.size for w in ws.values())
        volts = [_pad(ws[n], start - ws[n].tracking.start, total, axes[n].start_v)
                 for n in AXES]
        n_tr = traj.x_um.size
        desired = np.full((total, 2), np.nan)
        desired[start:start + n_tr] = np.column_stack([traj.x_um, traj.y_um])
        out[f] = XYWaveform(f, dt_s, np.column_stack(volts), desired,
                            slice(start, start + n_tr),
                            {n: ws[n].horizons for n in AXES}, coupling is not None)
    return out


def reach(axes: Mapping[str, AxisPlan]) -> dict[str, tuple[float, float]]:
    """Each axis's quasi-static reach (um) on its limits and envelope
    (:func:`afmctl.planning.track.reach`)."""
    return {n: track.reach(a.model, a.limits, a.envelope) for n, a in axes.items()}


def replace_start(axes: Mapping[str, AxisPlan], start_v: FloatArray) -> dict[str, AxisPlan]:
    """``axes`` with each axis's present output (V, in axis order)."""
    return {n: dc.replace(axes[n], start_v=float(start_v[k])) for k, n in enumerate(AXES)}
