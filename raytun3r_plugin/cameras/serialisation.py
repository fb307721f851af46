"""The dict form of a camera: the registry of models by name and :func:`from_dict`.

Every concrete model class registers itself in :data:`CAMERA_MODELS` when it is defined (see
``Camera.__init_subclass__``); :func:`from_dict` dispatches a ``Camera.to_dict`` description on
its ``"model"`` field. JSON text and the calibration file formats build on this.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from raytun3r_plugin._strict import quote
from raytun3r_plugin.errors import CameraError

if TYPE_CHECKING:  # annotations only: base.py imports this module
    from raytun3r_plugin.cameras.base import Camera

__all__ = ["CAMERA_MODELS", "from_dict"]

#: Registry of concrete models by their ``model`` name ("pinhole", "kb4", ...).
CAMERA_MODELS: dict[str, type[Camera]] = {}

_DICT_KEYS = {"model", "width", "height", "params", "max_fov_deg"}


def from_dict(d: Mapping[str, Any]) -> Camera:
    """Build a camera from :meth:`Camera.to_dict` output (dispatch on ``"model"``).

    Raises:
        CameraError: not a mapping, unknown model, missing/extra keys, bad parameters.
    """
    if not isinstance(d, Mapping):
        raise CameraError(f"camera description must be a JSON object, got {type(d).__name__}")
    for k in ("model", "width", "height", "params"):
        if k not in d:
            raise CameraError(f"camera description: field '{k}' is missing")
    extra = sorted(str(k) for k in d if k not in _DICT_KEYS)
    if extra:
        raise CameraError(f"camera description: unexpected field '{extra[0]}'")
    model = d["model"]
    # A list or dict here is unhashable: test the type before the dict lookup.
    if not isinstance(model, str) or model not in CAMERA_MODELS:
        raise CameraError(
            f"camera description: field 'model': unknown camera model {quote(model)} "
            f"(known: {sorted(CAMERA_MODELS)})"
        )
    params = d["params"]
    if not isinstance(params, Mapping):
        raise CameraError("camera description: field 'params' must be an object {name: value}")
    try:
        return CAMERA_MODELS[model](
            d["width"], d["height"], params, max_fov_deg=d.get("max_fov_deg")
        )
    except CameraError as e:
        p = getattr(e, "param", None)
        if p is None:
            raise
        err = CameraError(f"camera description: field 'params.{p}': {e}")
        err.param = p  # type: ignore[attr-defined]
        raise err from None
