"""The round-trip check every camera passes when it is built: ``project(unproject(uv))`` must
return ``uv`` within ``ROUND_TRIP_TOL_PX`` over a fixed grid of pixels spanning the image, in
float64 on the detached parameters. Results are cached by camera key, so resized / scaled copies
built again and again pay for the check once.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from raytun3r_plugin.cameras.checks import ROUND_TRIP_TOL_PX
from raytun3r_plugin.errors import CameraError

if TYPE_CHECKING:  # annotations only: base.py imports this module
    from raytun3r_plugin.cameras.base import Camera

__all__ = ["ROUND_TRIP_GRID", "check_round_trip", "round_trip_error", "validation_grid"]

# The validation grid: ROUND_TRIP_GRID x ROUND_TRIP_GRID pixels spanning the image (border
# included) plus BORDER_SAMPLES pixels along each edge.
ROUND_TRIP_GRID = 17
BORDER_SAMPLES = 33

# Round-trip results by camera key (worst error, worst pixel); see check_round_trip.
ROUND_TRIP_CACHE: dict[tuple, tuple[float, tuple[float, float] | None]] = {}
ROUND_TRIP_CACHE_SIZE = 4096


def validation_grid(width: int, height: int) -> Tensor:
    """(N, 2) float64 pixels of the validation grid: a 17 x 17 grid spanning the image,
    corners and edges included, plus 33 samples along each of the four edges."""
    w1, h1 = float(width - 1), float(height - 1)
    n = ROUND_TRIP_GRID
    us = torch.linspace(0.0, w1, n, dtype=torch.float64)
    vs = torch.linspace(0.0, h1, n, dtype=torch.float64)
    inner = torch.stack(torch.meshgrid(us, vs, indexing="xy"), dim=-1).reshape(-1, 2)
    t = torch.linspace(0.0, 1.0, BORDER_SAMPLES, dtype=torch.float64)
    zero, one = torch.zeros_like(t), torch.ones_like(t)
    edges = [
        torch.stack([t * w1, zero], -1),
        torch.stack([t * w1, one * h1], -1),
        torch.stack([zero, t * h1], -1),
        torch.stack([one * w1, t * h1], -1),
    ]
    return torch.cat([inner, *edges])


def round_trip_error(camera: Camera) -> tuple[float, tuple[float, float] | None, int]:
    """The computation behind :meth:`Camera.round_trip_error` (the returned tuple is described
    there): float64, on the CPU, on the detached parameters."""
    uv = validation_grid(camera.width, camera.height)
    p = camera.params.detach().to(device="cpu", dtype=torch.float64)
    with torch.no_grad():
        rays, valid = camera._unproject(uv, p)
        if camera._cap_cos is not None:
            valid = valid & (rays[..., 2] >= camera._cap_cos)
        if not bool(torch.isfinite(rays).all()):
            bad = (~torch.isfinite(rays).all(-1)).nonzero()[0, 0]
            return math.inf, (float(uv[bad, 0]), float(uv[bad, 1])), int(valid.sum())
        if not bool(valid.any()):
            return 0.0, None, 0
        back, _ = camera._project(rays[valid], p)
        err = torch.linalg.vector_norm(back - uv[valid], dim=-1)
        err = torch.where(torch.isfinite(err), err, torch.full_like(err, math.inf))
        i = int(err.argmax())
        worst = uv[valid][i]
        return float(err[i]), (float(worst[0]), float(worst[1])), int(valid.sum())


def check_round_trip(camera: Camera, use_cache: bool) -> float:
    """Raise :class:`CameraError` unless ``camera`` passes the round trip; returns its error (px).

    Calls ``camera.round_trip_error()`` (the method, so subclasses and tests see every run)
    unless the camera's key is cached.
    """
    # The result depends only on the camera key, so resized / scaled copies built again
    # and again (one per forward) pay for it once.
    key = (type(camera).__name__, *camera.key())
    hit = ROUND_TRIP_CACHE.get(key) if use_cache else None
    if hit is None:
        err, worst, n_valid = camera.round_trip_error()
        if n_valid == 0:
            hit = (-1.0, None)
        else:
            hit = (err, worst)
        if len(ROUND_TRIP_CACHE) >= ROUND_TRIP_CACHE_SIZE:
            ROUND_TRIP_CACHE.pop(next(iter(ROUND_TRIP_CACHE)))
        ROUND_TRIP_CACHE[key] = hit
    err, worst = hit
    name = type(camera).__name__
    if err < 0.0:
        raise CameraError(
            f"{name} ({camera.model}): no pixel of the {camera.width}x{camera.height} image has a "
            f"valid ray (the lens circle misses the image, or the distortion cannot be inverted "
            f"anywhere in it)"
        )
    if not err <= ROUND_TRIP_TOL_PX:
        assert worst is not None
        raise CameraError(
            f"{name} ({camera.model}): project(unproject(uv)) misses pixel "
            f"({worst[0]:.6g}, {worst[1]:.6g}) by {err:.3g} px (tolerance "
            f"{ROUND_TRIP_TOL_PX} px): the parameters are outside the range where the model "
            f"can be inverted"
        )
    return err
