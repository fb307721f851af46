"""Bounded YAML parsing for calibration files, and OpenCV FileStorage / camodocal YAML
(KITTI-360 ``image_02.yaml``: ``model_type: MEI``; camodocal ``PINHOLE`` and ``KANNALA_BRANDT``)."""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import yaml

from raytun3r_plugin._strict import quote
from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.cameras.formats._fields import (
    _SHORT,
    MAX_DEPTH,
    MAX_NUMBER_CHARS,
    MAX_YAML_BYTES,
    PathLike,
    _build,
    _fail,
    _get,
    _int,
    _num,
)
from raytun3r_plugin.cameras.kb import KannalaBrandt4
from raytun3r_plugin.cameras.pinhole import OpenCVRadTan
from raytun3r_plugin.cameras.unified import MEI
from raytun3r_plugin.errors import CameraError


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
