"""The dense photometric term and the photometric translation length (opt-in; docs/adaptation.md,
"Photometric options"): frames blurred to grey, pixels of frame ``i`` back-projected with the
predicted depth and warped into frame ``j`` by candidate relative poses. Pixels and depth follow
:mod:`~raytun3r_plugin.adaptation.losses`' conventions."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

from raytun3r_plugin.adaptation.losses import inside_mask, sample_bilinear
from raytun3r_plugin.poses import backproject

if TYPE_CHECKING:
    from raytun3r_plugin.cameras.base import Camera

__all__ = [
    "MIN_INSIDE_FRACTION",
    "OUTSIDE_COST",
    "blurred_gray",
    "photometric_loss",
    "photometric_optimal_scale",
    "warped_photometric_error",
]


#: Grey-level cost of a pixel that the photometric warp moves out of the image or its valid
#: region (about three times the mean difference of aligned 112 px frames, 0.03).
OUTSIDE_COST = 0.1
#: A candidate translation length of :func:`photometric_optimal_scale` that keeps fewer of the
#: sampled pixels in view than this fraction is not considered.
MIN_INSIDE_FRACTION = 0.1


def blurred_gray(images: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """(S, h, w) grey levels of (S, 3, h, w) images in [0, 1], blurred by a Gaussian of
    ``sigma_px`` input pixels (0 = no blur; separable, edges replicated). The blur widens the
    basin of the photometric term: a fine texture that moves several pixels aliases at 112 px."""
    gray = images.mean(dim=1, keepdim=True)
    if sigma_px <= 0:
        return gray[:, 0]
    radius = max(1, int(math.ceil(3 * sigma_px)))
    x = torch.arange(-radius, radius + 1, dtype=gray.dtype, device=gray.device)
    kernel = torch.exp(-(x**2) / (2 * sigma_px**2))
    kernel = kernel / kernel.sum()
    gray = F.conv2d(F.pad(gray, (radius, radius, 0, 0), mode="replicate"), kernel.view(1, 1, 1, -1))
    gray = F.conv2d(F.pad(gray, (0, 0, radius, radius), mode="replicate"), kernel.view(1, 1, -1, 1))
    return gray[:, 0]


def warped_photometric_error(
    points_i: torch.Tensor,
    gray_i: torch.Tensor,
    gray_j: torch.Tensor,
    rotation: torch.Tensor,
    translations: torch.Tensor,
    camera: Camera,
    valid: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Grey-level differences of ``points_i`` warped into frame ``j`` by ``G`` candidate poses.

    Args:
        points_i: (K, 3) points of frame ``i``'s pixels; gray_i: (K,) their grey levels.
        gray_j: (h, w) grey image of frame ``j``.
        rotation: (3, 3) and translations: (G, 3) of ``cam_j_from_cam_i``.
        valid: (h, w) bool valid region of frame ``j``.

    Returns:
        (G, K) absolute differences (grey levels in [0, 1]) and (G, K) bool: the warped point
        projects inside ``valid``.
    """
    moved = points_i @ rotation.T
    moved = moved[None] + translations[:, None, :]
    uv, projects = camera.project(moved)
    uv_flat = uv.reshape(-1, 2)
    usable = projects.reshape(-1) & inside_mask(uv_flat, valid)
    sampled = sample_bilinear(gray_j, uv_flat).reshape(uv.shape[:-1])
    return (sampled - gray_i[None]).abs(), usable.reshape(uv.shape[:-1])


