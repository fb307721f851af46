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
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from raytun3r_plugin._strict import quote
from raytun3r_plugin.atomic_files import atomic_write_text
from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.cameras.formats._fields import (
    _SHORT,
    MAX_DEPTH,
    MAX_FILE_BYTES,
    MAX_NUMBER_CHARS,
    MAX_YAML_BYTES,
    PathLike,
    _check_depth,
)
from raytun3r_plugin.cameras.formats.colmap import (
    COLMAP_EXPORT_MODEL,
    _looks_like_colmap,
    _read_colmap,
    to_colmap_line,
)
from raytun3r_plugin.cameras.formats.json_formats import _read_basalt, _read_own
from raytun3r_plugin.cameras.formats.kalibr import _read_kalibr
from raytun3r_plugin.cameras.formats.yaml_formats import _is_cam_key, _parse_yaml, _read_camodocal
from raytun3r_plugin.errors import CameraError

__all__ = [
    "COLMAP_EXPORT_MODEL",
    "MAX_DEPTH",
    "MAX_FILE_BYTES",
    "MAX_NUMBER_CHARS",
    "MAX_YAML_BYTES",
    "detect_format",
    "load",
    "save",
    "to_colmap_line",
]


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
