"""Twin files: where the model's twin of a stage was left (:mod:`afmctl.experiment.twin`).

``model.twin.json`` beside ``model.toml``: identify writes it from sweeps that say their holds
(``started_s``), ``track`` reads it, plans from it and writes it again after its runs, so that a
creeping stage's next run starts where the last one left the stage, in another process too. It
holds the model's state after the last sample played (hysteresis memory, rod, creep elements),
when that sample ended on the stage's clock, the output held since, the device's run counter
then (a later reading that differs: the stage ran something the twin did not see) and the
host's boot (the clock is the host's monotonic one). JSON::

    {"format": "afmctl-twin", "format_version": 1, "model_sha256": "...", "boot_id": "...",
     "run_count": 12, "ended_s": 5234.1, "held_V": 0.0, "dt_s": 1e-4,
     "state": {"kind": 1, "values": [...], "rod": [u, du], "creep": [...]},
     "observations": [[at_s, offset_um], ...]}

``observations`` (the readings of the recordings followed against the model,
:class:`afmctl.model.frame.Observation`) may be absent: none.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from afmctl.errors import FileFormatError

FORMAT, VERSION = "afmctl-twin", 1
FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Record:
    """A twin as the file holds it: the model's state arrays and where and when it was left.

    Parameters
    ----------
    model_sha256 : str
        Digest of the model file's bytes it belongs to.
    boot_id : str
        The host's boot (:func:`boot_id`).
    run_count : int or None
        The device's run counter after the last run the twin followed.
    ended_s, held_v, dt_s : float
        When the last sample ended (s, the stage's clock), the output held since (V), the
        sample period (s).
    kind : int
    values, rod, creep : ndarray
        The state (:class:`afmctl.model.transducer.StageState`'s arrays).
    observations : ndarray, shape (K, 2)
        Each observation's time (s, the stage's clock) and offset (um).
    """

    model_sha256: str
    boot_id: str
    run_count: int | None
    ended_s: float
    held_v: float
    dt_s: float
    kind: int
    values: FloatArray
    rod: FloatArray
    creep: FloatArray
    observations: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))


def path_for(model_path: str | Path) -> Path:
    """The twin file beside a model file: ``model.toml`` -> ``model.twin.json``."""
    p = Path(model_path)
    return p.with_name(p.stem + ".twin.json")


def digest(model_path: str | Path) -> str:
    """SHA-256 of the model file's bytes."""
    return hashlib.sha256(Path(model_path).read_bytes()).hexdigest()


def boot_id() -> str:
    """This host's boot (Linux's ``/proc/sys/kernel/random/boot_id``; "" elsewhere): the
    monotonic clock holds within one boot."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


def write(rec: Record, path: str | Path) -> None:
    """Write ``rec`` to ``path`` whole (a temporary file renamed over it)."""
    data = {"format": FORMAT, "format_version": VERSION, "model_sha256": rec.model_sha256,
            "boot_id": rec.boot_id, "run_count": rec.run_count, "ended_s": rec.ended_s,
            "held_V": rec.held_v, "dt_s": rec.dt_s,
            "state": {"kind": rec.kind, "values": rec.values.tolist(), "rod": rec.rod.tolist(),
                      "creep": rec.creep.tolist()},
            "observations": rec.observations.tolist()}
    tmp = Path(f"{path}.tmp")
    tmp.write_text(json.dumps(data) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def read(path: str | Path) -> Record:
    """The twin file at ``path``; :class:`~afmctl.errors.FileFormatError` if it is not one."""
    try:
        d: dict[str, Any] = json.loads(Path(path).read_text(encoding="utf-8"))
        if d.get("format") != FORMAT or d.get("format_version") != VERSION:
            raise ValueError(f"not an {FORMAT} file of version {VERSION}")
        st = d["state"]
        count = d["run_count"]
        return Record(str(d["model_sha256"]), str(d["boot_id"]),
                      None if count is None else int(count), float(d["ended_s"]),
                      float(d["held_V"]), float(d["dt_s"]), int(st["kind"]),
                      np.asarray(st["values"], float), np.asarray(st["rod"], float),
                      np.asarray(st["creep"], float),
                      np.asarray(d.get("observations", []), float).reshape(-1, 2))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise FileFormatError(f"{path}: not a twin file ({exc})") from exc
