"""Calibration file readers and writers.

``load(path, camera=...)`` detects the format from the file's content:

- raytun3r JSON (what :func:`save` writes): ``{"model", "width", "height", "params": {...}}``;
- basalt calibration JSON: ``{"value0": {"intrinsics": [...], "resolution": [...]}}``;
- OpenCV FileStorage YAML (``%YAML:1.0``, camodocal layout): KITTI-360 ``image_02.yaml`` /
  ``image_03.yaml`` (``model_type: MEI``), also camodocal ``PINHOLE`` and ``KANNALA_BRANDT``;
- Kalibr camchain YAML (``cam0: {camera_model, intrinsics, distortion_model, ...}``);
- COLMAP ``cameras.txt`` (pixel centres at +0.5 there: cx, cy lose 0.5 on import).

The format is decided from the parsed keys (``model_type`` -> camodocal/OpenCV, ``value0`` ->
basalt, ``camN.camera_model`` -> Kalibr, ``model`` -> raytun3r; COLMAP from its line shape),
never from the extension or the ``%YAML:1.0`` header line.

Every error is a :class:`CameraError` whose message starts with the file path and names the
offending field. Reading is bounded for any input: at most :data:`MAX_FILE_BYTES` read
(:data:`MAX_YAML_BYTES` for YAML), no YAML aliases, nesting at most :data:`MAX_DEPTH`, number
literals at most :data:`MAX_NUMBER_CHARS` characters, values in messages cut to ~80 characters.
See docs/cameras.md, "Calibration files: what is accepted".
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import yaml

from raytun3r_plugin._io import atomic_write_text
from raytun3r_plugin._strict import quote
from raytun3r_plugin.cameras.base import Camera, from_dict
from raytun3r_plugin.cameras.fisheye624 import Fisheye624
from raytun3r_plugin.cameras.fov import FOV
from raytun3r_plugin.cameras.kb import KannalaBrandt4, ThinPrismFisheye
from raytun3r_plugin.cameras.pinhole import OpenCVRadTan, Pinhole
from raytun3r_plugin.cameras.unified import EUCM, MEI, UCM, DoubleSphere
from raytun3r_plugin.errors import CameraError

__all__ = ["detect_format", "load", "save", "to_colmap_line"]

PathLike = str | os.PathLike


# ---------------------------------------------------------------------------- helpers
#: Largest calibration file read, in bytes. Real calibration files are a few KiB; the cap bounds
#: parse time and memory for any input.
MAX_FILE_BYTES = 1 << 20
#: Largest YAML text parsed, in bytes: PyYAML's pure-Python parser reads ~0.2 MB/s, so this
#: bounds a YAML file to ~0.3 s (a Kalibr camchain is ~1 KiB per camera).
MAX_YAML_BYTES = 64 << 10
#: Deepest nesting of lists/mappings accepted (Kalibr needs 4: cam0.T_cn_cnm1[i][j]).
MAX_DEPTH = 32
#: Longest number literal accepted, in characters (a float64 needs at most ~25).
MAX_NUMBER_CHARS = 64
_SHORT = 80


def _fail(path: PathLike, field: str, problem: str) -> CameraError:
    field = field if len(field) <= _SHORT else field[: _SHORT - 3] + "..."
    if len(problem) > 4 * _SHORT:
        problem = problem[: 4 * _SHORT - 3] + "..."
    return CameraError(f"{path}: field '{field}': {problem}")


def _num(path: PathLike, field: str, value: Any) -> float:
    """A float from a parsed file value: an int or float (bool is not a number, nor is a
    string; the YAML loader reads ``1e-05`` as a float). Non-finite values pass through and are
    rejected by the model, with the parameter's name."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        try:
            return float(value)
        except OverflowError:
            raise _fail(path, field, "number out of range") from None
    raise _fail(path, field, f"expected a number, got {quote(value, _SHORT)}")


