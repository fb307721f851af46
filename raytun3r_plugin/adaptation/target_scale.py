"""The MAGSAC++ target of a pair as a pose at the predicted depth's scale.

A target's translation is a unit direction; the fit scales it per pair to the depth the network
predicts (``AdaptConfig.scale``: the pixel-optimal scale, the 3-D least-squares one, or the
photometric one), so reprojection through the target measures depth, not the scale of the pair.
Used by the window terms (:mod:`~raytun3r_plugin.adaptation.step`), the parallax gate
(:mod:`~raytun3r_plugin.adaptation.parallax`) and the rig fit.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from raytun3r_plugin.adaptation.losses import backproject, pixel_optimal_scale, sample_bilinear
from raytun3r_plugin.adaptation.photometric import photometric_optimal_scale
from raytun3r_plugin.adaptation.pose_terms import fit_translation_scale
from raytun3r_plugin.errors import InputError

if TYPE_CHECKING:
    from raytun3r_plugin.adaptation.config import AdaptConfig
    from raytun3r_plugin.adaptation.problem import _Pair
    from raytun3r_plugin.cameras.base import Camera


def _target(pair: _Pair) -> tuple[torch.Tensor, torch.Tensor]:
    """The pair's MAGSAC++ (rotation, unit translation direction); the callers skip pairs
    without one."""
    if pair.rotation is None or pair.direction is None:
        raise InputError("a pair without a MAGSAC++ target reached the target scaling")
    return pair.rotation, pair.direction


__all__ = [
    "matched_points",
    "photometric_scale",
    "pose_scaled_to",
    "sample_valid_pixels",
    "subset_matches",
    "targets_pose",
]


def subset_matches(
    pair: _Pair, max_matches: int, generator: torch.Generator
) -> tuple[torch.Tensor, ...]:
    count = pair.uv_i.shape[0]
    if max_matches and count > max_matches:
        index = torch.randperm(count, generator=generator)[:max_matches]
        return (
            pair.uv_i[index],
            pair.uv_j[index],
            pair.confidence[index],
            pair.rays_i[index],
            pair.rays_j[index],
        )
    return pair.uv_i, pair.uv_j, pair.confidence, pair.rays_i, pair.rays_j


def matched_points(
    depth_i: torch.Tensor, uv_i: torch.Tensor, rays_i: torch.Tensor, convention: str
) -> tuple[torch.Tensor, torch.Tensor]:
    """(M, 3) points of the matches in camera i at the predicted depth, and (M,) where that depth
    is usable (finite, positive; the other points sit at depth 1)."""
    depth = sample_bilinear(depth_i, uv_i)
    usable = torch.isfinite(depth) & (depth > 0)
    points = backproject(torch.where(usable, depth, torch.ones_like(depth)), rays_i, convention)
    return points, usable


def pose_scaled_to(
    pair: _Pair,
    points: torch.Tensor,
    usable: torch.Tensor,
    uv_j: torch.Tensor,
    confidence: torch.Tensor,
    rays_j: torch.Tensor,
    camera: Camera,
    config: AdaptConfig,
    scale: torch.Tensor | None = None,
) -> torch.Tensor:
    """``cam_j_from_cam_i`` from the MAGSAC++ target, translation scaled to ``points``
    (``config.scale``: pixel-optimal and detached, or the differentiable least-squares scale),
    or by ``scale`` where given (``config.scale="photometric"``: :func:`photometric_scale`)."""
    rotation, direction = _target(pair)
    rotation, direction = rotation.to(points.dtype), direction.to(points.dtype)
    if scale is None:
        scale = fit_translation_scale(
            points[usable], rays_j[usable], rotation, direction, confidence[usable]
        )
        if config.scale == "pixel":
            scale = pixel_optimal_scale(
                points[usable],
                uv_j[usable],
                rotation,
                direction,
                camera,
                confidence[usable],
                robust_px=config.robust_px or 1.0,
                initial=scale.detach(),
            )
    scale = scale.to(points.dtype)
    pose = torch.eye(4, dtype=points.dtype)
    return torch.cat((torch.cat((rotation, (scale * direction)[:, None]), dim=1), pose[3:]), dim=0)


def targets_pose(
    pair: _Pair,
    depth_i: torch.Tensor,
    uv_i: torch.Tensor,
    uv_j: torch.Tensor,
    confidence: torch.Tensor,
    rays_i: torch.Tensor,
    rays_j: torch.Tensor,
    camera: Camera,
    config: AdaptConfig,
    scale: torch.Tensor | None = None,
) -> torch.Tensor:
    """``cam_j_from_cam_i`` from the MAGSAC++ target, translation scaled to the predicted depth
    (:func:`pose_scaled_to`)."""
    points, usable = matched_points(depth_i, uv_i, rays_i, config.depth_convention)
    return pose_scaled_to(pair, points, usable, uv_j, confidence, rays_j, camera, config, scale)


def sample_valid_pixels(
    valid: torch.Tensor, camera: Camera, count: int, generator: torch.Generator, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """(K, 2) long (column, row) pixels, at most ``count`` drawn at random from ``valid``, and
    their (K, 3) unit rays (pixels without a ray left out)."""
    rows, cols = torch.nonzero(valid, as_tuple=True)
    pick = torch.randperm(rows.shape[0], generator=generator)[:count]
    pixels = torch.stack((cols[pick], rows[pick]), dim=-1)
    with torch.no_grad():
        rays, ok = camera.unproject(pixels.to(dtype))
    return pixels[ok], rays[ok]


def photometric_scale(
    depth_i: torch.Tensor,
    gray_i: torch.Tensor,
    gray_j: torch.Tensor,
    pair: _Pair,
    camera: Camera,
    valid: torch.Tensor,
    config: AdaptConfig,
    generator: torch.Generator,
) -> torch.Tensor:
    """Translation length of ``pair``'s target for ``config.scale="photometric"``:
    :func:`photometric_optimal_scale` of frame ``i``'s predicted depth (detached) on
    ``config.photo_pixels`` random valid pixels."""
    with torch.no_grad():
        depth_i = depth_i.detach()
        pixels, rays = sample_valid_pixels(
            valid, camera, config.photo_pixels, generator, depth_i.dtype
        )
        points, usable = matched_points(
            depth_i, pixels.to(depth_i.dtype), rays, config.depth_convention
        )
        rotation, direction = _target(pair)
        return photometric_optimal_scale(
            points[usable],
            gray_i[pixels[:, 1], pixels[:, 0]][usable].to(depth_i.dtype),
            gray_j,
            rotation,
            direction,
            camera,
            valid,
        )
