"""Project Aria device calibration JSON and Aria Digital Twin (ADT) sequences.

Calibration JSON (``projectaria_tools`` ``device_calibration_to_json_string`` / the
``calibration.json`` of Aria datasets): ``CameraCalibrations`` is a list of objects with
``Label`` ("camera-rgb", "camera-slam-left", "camera-slam-right", ...), ``Projection``
``{"Name": "FisheyeRadTanThinPrism", "Params": [f, cx, cy, k0..k5, p0, p1, s0..s3]}`` (15
numbers, one focal length) and ``T_Device_Camera`` ``{"Translation": [x, y, z],
"UnitQuaternion": [w, [x, y, z]]}`` (camera-to-device, metres). The image size is not in the
JSON: it is taken from the first image (or given).

ADT sequence, raytun3r's extracted layout (frames live in VRS files, which need
``projectaria_tools`` to read, so they are exported once to PNG)::

    <seq>/aria_trajectory.csv              ADT / MPS closed-loop trajectory (device-to-world)
    <seq>/calibration.json                 the device calibration above
    <seq>/<label>/<timestamp_ns>.png       images of camera <label>, device time in ns
    <seq>/depth/<label>/<timestamp_ns>.png ADT depth, uint16 millimetres, planar z (optional)

Trajectory columns used: ``tracking_timestamp_us`` (device time, us), ``tx/ty/tz_world_device``
(m), ``qx/qy/qz/qw_world_device``. Depth is converted from planar z to range with the camera's
unprojection (range = z / ray_z).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from raytun3r_plugin.datasets._common import (
    check_rigid,
    fail,
    invert_pose,
    quat_to_rot,
    rot_to_quat,
    slerp,
)
from raytun3r_plugin.datasets.sequence import Sequence
from raytun3r_plugin.errors import CameraError, DatasetError

if TYPE_CHECKING:  # pragma: no cover - typing only
    from raytun3r_plugin.cameras import Camera

__all__ = ["load_adt", "read_aria_calibration", "read_aria_trajectory"]

_TRAJ_COLS = (
    "tracking_timestamp_us",
    "tx_world_device",
    "ty_world_device",
    "tz_world_device",
    "qx_world_device",
    "qy_world_device",
    "qz_world_device",
    "qw_world_device",
)


def _line_of(text: str, needle: str, start: int = 0) -> int | None:
    i = text.find(needle, start)
    return None if i < 0 else text.count("\n", 0, i) + 1


def _numbers(path: Path, line: int | None, v, count: int, what: str) -> np.ndarray:
    ok = isinstance(v, list) and len(v) == count
    ok = ok and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
    if not ok:
        raise fail(path, line, f"{what}: expected a list of {count} numbers, got {v!r:.80}")
    a = np.asarray(v, dtype=np.float64)
    if not np.isfinite(a).all():
        raise fail(path, line, f"{what}: non-finite value")
    return a


def read_aria_calibration(
    path: str | Path, label: str, width: int, height: int
) -> tuple[Camera, np.ndarray]:
    """Camera ``label`` of an Aria device calibration JSON.

    Args:
        path: the JSON file.
        label: ``Label`` of the camera ("camera-rgb", "camera-slam-left", ...).
        width, height: image size in pixels (not stored in the JSON).

    Returns:
        (camera, T_device_camera): a :class:`~raytun3r_plugin.cameras.Fisheye624` (fx = fy = f)
        and the (4, 4) float64 camera-to-device transform.

    Raises:
        DatasetError: invalid JSON, missing label or field, a projection other than
            ``FisheyeRadTanThinPrism`` (its parameter layout is not verified here), wrong
            parameter count, non-unit quaternion.
    """
    from raytun3r_plugin import cameras

    p = Path(path)
    if not p.is_file():
        raise fail(p, None, "calibration file not found")
    text = p.read_text(encoding="utf-8")
    try:
        d = json.loads(text)
    except json.JSONDecodeError as e:
        raise fail(p, e.lineno, f"invalid JSON: {e.msg}") from None
    cals = d.get("CameraCalibrations") if isinstance(d, dict) else None
    if not isinstance(cals, list):
        raise fail(p, None, "field 'CameraCalibrations' is missing or not a list")
    labels = [c.get("Label") for c in cals if isinstance(c, dict)]
    if label not in labels:
        raise fail(p, None, f"no CameraCalibrations entry with Label {label!r} (have {labels})")
    c = cals[labels.index(label)]
    line = _line_of(text, json.dumps(label))
    where = f"CameraCalibrations[Label={label}]"
    proj = c.get("Projection")
    if not isinstance(proj, dict) or "Name" not in proj or "Params" not in proj:
        raise fail(p, line, f"{where}.Projection must hold 'Name' and 'Params'")
    if proj["Name"] != "FisheyeRadTanThinPrism":
        raise fail(
            p,
            _line_of(text, json.dumps(proj["Name"]), text.find(json.dumps(label))),
            f"{where}.Projection.Name {proj['Name']!r} is not supported "
            "(only FisheyeRadTanThinPrism = Fisheye624)",
        )
    v = _numbers(p, line, proj["Params"], 15, f"{where}.Projection.Params")
    names = ("k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3")
    params = {"fx": v[0], "fy": v[0], "cx": v[1], "cy": v[2]}
    params.update({n: float(x) for n, x in zip(names, v[3:], strict=True)})
    try:
        cam = cameras.Fisheye624(int(width), int(height), params)
    except CameraError as e:
        raise fail(p, line, f"{where}: invalid camera: {e}") from e
    T = c.get("T_Device_Camera")
    if not isinstance(T, dict) or "Translation" not in T or "UnitQuaternion" not in T:
        raise fail(p, line, f"{where}.T_Device_Camera must hold 'Translation' and 'UnitQuaternion'")
    t = _numbers(p, line, T["Translation"], 3, f"{where}.T_Device_Camera.Translation")
    q = T["UnitQuaternion"]
    if not (isinstance(q, list) and len(q) == 2 and isinstance(q[1], list)):
        raise fail(
            p, line, f"{where}.T_Device_Camera.UnitQuaternion must be [w, [x, y, z]], got {q!r:.80}"
        )
    w = _numbers(p, line, [q[0]], 1, f"{where}.T_Device_Camera.UnitQuaternion[0]")
    xyz = _numbers(p, line, q[1], 3, f"{where}.T_Device_Camera.UnitQuaternion[1]")
    qv = np.concatenate([w, xyz])
    if abs(np.linalg.norm(qv) - 1.0) > 1e-3:
        raise fail(
            p,
            line,
            f"{where}.T_Device_Camera.UnitQuaternion is not unit length "
            f"(norm {np.linalg.norm(qv):.6g})",
        )
    M = np.eye(4)
    M[:3, :3] = quat_to_rot(qv)
    M[:3, 3] = t
    return cam, M


def read_aria_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """An ADT ``aria_trajectory.csv`` / MPS ``closed_loop_trajectory.csv``.

    Returns:
        (t_us, world_from_device): (M,) int64 device time in microseconds (strictly
        increasing) and (M, 4, 4) float64 device-to-world transforms.

    Raises:
        DatasetError: missing file or column, non-numeric value, zero quaternion,
            non-increasing timestamps (file and line named).
    """
    p = Path(path)
    if not p.is_file():
        raise fail(p, None, "trajectory file not found")
    with p.open(newline="", encoding="utf-8") as f:
        rows = list(csv.reader(f))
    if not rows:
        raise fail(p, 1, "empty file (expected a header row)")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in _TRAJ_COLS if c not in header]
    if missing:
        raise fail(p, 1, f"missing column(s) {missing}")
    idx = [header.index(c) for c in _TRAJ_COLS]
    ts: list[int] = []
    poses: list[np.ndarray] = []
    for k, row in enumerate(rows[1:], start=2):
        if not row or all(not x.strip() for x in row):
            continue
        if len(row) < len(header):
            raise fail(p, k, f"expected {len(header)} fields, got {len(row)}")
        try:
            t_us = int(row[idx[0]])
        except ValueError:
            raise fail(p, k, f"tracking_timestamp_us {row[idx[0]]!r} is not an integer") from None
        try:
            v = np.array([float(row[i]) for i in idx[1:]])
        except ValueError:
            raise fail(p, k, "tx..qw_world_device: a value is not a number") from None
        if not np.isfinite(v).all():
            raise fail(p, k, "tx..qw_world_device: non-finite value")
        q = np.array([v[6], v[3], v[4], v[5]])  # (w, x, y, z)
        if np.linalg.norm(q) < 1e-8:
            raise fail(p, k, "quaternion qx..qw_world_device is zero")
        if ts and t_us <= ts[-1]:
            raise fail(p, k, f"tracking_timestamp_us {t_us} is not increasing")
        T = np.eye(4)
        T[:3, :3] = quat_to_rot(q / np.linalg.norm(q))
        T[:3, 3] = v[:3]
        ts.append(t_us)
        poses.append(T)
    if len(ts) < 2:
        raise fail(p, None, f"need at least 2 trajectory rows, got {len(ts)}")
    return np.array(ts, dtype=np.int64), np.stack(poses)


def _interpolate(
    t_us: np.ndarray, wfd: np.ndarray, t_query_us: np.ndarray, max_dt_us: float
) -> tuple[np.ndarray, np.ndarray]:
    """Device-to-world at ``t_query_us`` (lerp of the position, slerp of the rotation) and
    which queries lie inside the trajectory with both bracketing samples within
    ``max_dt_us`` (a query on a sample is always kept)."""
    j = np.clip(np.searchsorted(t_us, t_query_us, side="right") - 1, 0, len(t_us) - 2)
    t0, t1 = t_us[j].astype(np.float64), t_us[j + 1].astype(np.float64)
    inside = (t_query_us >= t_us[0]) & (t_query_us <= t_us[-1])
    on_sample = (t_query_us == t0) | (t_query_us == t1)
    near = (t_query_us - t0 <= max_dt_us) & (t1 - t_query_us <= max_dt_us)
    ok = inside & (on_sample | near)
    a = np.clip((t_query_us - t0) / (t1 - t0), 0.0, 1.0)
    q0 = np.stack([rot_to_quat(R) for R in wfd[j, :3, :3]])
    q1 = np.stack([rot_to_quat(R) for R in wfd[j + 1, :3, :3]])
    q = slerp(q0, q1, a)
    out = np.tile(np.eye(4), (len(t_query_us), 1, 1))
    out[:, :3, :3] = np.stack([quat_to_rot(x) for x in q])
    out[:, :3, 3] = (1 - a)[:, None] * wfd[j, :3, 3] + a[:, None] * wfd[j + 1, :3, 3]
    return out, ok


def _z_to_range(camera: Camera, z: np.ndarray) -> np.ndarray:
    """Planar z (H, W) metres -> range along the unit ray through the camera's unproject."""
    rays, valid = camera.ray_table()
    rz = rays[..., 2].detach().cpu().numpy().astype(np.float64)
    ok = valid.detach().cpu().numpy().astype(bool) & (rz > 1e-6) & (z > 0)
    return np.where(ok, z / np.maximum(rz, 1e-6), 0.0).astype(np.float32)


