"""The :class:`Camera` base class shared by every camera model.

Conventions (docs/conventions.md section 2): OpenCV axes (x right, y down, z forward), pixel (0, 0) is the
centre of the top-left pixel, ``unproject`` returns unit rays (never points on the z = 1 plane),
angles from the optical axis are ``theta = atan2(sqrt(x^2 + y^2), z)`` so rays beyond 90 degrees
work. All maths is torch, batched over leading dimensions, in the dtype and on the device of the
input (parameters are cast to it), and differentiable in the inputs and in ``params``.

A subclass sets ``model`` and ``param_names`` (the first four are always ``fx, fy, cx, cy`` in
pixels) and implements ``_project`` / ``_unproject`` / ``_natural_max_angle``; optionally
``_check_domain`` for parameter constraints.
"""

from __future__ import annotations

import json
import math
import numbers
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import torch
from torch import Tensor

from raytun3r_plugin.errors import CameraError, CameraModelError

__all__ = ["CAMERA_MODELS", "Camera", "from_dict", "param_error", "pixel_grid"]

#: Registry of concrete models by their ``model`` name ("pinhole", "kb4", ...).
CAMERA_MODELS: dict[str, type[Camera]] = {}

# The mandatory leading parameters of every model, in this order.
_INTRINSIC_NAMES = ("fx", "fy", "cx", "cy")


def param_error(model: str, name: str, problem: str) -> CameraError:
    """A :class:`CameraError` about parameter ``name``; ``.param`` lets readers map it to a file field."""
    err = CameraError(f"{model}: parameter '{name}' {problem}")
    err.param = name  # type: ignore[attr-defined]
    return err


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


def _as_points(x: Any, what: str, last: int) -> Tensor:
    """Validate a (..., last) tensor and make it floating point (ints -> default dtype)."""
    if not isinstance(x, Tensor):
        x = torch.as_tensor(x)
    if x.ndim == 0 or x.shape[-1] != last:
        raise CameraError(f"{what} must have shape (..., {last}), got {tuple(x.shape)}")
    if not x.is_floating_point():
        if x.dtype == torch.bool or x.is_complex():
            raise CameraError(f"{what} must be a real tensor, got dtype {x.dtype}")
        x = x.to(torch.get_default_dtype())
    return x


