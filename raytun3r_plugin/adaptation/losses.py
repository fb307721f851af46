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

The pose term is :mod:`~raytun3r_plugin.adaptation.pose_terms`, the dense photometric term
:mod:`~raytun3r_plugin.adaptation.photometric`.

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

from raytun3r_plugin.adaptation.pose_terms import fit_translation_scale
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.poses import backproject, relative_pose  # re-exported: their one home
from raytun3r_plugin.preprocess import to_input_pixels  # re-exported: the one mapping

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

__all__ = [
    "LossWeights",
    "backproject",
    "pe_correction_grid",
    "pe_l2",
    "pe_tv",
    "pe_energy",
    "pixel_optimal_scale",
    "relative_pose",
    "robust_px_error",
    "silog_loss",
    "grouped_silog_loss",
    "reprojection_loss",
    "sample_bilinear",
    "smoothness_loss",
    "to_input_pixels",
    "total_loss",
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
        geometry: a :class:`raytun3r_plugin.size_geometry.SizeGeometry` (camera at the input size).
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