def load_adt(
    folder: str | Path,
    label: str = "camera-rgb",
    calibration: str | Path | None = None,
    trajectory: str | Path | None = None,
    size: tuple[int, int] | None = None,
    depth: bool = True,
    max_dt: float = 0.005,
    name: str | None = None,
) -> Sequence:
    """Read an (extracted) Aria Digital Twin sequence as a :class:`Sequence` (see module doc).

    Args:
        folder: the sequence folder.
        label: the camera (``CameraCalibrations`` ``Label`` and image sub-folder).
        calibration: the device calibration JSON (default ``<folder>/calibration.json``).
        trajectory: default ``<folder>/aria_trajectory.csv``.
        size: (width, height) in pixels; default: the first image's size.
        depth: read ``depth/<label>/<timestamp_ns>.png`` when that folder exists.
        max_dt: seconds; frames without a trajectory sample on each side within ``max_dt``
            are dropped (``meta["n_dropped"]``).
        name: sequence name (default: the folder name / label).

    ``cam_from_world = inv(world_from_device(t) @ T_device_camera)``; ``depth`` is range in
    metres (ADT planar-z millimetres converted), 0 = unknown; ``depth_kind = "range"``.
    ``meta``: ``T_device_camera`` (4, 4), ``per_frame["timestamp_ns"]``.

    Raises:
        DatasetError: missing files, malformed calibration / trajectory (file, field or line),
            image or depth file names that are not integer ns, depth of the wrong size or dtype,
            no frame with a pose.
    """
    import cv2

    root = Path(folder)
    img_dir = root / label
    if not img_dir.is_dir():
        raise fail(img_dir, None, "image folder not found")
    files = sorted(f for f in img_dir.iterdir() if f.suffix.lower() in (".png", ".jpg"))
    if not files:
        raise fail(img_dir, None, "no .png/.jpg images")
    for f in files:
        if not f.stem.isdigit():
            raise fail(f, None, "image file name is not an integer timestamp in ns")
    files.sort(key=lambda f: int(f.stem))
    t_ns = np.array([int(f.stem) for f in files], dtype=np.int64)
    if size is None:
        first = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise fail(files[0], None, "cannot decode image")
        size = (int(first.shape[1]), int(first.shape[0]))
    cam, T_dc = read_aria_calibration(calibration or root / "calibration.json", label, *size)
    check_rigid(calibration or root / "calibration.json", None, T_dc, "T_Device_Camera")
    t_us, wfd = read_aria_trajectory(trajectory or root / "aria_trajectory.csv")
    wfd_q, ok = _interpolate(t_us, wfd, t_ns.astype(np.float64) / 1e3, max_dt * 1e6)
    if not ok.any():
        raise DatasetError(
            f"{root}: no image of {label!r} has trajectory samples within {max_dt} s"
        )
    keep = np.flatnonzero(ok)
    files = [files[k] for k in keep]
    cfw = invert_pose(wfd_q[keep] @ T_dc)
    dmaps = None
    ddir = root / "depth" / label
    if depth and ddir.is_dir():
        dmaps = np.stack([_depth_png(ddir / f"{f.stem}.png", cam) for f in files])
    return Sequence(
        name=name or f"{root.name}/{label}",
        camera=cam,
        timestamps=t_ns[keep].astype(np.float64) * 1e-9,
        cam_from_world=cfw,
        image_paths=files,
        depth=dmaps,
        depth_kind="range",
        meta={
            "source": str(root),
            "format": "adt",
            "label": label,
            "T_device_camera": T_dc,
            "n_dropped": int(len(t_ns) - len(keep)),
            "per_frame": {"timestamp_ns": t_ns[keep]},
        },
    )


def _depth_png(path: Path, camera: Camera) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise fail(path, None, "depth file not found")
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None:
        raise fail(path, None, "cannot decode depth image")
    if d.dtype != np.uint16 or d.ndim != 2:
        raise fail(path, None, f"ADT depth must be 1-channel uint16 mm, got {d.dtype} {d.shape}")
    if d.shape != (camera.height, camera.width):
        raise fail(
            path,
            None,
            f"depth is {d.shape[1]}x{d.shape[0]} px, camera is {camera.width}x{camera.height}",
        )
    return _z_to_range(camera, d.astype(np.float64) * 1e-3)