def _token_num(path: PathLike, field: str, token: str) -> float:
    """A float from a text token (COLMAP)."""
    if len(token) <= MAX_NUMBER_CHARS:
        try:
            return float(token)
        except ValueError:
            pass
    raise _fail(path, field, f"expected a number, got {quote(token, _SHORT)}")


def _int(path: PathLike, field: str, value: Any) -> int:
    """A positive int; an integer-valued float (``640.0``) is accepted, a string is not."""
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
        raise _fail(path, field, f"expected a positive integer, got {quote(value, _SHORT)}")
    return value


def _token_int(path: PathLike, field: str, token: str) -> int:
    if re.fullmatch(r"[0-9]{1,9}", token):
        return _int(path, field, int(token))
    raise _fail(path, field, f"expected a positive integer, got {quote(token, _SHORT)}")


def _check_depth(path: PathLike, data: Any) -> None:
    """Refuse containers nested deeper than :data:`MAX_DEPTH` (iterative: no recursion)."""
    stack = [(data, 1)]
    while stack:
        v, depth = stack.pop()
        if isinstance(v, Mapping):
            children = list(v.values())
        elif isinstance(v, (list, tuple)):
            children = list(v)
        else:
            continue
        if depth > MAX_DEPTH:
            raise CameraError(f"{path}: nested deeper than {MAX_DEPTH} levels")
        stack.extend((c, depth + 1) for c in children)


def _get(path: PathLike, d: Mapping[str, Any], key: str, field: str) -> Any:
    if not isinstance(d, Mapping) or key not in d:
        raise _fail(path, field, "is missing")
    return d[key]


def _numbers(path: PathLike, value: Any, field: str, count: int, names: str) -> list[float]:
    if not isinstance(value, (list, tuple)):
        raise _fail(
            path, field, f"expected a list of {count} numbers [{names}], got {quote(value, _SHORT)}"
        )
    if len(value) != count:
        raise _fail(
            path,
            field,
            f"expected {count} values [{names}], got {len(value)}: {quote(value, _SHORT)}",
        )
    return [_num(path, f"{field}[{i}]", v) for i, v in enumerate(value)]


def _build(
    path: PathLike,
    cls: type[Camera],
    width: int,
    height: int,
    values: dict[str, float],
    fields: dict[str, str],
) -> Camera:
    """Construct the camera; a model-level error is re-raised naming the file field."""
    try:
        return cls(width, height, values)
    except CameraError as e:
        name = getattr(e, "param", None)
        field = fields.get(name, name) if name else "params"
        err = _fail(path, field, str(e))
        err.param = name  # type: ignore[attr-defined]
        raise err from None


def _camera_index(path: PathLike, camera: str | int | None, names: list[str]) -> int:
    """Index into ``names`` (e.g. ["cam0", "cam1"]) for ``camera`` given as name or index."""
    if camera is None:
        return 0
    if isinstance(camera, bool):
        raise _fail(path, "camera", f"unknown camera id {quote(camera, _SHORT)}")
    if isinstance(camera, int):
        if 0 <= camera < len(names):
            return camera
    elif isinstance(camera, str):
        if camera in names:
            return names.index(camera)
        m = re.fullmatch(r"(?:cam)?([0-9]{1,9})", camera.strip())
        if m and 0 <= int(m.group(1)) < len(names):
            return int(m.group(1))
    raise _fail(
        path,
        "camera",
        f"unknown camera id {quote(camera, _SHORT)} (available: {quote(names, _SHORT)})",
    )


# ---------------------------------------------------------------------------- raytun3r JSON
def _read_own(path: PathLike, d: Mapping[str, Any], camera: str | int | None) -> Camera:
    if camera not in (None, 0, "0", "cam0"):
        raise _fail(
            path, "camera", f"unknown camera id {quote(camera, _SHORT)} (the file holds one camera)"
        )
    try:
        return from_dict(d)
    except CameraError as e:
        raise CameraError(f"{path}: {e}") from None


# ---------------------------------------------------------------------------- basalt JSON
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


