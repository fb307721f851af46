"""VGGT-Omega's 9-D camera encoding: translation (3), quaternion xyzw (4), fov_h, fov_w (rad)."""

import torch

from .rotation import quat_to_mat


def encoding_to_camera(pose_encoding, image_size_hw, build_intrinsics=True):
    """(B, S, 9) encoding -> cam_from_world (B, S, 3, 4) and pinhole K (B, S, 3, 3) or None.

    fx = (W/2) / tan(fov_w/2), fy = (H/2) / tan(fov_h/2), principal point (W/2, H/2).
    """
    rotation = quat_to_mat(pose_encoding[..., 3:7])
    extrinsics = torch.cat([rotation, pose_encoding[..., :3, None]], dim=-1)
    if not build_intrinsics:
        return extrinsics, None
    height, width = image_size_hw
    intrinsics = torch.zeros(pose_encoding.shape[:2] + (3, 3), device=pose_encoding.device)
    intrinsics[..., 0, 0] = (width / 2.0) / torch.tan(pose_encoding[..., 8] / 2.0)
    intrinsics[..., 1, 1] = (height / 2.0) / torch.tan(pose_encoding[..., 7] / 2.0)
    intrinsics[..., 0, 2] = width / 2
    intrinsics[..., 1, 2] = height / 2
    intrinsics[..., 2, 2] = 1.0
    return extrinsics, intrinsics
