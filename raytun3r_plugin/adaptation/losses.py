"""Self-supervised adaptation losses (docs/conventions.md section 7, paper "Adapter training").

Every term is a small function of plain tensors, so it can be tested on ground truth and reused
by other trainers (LoRA and calibration-token baselines use the same objective).

Conventions (docs/conventions.md section 2):

* pixels ``(u, v)`` have the centre of the top-left pixel at ``(0, 0)``; every pixel argument of
  the functions here is in the pixels of the *network input* (the image the depth map belongs
  to); :func:`to_input_pixels` (of :mod:`raytun3r_plugin.preprocess`) converts matcher output
  from the native image;
* depth is range along the unit ray (``X = D * ray``), or z-depth with ``depth_convention="z"``
  (``X = D * ray / ray_z``, only meaningful for rays in front of the camera);
* poses are 4x4 rigid transforms; the relative pose of frame ``j`` w.r.t. ``i`` is
  ``cam_j_from_cam_i = cam_j_from_world @ inv(cam_i_from_world)`` (:func:`relative_pose`);
* angles inside the losses are radians.

Weights (paper, "Implementation details"): reprojection 1, smoothness 10, PE L2 2, PE TV 20,
pose 1 (:class:`LossWeights`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import torch
import torch.nn.functional as F

from raytun3r_plugin import poses
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.poses import backproject, relative_pose  # re-exported: their one home
from raytun3r_plugin.preprocess import to_input_pixels  # re-exported: the one mapping

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

__all__ = [
    "LossWeights",
    "backproject",
    "fit_translation_scale",
    "pe_correction_grid",
    "pe_l2",
    "pe_tv",
    "pose_loss",
    "pe_energy",
    "pixel_optimal_scale",
    "relative_pose",
    "robust_px_error",
    "silog_loss",
    "grouped_silog_loss",
    "reprojection_loss",
    "rotation_angle",
    "sample_bilinear",
    "smoothness_loss",
    "to_input_pixels",
    "total_loss",
    "translation_angle",
]

#: Small constant keeping norms and divisions differentiable at zero.
_EPS = 1e-12


@dataclass(frozen=True)
class LossWeights:
    """Weights of the adaptation objective (paper: pose 1, smooth 10, L2 2, TV 20; reproj 1).

    ``depth`` weighs the supervised term (:func:`silog_loss`), present only when ground-truth
    depth is given. ``teacher`` weighs the pinhole-view term (:func:`grouped_silog_loss` against
    the frozen model's own depth of virtual pinhole views,
    :mod:`raytun3r_plugin.adaptation.teacher`). How L2 and TV are measured (absolute PE units or
    relative to the backbone's own PE energy) is :attr:`AdaptConfig.pe_regulariser` of the
    trainer.
    """

    reproj: float = 1.0
    smooth: float = 10.0
    l2: float = 2.0
    tv: float = 20.0
    pose: float = 1.0
    depth: float = 1.0
    photo: float = 0.0
    teacher: float = 0.0

    def as_dict(self) -> dict[str, float]:
        """The weights by term name; ``photo`` and ``teacher`` only when they are on, so the
        identity of every configuration without them is what it was before they existed."""
        weights = asdict(self)
        for optional in ("photo", "teacher"):
            if not weights[optional]:
                del weights[optional]
        return weights


# --------------------------------------------------------------------------------------------
# Pixels, sampling, back-projection
# --------------------------------------------------------------------------------------------


def sample_bilinear(image: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of ``image`` at pixel positions, border-clamped, differentiable in both.

    Args:
        image: (H, W) or (C, H, W).
        uv: (M, 2) pixel positions (pixel-centre convention, (0, 0) = top-left pixel centre).

    Returns:
        (M,) for a 2-D image, (C, M) otherwise.
    """
    squeeze = image.ndim == 2
    planes = image[None, None] if squeeze else image[None]
    height, width = planes.shape[-2:]
    grid = torch.stack(((2 * uv[:, 0] + 1) / width - 1, (2 * uv[:, 1] + 1) / height - 1), dim=-1)
    out = F.grid_sample(
        planes,
        grid.to(planes.dtype)[None, None],
        mode="bilinear",
        padding_mode="border",
        align_corners=False,
    )
    out = out[0, :, 0, :]
    return out[0] if squeeze else out


def inside_mask(
    uv: torch.Tensor,
    mask: torch.Tensor | None,
    width: int | None = None,
    height: int | None = None,
) -> torch.Tensor:
    """(M,) bool: pixel positions ``uv`` (M, 2) inside the ``width`` x ``height`` image (pixel
    centres at integers, edges at -0.5) and, when given, on a set pixel of ``mask`` (H, W; its shape
    is the image's when ``width`` and ``height`` are not given)."""
    if width is None or height is None:
        height, width = mask.shape
    inside = (
        (uv[:, 0] >= -0.5)
        & (uv[:, 0] <= width - 0.5)
        & (uv[:, 1] >= -0.5)
        & (uv[:, 1] <= height - 0.5)
    )
    inside &= torch.isfinite(uv).all(dim=-1)
    if mask is not None:
        col = torch.round(uv[:, 0].detach()).clamp(0, width - 1).long()
        row = torch.round(uv[:, 1].detach()).clamp(0, height - 1).long()
        inside &= mask.to(uv.device)[row, col]
    return inside


# --------------------------------------------------------------------------------------------
# Reprojection
# --------------------------------------------------------------------------------------------


def reprojection_loss(
    depth_i: torch.Tensor,
    cam_j_from_cam_i: torch.Tensor,
    uv_i: torch.Tensor,
    uv_j: torch.Tensor,
    confidence: torch.Tensor | None,
    camera: Camera,
    valid: torch.Tensor | None = None,
    depth_convention: str = "range",
    rays_i: tuple[torch.Tensor, torch.Tensor] | None = None,
    robust_px: float | None = None,
) -> tuple[torch.Tensor, int]:
    """Confidence-weighted L1 reprojection error of matched pixels (paper eq. L_reproj).

    For every match, the point ``X_i = D_i(uv_i) * ray(uv_i)`` (depth sampled bilinearly) is
    moved by ``cam_j_from_cam_i``, projected with ``camera`` and compared with ``uv_j``:
    ``sum_k w_k |kappa(T X_k) - uv_j,k|_1 / N_valid``.

    Args:
        depth_i: (H, W) predicted depth of frame ``i`` at network-input size.
        cam_j_from_cam_i: (4, 4) relative pose (same length unit as the depth).
        uv_i, uv_j: (M, 2) matched pixels in input pixels of frames ``i`` and ``j``.
        confidence: (M,) weights in [0, 1], or None for 1.
        camera: the camera of the network input (``camera.width == W``, ``camera.height == H``).
        valid: (H, W) bool valid region (lens circle / user mask); default the camera's.
        depth_convention: ``"range"`` (fisheye default) or ``"z"``.
        rays_i: optional precomputed ``camera.unproject(uv_i)`` (rays (M, 3), valid (M,)); the
            camera is fixed during adaptation, so a trainer lifts every match once.
        robust_px: None for the plain L1 error ``e``; a scale ``c`` (px) for the log-L1 error
            :func:`robust_px_error` ``c log(1 + e / c)``, which is ``e`` for small errors and
            grows only logarithmically for wrong matches.

    Returns:
        (loss, n_valid): the mean weighted L1 error in input pixels (a 0-d tensor, zero but
        still attached to the graph when no term is valid) and the number of valid terms. A
        term is valid when both pixels lie in the image and inside ``valid``, the ray of
        ``uv_i`` exists, the depth is positive and finite and the moved point projects validly.
    """
    height, width = depth_i.shape[-2:]
    if (int(camera.width), int(camera.height)) != (width, height):
        raise InputError(
            f"camera is {camera.width}x{camera.height} px but the depth map is {width}x{height}"
        )
    if uv_i.shape != uv_j.shape or uv_i.ndim != 2 or uv_i.shape[-1] != 2:
        raise InputError(
            f"uv_i and uv_j must both be (M, 2), got {tuple(uv_i.shape)} and {tuple(uv_j.shape)}"
        )
    dtype, device = depth_i.dtype, depth_i.device
    uv_i = uv_i.to(device=device, dtype=dtype)
    uv_j = uv_j.to(device=device, dtype=dtype)
    weights = (
        torch.ones_like(uv_i[:, 0])
        if confidence is None
        else confidence.to(device=device, dtype=dtype)
    )
    if valid is None:
        valid = camera.valid_mask()
    valid = valid.to(device).bool()

    ok = inside_mask(uv_i, valid, width, height) & inside_mask(uv_j, valid, width, height)
    if rays_i is None:
        with torch.no_grad():
            rays_i = camera.unproject(uv_i)
    rays, ray_ok = rays_i
    depth = sample_bilinear(depth_i, uv_i)
    ok = ok & ray_ok.to(device) & torch.isfinite(depth) & (depth > 0)
    points = backproject(
        torch.where(ok, depth, torch.ones_like(depth)),
        rays.to(device=device, dtype=dtype),
        depth_convention,
    )
    rotation, translation = cam_j_from_cam_i[:3, :3].to(dtype), cam_j_from_cam_i[:3, 3].to(dtype)
    moved = points @ rotation.T + translation
    # Terms already known to be invalid project a harmless point, so no NaN/inf can reach the
    # backward pass through them (a zero gradient times an infinite Jacobian is NaN).
    moved = torch.where(ok[:, None], moved, moved.new_tensor([0.0, 0.0, 1.0]).expand_as(moved))
    projected, proj_ok = camera.project(moved)
    ok = ok & proj_ok & torch.isfinite(projected).all(dim=-1)
    n_valid = int(ok.sum())
    if n_valid == 0:
        return depth_i.sum() * 0.0 + cam_j_from_cam_i.sum().to(dtype) * 0.0, 0
    error = (projected[ok] - uv_j[ok]).abs().sum(dim=-1)
    if robust_px is not None:
        error = robust_px_error(error, robust_px)
    return (weights[ok] * error).sum() / n_valid, n_valid


def robust_px_error(error: torch.Tensor, scale_px: float) -> torch.Tensor:
    """Log-L1 penalty ``c log(1 + e / c)`` of non-negative pixel errors ``e`` (scale ``c`` px).

    Equal to ``e`` to first order, so well-matched pixels count as in the L1 loss; an error of
    ``10 c`` costs ``2.4 c`` instead of ``10 c``, so the few wrong matches that survive the
    matcher's checks cannot dominate the sum.
    """
    return scale_px * torch.log1p(error / scale_px)


def depth_parallax_px(
    points_i: torch.Tensor, cam_j_from_cam_i: torch.Tensor, camera: Camera, step: float = 0.05
) -> torch.Tensor:
    """(M,) pixels that each point's reprojection in frame j moves per unit change of its log
    depth: how much a match can tell about depth.

    With a translation of zero length (or points at infinity) a depth change moves nothing, so
    the reprojection term carries no depth information; outdoors at 112 px, where only far
    points keep matches, the pixel-optimal scale was 1.4-2.4 % of the depth-consistent one and
    the windows' median parallax 0.01-0.20 px, against 0.4-6.5 px indoors
    (``experiments/guided_matching.py``, docs/adaptation.md section 6). A finite difference of
    ``step`` in log depth; points that do not project give 0.

    Args:
        points_i: (M, 3) points in camera i (any unit); cam_j_from_cam_i: (4, 4).
        camera: the camera of frame j.
    """
    rotation, translation = cam_j_from_cam_i[:3, :3], cam_j_from_cam_i[:3, 3]
    near, ok_near = camera.project(points_i @ rotation.T + translation)
    far, ok_far = camera.project((points_i * math.exp(step)) @ rotation.T + translation)
    moved = (far - near).norm(dim=-1) / step
    ok = ok_near & ok_far & torch.isfinite(moved)
    return torch.where(ok, moved, torch.zeros_like(moved))


def _projected_error(
    points_i: torch.Tensor,
    rotation: torch.Tensor,
    direction: torch.Tensor,
    scales: torch.Tensor,
    uv_j: torch.Tensor,
    camera: Camera,
) -> torch.Tensor:
    """(S, M) L1 pixel errors of ``R X + s t`` for each candidate scale ``s`` (S,)."""
    moved = (points_i @ rotation.T)[None] + scales[:, None, None] * direction[None, None]
    projected, ok = camera.project(moved.reshape(-1, 3))
    projected = projected.reshape(scales.shape[0], -1, 2)
    ok = ok.reshape(scales.shape[0], -1) & torch.isfinite(projected).all(dim=-1)
    error = (projected - uv_j[None]).abs().sum(dim=-1)
    return torch.where(ok, error, torch.full_like(error, 1e6))


def pixel_optimal_scale(
    points_i: torch.Tensor,
    uv_j: torch.Tensor,
    rotation: torch.Tensor,
    direction: torch.Tensor,
    camera: Camera,
    weights: torch.Tensor | None = None,
    *,
    robust_px: float = 1.0,
    initial: torch.Tensor | float | None = None,
    span: float = 30.0,
    samples: int = 49,
) -> torch.Tensor:
    """Translation scale ``s`` of a unit-translation pose that minimises the pixel residual.

    The least-squares scale of :func:`fit_translation_scale` weighs every match by its 3-D
    lever arm, so far points decide it; outdoors, at true depth and pose, it returned 2.6 times
    the true translation and scored true depth at 7.05 px against 2.82 px for the zero adapter.
    This one minimises ``sum w rho(|project(R X + s t) - uv_j|_1)`` (``rho`` the log-L1 penalty
    of scale ``robust_px``) over ``log s``: a grid of ``samples`` values spanning ``initial``
    times ``[1 / span, span]``, then a finer grid around the best one. The result is detached:
    the scale is chosen for the current depth and held fixed for the gradient (it is a nuisance
    variable, as the per-pair scale of ``d_reproj``).

    Args:
        points_i: (M, 3) points in camera ``i``; uv_j: (M, 2) matched pixels in frame ``j``.
        rotation: (3, 3), direction: (3,) unit translation of ``cam_j_from_cam_i``.
        camera: the camera of ``uv_j``.
        weights: (M,) match weights or None.
        initial: centre of the search (default: the least-squares scale, or the median range
            of the points when that is 0).

    Returns:
        0-d tensor ``s >= 0`` (no gradient).
    """
    with torch.no_grad():
        points_i = points_i.detach()
        dtype = points_i.dtype
        rotation = rotation.to(dtype)
        direction = direction.to(dtype)
        weights = torch.ones_like(points_i[:, 0]) if weights is None else weights.detach().to(dtype)
        if points_i.shape[0] == 0:
            return points_i.new_zeros(())
        if initial is None:
            rays_j, _ = camera.unproject(uv_j.to(dtype))
            initial = fit_translation_scale(
                points_i, rays_j.to(dtype), rotation, direction, weights
            )
        centre = float(initial)
        if not math.isfinite(centre) or centre <= 0:
            centre = float(points_i.norm(dim=-1).median()) * 0.05
        centre = max(centre, 1e-9)

        def cost(log_scales: torch.Tensor) -> torch.Tensor:
            error = _projected_error(
                points_i, rotation, direction, log_scales.exp(), uv_j.to(dtype), camera
            )
            return (weights[None] * robust_px_error(error, robust_px)).sum(dim=-1)

        log_span = math.log(span)
        grid = torch.linspace(
            math.log(centre) - log_span, math.log(centre) + log_span, samples, dtype=dtype
        )
        best = grid[int(torch.argmin(cost(grid)))]
        step = float(grid[1] - grid[0])
        fine = torch.linspace(float(best) - step, float(best) + step, 21, dtype=dtype)
        best = fine[int(torch.argmin(cost(fine)))]
        return best.exp()


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


def silog_loss(
    pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None
) -> torch.Tensor:
    """Scale-invariant log error of depth samples: ``var(log pred - log target)``.

    The variance (Eigen et al.'s scale-invariant error with lambda = 1) ignores a global scale,
    which the backbones cannot know for a fisheye; samples with a non-positive or non-finite
    value on either side are left out.

    Args:
        pred, target: (M,) depth samples; weights: (M,) or None.

    Returns:
        0-d tensor (zero, attached to ``pred``, when fewer than 2 samples are usable).
    """
    ok = torch.isfinite(pred) & torch.isfinite(target) & (pred > 0) & (target > 0)
    if int(ok.sum()) < 2:
        return pred.sum() * 0.0
    w = torch.ones_like(pred[ok]) if weights is None else weights[ok].to(pred.dtype)
    difference = torch.log(pred[ok]) - torch.log(target[ok].to(pred.dtype))
    mean = (w * difference).sum() / w.sum()
    return (w * (difference - mean).pow(2)).sum() / w.sum()


def grouped_silog_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    groups: torch.Tensor,
    weights: Sequence[float] | None = None,
) -> torch.Tensor:
    """Mean (or weighted sum) over groups of :func:`silog_loss`: one free scale per group.

    The teacher term's targets come from several virtual pinhole views of one frame, each
    predicted on its own and so each with its own unknown scale; one variance per view keeps a
    view's scale from leaking into the others' residuals.

    Args:
        pred, target: (M,) depth samples; groups: (M,) integer group of each sample, ``0 <= g``.
        weights: None for the mean over the groups that have samples; else ``weights[g]`` is
            group ``g``'s weight and the result is the weighted *sum* (not renormalised: a
            group without samples adds nothing, and the others keep their weights).

    Returns:
        0-d tensor (zero, attached to ``pred``, when no group has 2 usable samples).
    """
    losses, used = [], []
    for group in torch.unique(groups):
        chosen = groups == group
        if int(chosen.sum()) >= 2:
            losses.append(silog_loss(pred[chosen], target[chosen]))
            used.append(int(group))
    if not losses:
        return pred.sum() * 0.0
    if weights is None:
        return torch.stack(losses).mean()
    factors = torch.tensor([float(weights[g]) for g in used], dtype=pred.dtype, device=pred.device)
    return (torch.stack(losses) * factors).sum()


