"""Command line: ``afmctl``: the group, error mapping and helpers every command shares.

``afmctl``. Composes the library; holds no numerics and no device I/O.

Exit codes, by the class of what afmctl raised (:mod:`afmctl.errors`): 0 success (``--help`` and
``--version`` too); 2 an :class:`~afmctl.errors.InputError` (bad input, a file that is not what it
claims, an output that cannot be written, a waveform outside the limits or the envelope: one line
on stderr naming the option or path, nothing written); 1 any other
:class:`~afmctl.errors.AfmctlError` (the stage failed, a fit did not converge); 130 interrupted (the
stage, if one was opened, was put in its safe state). Anything else is a bug: one line saying so
and where the traceback was written, exit 1 (``afmctl --debug ...`` shows the traceback instead).
"""

from __future__ import annotations

import logging
import math
import sys
import tempfile
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NoReturn

import click

from afmctl._version import __version__
from afmctl.errors import AfmctlError, FileFormatError, InputError, OutputError, StageError

#: ``ctx.meta`` key set once a command has opened a stage (the Ctrl-C message depends on it).
STAGE_OPENED = "afmctl.stage_opened"
#: ``ctx.meta`` key set by ``afmctl --debug``: an unexpected exception shows its traceback.
DEBUG = "afmctl.debug"


def fail(message: str, code: int = 2) -> NoReturn:
    click.echo(f"afmctl: error: {message}", err=True)
    sys.exit(code)


def _interrupted() -> NoReturn:
    ctx = click.get_current_context(silent=True)
    if ctx is not None and ctx.meta.get(STAGE_OPENED):
        fail("interrupted; the stage was sent to its safe state", 130)
    fail("interrupted; no stage was touched", 130)


class Group(click.Group):
    """Turns known failures into one line and an exit code instead of a traceback.

    Only afmctl's own errors are mapped: click's ``Exit`` (``--help``, ``--version``) and usage
    errors keep their meaning (exit 0, or one line and exit 2).
    """

    def main(self, *args: Any, standalone_mode: bool = True, **kw: Any) -> Any:
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL + 1)  # afmctl says what failed
        try:
            rv = super().main(*args, standalone_mode=False, **kw)
        except click.exceptions.NoArgsIsHelpError as exc:  # a bare group: its help, as click does
            exc.show()
            sys.exit(exc.exit_code)
        except click.ClickException as exc:
            fail(exc.format_message().replace("\n", " "), exc.exit_code)
        except click.Abort:
            _interrupted()
        if not standalone_mode:
            return rv
        sys.exit(rv if isinstance(rv, int) else 0)

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except (click.exceptions.Exit, click.ClickException, click.Abort):
            raise
        except InputError as exc:
            fail(_first_line(exc))
        except StageError as exc:
            fail(f"stage: {_first_line(exc)}", 1)
        except AfmctlError as exc:  # a fit that did not converge
            fail(_first_line(exc), 1)
        except KeyboardInterrupt:
            _interrupted()
        except Exception as exc:
            if ctx.meta.get(DEBUG):
                raise
            _bug(exc)


def _first_line(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


def _bug(exc: Exception) -> NoReturn:
    """An exception afmctl did not raise on purpose: one line saying so, the traceback to a file."""
    import traceback
    text = "".join(traceback.format_exception(exc))
    try:
        with tempfile.NamedTemporaryFile("w", prefix="afmctl-traceback-", suffix=".txt",
                                         delete=False) as f:
            f.write(text)
        where = f"the traceback is in {f.name}"
    except OSError:
        where = "the traceback could not be written: run again with afmctl --debug to see it"
    fail(f"unexpected {type(exc).__name__}: {_first_line(exc)} (a bug in afmctl, or in its "
         f"surroundings; {where})", 1)


@click.group(cls=Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="afmctl")
@click.option("--debug", is_flag=True, help="Show the traceback of an unexpected error (a bug).")
@click.pass_context
def main(ctx: click.Context, debug: bool) -> None:
    """Make a hysteretic piezo stage track what it is told (Hatch, Smith et al. inverse filter)."""
    ctx.meta[DEBUG] = debug


class Finite(click.ParamType):
    """A finite float, optionally bounded below (``--freq nan`` is bad input, not a traceback)."""

    name = "number"

    def __init__(self, minimum: float | None = None, open_min: bool = False) -> None:
        self.minimum, self.open_min = minimum, open_min

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> float:
        try:
            x = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number", param, ctx)
        if not math.isfinite(x):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        if self.minimum is not None and (x < self.minimum or (self.open_min and x == self.minimum)):
            self.fail(f"{value!r} must be {'>' if self.open_min else '>='} {self.minimum:g}",
                      param, ctx)
        return x


@contextmanager
def opened_stage(profile: Any) -> Iterator[Any]:
    """``afmctl.drivers.open_stage(profile)``, remembering that this command touched a stage.

    Ctrl-C anywhere inside sends the stage to its safe state (every channel to 0 V) before the
    KeyboardInterrupt goes on: ``play`` does it for a Ctrl-C during a run, this for one between
    runs (a sweep's rest before it plays, a ramp being planned), where outputs may be held away
    from 0 V. If that fails too, its error (a lost link) is what the command reports."""
    from afmctl.drivers import open_stage
    ctx = click.get_current_context(silent=True)
    if ctx is not None:
        ctx.meta[STAGE_OPENED] = True
    with open_stage(profile) as stage:
        stage.check_limits()  # the profile's limits against the device's, before anything moves
        try:
            yield stage
        except KeyboardInterrupt:
            stage.safe_state()
            raise


def load_profile_or_exit(path: str | None):  # noqa: ANN201 (Profile)
    """The profile at ``path`` (the shipped emulated one if None); one line and exit 2 if bad."""
    from afmctl.files.profile import default_profile, load_profile
    try:
        return default_profile() if path is None else load_profile(path)
    except FileFormatError as exc:
        fail(f"bad profile: {exc}")


def fit_settings(path: str | None):  # noqa: ANN201 (identify.Settings)
    """Identification settings from a profile: its ``[identify]`` table, and its ``[stack]``
    thickness for sweeps whose metadata gives none (defaults without a profile)."""
    from afmctl.files.profile import profile_table
    from afmctl.fit import identify as idf
    if path is None:
        return idf.Settings()
    prof = load_profile_or_exit(path)
    base = idf.Settings(fallback_thickness_um=prof.thickness_um)
    return idf.settings_from_table(profile_table(path).table("identify", required=False), base)


# ----------------------------------------------------------------------------------------------
# outputs: checked before any work; measured data never overwritten
# ----------------------------------------------------------------------------------------------


def _writable_folder(folder: Path, what: str) -> None:
    """Raise :class:`OutputError` unless a file can be created in ``folder`` (an existing folder)."""
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".afmctl-probe-"):
            pass
    except OSError as exc:
        raise OutputError(f"{what}: cannot write in {folder} ({exc.strerror or exc})") from None


