"""Command line: ``afmctl``. Composes the library; holds no numerics and no device I/O.

One module per command (or family); :mod:`afmctl.cli.base` holds the group, the mapping of
afmctl's own errors to exit codes, and the helpers they share.

Exit codes: 0 success; 1 the stage failed or a fit gave no finite model; 2 bad input (one line on
stderr, nothing written); 130 interrupted (the stage was put in its safe state).
"""

from afmctl.cli import diagnose, identify, play, scan, score, stage, sweep, track  # noqa: F401 (registers commands)
from afmctl.cli.base import main

__all__ = ["main"]