# ---------------------------------------------------------------------------- Kalibr YAML
def _read_kalibr(path: PathLike, d: Mapping[str, Any], camera: str | int | None) -> Camera:
    names = sorted((k for k in d if _is_cam_key(k)), key=lambda k: int(k[3:]))
    if camera is None:
        key = "cam0" if "cam0" in names else names[0]
    elif isinstance(camera, int) and not isinstance(camera, bool) and f"cam{camera}" in names:
        key = f"cam{camera}"
    elif isinstance(camera, str) and (camera in names or f"cam{camera}" in names):
        key = camera if camera in names else f"cam{camera}"
    else:
        raise _fail(
            path,
            "camera",
            f"unknown camera id {quote(camera, _SHORT)} (available: {quote(names, _SHORT)})",
        )
    c = d[key]
    if not isinstance(c, Mapping):
        raise _fail(path, key, "expected a mapping")
    cam_model = _get(path, c, "camera_model", f"{key}.camera_model")
    if not isinstance(cam_model, str):
        raise _fail(
            path, f"{key}.camera_model", f"expected a string, got {quote(cam_model, _SHORT)}"
        )
    dist_model = c.get("distortion_model", "none")
    if dist_model is None:
        dist_model = "none"
    if not isinstance(dist_model, str):
        raise _fail(
            path, f"{key}.distortion_model", f"expected a string, got {quote(dist_model, _SHORT)}"
        )
    # Kalibr's command line says "equi" for what its camchain files call "equidistant".
    dist_model = {"equi": "equidistant"}.get(dist_model, dist_model)
    res = _numbers(
        path,
        _get(path, c, "resolution", f"{key}.resolution"),
        f"{key}.resolution",
        2,
        "width height",
    )
    w = _int(path, f"{key}.resolution[0]", res[0])
    h = _int(path, f"{key}.resolution[1]", res[1])
    intr_field = f"{key}.intrinsics"
    raw_intr = _get(path, c, "intrinsics", intr_field)
    dist_field = f"{key}.distortion_coeffs"

    def dist(count: int, names: str) -> list[float]:
        return _numbers(
            path, _get(path, c, "distortion_coeffs", dist_field), dist_field, count, names
        )

    def no_dist() -> None:
        coeffs = c.get("distortion_coeffs", [])
        if coeffs is None:
            return
        if not isinstance(coeffs, list):
            raise _fail(path, dist_field, f"expected a list, got {quote(coeffs, _SHORT)}")
        if any(_num(path, f"{dist_field}[{i}]", x) != 0.0 for i, x in enumerate(coeffs)):
            raise _fail(path, dist_field, "must be empty for distortion_model 'none'")

    if dist_model not in ("none", "radtan", "equidistant"):
        raise _fail(
            path,
            f"{key}.distortion_model",
            f"unsupported distortion model {quote(dist_model, _SHORT)} (supported: none, radtan, equidistant)",
        )
    if cam_model == "pinhole":
        fu, fv, pu, pv = _numbers(path, raw_intr, intr_field, 4, "fu fv pu pv")
        base = {"fx": fu, "fy": fv, "cx": pu, "cy": pv}
        fields = {
            n: f"{intr_field}[{i}] ({k})"
            for i, (n, k) in enumerate(
                zip(("fx", "fy", "cx", "cy"), ("fu", "fv", "pu", "pv"), strict=True)
            )
        }
        if dist_model == "none":
            no_dist()
            return _build(path, Pinhole, w, h, base, fields)
        if dist_model == "radtan":
            k1, k2, r1, r2 = dist(4, "k1 k2 r1 r2")
            fields |= {
                n: f"{dist_field}[{i}] ({n})" for i, n in enumerate(("k1", "k2", "p1", "p2"))
            }
            return _build(
                path, OpenCVRadTan, w, h, base | {"k1": k1, "k2": k2, "p1": r1, "p2": r2}, fields
            )
        ks = dist(4, "k1 k2 k3 k4")
        fields |= {n: f"{dist_field}[{i}] ({n})" for i, n in enumerate(("k1", "k2", "k3", "k4"))}
        return _build(
            path,
            KannalaBrandt4,
            w,
            h,
            base | dict(zip(("k1", "k2", "k3", "k4"), ks, strict=True)),
            fields,
        )
    if cam_model == "omni":
        xi, fu, fv, pu, pv = _numbers(path, raw_intr, intr_field, 5, "xi fu fv pu pv")
        fields = {
            n: f"{intr_field}[{i}] ({k})"
            for i, (n, k) in enumerate(
                zip(("xi", "fx", "fy", "cx", "cy"), ("xi", "fu", "fv", "pu", "pv"), strict=True)
            )
        }
        if dist_model == "radtan":
            k1, k2, r1, r2 = dist(4, "k1 k2 r1 r2")
            fields |= {
                n: f"{dist_field}[{i}] ({n})" for i, n in enumerate(("k1", "k2", "p1", "p2"))
            }
            vals = {
                "fx": fu,
                "fy": fv,
                "cx": pu,
                "cy": pv,
                "xi": xi,
                "k1": k1,
                "k2": k2,
                "p1": r1,
                "p2": r2,
            }
            return _build(path, MEI, w, h, vals, fields)
        if dist_model == "none":
            no_dist()
            # xi form -> alpha form: alpha = xi / (1 + xi), f_alpha = f_xi / (1 + xi).
            if not (math.isfinite(xi) and xi >= 0.0):
                raise _fail(
                    path, fields["xi"], f"must be a finite number >= 0, got {quote(xi, _SHORT)}"
                )
            vals = {
                "fx": fu / (1.0 + xi),
                "fy": fv / (1.0 + xi),
                "cx": pu,
                "cy": pv,
                "alpha": xi / (1.0 + xi),
            }
            return _build(path, UCM, w, h, vals, fields | {"alpha": fields["xi"]})
        raise _fail(
            path,
            f"{key}.distortion_model",
            "camera_model 'omni' supports distortion_model none or radtan",
        )
    if cam_model in ("ds", "eucm"):
        if dist_model != "none":
            raise _fail(
                path,
                f"{key}.distortion_model",
                f"camera_model {quote(cam_model, _SHORT)} supports distortion_model none only",
            )
        no_dist()
        first = ("xi", "alpha") if cam_model == "ds" else ("alpha", "beta")
        vals6 = _numbers(path, raw_intr, intr_field, 6, f"{first[0]} {first[1]} fu fv pu pv")
        order = (*first, "fx", "fy", "cx", "cy")
        fields = {n: f"{intr_field}[{i}] ({n})" for i, n in enumerate(order)}
        cls = DoubleSphere if cam_model == "ds" else EUCM
        return _build(path, cls, w, h, dict(zip(order, vals6, strict=True)), fields)
    raise _fail(
        path,
        f"{key}.camera_model",
        f"unsupported camera model {quote(cam_model, _SHORT)} (supported: pinhole, omni, ds, eucm)",
    )


