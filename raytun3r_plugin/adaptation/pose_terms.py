"""The pose term of the adaptation objective: the network's relative pose against a MAGSAC++
target (rotation geodesic + translation-direction angle, radians), and the closed-form length of
a target's unit translation."""

from __future__ import annotations

import torch

from raytun3r_plugin import poses

__all__ = ["fit_translation_scale", "pose_loss", "rotation_angle", "translation_angle"]

_EPS = 1e-12


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
