"""COLMAP ``cameras.txt``: reading every COLMAP camera model raytun3r has a lens for, and writing
a camera as one line (pixel centres at +0.5 in COLMAP: cx, cy lose 0.5 on import and gain it on
export). :data:`COLMAP_EXPORT_MODEL` is the one table of which COLMAP model writes each raytun3r
model."""

from __future__ import annotations

import re
from collections.abc import Callable

from raytun3r_plugin._strict import quote
from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.cameras.fisheye624 import Fisheye624
from raytun3r_plugin.cameras.formats._fields import (
    _SHORT,
    PathLike,
    _build,
    _fail,
    _token_int,
    _token_num,
)
from raytun3r_plugin.cameras.fov import FOV
from raytun3r_plugin.cameras.kb import KannalaBrandt4, ThinPrismFisheye
from raytun3r_plugin.cameras.pinhole import OpenCVRadTan, Pinhole
from raytun3r_plugin.cameras.unified import EUCM
from raytun3r_plugin.errors import CameraError

_HALF = ("cx", "cy")

# COLMAP model -> (class, COLMAP parameter names, function to our {name: value}).
_COLMAP: dict[
    str, tuple[type[Camera], tuple[str, ...], Callable[[list[float]], dict[str, float]]]
] = {
    "SIMPLE_PINHOLE": (
        Pinhole,
        ("f", "cx", "cy"),
        lambda p: {"fx": p[0], "fy": p[0], "cx": p[1], "cy": p[2]},
    ),
    "PINHOLE": (
        Pinhole,
        ("fx", "fy", "cx", "cy"),
        lambda p: dict(zip(Pinhole.param_names, p, strict=True)),
    ),
    "SIMPLE_RADIAL": (
        OpenCVRadTan,
        ("f", "cx", "cy", "k"),
        lambda p: {
            "fx": p[0],
            "fy": p[0],
            "cx": p[1],
            "cy": p[2],
            "k1": p[3],
            "k2": 0.0,
            "p1": 0.0,
            "p2": 0.0,
        },
    ),
    "RADIAL": (
        OpenCVRadTan,
        ("f", "cx", "cy", "k1", "k2"),
        lambda p: {
            "fx": p[0],
            "fy": p[0],
            "cx": p[1],
            "cy": p[2],
            "k1": p[3],
            "k2": p[4],
            "p1": 0.0,
            "p2": 0.0,
        },
    ),
    "OPENCV": (
        OpenCVRadTan,
        OpenCVRadTan.param_names,
        lambda p: dict(zip(OpenCVRadTan.param_names, p, strict=True)),
    ),
    "OPENCV_FISHEYE": (
        KannalaBrandt4,
        KannalaBrandt4.param_names,
        lambda p: dict(zip(KannalaBrandt4.param_names, p, strict=True)),
    ),
    "THIN_PRISM_FISHEYE": (
        ThinPrismFisheye,
        ThinPrismFisheye.param_names,
        lambda p: dict(zip(ThinPrismFisheye.param_names, p, strict=True)),
    ),
    "EUCM": (EUCM, EUCM.param_names, lambda p: dict(zip(EUCM.param_names, p, strict=True))),
    "FOV": (FOV, FOV.param_names, lambda p: dict(zip(FOV.param_names, p, strict=True))),
    "RAD_TAN_THIN_PRISM_FISHEYE": (
        Fisheye624,
        Fisheye624.param_names,
        lambda p: dict(zip(Fisheye624.param_names, p, strict=True)),
    ),
    # COLMAP's equidistant family: theta_d = theta (1 + k1 theta^2 + k2 theta^4) on the angle
    # from the axis, i.e. Kannala-Brandt with the remaining coefficients zero (import only; a
    # KB4 camera exports as OPENCV_FISHEYE).
    "SIMPLE_FISHEYE": (KannalaBrandt4, ("f", "cx", "cy"), lambda p: _kb4(p[0], p[0], p[1], p[2])),
    "FISHEYE": (KannalaBrandt4, ("fx", "fy", "cx", "cy"), lambda p: _kb4(*p)),
    "SIMPLE_RADIAL_FISHEYE": (
        KannalaBrandt4,
        ("f", "cx", "cy", "k"),
        lambda p: _kb4(p[0], p[0], p[1], p[2], p[3]),
    ),
    "RADIAL_FISHEYE": (
        KannalaBrandt4,
        ("f", "cx", "cy", "k1", "k2"),
        lambda p: _kb4(p[0], p[0], p[1], p[2], p[3], p[4]),
    ),
}


def _kb4(fx: float, fy: float, cx: float, cy: float, *ks: float) -> dict[str, float]:
    """KannalaBrandt4 parameters from leading coefficients (the missing ones are zero)."""
    coefficients = [*ks, 0.0, 0.0, 0.0, 0.0][:4]
    return {
        "fx": fx,
        "fy": fy,
        "cx": cx,
        "cy": cy,
        **dict(zip(("k1", "k2", "k3", "k4"), coefficients, strict=True)),
    }


