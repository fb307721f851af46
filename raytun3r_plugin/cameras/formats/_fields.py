"""What every calibration reader shares: the reading limits, number and field checks, and the
error that names the file and the field (docs/cameras.md, "Calibration files: what is
accepted")."""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from typing import Any

from raytun3r_plugin._strict import quote
from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.errors import CameraError

PathLike = str | os.PathLike


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
