"""Quaternions (x, y, z, w: scalar last) to rotation matrices, as upstream's convention."""

import torch


def quat_to_mat(quaternions: torch.Tensor) -> torch.Tensor:
    """(..., 4) xyzw quaternions (any norm) -> (..., 3, 3) rotation matrices."""
    x, y, z, w = torch.unbind(quaternions, -1)
    s = 2.0 / (quaternions * quaternions).sum(-1)
    rows = (
        1 - s * (y * y + z * z),
        s * (x * y - z * w),
        s * (x * z + y * w),
        s * (x * y + z * w),
        1 - s * (x * x + z * z),
        s * (y * z - x * w),
        s * (x * z - y * w),
        s * (y * z + x * w),
        1 - s * (x * x + y * y),
    )
    return torch.stack(rows, -1).reshape(quaternions.shape[:-1] + (3, 3))
