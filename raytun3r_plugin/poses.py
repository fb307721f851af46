"""Rigid poses, rotation angles, back-projection and quaternions: the one home of each helper.

The functional layer of pose geometry (kornia's ``kornia.geometry.conversions`` style): plain
functions of arrays, no state. The adaptation losses, the metrics, the pose targets, the
synthetic renderer, the dataset readers, the exporters and the backbone patches all call these.

Conventions (docs/conventions.md section 2):

* a pose is a 4x4 rigid transform ``[R | t; 0 0 0 1]``; ``cam_from_world`` maps world points
  into the camera (``X_cam = R X_world + t``);
* the relative pose of frame ``j`` with respect to frame ``i`` is
  ``cam_j_from_cam_i = cam_j_from_world @ inv(cam_i_from_world)``;
* angles are radians (the metrics convert to degrees);
* quaternions are ``(w, x, y, z)`` with ``w >= 0`` (TUM files, which store ``(x, y, z, w)``,
  reorder at the writer);
* depth is range along the unit ray (``X = D ray``) or z-depth (``X = D ray / ray_z``).

Every function takes numpy arrays or torch tensors and returns the same kind (torch when either
argument is a tensor). numpy work is float64; torch keeps the caller's dtype and device and is
differentiable.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from raytun3r_plugin.errors import InputError

__all__ = [
    "backproject",
    "invert_rigid",
    "quaternion_to_rotation",
    "relative_pose",
    "relative_poses",
    "rotation_angle",
    "rotation_to_quaternion",
    "translation_angle",
]


def _is_torch(*values: Any) -> bool:
    return any(isinstance(value, torch.Tensor) for value in values)


def _as_torch_pair(a: Any, b: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """Both as tensors of one floating dtype on the device of the tensor argument."""
    ta = a if isinstance(a, torch.Tensor) else torch.as_tensor(np.asarray(a))
    tb = b if isinstance(b, torch.Tensor) else torch.as_tensor(np.asarray(b))
    dtype = torch.promote_types(ta.dtype, tb.dtype)
    if not dtype.is_floating_point:
        dtype = torch.float64
    device = ta.device if isinstance(a, torch.Tensor) else tb.device
    return ta.to(device=device, dtype=dtype), tb.to(device=device, dtype=dtype)


# --------------------------------------------------------------------------------------------
# Rigid transforms
# --------------------------------------------------------------------------------------------


def invert_rigid(pose: Any) -> Any:
    """Inverse of rigid transforms (..., 4, 4): ``[R | t] -> [R^T | -R^T t]``.

    Exact transpose of the rotation block (no LU solve), so the inverse of a rotation is again a
    rotation to the last bit. Only valid for rigid transforms; numpy in -> float64 numpy out,
    torch in -> torch out (same dtype, differentiable).
    """
    if isinstance(pose, torch.Tensor):
        rotation = pose[..., :3, :3].transpose(-1, -2)
        translation = -(rotation @ pose[..., :3, 3:4])
        top = torch.cat((rotation, translation), dim=-1)
        return torch.cat((top, pose[..., 3:4, :]), dim=-2)
    pose = np.asarray(pose, dtype=np.float64)
    out = np.zeros_like(pose)
    rotation_t = np.swapaxes(pose[..., :3, :3], -1, -2)
    out[..., :3, :3] = rotation_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rotation_t, pose[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def relative_pose(cam_from_world: Any, i: int, j: int) -> Any:
    """``cam_j_from_cam_i = cam_from_world[j] @ inv(cam_from_world[i])`` (4, 4) from (N, 4, 4).

    Uses the general matrix inverse, not :func:`invert_rigid`: the poses may be a network's
    prediction that is only nearly rigid, and the synthetic ground truth (flow, correspondences)
    and the benchmark's numbers are defined with this form. numpy or torch, like the input.
    """
    if isinstance(cam_from_world, torch.Tensor):
        return cam_from_world[j] @ torch.linalg.inv(cam_from_world[i])
    return cam_from_world[j] @ np.linalg.inv(cam_from_world[i])


def relative_poses(cam_from_world: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """``cam_j_from_cam_i`` (P, 4, 4) float64 for index pairs (P, 2) ``(i, j)`` of (N, 4, 4) poses.

    The batched form the metrics use; rigid poses (inverse by :func:`invert_rigid`).
    """
    poses = np.asarray(cam_from_world, dtype=np.float64)
    index = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    return poses[index[:, 1]] @ invert_rigid(poses[index[:, 0]])


# --------------------------------------------------------------------------------------------
# Angles
# --------------------------------------------------------------------------------------------


def rotation_angle(rotation_a: Any, rotation_b: Any, eps: float = 0.0) -> Any:
    """Geodesic angle (radians, 0..pi) between rotations (..., 3, 3): ``arccos((tr(A^T B) - 1) / 2)``.

    Evaluated as ``atan2(|vee(M - M^T)| / 2, (tr M - 1) / 2)`` with ``M = A^T B``: the same angle
    as the arccos, but accurate near 0 and pi. ``eps`` (> 0 for a loss) goes under the square
    root of the vector norm so the gradient at exactly zero is zero instead of NaN; 0 gives the
    exact angle. Returns (...,).
    """
    if _is_torch(rotation_a, rotation_b):
        a, b = _as_torch_pair(rotation_a, rotation_b)
        m = a.transpose(-1, -2) @ b
        cos = (m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2] - 1) / 2
        axis = torch.stack(
            (m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]),
            dim=-1,
        )
        sin = torch.sqrt(axis.pow(2).sum(dim=-1) + eps**2) / 2
        return torch.atan2(sin, cos)
    # numpy branch: own names, so each variable has one type (the torch branch above uses a, b, m).
    a_np = np.asarray(rotation_a, dtype=np.float64)
    b_np = np.asarray(rotation_b, dtype=np.float64)
    m_np = np.swapaxes(a_np, -1, -2) @ b_np
    cos_np = (np.trace(m_np, axis1=-2, axis2=-1) - 1.0) / 2.0
    axis_np = np.stack(
        [
            m_np[..., 2, 1] - m_np[..., 1, 2],
            m_np[..., 0, 2] - m_np[..., 2, 0],
            m_np[..., 1, 0] - m_np[..., 0, 1],
        ],
        -1,
    )
    sin_np = (
        np.linalg.norm(axis_np, axis=-1)
        if eps == 0
        else np.sqrt(np.sum(axis_np * axis_np, axis=-1) + eps**2)
    ) / 2.0
    return np.arctan2(sin_np, cos_np)


def translation_angle(t_a: Any, t_b: Any, eps: float = 0.0) -> Any:
    """Angle (radians, 0..pi) between translation directions (..., 3): ``arccos(<a, b> / (|a| |b|))``.

    Evaluated as ``atan2(|a x b|, <a, b>)``: scale-free and accurate near 0 and pi. A zero vector
    gives 0 (no direction; the metrics turn short vectors into NaN themselves). ``eps`` as in
    :func:`rotation_angle`. Returns (...,).
    """
    if _is_torch(t_a, t_b):
        a, b = _as_torch_pair(t_a, t_b)
        cross = torch.linalg.cross(a, b, dim=-1)
        sin = torch.sqrt(cross.pow(2).sum(dim=-1) + eps**2)
        return torch.atan2(sin, (a * b).sum(dim=-1))
    a_np = np.asarray(t_a, dtype=np.float64)  # own names again, as in rotation_angle
    b_np = np.asarray(t_b, dtype=np.float64)
    cross_np = np.cross(a_np, b_np)
    sin_np = (
        np.linalg.norm(cross_np, axis=-1)
        if eps == 0
        else np.sqrt(np.sum(cross_np * cross_np, axis=-1) + eps**2)
    )
    return np.arctan2(sin_np, np.sum(a_np * b_np, axis=-1))


# --------------------------------------------------------------------------------------------
# Back-projection
# --------------------------------------------------------------------------------------------

#: Smallest |ray_z| z-depth back-projection divides by (rays at or behind 90 degrees have no z-depth).
MIN_RAY_Z = 1e-6


def backproject(
    depth: torch.Tensor, rays: torch.Tensor, depth_convention: str = "range"
) -> torch.Tensor:
    """3-D points in the camera frame from depth values and unit rays.

    Args:
        depth: (...,) depth per ray: range along the ray, or z-depth.
        rays: (..., 3) unit rays (broadcast against ``depth``).
        depth_convention: ``"range"`` (``X = D ray``) or ``"z"`` (``X = D ray / ray_z``; only
            meaningful in front of the camera: a ``ray_z`` with ``|ray_z| <= MIN_RAY_Z`` is
            replaced by :data:`MIN_RAY_Z` so nothing divides by zero, and a ray behind the
            camera is divided by its own negative ``ray_z``).

    Returns:
        (..., 3) points, in the unit of ``depth``.

    Raises:
        InputError: for another ``depth_convention``.
    """
    if depth_convention == "range":
        return depth[..., None] * rays
    if depth_convention == "z":
        z = rays[..., 2:3]
        safe = torch.where(z.abs() > MIN_RAY_Z, z, torch.full_like(z, MIN_RAY_Z))
        return depth[..., None] * rays / safe
    raise InputError(f"depth_convention must be 'range' or 'z', got {depth_convention!r}")


# --------------------------------------------------------------------------------------------
# Quaternions (w, x, y, z)
# --------------------------------------------------------------------------------------------


def quaternion_to_rotation(quaternion: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) float64 from quaternions (..., 4) ``(w, x, y, z)``.

    The quaternion is normalised here; a zero quaternion gives NaN (callers that read files
    check for it first and name the line).
    """
    q = np.asarray(quaternion, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def rotation_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) ``(w, x, y, z)`` float64 with ``w >= 0`` from rotations (..., 3, 3).

    Shepperd's method: the trace branch when it is positive, else the branch of the largest
    diagonal element, so no division is by a small number; the result is renormalised so a
    slightly non-orthonormal input still gives a unit quaternion.
    """
    rotations = np.asarray(rotation, dtype=np.float64)
    flat = rotations.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for k, r in enumerate(flat):
        trace = r[0, 0] + r[1, 1] + r[2, 2]
        if trace > 0:
            s = 2.0 * math.sqrt(trace + 1.0)
            q = np.array(
                [
                    0.25 * s,
                    (r[2, 1] - r[1, 2]) / s,
                    (r[0, 2] - r[2, 0]) / s,
                    (r[1, 0] - r[0, 1]) / s,
                ]
            )
        else:
            i = int(np.argmax([r[0, 0], r[1, 1], r[2, 2]]))
            j, m = (i + 1) % 3, (i + 2) % 3
            s = 2.0 * math.sqrt(max(1.0 + r[i, i] - r[j, j] - r[m, m], 1e-300))
            q = np.zeros(4)
            q[0] = (r[m, j] - r[j, m]) / s
            q[1 + i] = 0.25 * s
            q[1 + j] = (r[j, i] + r[i, j]) / s
            q[1 + m] = (r[m, i] + r[i, m]) / s
        q /= np.linalg.norm(q)
        out[k] = q if q[0] >= 0 else -q
    return out.reshape(rotations.shape[:-2] + (4,))


def rotations_from_rotvecs(rotvecs: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices of (N, 3) axis-angle vectors (radians), by Rodrigues' formula."""
    w = np.asarray(rotvecs, dtype=np.float64).reshape(-1, 3)
    theta = np.linalg.norm(w, axis=1)
    k = np.zeros((len(w), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    small = theta < 1e-12
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(safe) / safe)[:, None, None]
    b = np.where(small, 0.5, (1.0 - np.cos(safe)) / safe**2)[:, None, None]
    return np.eye(3)[None] + a * k + b * (k @ k)