# ---------------------------------------------------------------------------- YAML
class _CalibLoader(yaml.SafeLoader):
    """Bounded SafeLoader for calibration YAML (Kalibr, OpenCV FileStorage / camodocal).

    - Aliases are refused outright: neither Kalibr nor OpenCV FileStorage writes them, and
      refusing them rules out alias bombs ("billion laughs") and merge keys.
    - Nesting deeper than :data:`MAX_DEPTH` is refused while composing (before recursion).
    - Number literals longer than :data:`MAX_NUMBER_CHARS` are refused before ``int()``.
    - ``1e-05`` (no dot) and ``1.0e5`` (no exponent sign) are floats, as in YAML 1.2 (YAML 1.1
      would read them as strings; Kalibr writes such numbers).
    - OpenCV's ``!!opencv-matrix`` nodes are read as plain mappings.
    """

    _depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:  # noqa: D102 - PyYAML hook
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None, None, "YAML aliases are not accepted in calibration files", event.start_mark
            )
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise yaml.composer.ComposerError(
                    None,
                    None,
                    f"nested deeper than {MAX_DEPTH} levels",
                    self.peek_event().start_mark,
                )
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_yaml_int(self, node: yaml.ScalarNode) -> int:  # noqa: D102
        if len(node.value) > MAX_NUMBER_CHARS:
            raise yaml.constructor.ConstructorError(
                None, None, f"integer longer than {MAX_NUMBER_CHARS} characters", node.start_mark
            )
        return super().construct_yaml_int(node)

    def construct_yaml_float(self, node: yaml.ScalarNode) -> float:  # noqa: D102
        if len(node.value) > MAX_NUMBER_CHARS:
            raise yaml.constructor.ConstructorError(
                None, None, f"number longer than {MAX_NUMBER_CHARS} characters", node.start_mark
            )
        return super().construct_yaml_float(node)


