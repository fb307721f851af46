"""KITTI-360 fisheye cameras (``image_02`` left, ``image_03`` right).

Files (relative to the KITTI-360 root)::

    calibration/image_02.yaml              MEI camera (OpenCV YAML, read by raytun3r cameras)
    calibration/calib_cam_to_pose.txt      "image_0X: " + 12 numbers (3x4 camera-to-pose)
    data_poses/<seq>/poses.txt             "frame" + 12 numbers (3x4 pose-to-world), only frames
                                           with a pose are listed
    data_2d_raw/<seq>/image_02/data_rgb/%010d.png
    data_2d_raw/<seq>/image_02/timestamps.txt (optional, "YYYY-MM-DD HH:MM:SS.fffffffff" per frame)

``world_from_cam = pose[frame] @ cam_to_pose[camera]`` (no rectification for the fisheyes),
``cam_from_world`` its inverse. Only frames with a pose and an image are kept.
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import numpy as np

from raytun3r_plugin.datasets._common import (
    check_rigid,
    fail,
    invert_pose,
    load_camera,
    parse_floats,
)
from raytun3r_plugin.datasets.sequence import Sequence

__all__ = ["load_kitti360", "read_cam_to_pose", "read_poses_txt"]


def _rows34(vals: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :4] = vals.reshape(3, 4)
    return T


def read_cam_to_pose(path: Path) -> dict[str, np.ndarray]:
    """``{"image_00": (4, 4), ...}`` camera-to-pose transforms from ``calib_cam_to_pose.txt``."""
    if not path.is_file():
        raise fail(path, None, "file not found")
    out: dict[str, np.ndarray] = {}
    for lineno, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        key, sep, rest = s.partition(":")
        if not sep:
            raise fail(path, lineno, "expected 'image_0X: <12 numbers>'")
        T = _rows34(
            parse_floats(path, lineno, rest.split(), 12, f"{key.strip()} (3x4 camera-to-pose)")
        )
        check_rigid(path, lineno, T, key.strip())
        out[key.strip()] = T
    return out


def read_poses_txt(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Frame indices (N,) int64 and pose-to-world transforms (N, 4, 4) from ``poses.txt``."""
    if not path.is_file():
        raise fail(path, None, "file not found")
    frames: list[int] = []
    poses: list[np.ndarray] = []
    for lineno, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        tok = s.split()
        if len(tok) != 13:
            raise fail(
                path, lineno, f"expected 'frame' + 12 numbers (3x4 pose), got {len(tok)} fields"
            )
        try:
            f = int(tok[0])
        except ValueError:
            raise fail(path, lineno, f"frame index {tok[0]!r} is not an integer") from None
        if frames and f <= frames[-1]:
            raise fail(path, lineno, f"frame {f} is not after the previous frame {frames[-1]}")
        T = _rows34(parse_floats(path, lineno, tok[1:], 12, "3x4 pose"))
        check_rigid(path, lineno, T, f"pose of frame {f}")
        frames.append(f)
        poses.append(T)
    return np.array(frames, dtype=np.int64), np.array(poses).reshape(-1, 4, 4)


def _timestamps(path: Path, frames: np.ndarray) -> np.ndarray | None:
    if not path.is_file():
        return None
    lines = path.read_text(encoding="utf-8").splitlines()
    out = np.zeros(frames.size)
    for i, f in enumerate(frames):
        if f >= len(lines):
            raise fail(path, None, f"no timestamp line for frame {f} (file has {len(lines)} lines)")
        s = lines[f].strip()
        try:
            date, _, frac = s.partition(".")
            base = _dt.datetime.strptime(date, "%Y-%m-%d %H:%M:%S").replace(tzinfo=_dt.timezone.utc)
            out[i] = base.timestamp() + (float("0." + frac) if frac else 0.0)
        except ValueError:
            raise fail(
                path, int(f) + 1, f"timestamp {s!r} is not 'YYYY-MM-DD HH:MM:SS.fffffffff'"
            ) from None
    return out


def load_kitti360(
    root: str | Path, sequence: str | int, camera: str = "image_02", name: str | None = None
) -> Sequence:
    """Read one KITTI-360 sequence of a fisheye camera.

    Args:
        root: KITTI-360 root (holding ``calibration``, ``data_poses``, ``data_2d_raw``).
        sequence: folder name such as ``2013_05_28_drive_0000_sync`` or its number (0).
        camera: "image_02" or "image_03".
        name: sequence name (default ``<sequence>/<camera>``).

    Timestamps come from ``timestamps.txt`` when present (UTC seconds), else frame * 0.1 s.
    ``meta["per_frame"]["frame"]`` holds the KITTI-360 frame indices.

    Raises:
        DatasetError: missing files or folders, malformed lines (file and line named).
    """
    base = Path(root)
    seq = (
        f"2013_05_28_drive_{int(sequence):04d}_sync" if isinstance(sequence, int) else str(sequence)
    )
    cam = load_camera(base / "calibration" / f"{camera}.yaml")
    c2p_path = base / "calibration" / "calib_cam_to_pose.txt"
    c2p = read_cam_to_pose(c2p_path)
    if camera not in c2p:
        raise fail(c2p_path, None, f"no line for camera '{camera}' (found {sorted(c2p)})")
    frames, poses = read_poses_txt(base / "data_poses" / seq / "poses.txt")
    img_dir = base / "data_2d_raw" / seq / camera / "data_rgb"
    if not img_dir.is_dir():
        raise fail(img_dir, None, "image folder not found")
    have = np.array([(img_dir / f"{f:010d}.png").is_file() for f in frames], dtype=bool)
    frames, poses = frames[have], poses[have]
    if frames.size == 0:
        raise fail(img_dir, None, "no image of a frame with a pose")
    world_from_cam = poses @ c2p[camera]
    ts = _timestamps(base / "data_2d_raw" / seq / camera / "timestamps.txt", frames)
    if ts is None:
        ts = frames.astype(np.float64) * 0.1
    return Sequence(
        name=name or f"{seq}/{camera}",
        camera=cam,
        timestamps=ts,
        cam_from_world=invert_pose(world_from_cam),
        image_paths=[img_dir / f"{f:010d}.png" for f in frames],
        meta={
            "source": str(base),
            "format": "kitti360",
            "sequence": seq,
            "per_frame": {"frame": frames},
        },
    )
