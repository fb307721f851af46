"""Helpers shared by the dataset readers: error messages, number parsing, pose maths."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from raytun3r_plugin.errors import CameraError, DatasetError

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


def parse_floats(path: str | Path, line: int, tokens: list[str], count: int | None, what: str) -> np.ndarray:
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


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from quaternions (..., 4) in (w, x, y, z) order (normalised
    here; the caller checks for zero quaternions)."""
    q = np.asarray(q, dtype=np.float64)
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


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) (w, x, y, z), w >= 0, from rotation matrices (..., 3, 3)."""
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    out = np.empty((m.shape[0], 4))
    for k, r in enumerate(m):
        tr = r[0, 0] + r[1, 1] + r[2, 2]
        if tr > 0:
            s = 2.0 * math.sqrt(tr + 1.0)
            q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
        else:
            i = int(np.argmax([r[0, 0], r[1, 1], r[2, 2]]))
            j, m_ = (i + 1) % 3, (i + 2) % 3
            s = 2.0 * math.sqrt(max(1.0 + r[i, i] - r[j, j] - r[m_, m_], 1e-300))
            q = [0.0, 0.0, 0.0, 0.0]
            q[0] = (r[m_, j] - r[j, m_]) / s
            q[1 + i] = 0.25 * s
            q[1 + j] = (r[j, i] + r[i, j]) / s
            q[1 + m_] = (r[m_, i] + r[i, m_]) / s
        q = np.array(q)
        out[k] = q if q[0] >= 0 else -q
    return out.reshape(R.shape[:-2] + (4,))


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


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4) (exact transpose of the rotation block)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def check_rigid(path: str | Path, line: int | None, T: np.ndarray, what: str, tol: float = 1e-3) -> None:
    """Fail unless the 3x3 block of ``T`` is a rotation within ``tol`` (orthonormal, det +1)."""
    R = T[:3, :3]
    err = np.abs(R @ R.T - np.eye(3)).max()
    if not np.isfinite(T).all():
        raise fail(path, line, f"{what}: non-finite value")
    if err > tol or np.linalg.det(R) <= 0:
        raise fail(path, line, f"{what}: rotation block is not a rotation (max |R R^T - I| = {err:.3g})")