# --------------------------------------------------------------------------------------------
# Edge-aware smoothness (Godard et al. 2017)
# --------------------------------------------------------------------------------------------


def smoothness_loss(
    depth: torch.Tensor, image: torch.Tensor, valid: torch.Tensor | None = None
) -> torch.Tensor:
    """Edge-aware smoothness of mean-normalised depth, averaged over frames.

    ``mean_x(exp(-|d_x I|) |d_x D*|) + mean_y(exp(-|d_y I|) |d_y D*|)`` with ``D* = D / mean(D)``
    (mean over the valid pixels of each frame) and ``|d I|`` the mean absolute difference of
    neighbouring pixels over the colour channels; a difference counts when both pixels are valid.

    Args:
        depth: (H, W) or (N, H, W) depth.
        image: (3, H, W) or (N, 3, H, W) the network's input image(s), values in [0, 1].
        valid: (H, W) bool valid region, or None for every pixel.

    Returns:
        0-d tensor (dimensionless).
    """
    if depth.ndim == 2:
        depth, image = depth[None], image[None]
    if (
        depth.ndim != 3
        or image.ndim != 4
        or image.shape[0] != depth.shape[0]
        or image.shape[-2:] != depth.shape[-2:]
    ):
        raise InputError(
            f"depth (N, H, W) and image (N, 3, H, W) must match, got {tuple(depth.shape)} and {tuple(image.shape)}"
        )
    image = image.to(depth.dtype)
    mask = (
        torch.ones(depth.shape[-2:], dtype=torch.bool, device=depth.device)
        if valid is None
        else valid.to(depth.device).bool()
    )
    maskf = mask.to(depth.dtype)
    mean = (depth * maskf).sum(dim=(-2, -1), keepdim=True) / maskf.sum().clamp_min(1.0)
    normalised = depth / mean.clamp_min(_EPS)

    pair_x = (mask[:, 1:] & mask[:, :-1]).to(depth.dtype)
    pair_y = (mask[1:, :] & mask[:-1, :]).to(depth.dtype)
    grad_dx = (normalised[..., :, 1:] - normalised[..., :, :-1]).abs()
    grad_dy = (normalised[..., 1:, :] - normalised[..., :-1, :]).abs()
    grad_ix = (image[..., :, 1:] - image[..., :, :-1]).abs().mean(dim=1)
    grad_iy = (image[..., 1:, :] - image[..., :-1, :]).abs().mean(dim=1)
    term_x = (torch.exp(-grad_ix) * grad_dx * pair_x).sum(dim=(-2, -1)) / pair_x.sum().clamp_min(
        1.0
    )
    term_y = (torch.exp(-grad_iy) * grad_dy * pair_y).sum(dim=(-2, -1)) / pair_y.sum().clamp_min(
        1.0
    )
    return (term_x + term_y).mean()


