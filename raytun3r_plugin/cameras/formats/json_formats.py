"""raytun3r JSON (what :func:`~raytun3r_plugin.cameras.formats.save` writes) and basalt calibration JSON."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from raytun3r_plugin._strict import quote
from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.cameras.formats._fields import (
    _SHORT,
    PathLike,
    _build,
    _camera_index,
    _fail,
    _get,
    _int,
    _num,
)
from raytun3r_plugin.cameras.kb import KannalaBrandt4
from raytun3r_plugin.cameras.pinhole import Pinhole
from raytun3r_plugin.cameras.serialisation import from_dict
from raytun3r_plugin.cameras.unified import EUCM, UCM, DoubleSphere
from raytun3r_plugin.errors import CameraError


def _read_own(path: PathLike, d: Mapping[str, Any], camera: str | int | None) -> Camera:
    if camera not in (None, 0, "0", "cam0"):
        raise _fail(
            path, "camera", f"unknown camera id {quote(camera, _SHORT)} (the file holds one camera)"
        )
    try:
        return from_dict(d)
    except CameraError as e:
        raise CameraError(f"{path}: {e}") from None


_BASALT = {
    "kb4": (KannalaBrandt4, ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    "ds": (DoubleSphere, ("fx", "fy", "cx", "cy", "xi", "alpha")),
    "eucm": (EUCM, ("fx", "fy", "cx", "cy", "alpha", "beta")),
    "ucm": (UCM, ("fx", "fy", "cx", "cy", "alpha")),
    "pinhole": (Pinhole, ("fx", "fy", "cx", "cy")),
}


def _read_basalt(path: PathLike, d: Mapping[str, Any], camera: str | int | None) -> Camera:
    v = d["value0"]
    intr = _get(path, v, "intrinsics", "value0.intrinsics")
    res = _get(path, v, "resolution", "value0.resolution")
    if not isinstance(intr, list) or not intr:
        raise _fail(path, "value0.intrinsics", "expected a non-empty list of cameras")
    i = _camera_index(path, camera, [f"cam{k}" for k in range(len(intr))])
    base = f"value0.intrinsics[{i}]"
    entry = intr[i]
    ctype = _get(path, entry, "camera_type", f"{base}.camera_type")
    if not isinstance(ctype, str) or ctype not in _BASALT:
        raise _fail(
            path,
            f"{base}.camera_type",
            f"unsupported camera type {quote(ctype, _SHORT)} (supported: {sorted(_BASALT)})",
        )
    cls, keys = _BASALT[ctype]
    block = _get(path, entry, "intrinsics", f"{base}.intrinsics")
    if not isinstance(block, Mapping):
        raise _fail(path, f"{base}.intrinsics", "expected an object of named parameters")
    extra = [k for k in block if k not in keys]
    if extra:
        raise _fail(
            path,
            f"{base}.intrinsics.{extra[0]}",
            f"unexpected parameter for {quote(ctype, _SHORT)} (expected {list(keys)})",
        )
    values = {
        k: _num(path, f"{base}.intrinsics.{k}", _get(path, block, k, f"{base}.intrinsics.{k}"))
        for k in keys
    }
    if not isinstance(res, list) or i >= len(res):
        raise _fail(path, f"value0.resolution[{i}]", "is missing")
    wh = res[i]
    if not isinstance(wh, (list, tuple)) or len(wh) != 2:
        raise _fail(
            path, f"value0.resolution[{i}]", f"expected [width, height], got {quote(wh, _SHORT)}"
        )
    w = _int(path, f"value0.resolution[{i}][0]", wh[0])
    h = _int(path, f"value0.resolution[{i}][1]", wh[1])
    return _build(path, cls, w, h, values, {k: f"{base}.intrinsics.{k}" for k in keys})
