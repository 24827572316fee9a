"""Figures for identification: measured vs fitted loops and the residual over time, per sweep.

Matplotlib with the Agg backend (no display); every figure is closed after saving.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402

from afmctl.sweeps import Sweep  # noqa: E402

FloatArray = NDArray[np.float64]


def _stem(sweep: Sweep, index: int) -> str:
    base = Path(sweep.path).stem if sweep.path else sweep.name
    return f"{index:02d}_" + re.sub(r"[^A-Za-z0-9_.-]+", "_", base)


@contextmanager
def _saved(path: str | Path, dpi: int, *grid: int, **kw: Any) -> Iterator[Any]:
    """``plt.subplots(*grid, **kw)``'s axes; the figure is saved to ``path`` when the block ends
    without error, and closed in any case."""
    fig, ax = plt.subplots(*grid, **kw)
    try:
        yield ax
        fig.tight_layout()
        fig.savefig(Path(path), dpi=dpi)
    finally:
        plt.close(fig)


def fit_figure(sweep: Sweep, fitted_um: FloatArray, path: str | Path) -> Path:
    """Save a two-panel PNG: displacement (um) vs voltage (V), measured and fitted, and the
    residual measured - fitted (um) vs time (s). Returns the path written."""
    with _saved(path, 110, 1, 2, figsize=(11, 4.2)) as (ax1, ax2):
        ax1.plot(sweep.voltage_v, sweep.displacement_um, ".", ms=1.5, alpha=0.4, label="measured")
        ax1.plot(sweep.voltage_v, fitted_um, "-", lw=1.0, label="model")
        ax1.set(xlabel="voltage (V)", ylabel="displacement (um)", title=sweep.name)
        ax1.legend(loc="upper left")
        ax2.plot(sweep.time_s, sweep.displacement_um - fitted_um, lw=0.6)
        ax2.set(xlabel="time (s)", ylabel="residual (um)", title="measured - model")
    return Path(path)


def fit_figures(sweeps: list[Sweep], fitted_um: list[FloatArray],
                out_dir: str | Path) -> list[Path]:
    """One :func:`fit_figure` per sweep into ``out_dir`` (created if needed)."""
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    return [fit_figure(s, u, d / f"{_stem(s, i)}.png")
            for i, (s, u) in enumerate(zip(sweeps, fitted_um, strict=True))]


def diagnosis_figure(sweeps: list[Sweep], before_um: list[FloatArray], after_um: list[FloatArray],
                     thickness_um: float, labels: tuple[str, str], path: str | Path) -> Path:
    """Residuals (measured - model, um) before and after the extension: per sweep against time
    (left column) and against field (MV/m, right column); the judged second half is shaded."""
    n = len(sweeps)
    with _saved(path, 100, n, 2, figsize=(12, 2.6 * n + 0.6), squeeze=False) as ax:
        for i, (s, b, a) in enumerate(zip(sweeps, before_um, after_um, strict=True)):
            m = s.mask(None)
            for u, lab, c in ((b, labels[0], "tab:red"), (a, labels[1], "tab:blue")):
                r = np.where(m, s.displacement_um - u, np.nan)
                ax[i, 0].plot(s.time_s, r, lw=0.6, color=c, label=lab)
                ax[i, 1].plot(s.voltage_v / thickness_um, r, ".", ms=1, alpha=0.4, color=c)
            ax[i, 0].axvspan(s.time_s[s.time_s.size // 2], s.time_s[-1], color="0.9", zorder=0)
            ax[i, 0].set(ylabel="residual (um)", title=f"{s.name}: held-out half shaded")
            ax[i, 1].set(ylabel="residual (um)", title=f"{s.name} against field")
        ax[-1, 0].set(xlabel="time (s)")
        ax[-1, 1].set(xlabel="field (MV/m)")
        ax[0, 0].legend(loc="upper right", fontsize=8)
    return Path(path)
