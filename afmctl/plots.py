"""Every figure afmctl draws: identification fits, diagnosis residuals, tracking and learning.

Figures are :class:`matplotlib.figure.Figure` objects saved straight to a PNG: no pyplot, so the
caller's matplotlib backend is never touched (a notebook's inline figures keep working) and no
figure is left open. matplotlib is imported when this module is, and only the CLI imports it.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator
from numpy.typing import NDArray

from afmctl.files.sweepfile import Sweep

if TYPE_CHECKING:
    from afmctl.experiment.learn import Result
    from afmctl.experiment.runner import Outcome
    from afmctl.experiment.scan import FrameRun
    from afmctl.planning.track import Desired

FloatArray = NDArray[np.float64]


def _stem(sweep: Sweep, index: int) -> str:
    base = Path(sweep.path).stem if sweep.path else sweep.name
    return f"{index:02d}_" + re.sub(r"[^A-Za-z0-9_.-]+", "_", base)


@contextmanager
def _saved(path: str | Path, dpi: int, *grid: int, **kw: Any) -> Iterator[Any]:
    """The axes of a new figure (``Figure.subplots(*grid, **kw)``); the figure is saved to ``path``
    when the block ends without error. ``layout`` defaults to ``"constrained"``."""
    fig = Figure(figsize=kw.pop("figsize", None), layout=kw.pop("layout", "constrained"))
    yield fig.subplots(*grid, **kw)
    fig.savefig(Path(path), dpi=dpi)


def _excluded_spans(sweep: Sweep, judged: NDArray[np.bool_]) -> list[tuple[float, float]]:
    """Time spans (s) of the runs of samples left out of the judging."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], (~judged).astype(int), [0]])))
    t = sweep.time_s
    return [(t[a], t[min(b, t.size - 1)]) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _binned_mean(x: FloatArray, y: FloatArray, bins: int = 60) -> tuple[FloatArray, FloatArray]:
    """Mean of ``y`` in ``bins`` equal bins of ``x`` (bins without samples left out): the line a
    reader sees through a noise cloud."""
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size == 0:
        return np.zeros(0), np.zeros(0)
    edges = np.linspace(x.min(), x.max(), bins + 1)
    idx = np.clip(np.digitize(x, edges) - 1, 0, bins - 1)
    count = np.bincount(idx, minlength=bins)
    total = np.bincount(idx, weights=y, minlength=bins)
    keep = count > 0
    return 0.5 * (edges[:-1] + edges[1:])[keep], total[keep] / count[keep]


def fit_figure(sweep: Sweep, fitted_um: FloatArray, path: str | Path,
               window_s: tuple[float, float] | None = None) -> Path:
    """Save a two-panel PNG: displacement (um) vs voltage (V), measured and fitted, and the
    residual measured - fitted (um) vs time (s), the part the fit does not judge (before the
    sweep's memory index, outside ``window_s``) shaded, the RMS of the judged part stated and a
    binned mean drawn over the noise cloud.
    Returns the path written."""
    judged = sweep.mask(window_s)
    r = sweep.displacement_um - fitted_um
    rms = float(np.sqrt(np.mean(r[judged] ** 2))) if judged.any() else float("nan")
    with _saved(path, 110, 1, 2, figsize=(11, 4.2)) as (ax1, ax2):
        ax1.plot(sweep.voltage_v, sweep.displacement_um, ".", ms=1.5, alpha=0.4, label="measured")
        ax1.plot(sweep.voltage_v, fitted_um, "-", lw=1.0, label="model")
        ax1.set(xlabel="voltage (V)", ylabel="displacement (um)", title=sweep.name)
        ax1.legend(loc="upper left")
        ax2.plot(sweep.time_s, r, lw=0.5, color="tab:blue", alpha=0.5,
                 label=f"judged RMS {rms:.3g} um")
        ax2.plot(*_binned_mean(sweep.time_s[judged], r[judged], 100), lw=1.4, color="k",
                 label="binned mean (what is not noise)")
        for i, (a, b) in enumerate(_excluded_spans(sweep, judged)):
            ax2.axvspan(a, b, color="0.85", zorder=0,
                        label="not judged (unknown start state)" if i == 0 else None)
        lim = 4 * rms if np.isfinite(rms) and rms > 0 else None
        if lim is not None and np.abs(r).max() > lim:  # the transient must not hide the fit
            ax2.set_ylim(-lim, lim)
        ax2.set(xlabel="time (s)", ylabel="residual (um)", title="measured - model")
        ax2.legend(loc="upper right", fontsize=8)
    return Path(path)


def fit_names(sweeps: list[Sweep]) -> list[str]:
    """The file names :func:`fit_figures` writes."""
    return [f"{_stem(s, i)}.png" for i, s in enumerate(sweeps)]


def fit_figures(sweeps: list[Sweep], fitted_um: list[FloatArray], out_dir: str | Path,
                window_s: tuple[float, float] | None = None) -> list[Path]:
    """One :func:`fit_figure` per sweep into ``out_dir`` (created if needed)."""
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    return [fit_figure(s, u, d / name, window_s)
            for s, u, name in zip(sweeps, fitted_um, fit_names(sweeps), strict=True)]


#: The binned means over the clouds of :func:`field_panel`: dark, outlined in white, on top.
MEAN_STYLES = (dict(color="black", lw=1.8, ls="--"), dict(color="navy", lw=1.4, ls="-"))


def field_panel(ax: Any, field: FloatArray, residuals: list[FloatArray],
                labels: tuple[str, str]) -> None:
    """Residuals (um) of the base and the extended model against field (MV/m): both noise clouds
    faint in their colours (red, blue), then each binned mean over both clouds, dark and
    outlined in white so that the mean stays visible inside a cloud of its own colour."""
    from matplotlib import patheffects
    for r, color in zip(residuals, ("tab:red", "tab:blue"), strict=True):
        ax.plot(field, r, ".", ms=1, alpha=0.15, color=color, zorder=1)
    outline = [patheffects.withStroke(linewidth=3.5, foreground="white")]
    for r, lab, st in zip(residuals, labels, MEAN_STYLES, strict=True):
        ax.plot(*_binned_mean(field, r), **st, zorder=5, path_effects=outline,
                label=f"mean: {lab}")
    ax.legend(loc="upper right", fontsize=7)


def diagnosis_figure(sweeps: list[Sweep], before_um: list[FloatArray], after_um: list[FloatArray],
                     thickness_um: float, labels: tuple[str, str], path: str | Path) -> Path:
    """Residuals (measured - model, um) before and after the extension: per sweep against time
    (left column; the judged second half shaded) and against field (MV/m, right column:
    :func:`field_panel`). The base model is drawn over the extension, thicker
    and dashed, so that identical models (cause ``none``) still show both."""
    n = len(sweeps)
    styles = (dict(color="tab:red", lw=1.4, ls="--", zorder=3),
              dict(color="tab:blue", lw=0.7, ls="-", zorder=2))
    with _saved(path, 100, n, 2, figsize=(12, 2.6 * n + 0.6), squeeze=False) as ax:
        for i, (s, b, a) in enumerate(zip(sweeps, before_um, after_um, strict=True)):
            m = s.mask(None)
            rs = [np.where(m, s.displacement_um - u, np.nan) for u in (b, a)]
            for r, lab, st in ((rs[1], labels[1], styles[1]), (rs[0], labels[0], styles[0])):
                rms = float(np.sqrt(np.nanmean(r[s.time_s.size // 2:] ** 2)))
                ax[i, 0].plot(s.time_s, r, label=f"{lab} (held-out RMS {rms:.3g} um)", **st)
            field_panel(ax[i, 1], s.voltage_v / thickness_um, rs, labels)
            ax[i, 0].axvspan(s.time_s[s.time_s.size // 2], s.time_s[-1], color="0.9", zorder=0)
            ax[i, 0].set(ylabel="residual (um)", title=f"{s.name}: held-out half shaded")
            ax[i, 0].legend(loc="upper right", fontsize=7)
            ax[i, 1].set(ylabel="residual (um)", title=f"{s.name} against field")
        ax[-1, 0].set(xlabel="time (s)")
        ax[-1, 1].set(xlabel="field (MV/m)")
    return Path(path)


def save_figure(fig: Figure, path: str | Path, dpi: int = 110) -> Path:
    """Save ``fig`` (from one of the ``*_figure`` functions) as a PNG at ``path``."""
    fig.savefig(Path(path), dpi=dpi)
    return Path(path)


def track_figure(outcomes: Mapping[str, Outcome], desired: Desired, thickness_um: float,
                 corrected_for: str = "") -> Figure:
    """``track.png`` (and ``play.png``, ``afmctl score``'s): desired and achieved trajectories,
    errors, and the field-displacement loop (the paper's Figs. 9-11).

    What is drawn is what is scored (:attr:`~afmctl.experiment.runner.Outcome.scored_um`): the
    readings, or the readings corrected for the sensor effects the model knows (``corrected_for``
    names them in the legend). The desired trajectory is drawn last (dashed, on top) so the
    filters cannot hide it; the first period, left out of the headline figures, is shaded, and
    each error's legend states its RMS.
    """
    t = np.arange(desired.u_um.size) * desired.dt_s
    colors = {"inverse": "tab:blue", "linear": "tab:red"}
    fig = Figure(figsize=(8, 9.5), layout="constrained")
    ax = fig.subplots(3, 1)
    t0 = 0.0
    for name, o in outcomes.items():
        u = o.scored_um[o.waveform.tracking]
        v = o.waveform.voltage_v[o.waveform.tracking]
        c = colors.get(name, None)
        t0 = o.score.steady_from_s
        what = (f" (readings corrected for {corrected_for})"
                if o.corrected_um is not None and corrected_for else "")
        ax[0].plot(t, u, color=c, lw=1.6, alpha=0.8, label=f"{name} filter{what}")
        part = "steady part" if o.score.steady else "whole run"
        ax[1].plot(t, u - desired.u_um, color=c, lw=0.9,
                   label=f"{name}: RMS {o.score.rms_um:.3g} um ({o.score.rms_pct:.2g} %, {part})")
        ax[2].plot(v / thickness_um, u, color=c, lw=0.8, label=name)
    ax[0].plot(t, desired.u_um, "k--", lw=1.0, label="desired", zorder=5)
    for a in ax[:2]:
        if t0 > 0:
            a.axvspan(0, t0, color="0.9", zorder=0, label="first period (transient, not in RMS)")
    ax[0].set(xlabel="time (s)", ylabel="displacement (um)", title=f"Tracking: {desired.label}")
    ax[1].set(xlabel="time (s)", ylabel="error (um)")
    ax[2].set(xlabel="field (MV/m)", ylabel="displacement (um)", title="field-displacement")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(loc="best", fontsize=8)
    return fig


def learn_figure(result: Result, desired: Desired) -> Figure:
    """``learn.png``: error RMS against iteration (whole iterations on the axis), and the error of
    the first and last iteration against time."""
    its = result.iterations
    fig = Figure(figsize=(8, 7), layout="constrained")
    ax = fig.subplots(2, 1)
    idx = [it.index for it in its]
    ax[0].semilogy(idx, [it.steady_um for it in its], "o-", label="steady RMS (readings, corrected)")
    ax[0].semilogy(idx, [it.outcome.score.rms_between_um or np.nan for it in its], "s--",
                   label="RMS between samples (plant)")
    ax[0].semilogy(idx, [it.rms_imaging_um for it in its], "^:", label="imaging region RMS")
    if np.isfinite(result.noise_um):
        ax[0].axhline(result.noise_um, color="gray", lw=0.8, label="noise estimate")
    ax[0].set(xlabel="iteration", ylabel="error (um)", title=f"Learning: {desired.label}")
    ax[0].xaxis.set_major_locator(MaxNLocator(integer=True))
    t = np.arange(desired.u_um.size) * desired.dt_s
    for it, c in ((its[0], "tab:red"), (its[-1], "tab:blue")):
        ax[1].plot(t, -it.error_um, color=c, lw=0.8,
                   label=f"iteration {it.index}: RMS {it.steady_um:.3g} um")
    ax[1].set(xlabel="time (s)", ylabel="error (um)")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(loc="best", fontsize=8)
    return fig



def scan_figure(runs: list[FrameRun]) -> Figure:
    """``scan.png``: for the last frame of each filter (side by side), the fast-axis error of the
    trace and the retrace, the slow-axis error of the trace, and the trace/retrace registration
    (pixels), each image line by line as the frame was scanned (rows by increasing slow
    coordinate); a row's colour scale is shared by the filters, so they compare at a glance."""
    cols = list({r.filter: r for r in runs}.values())
    rows = (("fast error, trace", "um", "fast_rms_um", lambda r: r.images.error_fast_um[0]),
            ("fast error, retrace", "um", "fast_rms_um", lambda r: r.images.error_fast_um[1]),
            ("slow error, trace", "px", "slow_deviation_px",
             lambda r: r.images.error_slow_um[0]),
            ("registration trace - retrace", "px", "registration_px",
             lambda r: r.images.registration_px))
    fig = Figure(figsize=(4.2 * len(cols) + 1.2, 12), layout="constrained")
    ax = np.array(fig.subplots(len(rows), len(cols), squeeze=False))
    for i, (what, unit, key, get) in enumerate(rows):
        imgs = [get(r) for r in cols]
        lim = max((float(np.nanmax(np.abs(m))) for m in imgs if np.isfinite(m).any()),
                  default=0.0) or 1.0
        for j, (r, img) in enumerate(zip(cols, imgs, strict=True)):
            im = ax[i, j].imshow(img, origin="lower", aspect="auto", cmap="RdBu_r",
                                 vmin=-lim, vmax=lim, interpolation="nearest")
            ax[i, j].set(title=f"{r.filter}, frame {r.number}: {what}\nRMS {r.merit[key]:.3g} "
                               f"{unit}", xlabel="pixel", ylabel="line")
        fig.colorbar(im, ax=ax[i, :].tolist(), shrink=0.9,
                     label="um" if "error" in what else "pixels")
    return fig
