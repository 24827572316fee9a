"""Gwyddion files (``.gwy``): the images of a raster scan, for the tool labs open them in.

Written with the ``gwyfile`` package (MIT, numpy only): one data field per channel in a
``GwyContainer``, under ``/<n>/data`` with its title at ``/<n>/data/title``, lateral and value
units in metres (SI, as Gwyddion expects), the frame's size and offset in metres. A pixel that
was not measured (NaN) is stored as the channel's mean and marked in the channel's mask
(``/<n>/mask``, 1 where missing), Gwyddion's way of flagging bad data. Metadata (the scan's
settings, the software version) go to ``/<n>/meta`` as strings.

Rows are as the images' (row 0 at the lowest slow coordinate); Gwyddion draws row 0 at the top.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from gwyfile.objects import GwyContainer, GwyDataField
from numpy.typing import NDArray

from afmctl._version import __version__
from afmctl.errors import FileFormatError

UM = 1e-6  # metres per um


def _field(image_um: NDArray[np.float64], size_um: tuple[float, float],
           offset_um: tuple[float, float]) -> GwyDataField:
    data = np.ascontiguousarray(image_um, dtype=float) * UM
    return GwyDataField(data, xreal=size_um[0] * UM, yreal=size_um[1] * UM,
                        xoff=offset_um[0] * UM, yoff=offset_um[1] * UM,
                        si_unit_xy="m", si_unit_z="m")


def container(channels: Mapping[str, NDArray[np.float64]], size_um: tuple[float, float],
              offset_um: tuple[float, float] = (0.0, 0.0),
              meta: Mapping[str, object] | None = None) -> GwyContainer:
    """A Gwyddion container of ``channels`` (title -> image in um, shape (rows, columns)).

    Parameters
    ----------
    channels : mapping of str to ndarray
        Images in um, by title (e.g. ``inverse: error x trace``).
    size_um : tuple of float
        Frame width and height, um (the height of a one-line frame: its line pitch).
    offset_um : tuple of float
        The frame's lower-left corner, um.
    meta : mapping, optional
        Key-value metadata stored with every channel (as strings).
    """
    obj = GwyContainer()
    info = {"software": f"afmctl {__version__}", **{k: str(v) for k, v in (meta or {}).items()}}
    for n, (title, img) in enumerate(channels.items()):
        img = np.asarray(img, dtype=float)
        bad = ~np.isfinite(img)
        fill = float(np.mean(img[~bad])) if (~bad).any() else 0.0
        obj[f"/{n}/data"] = _field(np.where(bad, fill, img), size_um, offset_um)
        obj[f"/{n}/data/title"] = title
        obj.typecodes[f"/{n}/data/title"] = "s"  # a one-letter str is a char to gwyfile
        obj[f"/{n}/meta"] = GwyContainer(info, typecodes=dict.fromkeys(info, "s"))
        if bad.any():
            obj[f"/{n}/mask"] = GwyDataField(bad.astype(float), xreal=size_um[0] * UM,
                                             yreal=size_um[1] * UM, si_unit_xy="m")
    return obj


def write(path: str | Path, channels: Mapping[str, NDArray[np.float64]],
          size_um: tuple[float, float], offset_um: tuple[float, float] = (0.0, 0.0),
          meta: Mapping[str, object] | None = None) -> Path:
    """Write ``channels`` to the ``.gwy`` file ``path`` (replaced atomically; see
    :func:`container` for the arguments)."""
    p = Path(path)
    tmp = p.with_name(p.name + ".partial")
    container(channels, size_um, offset_um, meta).tofile(str(tmp))
    os.replace(tmp, p)
    return p


def read(path: str | Path) -> dict[str, NDArray[np.float64]]:
    """The channels of a ``.gwy`` file, by title, in um (masked pixels as NaN)."""
    import gwyfile

    try:
        obj = gwyfile.load(str(path))
    except Exception as exc:  # gwyfile raises bare ValueError/struct errors on a bad file
        raise FileFormatError(f"{path}: not a Gwyddion file ({exc})") from None
    out = {}
    for key in sorted((k for k in obj if k.endswith("/data") and k.count("/") == 2),
                      key=lambda k: int(k.split("/")[1])):
        img = np.asarray(obj[key].data, dtype=float) / UM
        mask = obj.get(key.replace("/data", "/mask"))
        if mask is not None:
            img = np.where(np.asarray(mask.data) > 0.5, np.nan, img)
        out[str(obj.get(key + "/title", key))] = img
    return out
