"""Geometry helpers of Pi3 used by the models (stub: only those the models call)."""

from __future__ import annotations

import numpy as np
import torch


def se3_inverse(T):
    """Inverse of (..., 4, 4) rigid transforms (torch or numpy)."""
    if torch.is_tensor(T):
        R_inv = T[..., :3, :3].transpose(-2, -1)
        t_inv = -(R_inv @ T[..., :3, 3:4])
        bottom = torch.zeros_like(T[..., 3:4, :])
        bottom[..., 0, 3] = 1
        return torch.cat([torch.cat([R_inv, t_inv], dim=-1), bottom], dim=-2)
    R_inv = np.swapaxes(T[..., :3, :3], -2, -1)
    t_inv = -R_inv @ T[..., :3, 3:4]
    bottom = np.zeros(T.shape[:-2] + (1, 4), dtype=T.dtype)
    bottom[..., 0, 3] = 1
    return np.concatenate([np.concatenate([R_inv, t_inv], axis=-1), bottom], axis=-2)


def get_pixel(H, W):
    """(3, H*W) homogeneous pixel centres (u + 0.5, v + 0.5, 1), row-major."""
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    return np.stack([u.reshape(-1) + 0.5, v.reshape(-1) + 0.5, np.ones(H * W)], axis=0)


def homogenize_points(points):
    """(..., 3) -> (..., 4) with a trailing 1."""
    return torch.cat([points, torch.ones_like(points[..., :1])], dim=-1)