def _check_size(name: str, value: Any) -> int:
    # bool is an int subclass; a float such as 512.0 is accepted only if integral.
    if isinstance(value, bool):
        raise CameraError(f"camera {name} must be a positive integer, got {value!r}")
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if not isinstance(value, numbers.Integral) or value <= 0:
        raise CameraError(f"camera {name} must be a positive integer, got {value!r}")
    return int(value)


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
        CameraError: missing/extra parameters, non-finite values, non-positive focal lengths,
            parameters outside the model's domain, bad size.
    """

    model: ClassVar[str] = ""
    param_names: ClassVar[tuple[str, ...]] = ()

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
        width = _check_size("width", width)
        height = _check_size("height", height)
        p = self._params_tensor(params)
        values = tuple(float(v) for v in p.detach().cpu().tolist())
        named = dict(zip(cls.param_names, values, strict=True))
        for name, v in named.items():
            if not math.isfinite(v):
                raise param_error(cls.__name__, name, f"must be finite, got {v!r}")
        for name in ("fx", "fy"):
            if named[name] <= 0.0:
                raise param_error(cls.__name__, name, f"must be positive, got {named[name]!r}")
        self._check_domain(named)
        if max_fov_deg is not None:
            if isinstance(max_fov_deg, bool) or not isinstance(max_fov_deg, numbers.Real):
                raise CameraError(
                    f"{cls.__name__}: max_fov_deg must be a number, got {max_fov_deg!r}"
                )
            max_fov_deg = float(max_fov_deg)
            if not (math.isfinite(max_fov_deg) and 0.0 < max_fov_deg <= 360.0):
                raise CameraError(
                    f"{cls.__name__}: max_fov_deg must be in (0, 360], got {max_fov_deg!r}"
                )
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

    @classmethod
    def _params_tensor(cls, params: Any) -> Tensor:
        names = cls.param_names
        if isinstance(params, Mapping):
            missing = [n for n in names if n not in params]
            extra = [str(k) for k in params if k not in names]
            if missing:
                raise param_error(cls.__name__, missing[0], f"is missing (expected {list(names)})")
            if extra:
                err = CameraError(
                    f"{cls.__name__}: unexpected parameter '{extra[0]}' (expected {list(names)})"
                )
                err.param = extra[0]  # type: ignore[attr-defined]
                raise err
            vals = []
            for n in names:
                v = params[n]
                if isinstance(v, Tensor):
                    if v.numel() != 1:
                        raise param_error(cls.__name__, n, "must be a scalar")
                    vals.append(v.reshape(()).to(torch.float64))
                elif isinstance(v, bool) or not isinstance(v, numbers.Real):
                    raise param_error(cls.__name__, n, f"must be a number, got {v!r}")
                else:
                    vals.append(torch.tensor(float(v), dtype=torch.float64))
            if any(v.requires_grad for v in vals):
                return torch.stack(vals)
            return torch.stack(vals).detach()
        if isinstance(params, Tensor):
            if params.dtype == torch.bool or params.is_complex():
                raise CameraError(
                    f"{cls.__name__}: params must be real numbers, got {params.dtype}"
                )
            p = params.to(torch.float64)
            if p is params:
                p = p.clone()  # decouple from the caller's storage (clone keeps the graph)
        else:
            if isinstance(params, (str, bytes)):
                raise CameraError(f"{cls.__name__}: params must be numbers, got {params!r}")
            try:
                seq = list(params)
            except TypeError:
                raise CameraError(
                    f"{cls.__name__}: params must be a sequence, got {params!r}"
                ) from None
            for i, v in enumerate(seq):
                if isinstance(v, bool) or not isinstance(v, numbers.Real):
                    name = names[i] if i < len(names) else f"#{i}"
                    raise param_error(cls.__name__, name, f"must be a number, got {v!r}")
            p = torch.tensor([float(v) for v in seq], dtype=torch.float64)
        if p.ndim != 1 or p.shape[0] != len(names):
            raise CameraError(
                f"{cls.__name__}: expected {len(names)} parameters {list(names)}, got shape "
                f"{tuple(p.shape)}"
            )
        return p

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
        pts = _as_points(points, "points", 3)
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
        q = _as_points(uv, "uv", 2)
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
        for name, s in (("sx", sx), ("sy", sy)):
            if (
                isinstance(s, bool)
                or not isinstance(s, numbers.Real)
                or not (math.isfinite(s) and s > 0)
            ):
                raise CameraError(f"scale {name} must be a positive finite number, got {s!r}")
        w = max(1, round(self.width * sx))
        h = max(1, round(self.height * sy))
        return self._replace(
            w, h, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5
        )

    def resized(self, width: int, height: int) -> Camera:
        """The camera of the image resized to ``width x height`` pixels (pure resize)."""
        width = _check_size("width", width)
        height = _check_size("height", height)
        cam = self.scaled(width / self.width, height / self.height)
        if (cam.width, cam.height) == (width, height):
            return cam
        return cam._replace(width, height, cam.fx, cam.fy, cam.cx, cam.cy)

    def cropped(self, x0: int, y0: int, w: int, h: int) -> Camera:
        """The camera of the window with top-left pixel (x0, y0) and size w x h.

        The window may extend beyond the image (padding): a pixel (u, v) of the original image
        is pixel (u - x0, v - y0) of the result.
        """
        for name, v in (("x0", x0), ("y0", y0)):
            if isinstance(v, bool) or not isinstance(v, numbers.Integral):
                raise CameraError(f"crop {name} must be an integer, got {v!r}")
        w = _check_size("crop width", w)
        h = _check_size("crop height", h)
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


def _rebuild(
    model: str, width: int, height: int, params: Tensor, max_fov_deg: float | None
) -> Camera:
    return CAMERA_MODELS[model](width, height, params, max_fov_deg=max_fov_deg)


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
    if model not in CAMERA_MODELS:
        raise CameraError(
            f"camera description: field 'model': unknown camera model {model!r} "
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