# --------------------------------------------------------------------------------------------
# PE regularisers
# --------------------------------------------------------------------------------------------


def pe_correction_grid(
    adapter: Any,
    geometry: Any,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """The adapter's PE correction ``P' - P_A`` over the token grid, differentiable in the tables.

    :meth:`Adapter.pe_correction <raytun3r_plugin.adapter.Adapter.pe_correction>` (the same
    computation the patched PE hook adds) on the patch grid, so it depends only on the adapter
    and the (camera, input size), never on the backbone's table.

    Args:
        adapter: a :class:`raytun3r_plugin.adapter.Adapter`.
        geometry: a :class:`raytun3r_plugin.geometry.SizeGeometry` (camera at the input size).
        device, dtype: of the result (default: the adapter's device, float32).

    Returns:
        (h, w, C) correction, ``t_r(rho) + rho d_theta(theta)`` per token, h x w the patch grid.
    """
    correction = adapter.pe_correction(geometry, device, dtype)
    rows, cols = geometry.height // geometry.patch, geometry.width // geometry.patch
    return correction.reshape(rows, cols, -1)


def pe_energy(pos_embed: torch.Tensor | None) -> float:
    """Mean squared norm of the backbone's own patch-token PE, ``mean_k ||P_A[k]||^2``.

    The unit in which the relative PE regularisers count (:attr:`AdaptConfig.pe_regulariser`):
    dividing ``||correction||^2`` by it makes the L2 and TV terms dimensionless, so one weight
    means the same for a backbone whose PE has std 0.5 (the built-in network, energy about 32)
    and one whose PE is 40 times larger. The class token (the first row when the row count is
    a square plus one) is left out. Returns 1.0 for a backbone without a PE table, or one
    whose table is all zeros.
    """
    if pos_embed is None:
        return 1.0
    table = pos_embed.detach().float().reshape(-1, pos_embed.shape[-1])
    rows = table.shape[0]
    if rows > 1 and math.isqrt(rows - 1) ** 2 == rows - 1:
        table = table[1:]
    energy = float(table.pow(2).sum(dim=-1).mean())
    return energy if math.isfinite(energy) and energy > 0 else 1.0


def pe_l2(correction: torch.Tensor) -> torch.Tensor:
    """``mean over tokens of ||P' - P_A||^2`` for a (h, w, C) correction (PE units squared)."""
    return correction.pow(2).sum(dim=-1).mean()


def pe_tv(correction: torch.Tensor) -> torch.Tensor:
    """Squared total variation of a (h, w, C) correction over the token grid.

    ``(1 / (h w)) sum (||c[y, x+1] - c[y, x]||^2 + ||c[y+1, x] - c[y, x]||^2)``, neighbours
    inside the grid only (paper eq. L_TV).
    """
    rows, cols = correction.shape[:2]
    horizontal = (correction[:, 1:] - correction[:, :-1]).pow(2).sum()
    vertical = (correction[1:, :] - correction[:-1, :]).pow(2).sum()
    return (horizontal + vertical) / (rows * cols)


# --------------------------------------------------------------------------------------------
# Pose term
# --------------------------------------------------------------------------------------------


def rotation_angle(rotation_a: torch.Tensor, rotation_b: torch.Tensor) -> torch.Tensor:
    """Geodesic angle (radians) between rotations (..., 3, 3), the loss form of
    :func:`raytun3r_plugin.poses.rotation_angle`: the paper's ``arccos((tr(A^T B) - 1) / 2)``
    evaluated by atan2, with a tiny epsilon under the norm so the gradient at exactly zero is
    zero, not NaN."""
    return poses.rotation_angle(rotation_a, rotation_b, eps=_EPS)


def translation_angle(t_a: torch.Tensor, t_b: torch.Tensor) -> torch.Tensor:
    """Angle (radians) between translation directions (..., 3), the loss form of
    :func:`raytun3r_plugin.poses.translation_angle` (finite gradients; 0 when either vector is
    zero)."""
    return poses.translation_angle(t_a, t_b, eps=_EPS)


def pose_loss(
    cam_j_from_cam_i: torch.Tensor, target_rotation: torch.Tensor, target_translation: torch.Tensor
) -> torch.Tensor:
    """Rotation geodesic + translation-direction angle (radians) against a MAGSAC++ target.

    Args:
        cam_j_from_cam_i: (4, 4) predicted relative pose.
        target_rotation: (3, 3) target rotation ``R~`` (``X_j = R~ X_i + t~``).
        target_translation: (3,) target translation direction (any positive scale).

    Returns:
        0-d tensor in radians, computed in float64 and cast back to the pose's dtype.
    """
    dtype = cam_j_from_cam_i.dtype
    pose = cam_j_from_cam_i.double()
    rotation = target_rotation.to(pose.device, torch.float64)
    translation = target_translation.to(pose.device, torch.float64)
    loss = rotation_angle(rotation, pose[:3, :3]) + translation_angle(translation, pose[:3, 3])
    return loss.to(dtype)


def fit_translation_scale(
    points_i: torch.Tensor,
    rays_j: torch.Tensor,
    rotation: torch.Tensor,
    direction: torch.Tensor,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """Scale ``s`` making ``R X_i + s t`` parallel to the rays of the matches in frame ``j``.

    Used when the relative pose comes from a MAGSAC++ target (unit translation) instead of the
    network: the scale of the translation must agree with the predicted depth. Weighted linear
    least squares on ``r_j x (R X_i + s t) = 0``:
    ``s = -sum w <r_j x R X_i, r_j x t> / sum w |r_j x t|^2``, clamped at 0 (no motion rather
    than a flipped direction). Differentiable in the points, so the reprojection error it feeds
    is invariant to the global depth scale.

    Args:
        points_i: (M, 3) points in camera ``i`` (same unit as the depth).
        rays_j: (M, 3) unit rays of the matched pixels in camera ``j``.
        rotation: (3, 3) ``R`` of ``cam_j_from_cam_i``; direction: (3,) translation direction.
        weights: (M,) non-negative weights, or None.

    Returns:
        0-d tensor ``s`` (depth unit per unit of ``direction``).
    """
    weights = torch.ones_like(points_i[:, 0]) if weights is None else weights.to(points_i.dtype)
    rotated = points_i @ rotation.to(points_i.dtype).T
    direction = direction.to(points_i.dtype).expand_as(rotated)
    a = torch.linalg.cross(rays_j, rotated, dim=-1)
    b = torch.linalg.cross(rays_j, direction, dim=-1)
    numerator = -(weights * (a * b).sum(dim=-1)).sum()
    denominator = (weights * b.pow(2).sum(dim=-1)).sum().clamp_min(_EPS)
    return (numerator / denominator).clamp_min(0.0)


# --------------------------------------------------------------------------------------------
# Total
# --------------------------------------------------------------------------------------------


def total_loss(terms: Mapping[str, torch.Tensor], weights: LossWeights) -> torch.Tensor:
    """``reproj + w_smooth smooth + w_l2 l2 + w_tv tv + w_pose pose`` over the terms present."""
    factors = asdict(weights)
    unknown = set(terms) - set(factors)
    if unknown:
        raise InputError(f"unknown loss terms {sorted(unknown)}; known: {sorted(factors)}")
    total = None
    for name, value in terms.items():
        contribution = factors[name] * value
        total = contribution if total is None else total + contribution
    if total is None:
        raise InputError("no loss term given")
    return total
