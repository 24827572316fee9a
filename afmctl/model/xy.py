"""The model of a two-axis (x/y) stage: each axis's one-axis model and the coupling both ways.

Axis ``a``'s sensor reads its own transducer's displacement (the paper's model, driven by its own
voltage) plus the motion the other axis causes (:mod:`afmctl.model.coupling`)::

    u_y = T_y(V_y) + H_yx (u_x - reference_yx)
    u_x = T_x(V_x) + H_xy (u_y - reference_xy)

Direction names: ``"yx"`` is y motion caused by x, ``"xy"`` x motion caused by y.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only: the file rooms take AXES from here without numba or scipy
    from afmctl.model.coupling import Coupling
    from afmctl.model.transducer import Transducer

#: The axes of a two-axis stage, in channel order (channel 0 is x).
AXES = ("x", "y")
DIRECTIONS = ("yx", "xy")


@dataclass(frozen=True)
class XYModel:
    """Two axes and their coupling.

    Parameters
    ----------
    axes : mapping of str to Transducer
        The one-axis model of each axis ("x", "y").
    coupling : mapping of str to Coupling
        ``"yx"`` (y caused by x) and ``"xy"`` (x caused by y), um of target per um of source.
    """

    axes: Mapping[str, Transducer]
    coupling: Mapping[str, Coupling]

    def __post_init__(self) -> None:
        if set(self.axes) != set(AXES):
            raise ValueError(f"an XYModel needs axes {AXES}, got {tuple(self.axes)}")
        if set(self.coupling) != set(DIRECTIONS):
            raise ValueError(f"an XYModel needs couplings {DIRECTIONS}, got {tuple(self.coupling)}")

    def axis(self, name: str) -> Transducer:
        """The one-axis model of axis ``name``."""
        return self.axes[name]


def direction(target: str, source: str) -> str:
    """The direction name of ``target`` motion caused by ``source`` ("yx" for y caused by x)."""
    return target + source
