"""The CLI maps afmctl's error kinds to exit codes by class (afmctl.errors), and an exception
afmctl did not raise on purpose is reported as a bug with its traceback kept, not hidden."""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import pytest
from click.testing import CliRunner

import afmctl.drivers
from afmctl import errors
from afmctl.cli import main


def _status_raising(monkeypatch: pytest.MonkeyPatch, exc: BaseException,
                    *args: str) -> tuple[int, str, BaseException | None]:
    def broken(profile: object) -> object:
        raise exc
    monkeypatch.setattr(afmctl.drivers, "open_stage", broken)
    res = CliRunner().invoke(main, [*args, "status"])
    return res.exit_code, res.stderr, res.exception


@pytest.mark.parametrize(("exc", "code", "line"), [
    (errors.InputError("bad value for --x"), 2, "afmctl: error: bad value for --x"),
    (errors.LimitError("sample 3 is 151 V, above 150 V"), 2, "afmctl: error: sample 3 is 151 V"),
    (errors.StageError(7, "SVA 5"), 1, "afmctl: error: stage: stage error 7: read-only device"),
    (errors.StageTimeoutError("run not done after 5 s"), 1, "afmctl: error: stage: run not done"),
    (errors.FitError("calibration fit did not converge"), 1, "afmctl: error: calibration fit"),
], ids=["input", "limit", "stage", "timeout", "fit"])
def test_each_kind_has_its_exit_code_and_one_line(monkeypatch: pytest.MonkeyPatch,
                                                  exc: Exception, code: int, line: str) -> None:
    exit_code, stderr, _ = _status_raising(monkeypatch, exc)
    assert exit_code == code and stderr.startswith(line) and stderr.count("\n") == 1


def test_a_bug_exits_1_saying_so_with_the_traceback_written(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # TMPDIR is read once, then cached
    exit_code, stderr, _ = _status_raising(monkeypatch, ZeroDivisionError("division by zero"))
    assert exit_code == 1 and stderr.count("\n") == 1
    assert "unexpected ZeroDivisionError: division by zero (a bug" in stderr
    where = Path(re.search(r"the traceback is in (\S+)\)", stderr).group(1))
    assert where.parent == tmp_path  # written to the temporary directory, and not left elsewhere
    text = where.read_text()
    assert "Traceback (most recent call last)" in text and "def broken" not in stderr
    assert "in broken" in text and "ZeroDivisionError: division by zero" in text


def test_debug_shows_the_bug_instead(monkeypatch: pytest.MonkeyPatch) -> None:
    exit_code, stderr, exc = _status_raising(monkeypatch, ZeroDivisionError("oops"), "--debug")
    assert isinstance(exc, ZeroDivisionError) and "unexpected" not in stderr


def test_a_real_oserror_is_not_mistaken_for_a_stage_failure(monkeypatch: pytest.MonkeyPatch,
                                                            tmp_path: Path) -> None:
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # TMPDIR is read once, then cached
    exit_code, stderr, _ = _status_raising(monkeypatch, OSError(28, "No space left on device"))
    assert exit_code == 1 and "stage:" not in stderr and "unexpected OSError" in stderr