_CalibLoader.add_constructor("tag:yaml.org,2002:int", _CalibLoader.construct_yaml_int)
_CalibLoader.add_constructor("tag:yaml.org,2002:float", _CalibLoader.construct_yaml_float)
_CalibLoader.add_constructor(
    "tag:yaml.org,2002:opencv-matrix",
    lambda loader, node: loader.construct_mapping(node, deep=True),
)
_CalibLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def _parse_yaml(path: PathLike, text: str) -> Any:
    if len(text.encode("utf-8")) > MAX_YAML_BYTES:
        raise CameraError(
            f"{path}: YAML calibration file larger than {MAX_YAML_BYTES} bytes; not a calibration"
        )
    lines = text.splitlines()
    # PyYAML does not understand the "%YAML:1.0" directive OpenCV writes (nor does it need it).
    if lines and lines[0].lstrip().startswith("%YAML:"):
        lines = lines[1:]
    # OpenCV may write "key:value"; YAML needs a space after the colon of a key.
    fixed = [re.sub(r"^(\s*[A-Za-z_][\w.\-]*):(?=[^\s:/])", r"\1: ", ln) for ln in lines]
    try:
        return yaml.load("\n".join(fixed), Loader=_CalibLoader)  # noqa: S506 - SafeLoader subclass
    except yaml.YAMLError as e:
        msg = str(e)
        if len(msg) > 4 * _SHORT:
            msg = msg[: 4 * _SHORT - 3] + "..."
        raise CameraError(f"{path}: not a valid YAML file: {msg}") from None


def _is_cam_key(k: Any) -> bool:
    return isinstance(k, str) and re.fullmatch(r"cam[0-9]{1,6}", k) is not None


_CAMODOCAL: dict[str, tuple[type[Camera], list[tuple[str, str, str]]]] = {
    # model_type -> (class, [(our name, group, file name)])
    "MEI": (
        MEI,
        [
            ("xi", "mirror_parameters", "xi"),
            ("k1", "distortion_parameters", "k1"),
            ("k2", "distortion_parameters", "k2"),
            ("p1", "distortion_parameters", "p1"),
            ("p2", "distortion_parameters", "p2"),
            ("fx", "projection_parameters", "gamma1"),
            ("fy", "projection_parameters", "gamma2"),
            ("cx", "projection_parameters", "u0"),
            ("cy", "projection_parameters", "v0"),
        ],
    ),
    "PINHOLE": (
        OpenCVRadTan,
        [
            ("k1", "distortion_parameters", "k1"),
            ("k2", "distortion_parameters", "k2"),
            ("p1", "distortion_parameters", "p1"),
            ("p2", "distortion_parameters", "p2"),
            ("fx", "projection_parameters", "fx"),
            ("fy", "projection_parameters", "fy"),
            ("cx", "projection_parameters", "cx"),
            ("cy", "projection_parameters", "cy"),
        ],
    ),
    # camodocal's EquidistantCamera names the same four coefficients k2..k5.
    "KANNALA_BRANDT": (
        KannalaBrandt4,
        [
            ("k1", "projection_parameters", "k2"),
            ("k2", "projection_parameters", "k3"),
            ("k3", "projection_parameters", "k4"),
            ("k4", "projection_parameters", "k5"),
            ("fx", "projection_parameters", "mu"),
            ("fy", "projection_parameters", "mv"),
            ("cx", "projection_parameters", "u0"),
            ("cy", "projection_parameters", "v0"),
        ],
    ),
}


