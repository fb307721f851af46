"""What a camera accepts: the bounds of docs/cameras.md and the checks of camera inputs.

Every check raises :class:`~raytun3r_plugin.errors.CameraError` naming the bad input (for a
parameter it also sets ``.param``, so file readers can map the error to a field). ``Camera``
(cameras/base.py) runs them in its constructor and in its resize / crop edits; the model modules
use :func:`param_error` and :func:`check_range` for their own domain checks.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from raytun3r_plugin._strict import quote
from raytun3r_plugin.errors import CameraError

__all__ = [
    "DISTORTION_BOUND",
    "FOCAL_RANGE_PX",
    "MAX_CROP_OFFSET",
    "MAX_IMAGE_SIDE",
    "PRINCIPAL_MARGIN",
    "ROUND_TRIP_TOL_PX",
    "as_points",
    "check_crop_offsets",
    "check_intrinsics",
    "check_max_fov",
    "check_range",
    "check_scale_factors",
    "check_size",
    "param_error",
    "params_tensor",
    "to_float",
]

# ---------------------------------------------------------------------------- bounds
# What a camera accepts (docs/cameras.md, "What a camera accepts"). Every bound is far outside
# real calibrations and inside the range where the maths stays finite and invertible.

#: Largest image side in pixels (width and height each in 1..MAX_IMAGE_SIDE).
MAX_IMAGE_SIDE = 16384

#: Focal lengths fx, fy must lie in this closed range, pixels.
FOCAL_RANGE_PX = (1e-3, 1e6)

#: The principal point may lie up to this many image sides outside the image:
#: cx in [-m W, (1 + m) W], cy in [-m H, (1 + m) H] (crops may push it outside the image).
PRINCIPAL_MARGIN = 2.0

#: Bound on the magnitude of every polynomial distortion coefficient (k, p, s terms).
DISTORTION_BOUND = 1e3

#: Largest accepted project(unproject(uv)) - uv error, pixels, over the validation grid.
ROUND_TRIP_TOL_PX = 0.05

# Largest |crop offset| accepted by cropped(), pixels (keeps the offsets exact in float64 and
# far from overflow; the principal-point margin decides what is really accepted).
MAX_CROP_OFFSET = 8 * MAX_IMAGE_SIDE


def param_error(model: str, name: str, problem: str) -> CameraError:
    """A :class:`CameraError` about parameter ``name``; ``.param`` lets readers map it to a file field."""
    err = CameraError(f"{model}: parameter '{name}' {problem}")
    err.param = name  # type: ignore[attr-defined]
    return err


def check_range(
    model: str,
    name: str,
    value: float,
    lo: float,
    hi: float,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
    unit: str = "",
) -> None:
    """Raise :func:`param_error` unless ``lo <= value <= hi`` (``<`` on an open end)."""
    above = value > lo if lo_open else value >= lo
    below = value < hi if hi_open else value <= hi
    if not (above and below):
        left = "(" if lo_open else "["
        right = ")" if hi_open else "]"
        raise param_error(
            model, name, f"must be in {left}{lo:g}, {hi:g}{right}{unit}, got {value!r}"
        )


def to_float(model: str, name: str, v: Any) -> float:
    """``float(v)``; a value that has none raises :func:`param_error` for parameter ``name``."""
    # float() of a huge Python int raises OverflowError; that is a bad parameter, not a crash.
    try:
        return float(v)
    except (OverflowError, TypeError, ValueError):
        raise param_error(model, name, f"must be a finite number, got {quote(v)}") from None


def as_points(x: Any, what: str, last: int) -> Tensor:
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


def check_size(name: str, value: Any) -> int:
    """An image side ``name`` as an int in 1..``MAX_IMAGE_SIDE`` pixels."""
    # bool is an int subclass; a float such as 512.0 is accepted only if integral.
    bad = CameraError(
        f"camera {name} must be an integer in 1..{MAX_IMAGE_SIDE} pixels, got {quote(value)}"
    )
    if isinstance(value, bool):
        raise bad
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    # Python ints compare exactly at any size (10**400 included): no float conversion here.
    if not isinstance(value, numbers.Integral):
        raise bad
    n = int(value)
    if not 1 <= n <= MAX_IMAGE_SIDE:
        raise bad
    return n


def params_tensor(owner: str, names: Sequence[str], params: Any) -> Tensor:
    """The parameters of a camera of class ``owner`` as a (P,) float64 tensor.

    ``params`` is a tensor or sequence in ``names`` order, or a mapping ``{name: value}`` with
    exactly ``names``; a tensor that requires grad keeps its graph (see ``Camera``).
    """
    if isinstance(params, Mapping):
        missing = [n for n in names if n not in params]
        extra = [str(k) for k in params if k not in names]
        if missing:
            raise param_error(owner, missing[0], f"is missing (expected {list(names)})")
        if extra:
            err = CameraError(
                f"{owner}: unexpected parameter '{extra[0]}' (expected {list(names)})"
            )
            err.param = extra[0]  # type: ignore[attr-defined]
            raise err
        vals = []
        for n in names:
            v = params[n]
            if isinstance(v, Tensor):
                if v.numel() != 1:
                    raise param_error(owner, n, "must be a scalar")
                if v.dtype == torch.bool or v.is_complex():
                    raise param_error(owner, n, f"must be a real number, got {v.dtype}")
                vals.append(v.reshape(()).to(torch.float64))
            elif isinstance(v, bool) or not isinstance(v, numbers.Real):
                raise param_error(owner, n, f"must be a number, got {quote(v)}")
            else:
                vals.append(torch.tensor(to_float(owner, n, v), dtype=torch.float64))
        if any(v.requires_grad for v in vals):
            return torch.stack(vals)
        return torch.stack(vals).detach()
    if isinstance(params, Tensor):
        if params.dtype == torch.bool or params.is_complex():
            raise CameraError(f"{owner}: params must be real numbers, got {params.dtype}")
        p = params.to(torch.float64)
        if p is params:
            p = p.clone()  # decouple from the caller's storage (clone keeps the graph)
    else:
        if isinstance(params, (str, bytes)):
            raise CameraError(f"{owner}: params must be numbers, got {params!r}")
        try:
            seq = list(params)
        except TypeError:
            raise CameraError(f"{owner}: params must be a sequence, got {params!r}") from None
        floats = []
        for i, v in enumerate(seq):
            name = names[i] if i < len(names) else f"#{i}"
            if isinstance(v, bool) or not isinstance(v, numbers.Real):
                raise param_error(owner, name, f"must be a number, got {quote(v)}")
            floats.append(to_float(owner, name, v))
        p = torch.tensor(floats, dtype=torch.float64)
    if p.ndim != 1 or p.shape[0] != len(names):
        raise CameraError(
            f"{owner}: expected {len(names)} parameters {list(names)}, got shape {tuple(p.shape)}"
        )
    return p


def check_intrinsics(
    owner: str,
    named: Mapping[str, float],
    width: int,
    height: int,
    distortion_names: Sequence[str],
) -> None:
    """Finite parameters, focal lengths, principal-point margin and distortion magnitude."""
    for name, v in named.items():
        if not math.isfinite(v):
            raise param_error(owner, name, f"must be finite, got {v!r}")
    lo_f, hi_f = FOCAL_RANGE_PX
    for name in ("fx", "fy"):
        check_range(owner, name, named[name], lo_f, hi_f, unit=" px")
    m = PRINCIPAL_MARGIN
    check_range(owner, "cx", named["cx"], -m * width, (1 + m) * width, unit=" px")
    check_range(owner, "cy", named["cy"], -m * height, (1 + m) * height, unit=" px")
    for name in distortion_names:
        b = DISTORTION_BOUND
        check_range(owner, name, named[name], -b, b)


def check_max_fov(owner: str, max_fov_deg: Any) -> float | None:
    """The lens field-of-view cap as a float in (0, 360] degrees, or ``None`` when not given."""
    if max_fov_deg is not None:
        if isinstance(max_fov_deg, bool) or not isinstance(max_fov_deg, numbers.Real):
            raise CameraError(f"{owner}: max_fov_deg must be a number, got {quote(max_fov_deg)}")
        max_fov_deg = to_float(owner, "max_fov_deg", max_fov_deg)
        if not (math.isfinite(max_fov_deg) and 0.0 < max_fov_deg <= 360.0):
            raise CameraError(f"{owner}: max_fov_deg must be in (0, 360], got {max_fov_deg!r}")
    return max_fov_deg


def check_scale_factors(width: int, height: int, sx: float, sy: float) -> None:
    """Resize factors of a ``width x height`` image: positive, finite, and leaving at most
    2 x ``MAX_IMAGE_SIDE`` pixels per side."""
    for name, s in (("sx", sx), ("sy", sy)):
        if isinstance(s, bool) or not isinstance(s, numbers.Real):
            raise CameraError(f"scale {name} must be a positive finite number, got {quote(s)}")
        try:
            f = float(s)
        except OverflowError:
            f = math.inf
        if not (math.isfinite(f) and f > 0):
            raise CameraError(f"scale {name} must be a positive finite number, got {quote(s)}")
    # A factor that leaves more than MAX_IMAGE_SIDE pixels is refused by the constructor;
    # refusing it here keeps round() away from huge floats.
    for name, side, s in (("width", width, sx), ("height", height, sy)):
        if side * float(s) > 2 * MAX_IMAGE_SIDE:
            raise CameraError(
                f"scaled {name} {side} x {float(s):g} exceeds {MAX_IMAGE_SIDE} pixels"
            )


def check_crop_offsets(x0: int, y0: int) -> None:
    """Crop offsets: integers within +-``MAX_CROP_OFFSET`` pixels."""
    for name, v in (("x0", x0), ("y0", y0)):
        if isinstance(v, bool) or not isinstance(v, numbers.Integral):
            raise CameraError(f"crop {name} must be an integer, got {quote(v)}")
        if abs(v) > MAX_CROP_OFFSET:
            raise CameraError(
                f"crop {name} must be within +-{MAX_CROP_OFFSET} pixels, got {quote(v)}"
            )