def _existing_ancestor(path: Path, what: str) -> Path:
    """The nearest existing ancestor of ``path``; it must be a folder."""
    for parent in path.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise OutputError(f"{what}: {parent} is a file, not a folder")
            return parent
    raise OutputError(f"{what}: no existing folder above it")  # pragma: no cover (/ exists)


def check_output_file(path: str | Path, option: str, force: bool) -> Path:
    """Check that the file ``path`` may be written, before any work.

    An existing file is refused unless ``force``; a measured file (a sweep or run file) always.
    The folder must exist and be writable.
    """
    from afmctl.files.sweepfile import measured_kind
    p = Path(path)
    what = f"{option} {p}"
    if p.is_dir():
        raise OutputError(f"{what}: is a folder, not a file")
    if p.exists():
        kind = measured_kind(p)
        if kind:
            raise OutputError(f"{what}: holds measured data ({kind}); it is never overwritten, "
                              f"not even with --force")
        if not force:
            raise OutputError(f"{what}: exists; add --force to overwrite it")
    parent = p.absolute().parent
    if not parent.is_dir():
        _existing_ancestor(p, what)  # a file on the way is named as such
        raise OutputError(f"{what}: folder {p.parent} does not exist")
    _writable_folder(parent, what)
    return p


def check_output_dir(path: str | Path, option: str, names: Iterable[str], force: bool,
                     measured: Iterable[str] = ()) -> Path:
    """Check that the folder ``path`` may receive the files ``names`` (glob patterns), before any
    work. It is not created here. Files matching ``measured`` are never overwritten; other
    existing outputs are refused unless ``force``.
    """
    from afmctl.files.sweepfile import measured_kind
    p = Path(path)
    what = f"{option} {p}"
    if p.exists() and not p.is_dir():
        raise OutputError(f"{what}: exists and is not a folder")
    if not p.exists():
        _writable_folder(_existing_ancestor(p, what), what)
        return p
    for pattern in measured:
        for old in sorted(p.glob(pattern)):
            raise OutputError(f"{what}: already holds measured data ({old.name}); it is never "
                              f"overwritten: choose another folder")
    for pattern in names:
        for old in sorted(p.glob(pattern)):
            kind = measured_kind(old)
            if kind:
                raise OutputError(f"{what}: {old.name} holds measured data ({kind}); it is never "
                                  f"overwritten: choose another folder")
            if not force:
                raise OutputError(f"{what}: {old.name} exists; choose another folder or add "
                                  f"--force to overwrite it")
    _writable_folder(p, what)
    return p


def make_dir(path: Path, option: str) -> Path:
    """Create the output folder checked by :func:`check_output_dir` (exit 2 naming it if not)."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{option} {path}: cannot create ({exc.strerror or exc})") from None
    return path


@contextmanager
def writing(path: str | Path, option: str) -> Iterator[None]:
    """Turn an OSError while writing an output into :class:`OutputError` naming the path."""
    try:
        yield
    except OSError as exc:
        raise OutputError(f"{option} {path}: cannot write ({exc.strerror or exc})") from None


def timestamped(prefix: str) -> Path:
    """``./<prefix>-<YYYYmmdd-HHMMSS>``, the default output folder."""
    import time
    return Path(f"{prefix}-{time.strftime('%Y%m%d-%H%M%S')}")


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


def say(message: str) -> None:
    """A line of progress or human-readable results on stderr."""
    click.echo(message, err=True)


def say_no_twin(sweeps: Any) -> None:
    """Why no twin was written beside a model, when ``sweeps`` say when they started: one of
    the holds between them is not known (:func:`afmctl.files.sweepfile.holds_s`)."""
    from afmctl.files.sweepfile import HOLD_MAX_S
    if any(math.isfinite(s.started_s) for s in sweeps):
        say(f"no twin written: the sweeps do not say every hold between them (each needs "
            f"started_s, one sample rate, no overlap and at most {HOLD_MAX_S:g} s between two; "
            f"record them back to back): track starts the model at rest")

