"""9-D camera encoding: [T (3), quaternion xyzw (4), fov_h, fov_w] <-> extrinsics, intrinsics.

Extrinsics are camera-from-world [R | t] (B, S, 3, 4), OpenCV axes; intrinsics in pixels with
the principal point at (W/2, H/2).
"""

from __future__ import annotations

import torch

from .rotation import mat_to_quat, quat_to_mat


def extri_intri_to_pose_encoding(extrinsics, intrinsics, image_size_hw=None, pose_encoding_type="absT_quaR_FoV"):
    if pose_encoding_type != "absT_quaR_FoV":
        raise NotImplementedError(pose_encoding_type)
    rotation = extrinsics[:, :, :3, :3]
    translation = extrinsics[:, :, :3, 3]
    quat = mat_to_quat(rotation)
    height, width = image_size_hw
    fov_h = 2 * torch.atan((height / 2) / intrinsics[..., 1, 1])
    fov_w = 2 * torch.atan((width / 2) / intrinsics[..., 0, 0])
    return torch.cat([translation, quat, fov_h[..., None], fov_w[..., None]], dim=-1).float()


def pose_encoding_to_extri_intri(
    pose_encoding, image_size_hw=None, pose_encoding_type="absT_quaR_FoV", build_intrinsics=True
):
    if pose_encoding_type != "absT_quaR_FoV":
        raise NotImplementedError(pose_encoding_type)
    translation = pose_encoding[..., :3]
    rotation = quat_to_mat(pose_encoding[..., 3:7])
    extrinsics = torch.cat([rotation, translation[..., None]], dim=-1)
    intrinsics = None
    if build_intrinsics:
        height, width = image_size_hw
        fy = (height / 2.0) / torch.tan(pose_encoding[..., 7] / 2.0)
        fx = (width / 2.0) / torch.tan(pose_encoding[..., 8] / 2.0)
        intrinsics = torch.zeros(pose_encoding.shape[:2] + (3, 3), device=pose_encoding.device)
        intrinsics[..., 0, 0] = fx
        intrinsics[..., 1, 1] = fy
        intrinsics[..., 0, 2] = width / 2
        intrinsics[..., 1, 2] = height / 2
        intrinsics[..., 2, 2] = 1.0
    return extrinsics, intrinsics
