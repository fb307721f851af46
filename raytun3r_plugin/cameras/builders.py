"""Synthetic-lens constructors: "an equidistant-like fisheye of size S and field of view F".

The demo, the benchmark, the benchmark scripts and the tests all need a fisheye whose image
circle (the boundary ray at ``fov_deg / 2``) lands at a chosen radius. :func:`fisheye` is the one
constructor; its formulas are the ones those callers used by hand, so the cameras they build are
unchanged to the last bit (``tests/test_cameras_builders.py`` holds the old formulas and checks).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

from raytun3r_plugin._strict import quote
from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.cameras.checks import MAX_IMAGE_SIDE
from raytun3r_plugin.cameras.kb import KannalaBrandt4
from raytun3r_plugin.cameras.unified import EUCM, UCM, DoubleSphere
from raytun3r_plugin.errors import CameraError

__all__ = ["FISHEYE_MODELS", "fisheye", "perturbed"]

#: Lens models :func:`fisheye` builds.
FISHEYE_MODELS = ("kb4", "ds", "ucm", "eucm")


def _kb4_theta_d(theta: float, k: Sequence[float]) -> float:
    # Written term by term, in the order the hand-built cameras used: with trailing zero
    # coefficients the extra ``+ 0.0`` terms leave every bit of the old focal length unchanged.
    k1, k2, k3, k4 = k
    return theta * (1 + k1 * theta**2 + k2 * theta**4 + k3 * theta**6 + k4 * theta**8)


def _ds_boundary_radius(half: float, xi: float, alpha: float) -> float:
    """Radius of the ray at angle ``half`` in the normalised double-sphere image plane."""
    x, z = math.sin(half), math.cos(half)
    d1 = 1.0  # a unit ray
    k = xi * d1 + z
    d2 = math.sqrt(x * x + k * k)
    return x / (alpha * d2 + (1 - alpha) * k)


def _unified_boundary_radius(half: float, alpha: float, beta: float = 1.0) -> float:
    """Radius of the ray at angle ``half`` in the normalised (E)UCM image plane (beta 1: UCM)."""
    x, z = math.sin(half), math.cos(half)
    return x / (alpha * math.sqrt(beta * x * x + z * z) + (1 - alpha) * z)


def fisheye(
    size: int | tuple[int, int],
    fov_deg: float,
    model: str = "kb4",
    *,
    k: Sequence[float] = (0.02, 0.0, 0.0, 0.0),
    xi: float = -0.15,
    alpha: float = 0.6,
    beta: float = 1.0,
    radius_px: float | None = None,
) -> Camera:
    """A centred fisheye whose ``fov_deg`` image circle has radius ``radius_px``.

    The focal length (square pixels, ``fx = fy``) is chosen so the ray at ``fov_deg / 2`` from
    the axis projects ``radius_px`` pixels from the principal point, which sits at the image
    centre ``((W - 1) / 2, (H - 1) / 2)`` (pixel centres at integers). The camera's
    ``max_fov_deg`` is ``fov_deg``.

    Args:
        size: ``S`` for an S x S image, or ``(width, height)`` in pixels.
        fov_deg: full field of view of the image circle, degrees (may exceed 180).
        model: ``"kb4"`` (:class:`KannalaBrandt4`, ``theta_d = theta (1 + k1 theta^2 + ...)``),
            ``"ds"`` (:class:`DoubleSphere` with ``xi`` and ``alpha``), ``"ucm"`` (:class:`UCM`
            with ``alpha``) or ``"eucm"`` (:class:`EUCM` with ``alpha`` and ``beta``).
        k: the four KB4 coefficients ``(k1, k2, k3, k4)``; the default ``k1 = 0.02`` is the lens
            of the demo and the benchmark; ``(0, 0, 0, 0)`` is the ideal equidistant lens.
        xi: the double-sphere ``xi`` (the benchmark's DS 195 by default).
        alpha: the double-sphere ``alpha`` (the benchmark's DS 195 by default), also the
            (E)UCM's.
        beta: the EUCM's ``beta``.
        radius_px: image-circle radius in pixels; default half the shorter side (the circle
            touches the shorter side's edges).

    Returns:
        The camera (immutable).

    Raises:
        CameraError: for an unknown ``model``, a size that is not positive, a field of view
            outside (0, 360) degrees, or fewer or more than four ``k``.
    """
    if isinstance(size, (str, bytes)):
        raise CameraError(f"fisheye: size must be S or (width, height), got {size!r}")
    try:
        width, height = (size, size) if isinstance(size, int) else (int(size[0]), int(size[1]))
    except (TypeError, ValueError, IndexError, OverflowError):
        raise CameraError(f"fisheye: size must be S or (width, height), got {size!r}") from None
    if not (0 < width <= MAX_IMAGE_SIDE and 0 < height <= MAX_IMAGE_SIDE):
        raise CameraError(
            f"fisheye: size must be in 1..{MAX_IMAGE_SIDE} pixels per side, got {quote(width)} x {quote(height)}"
        )
    if isinstance(fov_deg, bool) or not isinstance(fov_deg, numbers.Real):
        raise CameraError(f"fisheye: fov_deg must be a number, got {fov_deg!r}")
    if not 0.0 < fov_deg < 360.0:
        raise CameraError(f"fisheye: fov_deg must be in (0, 360) degrees, got {fov_deg!r}")
    radius = min(width, height) / 2 if radius_px is None else float(radius_px)
    half = math.radians(fov_deg / 2)
    cx, cy = (width - 1) / 2, (height - 1) / 2
    if model == "kb4":
        if len(k) != 4:
            raise CameraError(
                f"fisheye: k must hold the four KB4 coefficients (k1, k2, k3, k4), got {tuple(k)!r}"
            )
        focal = radius / _kb4_theta_d(half, k)
        k1, k2, k3, k4 = (float(value) for value in k)
        return KannalaBrandt4(
            width,
            height,
            {"fx": focal, "fy": focal, "cx": cx, "cy": cy, "k1": k1, "k2": k2, "k3": k3, "k4": k4},
            max_fov_deg=fov_deg,
        )
    if model == "ds":
        focal = radius / _ds_boundary_radius(half, xi, alpha)
        return DoubleSphere(
            width,
            height,
            {"fx": focal, "fy": focal, "cx": cx, "cy": cy, "xi": xi, "alpha": alpha},
            max_fov_deg=fov_deg,
        )
    if model in ("ucm", "eucm"):
        unified = UCM if model == "ucm" else EUCM
        extra = {"alpha": alpha} if model == "ucm" else {"alpha": alpha, "beta": beta}
        focal = radius / _unified_boundary_radius(half, alpha, 1.0 if model == "ucm" else beta)
        return unified(
            width,
            height,
            {"fx": focal, "fy": focal, "cx": cx, "cy": cy, **extra},
            max_fov_deg=fov_deg,
        )
    raise CameraError(f"fisheye: model must be one of {FISHEYE_MODELS}, got {model!r}")


def perturbed(
    camera: Camera, *, focal: float = 0.0, principal: float = 0.0, distortion: float = 0.0
) -> Camera:
    """``camera`` with a controlled calibration error: the rough calibration a user may have.

    Args:
        focal: relative change of fx and fy (0.05: 5 % longer focal lengths).
        principal: shift of cx and cy as a fraction of the image width and height.
        distortion: relative change of every parameter after the four intrinsics (k, xi,
            alpha, ...).

    Returns:
        a camera of the same model, size and ``max_fov_deg``.

    Raises:
        CameraError: the perturbed parameters leave the model's domain (e.g. alpha > 1).
    """
    for name, value in (("focal", focal), ("principal", principal), ("distortion", distortion)):
        if (
            isinstance(value, bool)
            or not isinstance(value, numbers.Real)
            or not math.isfinite(value)
            or abs(value) >= 1.0
        ):
            raise CameraError(f"perturbed: {name} must be a number in (-1, 1), got {quote(value)}")
    p = camera.params.detach().clone()
    p[:2] = p[:2] * (1.0 + focal)
    p[2] = p[2] + principal * camera.width
    p[3] = p[3] + principal * camera.height
    p[4:] = p[4:] * (1.0 + distortion)
    return type(camera)(camera.width, camera.height, p, max_fov_deg=camera.max_fov_deg)
