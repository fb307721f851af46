"""Writing predictions: depth (.npy + colour .png), TUM trajectories, coloured PLY point clouds."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def colourise_depth(depth: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """(H, W) depth -> (H, W, 3) uint8 BGR (OpenCV turbo map on inverse depth, 2-98% range)."""
    import cv2

    valid = np.isfinite(depth) & (depth > 0) if valid is None else valid & np.isfinite(depth) & (depth > 0)
    inverse = np.zeros_like(depth, dtype=np.float32)
    inverse[valid] = 1.0 / depth[valid]
    if valid.any():
        low, high = np.percentile(inverse[valid], [2, 98])
        inverse = np.clip((inverse - low) / max(high - low, 1e-12), 0, 1)
    image = cv2.applyColorMap((inverse * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    image[~valid] = 0
    return image


def rotation_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> unit quaternion (qx, qy, qz, qw) with qw >= 0."""
    m = rotation
    trace = np.trace(m)
    if trace > 0:
        s = np.sqrt(trace + 1.0) * 2
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k]) * 2
        q = np.empty(4)
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
        q[3] = (m[k, j] - m[j, k]) / s
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def write_tum(path: str | os.PathLike, timestamps: np.ndarray, cam_from_world: np.ndarray) -> None:
    """TUM trajectory: one line ``t tx ty tz qx qy qz qw`` per frame, camera-to-world poses."""
    lines = ["# timestamp tx ty tz qx qy qz qw (world_from_cam)"]
    for stamp, pose in zip(timestamps, cam_from_world, strict=True):
        world_from_cam = np.linalg.inv(pose)
        t = world_from_cam[:3, 3]
        q = rotation_to_quaternion(world_from_cam[:3, :3])
        lines.append(" ".join(f"{v:.9g}" for v in (stamp, *t, *q)))
    Path(path).write_text("\n".join(lines) + "\n")


def write_ply(path: str | os.PathLike, points: np.ndarray, colours: np.ndarray) -> None:
    """Binary little-endian PLY with float32 xyz and uint8 rgb; points (N, 3), colours (N, 3) in [0, 1]."""
    points = np.asarray(points, dtype="<f4")
    colours = (np.clip(np.asarray(colours), 0, 1) * 255 + 0.5).astype(np.uint8)
    record = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    record["x"], record["y"], record["z"] = points.T
    record["red"], record["green"], record["blue"] = colours.T
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    with open(path, "wb") as handle:
        handle.write(header.encode("ascii"))
        handle.write(record.tobytes())


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read back what :func:`write_ply` writes: (N, 3) float32 points and (N, 3) uint8 colours."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    count = int(next(line for line in data[:end].decode().splitlines() if line.startswith("element vertex")).split()[-1])
    record = np.frombuffer(data[end:], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")], count=count)
    return np.stack([record["x"], record["y"], record["z"]], -1), np.stack([record["red"], record["green"], record["blue"]], -1)