def _read_camodocal(path: PathLike, d: Mapping[str, Any], camera: str | int | None) -> Camera:
    name = d.get("camera_name")
    if camera not in (None, 0, "0") and camera != name:
        raise _fail(
            path,
            "camera",
            f"unknown camera id {quote(camera, _SHORT)} (the file holds {quote(name, _SHORT)})",
        )
    mt = d["model_type"]
    key = mt.upper() if isinstance(mt, str) else None
    if key not in _CAMODOCAL:
        raise _fail(
            path,
            "model_type",
            f"unsupported model type {quote(mt, _SHORT)} (supported: {sorted(_CAMODOCAL)})",
        )
    cls, spec = _CAMODOCAL[key]
    w = _int(path, "image_width", _get(path, d, "image_width", "image_width"))
    h = _int(path, "image_height", _get(path, d, "image_height", "image_height"))
    groups: dict[str, set[str]] = {}
    for _n, g, f in spec:
        groups.setdefault(g, set()).add(f)
    for g, allowed in groups.items():
        block = _get(path, d, g, g)
        if not isinstance(block, Mapping):
            raise _fail(path, g, "expected a mapping")
        extra = [k for k in block if k not in allowed]
        if extra:
            raise _fail(
                path,
                f"{g}.{extra[0]}",
                f"unexpected parameter for model_type {quote(mt, _SHORT)} (expected {sorted(allowed)})",
            )
    values = {n: _num(path, f"{g}.{f}", _get(path, d[g], f, f"{g}.{f}")) for n, g, f in spec}
    # camodocal files also hold camera_name (a string); other top-level keys are ignored.
    return _build(path, cls, w, h, values, {n: f"{g}.{f}" for n, g, f in spec})


# ---------------------------------------------------------------------------- COLMAP
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


# Our model -> the COLMAP model used on export (parameters in our order = COLMAP order).
_COLMAP_EXPORT = {
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
    if camera.model not in _COLMAP_EXPORT:
        raise CameraError(f"camera model {camera.model!r} has no COLMAP equivalent")
    if camera.max_fov_deg is not None:
        raise CameraError("COLMAP cannot store max_fov_deg; export a camera without it")
    v = camera.values
    v["cx"] += 0.5
    v["cy"] += 0.5
    name = model or _COLMAP_EXPORT[camera.model]
    if name == "SIMPLE_PINHOLE":
        if camera.model != "pinhole" or v["fx"] != v["fy"]:
            raise CameraError("SIMPLE_PINHOLE needs a pinhole camera with fx == fy")
        nums = [v["fx"], v["cx"], v["cy"]]
    elif name == _COLMAP_EXPORT[camera.model]:
        nums = [v[n] for n in camera.param_names]
    else:
        raise CameraError(f"cannot export a {camera.model!r} camera as COLMAP {name!r}")
    return " ".join(
        [str(int(camera_id)), name, str(camera.width), str(camera.height)]
        + [repr(float(x)) for x in nums]
    )


# ---------------------------------------------------------------------------- entry points
def detect_format(path: PathLike) -> str:
    """Name of the calibration format of ``path``: ``raytun3r``, ``basalt``, ``opencv_yaml``,
    ``kalibr`` or ``colmap``, decided from the parsed content (keys), never from the extension
    or the ``%YAML`` header line (raises :class:`CameraError` if none fits)."""
    return _parse(Path(path))[0]


def _read_text(path: Path) -> str:
    """The file as UTF-8 text, at most :data:`MAX_FILE_BYTES` bytes."""
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)
    except OSError as e:
        raise CameraError(f"{path}: cannot read calibration file: {e.strerror or e}") from None
    if len(raw) > MAX_FILE_BYTES:
        raise CameraError(
            f"{path}: calibration file larger than {MAX_FILE_BYTES} bytes; not a calibration"
        )
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise CameraError(f"{path}: not UTF-8 text (byte {e.start})") from None
    if text.startswith("\ufeff"):  # a byte-order mark some editors write
        text = text[1:]
    if "\x00" in text:
        raise CameraError(f"{path}: not a text file (NUL byte)")
    return text