#: raytun3r model -> the COLMAP model that writes it (parameters in our order = COLMAP order).
COLMAP_EXPORT_MODEL = {
    "pinhole": "PINHOLE",
    "opencv": "OPENCV",
    "kb4": "OPENCV_FISHEYE",
    "thin_prism_fisheye": "THIN_PRISM_FISHEYE",
    "eucm": "EUCM",
    "fov": "FOV",
    "fisheye624": "RAD_TAN_THIN_PRISM_FISHEYE",
}

_COLMAP_LINE = re.compile(r"^\s*-?[0-9]{1,18}\s+[A-Z][A-Z0-9_]*\s")


def _looks_like_colmap(text: str) -> bool:
    rows = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    return bool(rows) and all(_COLMAP_LINE.match(ln + " ") for ln in rows)


def _read_colmap(path: PathLike, text: str, camera: str | int | None) -> Camera:
    rows: list[tuple[int, list[str]]] = []
    for n, ln in enumerate(text.splitlines(), start=1):
        if ln.strip() and not ln.lstrip().startswith("#"):
            rows.append((n, ln.split()))
    ids = [int(t[0]) for _n, t in rows]
    if camera is None:
        idx = 0
    else:
        want: int | None = None
        if isinstance(camera, int) and not isinstance(camera, bool):
            want = camera
        elif isinstance(camera, str) and re.fullmatch(r"\s*-?[0-9]{1,18}\s*", camera):
            want = int(camera)
        if want is None or want not in ids:
            raise _fail(
                path,
                "camera",
                f"unknown camera id {quote(camera, _SHORT)} (available: {quote(ids, _SHORT)})",
            )
        idx = ids.index(want)
    lineno, tok = rows[idx]
    where = f"camera {tok[0]} (line {lineno})"
    model = tok[1]
    if model not in _COLMAP:
        raise _fail(
            path,
            f"{where} MODEL",
            f"unsupported COLMAP camera model {quote(model, _SHORT)} (supported: {sorted(_COLMAP)})",
        )
    cls, names, convert = _COLMAP[model]
    if len(tok) < 4:
        raise _fail(path, f"{where} WIDTH HEIGHT", "is missing")
    w = _token_int(path, f"{where} WIDTH", tok[2])
    h = _token_int(path, f"{where} HEIGHT", tok[3])
    raw = tok[4:]
    if len(raw) != len(names):
        raise _fail(
            path,
            f"{where} PARAMS",
            f"{model} takes {len(names)} parameters {list(names)}, got {len(raw)}",
        )
    vals = [_token_num(path, f"{where} param {n}", v) for n, v in zip(names, raw, strict=True)]
    values = convert(vals)
    # COLMAP's pixel (0, 0) is the top-left corner of the image; ours is the first pixel centre.
    values["cx"] -= 0.5
    values["cy"] -= 0.5
    fields = {}
    for ours in cls.param_names:
        colmap_name = "f" if ours in ("fx", "fy") and "f" in names else ours
        if ours == "k1" and "k" in names:
            colmap_name = "k"
        fields[ours] = f"{where} param {colmap_name}"
    return _build(path, cls, w, h, values, fields)


def to_colmap_line(camera: Camera, camera_id: int, model: str | None = None) -> str:
    """One COLMAP ``cameras.txt`` line ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``.

    Adds 0.5 to cx, cy (COLMAP's pixel-centre convention) and writes floats with ``repr`` so
    that import followed by export reproduces the line. ``model`` may force ``SIMPLE_PINHOLE``
    (pinhole with fx == fy); by default pinhole -> PINHOLE, opencv -> OPENCV, kb4 ->
    OPENCV_FISHEYE, thin_prism_fisheye -> THIN_PRISM_FISHEYE, eucm -> EUCM, fov -> FOV,
    fisheye624 -> RAD_TAN_THIN_PRISM_FISHEYE.

    Raises:
        CameraError: the model has no COLMAP equivalent.
    """
    if not isinstance(camera, Camera):
        raise CameraError(f"to_colmap_line needs a Camera, got {type(camera).__name__}")
    if camera.model not in COLMAP_EXPORT_MODEL:
        raise CameraError(f"camera model {camera.model!r} has no COLMAP equivalent")
    if camera.max_fov_deg is not None:
        raise CameraError("COLMAP cannot store max_fov_deg; export a camera without it")
    v = camera.values
    v["cx"] += 0.5
    v["cy"] += 0.5
    name = model or COLMAP_EXPORT_MODEL[camera.model]
    if name == "SIMPLE_PINHOLE":
        if camera.model != "pinhole" or v["fx"] != v["fy"]:
            raise CameraError("SIMPLE_PINHOLE needs a pinhole camera with fx == fy")
        nums = [v["fx"], v["cx"], v["cy"]]
    elif name == COLMAP_EXPORT_MODEL[camera.model]:
        nums = [v[n] for n in camera.param_names]
    else:
        raise CameraError(f"cannot export a {camera.model!r} camera as COLMAP {name!r}")
    return " ".join(
        [str(int(camera_id)), name, str(camera.width), str(camera.height)]
        + [repr(float(x)) for x in nums]
    )
