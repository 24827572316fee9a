"""``afmctl track --axis x|y``: today's track on one axis of a two-axis stage, the other held."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from afmctl.cli.base import check_output_dir, load_profile_or_exit, opened_stage, say, timestamped
from afmctl.errors import InputError


@dataclass
class Opened:
    """The two-axis profile, the driven axis's one-axis profile and how to open its stage."""

    full: Any
    profile: Any
    axis: str

    @contextmanager
    def stage(self) -> Iterator[Any]:
        """The stage of the full profile, as the driven axis's one-axis stage."""
        from afmctl.experiment.axisstage import AxisStage
        with opened_stage(self.full) as stage:
            if stage.channels != len(self.full.axis_names):
                raise InputError(f"--axis {self.axis}: the stage reports {stage.channels} "
                                 f"channel(s), the profile {len(self.full.axis_names)}")
            yield AxisStage(stage, self.full.axis_names.index(self.axis))

    def report(self, stage: Any) -> dict[str, Any]:
        """How far the held axis moved (``held_axis`` of summary.json), said on stderr."""
        other = next(a for a in self.full.axis_names if a != self.axis)
        motion = {"axis": other, **stage.held_motion()}
        say(f"held axis {other} (at {motion.get('held_voltage_V', float('nan')):.4g} V) moved "
            f"RMS {motion['rms_um']:.4f} um, peak {motion['peak_um']:.4f} um while {self.axis} "
            f"was driven")
        return motion


def on_axis(axis: str, profile_path: str | None, model_path: str | None,
            unsupported: tuple[bool, bool, int], out_dir: str | None, force: bool,
            run: Callable[[str, str, Opened], None]) -> None:
    """Check the options, take the axis's model out of a two-axis model file (written beside the
    outputs as ``model_<axis>.toml``: the model track used) and ``run(model, out, opened)``."""
    from afmctl.files import modelfile, xymodelfile
    if model_path is None or any(unsupported):
        raise InputError(f"--axis {axis} drives one axis of a two-axis stage with a given model: "
                         f"--model (a two-axis model from `afmctl identify` on two-axis sweeps, or "
                         f"the axis's own), without --calibrate, --recalibrate or --learn")
    full = load_profile_or_exit(profile_path)
    if axis not in full.axis_names or len(full.axis_names) < 2:
        raise InputError(f"--axis {axis}: profile {full.name!r} is not a two-axis profile with "
                         f"axis {axis} (axes: {', '.join(full.axis_names)})")
    out = check_output_dir(Path(out_dir) if out_dir else timestamped("afmctl-track"), "--out",
                           [f"model_{axis}.toml"], force, measured=("run_*.csv",))
    model, env, fit = xymodelfile.read_axis(model_path, axis)
    out.mkdir(parents=True, exist_ok=True)
    own = out / f"model_{axis}.toml"
    modelfile.write(model, own, header=f"axis {axis} of {Path(model_path).name}", envelope=env,
                    fit=fit)
    run(str(own), str(out), Opened(full, full.axis(axis), axis))
