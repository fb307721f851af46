"""The :class:`Camera` base class shared by every camera model.

Conventions (docs/conventions.md section 2): OpenCV axes (x right, y down, z forward), pixel (0, 0) is the
centre of the top-left pixel, ``unproject`` returns unit rays (never points on the z = 1 plane),
angles from the optical axis are ``theta = atan2(sqrt(x^2 + y^2), z)`` so rays beyond 90 degrees
work. All maths is torch, batched over leading dimensions, in the dtype and on the device of the
input (parameters are cast to it), and differentiable in the inputs and in ``params``.

A subclass sets ``model`` and ``param_names`` (the first four are always ``fx, fy, cx, cy`` in
pixels) and implements ``_project`` / ``_unproject`` / ``_natural_max_angle``; optionally
``_check_domain`` for parameter constraints.

This module holds the camera contract and what every camera does with it (projection, whole-image
helpers, resize / crop, identity). Its neighbours hold the parts it uses: ``checks`` (the bounds
and input checks), ``round_trip`` (the invertibility check at construction) and
``serialisation`` (the model registry and the dict form). The names users import from here
(bounds, ``check_range``, ``param_error``, ``from_dict``, ...) are re-exported.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import torch
from torch import Tensor

from raytun3r_plugin.cameras.checks import (
    DISTORTION_BOUND,
    FOCAL_RANGE_PX,
    MAX_IMAGE_SIDE,
    PRINCIPAL_MARGIN,
    ROUND_TRIP_TOL_PX,
    as_points,
    check_crop_offsets,
    check_intrinsics,
    check_max_fov,
    check_range,
    check_scale_factors,
    check_size,
    param_error,
    params_tensor,
)
from raytun3r_plugin.cameras.round_trip import ROUND_TRIP_GRID, check_round_trip, round_trip_error
from raytun3r_plugin.cameras.serialisation import CAMERA_MODELS, from_dict
from raytun3r_plugin.errors import CameraError, CameraModelError

__all__ = [
    "CAMERA_MODELS",
    "DISTORTION_BOUND",
    "FOCAL_RANGE_PX",
    "MAX_IMAGE_SIDE",
    "PRINCIPAL_MARGIN",
    "ROUND_TRIP_GRID",
    "ROUND_TRIP_TOL_PX",
    "Camera",
    "check_range",
    "from_dict",
    "param_error",
    "pixel_grid",
    "validate",
]

# The mandatory leading parameters of every model, in this order.
_INTRINSIC_NAMES = ("fx", "fy", "cx", "cy")


def pixel_grid(
    width: int,
    height: int,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """Pixel-centre coordinates of a ``height x width`` image.

    Returns:
        (H, W, 2) tensor with ``[..., 0] = u`` (column) and ``[..., 1] = v`` (row), in pixels;
        pixel (0, 0) is the centre of the top-left pixel.
    """
    u = torch.arange(width, device=device, dtype=dtype)
    v = torch.arange(height, device=device, dtype=dtype)
    return torch.stack(torch.meshgrid(u, v, indexing="xy"), dim=-1)


class Camera:
    """An immutable camera model: image size plus named intrinsic parameters.

    Args:
        width, height: image size in pixels.
        params: the parameters in ``param_names`` order (tensor or sequence), or a mapping
            ``{name: value}`` with exactly the model's names. Stored as a (P,) float64 tensor;
            a tensor that requires grad keeps its graph, so the camera is differentiable in it.
        max_fov_deg: optional full field of view (degrees) of the lens, e.g. 195 for a
            195-degree fisheye; rays further than ``max_fov_deg / 2`` from the optical axis are
            then invalid in ``project`` and ``unproject``. ``None`` = the model's own domain.

    Raises:
        CameraError: for any bad input and only that error type: missing/extra parameters,
            wrong types, non-finite values, parameters outside the bounds of docs/cameras.md
            ("What a camera accepts": focal lengths, principal-point margin, distortion
            magnitude, the model's domain), a size outside 1..``MAX_IMAGE_SIDE``, or a camera
            whose ``project(unproject(uv))`` misses ``uv`` by more than ``ROUND_TRIP_TOL_PX``
            on the validation grid (checked in float64 on the detached parameters).
    """

    model: ClassVar[str] = ""
    param_names: ClassVar[tuple[str, ...]] = ()
    #: Polynomial distortion coefficients, each bounded by ``DISTORTION_BOUND`` in magnitude.
    distortion_names: ClassVar[tuple[str, ...]] = ()

    # Instances are frozen after __init__ (see __setattr__).
    width: int
    height: int
    params: Tensor
    # Set once in __init__ through object.__setattr__; declared so the type checker knows them.
    _values: tuple[float, ...]
    _named: dict[str, float]
    _max_fov_deg: float | None
    _max_angle: float
    _cap_cos: float | None
    _cache: dict[Any, Any]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.model:
            if cls.param_names[:4] != _INTRINSIC_NAMES:
                raise CameraModelError(
                    f"{cls.__name__}.param_names must start with {_INTRINSIC_NAMES}"
                )
            CAMERA_MODELS[cls.model] = cls

    def __init__(
        self,
        width: int,
        height: int,
        params: Tensor | Sequence[float] | Mapping[str, float],
        *,
        max_fov_deg: float | None = None,
    ) -> None:
        cls = type(self)
        if not cls.model:
            raise CameraModelError(
                "Camera is abstract: use a model such as Pinhole or KannalaBrandt4"
            )
        try:
            self._build(width, height, params, max_fov_deg)
        except CameraError:
            raise
        except (TypeError, ValueError, ArithmeticError, RecursionError, RuntimeError) as e:
            # The checks above are meant to catch every bad input; this net turns anything
            # they miss (an exotic tensor type, a NumPy quirk) into the library's error type.
            raise CameraError(
                f"{cls.__name__}: invalid camera input ({type(e).__name__}: {str(e)[:200]})"
            ) from None

    def _build(self, width: Any, height: Any, params: Any, max_fov_deg: Any) -> None:
        cls = type(self)
        width = check_size("width", width)
        height = check_size("height", height)
        p = self._params_tensor(params)
        values = tuple(float(v) for v in p.detach().cpu().tolist())
        named = dict(zip(cls.param_names, values, strict=True))
        check_intrinsics(cls.__name__, named, width, height, cls.distortion_names)
        self._check_domain(named)
        max_fov_deg = check_max_fov(cls.__name__, max_fov_deg)
        natural = float(self._natural_max_angle(named))
        cap = math.inf if max_fov_deg is None else math.radians(max_fov_deg) / 2.0
        # A cap is only enforced when it is tighter than the model's own domain.
        cap_cos = math.cos(cap) if cap < natural else None
        set_ = object.__setattr__
        set_(self, "width", width)
        set_(self, "height", height)
        set_(self, "params", p)
        set_(self, "_values", values)
        set_(self, "_named", named)
        set_(self, "_max_fov_deg", max_fov_deg)
        set_(self, "_max_angle", min(natural, cap))
        set_(self, "_cap_cos", cap_cos)
        set_(self, "_cache", {})
        check_round_trip(self, use_cache=True)

    @classmethod
    def _params_tensor(cls, params: Any) -> Tensor:
        return params_tensor(cls.__name__, cls.param_names, params)

    # ------------------------------------------------------------------ model hooks
    def _check_domain(self, p: dict[str, float]) -> None:
        """Raise ``param_error`` for parameters outside the model's domain (default: none)."""

    def _natural_max_angle(self, p: dict[str, float]) -> float:  # pragma: no cover - abstract
        raise NotImplementedError

    def _project(self, points: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:  # pragma: no cover
        raise NotImplementedError

    def _unproject(self, uv: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:  # pragma: no cover
        raise NotImplementedError

    def _set(self, name: str, value: Any) -> None:
        """Store a derived constant (for model hooks running inside ``__init__``)."""
        object.__setattr__(self, name, value)

    # ------------------------------------------------------------------ validation
    def round_trip_error(self) -> tuple[float, tuple[float, float] | None, int]:
        """The worst ``|project(unproject(uv)) - uv|`` over the validation grid, in float64
        on the detached parameters (so a differentiable camera is checked on its values).

        Returns:
            (error in pixels, the worst pixel (u, v) or None, number of grid pixels with a
            valid ray). The error is ``inf`` where a valid pixel's ray or its projection is
            not finite, and also where any grid pixel's ray is not finite (unproject promises
            finite rays everywhere). A camera with no valid grid pixel reports 0 valid pixels.
        """
        return round_trip_error(self)

    # ------------------------------------------------------------------ immutability
    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"{type(self).__name__} is immutable (tried to set {name!r})")

    def __delattr__(self, name: str) -> None:
        raise AttributeError(f"{type(self).__name__} is immutable (tried to delete {name!r})")

    def __reduce__(self) -> tuple[Any, ...]:
        # Rebuild through __init__ (validation included); the ray-table cache is not pickled.
        return (
            _rebuild,
            (type(self).model, self.width, self.height, self.params, self._max_fov_deg),
        )

    # ------------------------------------------------------------------ properties
    @property
    def fx(self) -> Tensor:
        """Focal length along u, pixels (0-d tensor, shares the graph of ``params``)."""
        return self.params[0]

    @property
    def fy(self) -> Tensor:
        """Focal length along v, pixels (0-d tensor)."""
        return self.params[1]

    @property
    def cx(self) -> Tensor:
        """Principal point u, pixels, pixel-centre convention (0-d tensor)."""
        return self.params[2]

    @property
    def cy(self) -> Tensor:
        """Principal point v, pixels, pixel-centre convention (0-d tensor)."""
        return self.params[3]

    @property
    def values(self) -> dict[str, float]:
        """Parameters as a ``{name: float}`` dict (detached copy)."""
        return dict(self._named)

    @property
    def max_fov_deg(self) -> float | None:
        """The lens field-of-view cap given at construction (degrees), or ``None``."""
        return self._max_fov_deg

    @property
    def max_angle(self) -> float:
        """Largest angle from the optical axis (radians) the camera represents (may exceed pi/2).

        The model's own limit (fold of the projection, domain of the formula) or the
        ``max_fov_deg / 2`` cap, whichever is smaller.
        """
        return self._max_angle

    @property
    def requires_grad(self) -> bool:
        """True when ``params`` is part of an autograd graph."""
        return self.params.requires_grad

    # ------------------------------------------------------------------ projection
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Project camera-frame points to pixels.

        Args:
            points: (..., 3) points in the camera frame (any scale; only the direction matters).

        Returns:
            uv: (..., 2) pixel coordinates (finite everywhere, meaningful only where valid).
            valid: (...,) bool, false where the model is undefined or the ray is beyond
            ``max_angle``. The image bounds are *not* checked.
        """
        pts = as_points(points, "points", 3)
        p = self.params.to(device=pts.device, dtype=pts.dtype)
        uv, valid = self._project(pts, p)
        if self._cap_cos is not None:
            z = pts[..., 2]
            n = torch.linalg.vector_norm(pts.detach(), dim=-1)
            valid = valid & (z.detach() >= self._cap_cos * n)
        return uv, valid

    def unproject(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        """Lift pixels to unit rays.

        Args:
            uv: (..., 2) pixel coordinates (pixel-centre convention).

        Returns:
            rays: (..., 3) unit vectors in the camera frame (finite everywhere).
            valid: (...,) bool, false where the pixel has no ray in the model's domain.
        """
        q = as_points(uv, "uv", 2)
        p = self.params.to(device=q.device, dtype=q.dtype)
        rays, valid = self._unproject(q, p)
        if self._cap_cos is not None:
            valid = valid & (rays[..., 2].detach() >= self._cap_cos)
        return rays, valid

    # ------------------------------------------------------------------ whole-image helpers
    def pixel_grid(
        self, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
    ) -> Tensor:
        """(H, W, 2) pixel-centre coordinates of this camera's image (see :func:`pixel_grid`)."""
        return pixel_grid(self.width, self.height, device=device, dtype=dtype)

    def ray_table(
        self, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
    ) -> tuple[Tensor, Tensor]:
        """Rays of all pixel centres.

        Returns:
            rays (H, W, 3) unit vectors and valid (H, W) bool. Cached per (device, dtype) unless
            ``params`` requires grad; the cached tensors are shared, do not modify them in place.
        """
        dev = torch.device(device) if device is not None else self.params.device
        if self.params.requires_grad:
            return self.unproject(self.pixel_grid(dev, dtype))
        key = ("rays", str(dev), dtype)
        hit = self._cache.get(key)
        if hit is None:
            with torch.no_grad():
                hit = self.unproject(self.pixel_grid(dev, dtype))
            self._cache[key] = hit
        return hit

    def _mask_and_fov(self) -> tuple[Tensor, float]:
        # One float64 pass on the CPU (float64 is not available on every accelerator); only
        # the mask and the angle are kept, not the 3 x 8 bytes per pixel of the rays.
        hit = self._cache.get("mask_fov")
        if hit is None:
            with torch.no_grad():
                rays, valid = self.unproject(self.pixel_grid("cpu", torch.float64))
            z = rays[..., 2][valid]
            zmin = float(z.min()) if z.numel() else 1.0
            fov = 0.0 if not z.numel() else 2.0 * math.degrees(math.acos(max(-1.0, min(1.0, zmin))))
            hit = (valid, fov)
            self._cache["mask_fov"] = hit
        return hit

    def valid_mask(self, device: torch.device | str | None = None) -> Tensor:
        """(H, W) bool mask of pixels whose ray is valid (lens circle / field of view).

        Decided in float64 (boundary pixels at full precision) and cached per device; equal to
        ``ray_table(dtype=torch.float64)[1]``.
        """
        dev = torch.device(device) if device is not None else self.params.device
        key = ("mask", str(dev))
        hit = self._cache.get(key)
        if hit is None:
            hit = self._mask_and_fov()[0].to(dev)
            self._cache[key] = hit
        return hit

    @property
    def fov_deg(self) -> float:
        """Full field of view in degrees: twice the largest angle from the optical axis among
        the valid pixel centres of the image (computed in float64, cached)."""
        return self._mask_and_fov()[1]

    # ------------------------------------------------------------------ geometry edits
    def _replace(self, width: int, height: int, fx: Any, fy: Any, cx: Any, cy: Any) -> Camera:
        p = torch.cat([torch.stack([fx, fy, cx, cy]), self.params[4:]])
        return type(self)(width, height, p, max_fov_deg=self._max_fov_deg)

    def scaled(self, sx: float, sy: float) -> Camera:
        """The camera of the image resized by factors (sx, sy) (pure resize, no crop).

        Pixel centres map as ``u' = (u + 0.5) * sx - 0.5`` (same for v), so ``fx' = fx * sx``,
        ``cx' = (cx + 0.5) * sx - 0.5``; the new size is ``round(width * sx) x round(height * sy)``.
        Distortion acts on normalised coordinates in every model, so it is unchanged.
        """
        check_scale_factors(self.width, self.height, sx, sy)
        w = max(1, round(self.width * sx))
        h = max(1, round(self.height * sy))
        return self._replace(
            w, h, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5
        )

    def resized(self, width: int, height: int) -> Camera:
        """The camera of the image resized to ``width x height`` pixels (pure resize)."""
        width = check_size("width", width)
        height = check_size("height", height)
        cam = self.scaled(width / self.width, height / self.height)
        if (cam.width, cam.height) == (width, height):
            return cam
        return cam._replace(width, height, cam.fx, cam.fy, cam.cx, cam.cy)

    def cropped(self, x0: int, y0: int, w: int, h: int) -> Camera:
        """The camera of the window with top-left pixel (x0, y0) and size w x h.

        The window may extend beyond the image (padding): a pixel (u, v) of the original image
        is pixel (u - x0, v - y0) of the result.
        """
        check_crop_offsets(x0, y0)
        w = check_size("crop width", w)
        h = check_size("crop height", h)
        return self._replace(w, h, self.fx, self.fy, self.cx - int(x0), self.cy - int(y0))

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """``{"model", "width", "height", "params": {name: float}}`` (+ ``"max_fov_deg"`` if set)."""
        d: dict[str, Any] = {
            "model": self.model,
            "width": self.width,
            "height": self.height,
            "params": dict(self._named),
        }
        if self._max_fov_deg is not None:
            d["max_fov_deg"] = self._max_fov_deg
        return d

    def to_json(self) -> str:
        """JSON text of :meth:`to_dict`; floats are written with ``repr`` so the round trip is exact."""
        return json.dumps(self.to_dict())

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Camera:
        """Inverse of :meth:`to_dict`; on a subclass, the model must match it."""
        cam = from_dict(d)
        if cls is not Camera and not isinstance(cam, cls):
            raise CameraError(f"expected a {cls.model!r} camera, got model {cam.model!r}")
        return cam

    @classmethod
    def from_json(cls, s: str) -> Camera:
        """Inverse of :meth:`to_json`."""
        try:
            d = json.loads(s)
        except (json.JSONDecodeError, TypeError) as e:
            raise CameraError(f"camera JSON is not valid JSON: {e}") from None
        return cls.from_dict(d)

    # ------------------------------------------------------------------ identity
    def key(self) -> tuple:
        """Hashable identity ``(model, width, height, params as floats, max_fov_deg)``."""
        return (self.model, self.width, self.height, self._values, self._max_fov_deg)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return self.key() == other.key()

    def __hash__(self) -> int:
        return hash(self.key())

    def __repr__(self) -> str:
        vals = ", ".join(f"{n}={v:.6g}" for n, v in self._named.items())
        cap = "" if self._max_fov_deg is None else f", max_fov_deg={self._max_fov_deg:g}"
        return f"{type(self).__name__}({self.width}x{self.height}, {vals}{cap})"


def validate(camera: Camera) -> float:
    """Re-run every construction check on ``camera`` (bounds, domain, round trip), uncached.

    Construction already does this; the function is for scripts that want the number.

    Returns:
        The worst round-trip error ``|project(unproject(uv)) - uv|`` over the validation grid,
        pixels (at most ``ROUND_TRIP_TOL_PX``).

    Raises:
        CameraError: ``camera`` is not a :class:`Camera`, or fails a check.
    """
    if not isinstance(camera, Camera):
        raise CameraError(f"validate: expected a Camera, got {type(camera).__name__}")
    rebuilt = type(camera)(
        camera.width, camera.height, camera.params.detach(), max_fov_deg=camera.max_fov_deg
    )
    return check_round_trip(rebuilt, use_cache=False)


def _rebuild(
    model: str, width: int, height: int, params: Tensor, max_fov_deg: float | None
) -> Camera:
    return CAMERA_MODELS[model](width, height, params, max_fov_deg=max_fov_deg)
