"""The checkout's folders, for tests and benchmarks that read shipped or shared files."""

from __future__ import annotations

from pathlib import Path

#: The checkout's root (the folder holding ``pyproject.toml``).
REPO = Path(__file__).resolve().parents[2]
#: The shipped stage profiles (installed as ``afmctl.profiles``).
PROFILES = REPO / "profiles"
#: The benchmarks (a package: ``benchmarks.bench_track`` ...).
BENCHMARKS = REPO / "benchmarks"
#: Sweep sets shared beside the checkout (``../shared/data``), where present.
SHARED_DATA = REPO.parent / "shared" / "data"
