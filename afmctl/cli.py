"""Command line: ``afmctl``. Composes the library; holds no numerics and no device I/O."""

from __future__ import annotations

import click

from afmctl import __version__


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="afmctl")
def main() -> None:
    """Make a hysteretic piezo stage track what it is told (Hatch, Smith et al. inverse filter)."""
