"""Every error afmctl raises on purpose, under one root: :class:`AfmctlError`.

A caller tells apart the few kinds it can act on; the command line maps each kind to an exit code by
its class (:mod:`afmctl.cli.base`):

=========================  ===========================================================  ====
kind                       what it means                                                exit
=========================  ===========================================================  ====
:class:`InputError`        bad input: an option, a value, a file's content              2
:class:`FileFormatError`   a file that is not what it claims (a sweep, a model ...)     2
:class:`OutputError`       an output that cannot or must not be written                 2
:class:`LimitError`        a waveform outside the stage's voltage, slew or current      2
:class:`ReachError`       a trajectory beyond what the stage can reach                 2
:class:`FrameReachError`   a raster frame beyond the stage's reach (names what fits)    2
:class:`EnvelopeError`     a waveform outside the model's validity envelope             2
:class:`StageError`        the stage or its link failed (a refusal, a timeout, a loss)  1
:class:`StageTimeoutError` the stage did not finish or answer within its bound          1
:class:`SamplesLostError`  a sweep lost samples (it is kept, marked; record it again)    1
:class:`StoppedError`      the run was stopped from elsewhere (another terminal's safe)  1
:class:`FitError`          a fit that did not converge                                  1
=========================  ===========================================================  ====

Anything else that escapes is a bug: the command line says so in one line and writes the traceback
to a file (or shows it with ``afmctl --debug``).

:class:`InputError` is also a :class:`ValueError` and :class:`StageError` a :class:`RuntimeError`,
so code written against the built-in kinds keeps working. The device's error codes (the table of
``docs/reference/protocol.md``, shared by both wire protocols) live here too, since both kinds of
stage error carry one. Nothing here imports anything.
"""

from __future__ import annotations

#: Error codes shared by both wire protocols (sticky until queried or cleared).
DEVICE_ERRORS: dict[int, str] = {
    0: "no error",
    1: "unknown command",
    2: "bad argument",
    3: "voltage outside limits",
    4: "slew limit exceeded",
    5: "busy: generator running",
    6: "index outside table or recorder",
    7: "read-only device",
    8: "watchdog expired: ramped to 0 V",
    9: "waveform table incomplete",
    10: "stream underrun: ramped to 0 V",
}


class AfmctlError(Exception):
    """The root of every error afmctl raises on purpose."""


class InputError(AfmctlError, ValueError):
    """Bad input: an option, a value or a file's content afmctl refuses (exit 2, one line)."""


class FileFormatError(InputError):
    """A file that cannot be read as what it claims to be (a profile, model, sweep or run file)."""


class SweepFormatError(FileFormatError):
    """A sweep file afmctl cannot read as ``time_s, voltage_V, displacement_um`` samples."""


class OutputError(InputError):
    """An output path that cannot or must not be written (measured data is never overwritten)."""


class LimitError(InputError):
    """A waveform the stage's profile forbids: voltage range, slew or current limit."""


class ReachError(LimitError):
    """A trajectory that asks for a displacement the model cannot give within the voltage limits
    (refused before anything moves, never clipped)."""


class FrameReachError(ReachError):
    """A raster frame beyond the stage's reach on either axis (refused before anything moves,
    naming the largest frame of the same shape that fits)."""


class EnvelopeError(InputError):
    """A waveform that leaves the model's validity envelope (the fields its sweeps covered)."""


class FitInputError(InputError):
    """Sweeps that cannot identify a model (too few, too short, too noisy, inconsistent)."""


class DiagnoseInputError(FitInputError):
    """Sweeps or a starting model that ``diagnose`` cannot work from."""


class LinkCapacityError(InputError):
    """A run the link cannot carry at the profile's sample rate (a slower rate or a faster wire)."""


class StageError(AfmctlError, RuntimeError):
    """The stage refused a command (``code`` from :data:`DEVICE_ERRORS`) or its link failed
    (``code`` -1: a transport or protocol failure, a lost or corrupt reply)."""

    def __init__(self, code: int, detail: str = "") -> None:
        what = DEVICE_ERRORS.get(code, "transport or protocol failure")
        super().__init__(f"stage error {code}: {what}" + (f" ({detail})" if detail else ""))
        self.code = code


class StageFailure(StageError):
    """A stage failure afmctl's host side describes in words (``code`` -1)."""

    def __init__(self, message: str) -> None:
        Exception.__init__(self, message)
        self.code = -1


class StageTimeoutError(StageFailure, TimeoutError):
    """The stage did not finish, or did not answer, within its bound."""


class SamplesLostError(StageFailure):
    """A recording that lost samples where none may be missing (a sweep: record it again)."""


class StoppedError(StageError):
    """The device stopped a run without an error of its own: something else told it to (another
    terminal's ``afmctl safe``, another host's stop or safe command). ``code`` is 0."""

    def __init__(self, detail: str) -> None:
        Exception.__init__(
            self, f"{detail}: the stage was stopped from elsewhere (another terminal's `afmctl "
                  f"safe`, or another host's stop or safe command; no error on the device)")
        self.code = 0


class LimitMismatchError(InputError):
    """The profile's ``[amplifier]`` limits go beyond the device's own (``LIM?``, the register
    map's limits): refused before anything moves, naming both."""


class FrameError(AfmctlError, ValueError):
    """A line of the serial protocol whose framing (tag, checksum) is broken."""


class DeviceError(AfmctlError):
    """The emulated device refuses a command; ``code`` is a key of :data:`DEVICE_ERRORS`."""

    def __init__(self, code: int, detail: str = "") -> None:
        super().__init__(f"error {code}: {DEVICE_ERRORS[code]}" + (f" ({detail})" if detail else ""))
        self.code = code


class FitError(AfmctlError, RuntimeError):
    """A fit that did not converge (the sweeps it was given are kept)."""
