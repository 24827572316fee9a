"""Checked reading and plain writing of the TOML files afmctl uses (model files, profiles).

Every failure raises :class:`FileFormatError` whose message names the file and the dotted key, so
the CLI can print it as one line and exit 2.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from afmctl.errors import FileFormatError


@dataclass(frozen=True)
class Table:
    """A TOML table with typed, validated access. ``where`` is ``file: dotted.path``."""

    data: Mapping[str, Any]
    where: str
    _read: set[str] = field(default_factory=set, repr=False, compare=False)
    _children: list[Table] = field(default_factory=list, repr=False, compare=False)

    def reject_unknown(self, ignore: tuple[str, ...] = ()) -> None:
        """FileFormatError naming the first key that no reader asked for (a misspelt key must
        not silently become its default), in this table and every sub-table read."""
        for key in self.data:
            if key not in self._read and key not in ignore:
                raise self.fail(key, "unknown key (misspelt?)")
        for child in self._children:
            child.reject_unknown()

    def _key(self, key: str) -> str:
        return f"{self.where}.{key}" if not self.where.endswith(":") else f"{self.where} {key}"

    def fail(self, key: str, what: str) -> FileFormatError:
        return FileFormatError(f"{self._key(key)}: {what}")

    def check_format(self, name: str, version: int) -> None:
        """Require ``format = name`` and ``format_version = version`` (the file-type header)."""
        fmt = self.string("format")
        if fmt != name:
            raise self.fail("format", f"expected {name!r}, got {fmt!r}")
        ver = self.integer("format_version")
        if ver != version:
            raise self.fail("format_version", f"this afmctl reads version {version}, got {ver}")

    def has(self, key: str) -> bool:
        self._read.add(key)
        return key in self.data

    def table(self, key: str, required: bool = True) -> Table | None:
        if key not in self.data:
            if required:
                raise self.fail(key, "missing table")
            return None
        val = self.data[key]
        if not isinstance(val, Mapping):
            raise self.fail(key, f"expected a table, got {type(val).__name__}")
        self._read.add(key)
        child = Table(val, self._key(key))
        self._children.append(child)
        return child

    def number(self, key: str, default: float | None = None, *, positive: bool = False,
               nonnegative: bool = False) -> float:
        self._read.add(key)
        if key not in self.data:
            if default is None:
                raise self.fail(key, "missing key")
            return default
        val = self.data[key]
        if isinstance(val, bool) or not isinstance(val, (int, float)):
            raise self.fail(key, f"expected a number, got {type(val).__name__} {val!r}")
        val = float(val)
        if not math.isfinite(val):
            raise self.fail(key, f"must be finite, got {val}")
        if positive and val <= 0:
            raise self.fail(key, f"must be > 0, got {val}")
        if nonnegative and val < 0:
            raise self.fail(key, f"must be >= 0, got {val}")
        return val

    def integer(self, key: str, default: int | None = None, *, minimum: int = 0) -> int:
        self._read.add(key)
        if key not in self.data:
            if default is None:
                raise self.fail(key, "missing key")
            return default
        val = self.data[key]
        if isinstance(val, bool) or not isinstance(val, int):
            raise self.fail(key, f"expected an integer, got {type(val).__name__} {val!r}")
        if val < minimum:
            raise self.fail(key, f"must be >= {minimum}, got {val}")
        return val

    def string(self, key: str, default: str | None = None,
               choices: tuple[str, ...] | None = None) -> str:
        self._read.add(key)
        if key not in self.data:
            if default is None:
                raise self.fail(key, "missing key")
            return default
        val = self.data[key]
        if not isinstance(val, str):
            raise self.fail(key, f"expected a string, got {type(val).__name__} {val!r}")
        if choices is not None and val not in choices:
            raise self.fail(key, f"must be one of {', '.join(choices)}, got {val!r}")
        return val

    def boolean(self, key: str, default: bool = False) -> bool:
        self._read.add(key)
        val = self.data.get(key, default)
        if not isinstance(val, bool):
            raise self.fail(key, f"expected true or false, got {val!r}")
        return val

    def numbers(self, key: str) -> tuple[float, ...]:
        self._read.add(key)
        val = self.data.get(key)
        if not isinstance(val, list) or not val:
            raise self.fail(key, "expected a non-empty array of numbers")
        out = []
        for i, x in enumerate(val):
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                raise self.fail(key, f"element {i} is not a finite number: {x!r}")
            out.append(float(x))
        return tuple(out)


def load(path: str | Path) -> Table:
    """Parse a TOML file into a :class:`Table` (FileFormatError on any read or syntax error)."""
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise FileFormatError(f"{p}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise FileFormatError(f"{p}: cannot read as UTF-8 text ({exc.__class__.__name__})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise FileFormatError(f"{p}: not valid TOML ({exc})") from None
    return Table(data, f"{p}:")


def _value(v: Any) -> str:
    if isinstance(v, bool | np.bool_):
        return "true" if v else "false"
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        return repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dumps(data: Mapping[str, Any], prefix: str = "") -> str:
    """Serialize nested dicts of numbers, strings, booleans and arrays (the subset afmctl writes)."""
    scalars = [f"{k} = {_value(v)}" for k, v in data.items() if not isinstance(v, Mapping)]
    lines = [f"[{prefix}]"] if prefix and scalars else []
    lines += scalars
    out = "\n".join(lines) + ("\n" if lines else "")
    for k, v in data.items():
        if isinstance(v, Mapping):
            out += "\n" + dumps(v, f"{prefix}.{k}" if prefix else k)
    return out
