"""Quaternion <-> rotation matrix, quaternions in x, y, z, w order (scalar last)."""

from __future__ import annotations

import torch


def quat_to_mat(quaternions: torch.Tensor) -> torch.Tensor:
    """(..., 4) xyzw (any norm) -> (..., 3, 3)."""
    x, y, z, w = torch.unbind(quaternions, -1)
    s = 2.0 / (quaternions * quaternions).sum(-1)
    rows = (
        1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w),
        s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w),
        s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y),
    )  # fmt: skip
    return torch.stack(rows, -1).reshape(quaternions.shape[:-1] + (3, 3))


def mat_to_quat(matrix: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 4) xyzw with w >= 0.

    Computes the four candidate quaternions (one per largest component) and keeps the best
    conditioned one for each matrix.
    """
    if matrix.shape[-2:] != (3, 3):
        raise ValueError(f"Invalid rotation matrix shape {tuple(matrix.shape)}.")
    m = matrix
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # 4 * (w^2, x^2, y^2, z^2)
    four_sq = torch.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1
    )
    root = _sqrt_positive_part(four_sq)  # 2 * |component|
    d_x = m[..., 2, 1] - m[..., 1, 2]
    d_y = m[..., 0, 2] - m[..., 2, 0]
    d_z = m[..., 1, 0] - m[..., 0, 1]
    s_xy = m[..., 1, 0] + m[..., 0, 1]
    s_xz = m[..., 0, 2] + m[..., 2, 0]
    s_yz = m[..., 2, 1] + m[..., 1, 2]
    # candidate c holds 4*q_c * (w, x, y, z)
    cands = torch.stack(
        [
            torch.stack([root[..., 0] ** 2, d_x, d_y, d_z], -1),
            torch.stack([d_x, root[..., 1] ** 2, s_xy, s_xz], -1),
            torch.stack([d_y, s_xy, root[..., 2] ** 2, s_yz], -1),
            torch.stack([d_z, s_xz, s_yz, root[..., 3] ** 2], -1),
        ],
        dim=-2,
    )
    cands = cands / (2.0 * root.clamp(min=0.1))[..., None]
    best = root.argmax(dim=-1)
    wxyz = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    return standardize_quaternion(wxyz[..., [1, 2, 3, 0]])


def _sqrt_positive_part(x: torch.Tensor) -> torch.Tensor:
    """sqrt(max(0, x)) with a zero sub-gradient at 0."""
    positive = x > 0
    return torch.where(positive, torch.sqrt(torch.where(positive, x, torch.ones_like(x))), torch.zeros_like(x))


def standardize_quaternion(quaternions: torch.Tensor) -> torch.Tensor:
    """Flip xyzw quaternions so that the real part w is non-negative."""
    return torch.where(quaternions[..., 3:4] < 0, -quaternions, quaternions)