def _json_number(path: PathLike, kind: str) -> Callable[[str], Any]:
    """``json.loads`` hook: refuse a number literal longer than :data:`MAX_NUMBER_CHARS` before
    ``int()`` / ``float()`` sees it (Python 3.11 refuses ints over 4300 digits only after
    spending time on them, and with a ValueError)."""

    def parse(s: str) -> Any:
        if len(s) > MAX_NUMBER_CHARS:
            raise CameraError(f"{path}: JSON {kind} longer than {MAX_NUMBER_CHARS} characters")
        return int(s) if kind == "integer" else float(s)

    return parse


def _classify(d: Any) -> str | None:
    """Format name from the top-level keys of parsed JSON/YAML, or None."""
    if not isinstance(d, Mapping):
        return None
    if "model_type" in d:
        return "opencv_yaml"
    if "value0" in d:
        return "basalt"
    if any(_is_cam_key(k) and isinstance(v, Mapping) and "camera_model" in v for k, v in d.items()):
        return "kalibr"
    if "model" in d:
        return "raytun3r"
    return None


def _parse(path: Path) -> tuple[str, Any]:
    text = _read_text(path)
    head = text.lstrip()
    if head.startswith(("{", "[")):
        try:
            d = json.loads(
                text,
                parse_int=_json_number(path, "integer"),
                parse_float=_json_number(path, "number"),
            )
        except RecursionError:
            raise CameraError(f"{path}: not valid JSON: nested too deeply") from None
        except ValueError as e:  # JSONDecodeError is a ValueError, as are the number limits
            raise CameraError(f"{path}: not valid JSON: {str(e)[: 4 * _SHORT]}") from None
    elif _looks_like_colmap(text):
        return "colmap", text
    else:
        d = _parse_yaml(path, text)
    _check_depth(path, d)
    kind = _classify(d)
    if kind is None:
        keys = sorted(str(k) for k in d)[:8] if isinstance(d, Mapping) else None
        found = (
            f"top-level keys {quote(keys, _SHORT)}"
            if keys is not None
            else quote(type(d).__name__, _SHORT)
        )
        raise CameraError(
            f"{path}: unknown calibration format, found {found} (expected raytun3r JSON 'model', "
            "basalt 'value0', Kalibr 'cam0.camera_model', camodocal/OpenCV 'model_type', or "
            "COLMAP cameras.txt lines)"
        )
    return kind, d


def load(path: PathLike, camera: str | int | None = None) -> Camera:
    """Read a camera from a calibration file, detecting the format from its content.

    Args:
        path: the file.
        camera: which camera of a multi-camera file: Kalibr ``"cam1"`` or ``1`` (default cam0),
            basalt index (default 0), COLMAP camera id (default: the first line). Single-camera
            formats accept ``None``/``0`` (and KITTI-360 its ``camera_name``).

    Raises:
        CameraError: unreadable or unknown format, missing/extra fields, bad values, unknown
            camera id. The message names the file and the field.
    """
    p = Path(path)
    kind, data = _parse(p)
    if kind == "raytun3r":
        return _read_own(p, data, camera)
    if kind == "basalt":
        return _read_basalt(p, data, camera)
    if kind == "opencv_yaml":
        return _read_camodocal(p, data, camera)
    if kind == "kalibr":
        return _read_kalibr(p, data, camera)
    return _read_colmap(p, data, camera)


def save(camera: Camera, path: PathLike) -> None:
    """Write ``camera`` as raytun3r JSON (``camera.to_json()``), atomically (temp file + rename)."""
    if not isinstance(camera, Camera):
        raise CameraError(f"save needs a Camera, got {type(camera).__name__}")
    atomic_write_text(path, camera.to_json() + "\n")
