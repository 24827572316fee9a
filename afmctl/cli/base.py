"""Command line: ``afmctl``: the group, error mapping and helpers every command shares.

``afmctl``. Composes the library; holds no numerics and no device I/O.

Exit codes: 0 success; 1 the stage failed or a fit did not converge; 2 bad input (one line on
stderr, nothing written); 130 interrupted (the stage was put in its safe state).
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any, NoReturn

import click

from afmctl import __version__
from afmctl.tomlfile import FileFormatError, InputError


def fail(message: str, code: int = 2) -> NoReturn:
    click.echo(f"afmctl: error: {message}", err=True)
    sys.exit(code)


class Group(click.Group):
    """Turns known failures into one line and an exit code instead of a traceback."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except InputError as exc:
            fail(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        except KeyboardInterrupt:
            fail("interrupted; the stage was sent to its safe state", 130)
        except Exception as exc:
            if type(exc).__name__ == "StageError" or isinstance(exc, TimeoutError | OSError):
                fail(f"stage: {exc}", 1)
            if isinstance(exc, RuntimeError):  # a failed calibration fit, a sweep that lost data
                fail(str(exc), 1)
            raise


@click.group(cls=Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="afmctl")
def main() -> None:
    """Make a hysteretic piezo stage track what it is told (Hatch, Smith et al. inverse filter)."""


def load_profile_or_exit(path: str | None):  # noqa: ANN201 (Profile)
    """The profile at ``path`` (the shipped emulated one if None); one line and exit 2 if bad."""
    from afmctl.profile import default_profile, load_profile
    try:
        return default_profile() if path is None else load_profile(path)
    except FileFormatError as exc:
        fail(f"bad profile: {exc}")


def fit_settings(path: str | None):  # noqa: ANN201 (identify.Settings)
    """Identification settings from a profile: its ``[identify]`` table, and its ``[stack]``
    thickness for sweeps whose metadata gives none (defaults without a profile)."""
    from afmctl import identify as idf
    from afmctl import tomlfile
    if path is None:
        return idf.Settings()
    prof = load_profile_or_exit(path)
    base = idf.Settings(fallback_thickness_um=prof.thickness_um)
    return idf.settings_from_table(tomlfile.load(path).table("identify", required=False), base)


def progress_printer(quiet: bool) -> Callable[[str, int, int], None]:
    """Progress on stderr: a line per 10 % (and the last sample) of each run."""
    last: dict[str, int] = {}

    def show(what: str, done: int, total: int) -> None:
        step = 10 * done // max(total, 1)
        if quiet or last.get(what) == step:
            return
        last[what] = step
        click.echo(f"  {what}: {done}/{total} samples ({100 * done // max(total, 1)} %)",
                   err=True)

    return show