def photometric_optimal_scale(
    points_i: torch.Tensor,
    gray_i: torch.Tensor,
    gray_j: torch.Tensor,
    rotation: torch.Tensor,
    direction: torch.Tensor,
    camera: Camera,
    valid: torch.Tensor,
    *,
    span: tuple[float, float] = (1e-4, 1.0),
    samples: int = 41,
) -> torch.Tensor:
    """Length ``s`` of the unit target translation that best aligns frame ``j`` with frame ``i``.

    Matches cannot give it outdoors: they are far points whose residual is smallest for almost
    no translation (the pixel-optimal scale collapses to 1-2 % of the consistent one, section 6
    of docs/adaptation.md). The dense warp of every pixel, the near road included, decides it
    instead: ``s`` minimises the mean absolute grey-level difference between ``gray_i`` and
    ``gray_j`` sampled at ``project(R X + s t)``, over a grid of ``samples`` values of ``log s``
    spanning ``span`` times the median range of the points, then a finer grid around the best.
    The difference is averaged over the pixels that stay in view (at least
    :data:`MIN_INSIDE_FRACTION` of them). Detached: it is a nuisance variable, held fixed for the
    gradient.

    Args:
        points_i: (K, 3) points of frame ``i``'s sampled pixels; gray_i: (K,) their grey levels.
        gray_j: (h, w) blurred grey image of frame ``j``.
        rotation: (3, 3), direction: (3,) unit translation of ``cam_j_from_cam_i``.
        valid: (h, w) bool valid region.

    Returns:
        0-d tensor ``s > 0`` (no gradient).
    """
    with torch.no_grad():
        points_i = points_i.detach()
        dtype = points_i.dtype
        rotation, direction = rotation.to(dtype), direction.to(dtype)
        if points_i.shape[0] == 0:
            return points_i.new_ones(())
        centre = float(points_i.norm(dim=-1).median())
        if not math.isfinite(centre) or centre <= 0:
            return points_i.new_ones(())

        def cost(log_scales: torch.Tensor) -> torch.Tensor:
            error, usable = warped_photometric_error(
                points_i,
                gray_i,
                gray_j,
                rotation,
                log_scales.exp()[:, None] * direction[None],
                camera,
                valid,
            )
            # The mean over the pixels that stay in view. Charging the others OUTSIDE_COST here
            # would favour no translation at all: driving at the benchmark's speed, half the
            # pixels leave a 190-degree view between consecutive frames (at true depth and pose
            # the search then returned 0.1 % of the true length; over the pixels in view,
            # 86-109 %).
            inside = usable.sum(-1)
            mean = (error * usable).sum(-1) / inside.clamp_min(1)
            enough = inside >= MIN_INSIDE_FRACTION * usable.shape[-1]
            return torch.where(enough, mean, torch.full_like(mean, math.inf))

        grid = torch.linspace(
            math.log(centre * span[0]), math.log(centre * span[1]), samples, dtype=dtype
        )
        best = grid[int(torch.argmin(cost(grid)))]
        step = float(grid[1] - grid[0])
        fine = torch.linspace(float(best) - step, float(best) + step, 11, dtype=dtype)
        return fine[int(torch.argmin(cost(fine)))].exp()


def photometric_loss(
    depth_i: torch.Tensor,
    rays: torch.Tensor,
    pixels: torch.Tensor,
    gray_i: torch.Tensor,
    gray_j: torch.Tensor,
    rotation: torch.Tensor,
    direction: torch.Tensor,
    camera: Camera,
    valid: torch.Tensor,
    depth_convention: str = "range",
) -> tuple[torch.Tensor, int]:
    """Mean absolute grey-level difference of a dense warp of frame ``i`` into frame ``j``.

    Every sampled pixel of frame ``i`` is lifted with its predicted depth, moved by the target
    rotation and the unit target translation scaled by :func:`photometric_optimal_scale`, and
    compared with the blurred frame ``j`` there. Unlike the matches it needs no correspondence
    on the near, fast-moving ground, which is where the outdoor depth signal is (the paper
    avoids a photometric term because of low texture and initialisation; here it is an
    optional term, off by default, the initial depth is the network's own and the images are
    blurred).

    Args:
        depth_i: (h, w) predicted depth of frame ``i`` (differentiable).
        rays: (K, 3) unit rays of the sampled pixels; pixels: (K, 2) long (column, row).
        gray_i, gray_j: (h, w) blurred grey images (:func:`blurred_gray`).
        rotation: (3, 3), direction: (3,) of ``cam_j_from_cam_i`` (the MAGSAC++ target).
        valid: (h, w) bool valid region.

    Returns:
        (loss, count): 0-d tensor and the number of pixels that entered it.
    """
    depth = depth_i[pixels[:, 1], pixels[:, 0]]
    usable = torch.isfinite(depth) & (depth > 0)
    safe = torch.where(usable, depth, torch.ones_like(depth))
    points = backproject(safe, rays.to(depth.dtype), depth_convention)
    intensity = gray_i[pixels[:, 1], pixels[:, 0]].to(depth.dtype)
    scale = photometric_optimal_scale(
        points[usable], intensity[usable], gray_j, rotation, direction, camera, valid
    )
    rotation, direction = rotation.to(depth.dtype), direction.to(depth.dtype)
    error, inside = warped_photometric_error(
        points, intensity, gray_j, rotation, (scale * direction)[None], camera, valid
    )
    count = int(usable.sum())
    if count == 0:
        return depth.sum() * 0.0, 0
    # A pixel warped out of the image costs OUTSIDE_COST instead of leaving the mean: otherwise
    # the cheapest way to lower the mean is to push the hard pixels (the near road) out of view.
    error = torch.where(inside[0], error[0], torch.full_like(error[0], OUTSIDE_COST))
    return error[usable].mean(), count
