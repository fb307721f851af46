"""Helpers shared by the dataset readers: error messages, number parsing, pose maths."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from raytun3r_plugin.errors import CameraError, DatasetError

# Pose maths lives in raytun3r_plugin.poses; the readers keep their short names.
from raytun3r_plugin.poses import invert_rigid as invert_pose
from raytun3r_plugin.poses import quaternion_to_rotation as quat_to_rot
from raytun3r_plugin.poses import rotation_to_quaternion as rot_to_quat

__all__ = [
    "check_rigid",
    "fail",
    "invert_pose",
    "load_camera",
    "parse_floats",
    "quat_to_rot",
    "rot_to_quat",
    "slerp",
]


def fail(path: str | Path, line: int | None, problem: str) -> DatasetError:
    """A :class:`DatasetError` whose message starts with ``path:line:`` (or ``path:``)."""
    where = f"{path}:{line}" if line is not None else f"{path}"
    return DatasetError(f"{where}: {problem}")


def parse_floats(
    path: str | Path, line: int, tokens: list[str], count: int | None, what: str
) -> np.ndarray:
    """Parse ``tokens`` as finite floats (exactly ``count`` of them unless None) or fail naming
    the file, the line and ``what`` the numbers are."""
    if count is not None and len(tokens) != count:
        raise fail(path, line, f"{what}: expected {count} numbers, got {len(tokens)}")
    try:
        vals = np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise fail(path, line, f"{what}: {bad!r} is not a number") from None
    if not np.isfinite(vals).all():
        raise fail(path, line, f"{what}: non-finite value")
    return vals


def _is_float(t: str) -> bool:
    try:
        float(t)
    except ValueError:
        return False
    return True


def load_camera(path: str | Path, camera: str | int | None = None):
    """``raytun3r_plugin.cameras.load`` with errors re-raised as :class:`DatasetError` (the
    camera reader's message already names the file and the field)."""
    from raytun3r_plugin import cameras

    p = Path(path)
    if not p.is_file():
        raise fail(p, None, "calibration file not found")
    try:
        return cameras.load(p, camera=camera)
    except CameraError as e:
        raise DatasetError(str(e)) from e


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (N, 4) (w, x, y, z) at ``alpha`` (N,)
    in [0, 1], along the shorter arc."""
    q0 = q0 / np.linalg.norm(q0, axis=-1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.abs(dot)
    a = alpha[:, None]
    theta = np.arccos(np.clip(dot, -1.0, 1.0))[:, None]
    sin = np.sin(theta)
    small = sin < 1e-9
    w0 = np.where(small, 1.0 - a, np.sin((1.0 - a) * theta) / np.where(small, 1.0, sin))
    w1 = np.where(small, a, np.sin(a * theta) / np.where(small, 1.0, sin))
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def check_rigid(
    path: str | Path, line: int | None, T: np.ndarray, what: str, tol: float = 1e-3
) -> None:
    """Fail unless the 3x3 block of ``T`` is a rotation within ``tol`` (orthonormal, det +1)."""
    R = T[:3, :3]
    err = np.abs(R @ R.T - np.eye(3)).max()
    if not np.isfinite(T).all():
        raise fail(path, line, f"{what}: non-finite value")
    if err > tol or np.linalg.det(R) <= 0:
        raise fail(
            path, line, f"{what}: rotation block is not a rotation (max |R R^T - I| = {err:.3g})"
        )
