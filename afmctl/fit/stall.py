"""Stopping a least-squares solve that crawls far from the data.

A model off its family often reaches its best shape in a few steps and then crawls: the paper's
model on preisach-u of the benches stood at 47.80x the noise after 12 steps and at 47.84x after
its budget's 300 (26 s); Bouc-Wen on pi-b-creep at 99.3e6 after 40 steps and 99.2e6 after 125
(20 s). Where the caller already knows such a fit cannot be kept (another representation is asked
next, or is far below), the solve is stopped there: :func:`callback` for
:func:`scipy.optimize.least_squares`, which then ends with status -2.
"""

from __future__ import annotations

from collections.abc import Callable

from scipy import optimize

#: Stalled: the cost fell by less than this share of itself ...
SHARE = 1e-3
#: ... over this many steps.
STEPS = 10


def callback(far_off: Callable[[optimize.OptimizeResult], bool], share: float = SHARE
             ) -> Callable[[optimize.OptimizeResult], None]:
    """A ``callback`` that raises ``StopIteration`` once the cost has fallen by less than
    ``share`` of itself over the last :data:`STEPS` steps while ``far_off(result)`` (the step's
    ``cost``, ``fun`` ...) is true.

    Examples
    --------
    >>> stop = callback(lambda r: True)
    >>> for step in range(1, 20):
    ...     try:
    ...         stop(optimize.OptimizeResult(cost=1.0))
    ...     except StopIteration:
    ...         break
    >>> step
    11
    """
    costs: list[float] = []

    def check(intermediate_result: optimize.OptimizeResult) -> None:
        costs.append(float(intermediate_result.cost))
        if (len(costs) > STEPS and costs[-1 - STEPS] - costs[-1] < share * costs[-1]
                and far_off(intermediate_result)):
            raise StopIteration

    return check


def message(far: str, share: float = SHARE) -> str:
    """The solve's message where :func:`callback` (with ``share``) stopped it; ``far`` says how
    far off."""
    return f"stalled: the cost fell by less than {share:.1%} of itself in {STEPS} steps, {far}"


__all__ = ["SHARE", "STEPS", "callback", "message"]
