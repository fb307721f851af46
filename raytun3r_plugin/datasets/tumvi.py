"""TUM-VI in the ASL/EuRoC layout.

Files::

    <root>/mav0/<cam>/data.csv        "#timestamp [ns],filename"
    <root>/mav0/<cam>/data/<filename> images (8- or 16-bit grey PNG)
    <root>/mav0/mocap0/data.csv       "#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m],
                                       q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"
    Kalibr camchain YAML              camN: {T_cam_imu (4x4 rows), camera_model, intrinsics, ...}

The mocap rows give the IMU/body frame S in the mocap world R (T_world_imu). Ground truth at an
image timestamp: linear interpolation of the position and slerp of the rotation between the
bracketing mocap samples; an image with no mocap sample within ``max_dt`` (10 ms) is dropped.
``world_from_cam = T_world_imu @ inv(T_cam_imu)``, ``cam_from_world`` its inverse.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from raytun3r_plugin.datasets._common import (
    check_rigid,
    fail,
    invert_pose,
    load_camera,
    parse_floats,
    quat_to_rot,
    slerp,
)
from raytun3r_plugin.datasets.sequence import Sequence

__all__ = ["load_tumvi", "read_euroc_csv"]


def read_euroc_csv(
    path: Path, columns: int, what: str
) -> tuple[np.ndarray, list[list[str]], list[int]]:
    """Rows of an ASL/EuRoC csv: int64 nanosecond timestamps (N,), the other fields as strings,
    and the line number of each row. ``#`` lines are comments; ``columns`` counts all fields."""
    if not path.is_file():
        raise fail(path, None, "file not found")
    stamps: list[int] = []
    rows: list[list[str]] = []
    linenos: list[int] = []
    for lineno, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        tok = [t.strip() for t in s.split(",")]
        if len(tok) != columns:
            raise fail(
                path, lineno, f"{what}: expected {columns} comma-separated fields, got {len(tok)}"
            )
        try:
            ts = int(tok[0])
        except ValueError:
            raise fail(
                path, lineno, f"timestamp {tok[0]!r} is not an integer (nanoseconds)"
            ) from None
        if stamps and ts <= stamps[-1]:
            raise fail(path, lineno, f"timestamp {ts} is not after the previous one ({stamps[-1]})")
        stamps.append(ts)
        rows.append(tok[1:])
        linenos.append(lineno)
    return np.array(stamps, dtype=np.int64), rows, linenos


def _find_camchain(root: Path, given: str | Path | None) -> Path:
    if given is not None:
        p = Path(given)
        if not p.is_file():
            raise fail(p, None, "camchain file not found")
        return p
    cands = [root / "camchain.yaml", root / "dso" / "camchain.yaml"]
    cands += sorted(root.glob("*camchain*.yaml")) + sorted((root / "dso").glob("*camchain*.yaml"))
    cands += sorted((root / "mav0").glob("*camchain*.yaml"))
    for c in cands:
        if c.is_file():
            return c
    raise fail(
        root,
        None,
        "no Kalibr camchain YAML found (camchain.yaml, dso/camchain.yaml, *camchain*.yaml); pass camchain=",
    )


def _t_cam_imu(path: Path, cam: str) -> np.ndarray:
    text = path.read_text(encoding="utf-8")
    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError as e:
        line = getattr(getattr(e, "problem_mark", None), "line", None)
        raise fail(path, None if line is None else line + 1, f"invalid YAML: {e}") from None
    if not isinstance(d, dict) or cam not in d or not isinstance(d[cam], dict):
        raise fail(path, None, f"camera '{cam}' not found")
    lines = text.splitlines()
    start = next((i for i, ln in enumerate(lines) if ln.startswith(f"{cam}:")), 0)
    line = next((i + 1 for i in range(start, len(lines)) if "T_cam_imu" in lines[i]), None)
    if "T_cam_imu" not in d[cam]:
        raise fail(path, None, f"field '{cam}.T_cam_imu' is missing")
    try:
        T = np.asarray(d[cam]["T_cam_imu"], dtype=np.float64)
    except (TypeError, ValueError):
        raise fail(path, line, f"field '{cam}.T_cam_imu' is not a numeric matrix") from None
    if T.shape != (4, 4):
        raise fail(path, line, f"field '{cam}.T_cam_imu' must be 4x4, got shape {T.shape}")
    check_rigid(path, line, T, f"{cam}.T_cam_imu")
    return T


def load_tumvi(
    folder: str | Path,
    cam: str = "cam0",
    camchain: str | Path | None = None,
    max_dt: float = 0.010,
    name: str | None = None,
) -> Sequence:
    """Read a TUM-VI (ASL/EuRoC layout) sequence with mocap ground truth.

    Args:
        folder: dataset root holding ``mav0/`` (e.g. ``dataset-room1_512_16``).
        cam: "cam0" or "cam1".
        camchain: Kalibr camchain YAML; by default ``camchain.yaml``, ``dso/camchain.yaml`` or
            the first ``*camchain*.yaml`` in the root, ``dso/`` or ``mav0/``.
        max_dt: drop images with no mocap sample within this many seconds.
        name: sequence name (default ``<folder name>/<cam>``).

    Returns a lazy :class:`Sequence` with timestamps in seconds (``meta["per_frame"]
    ["timestamp_ns"]`` keeps the integer nanoseconds) and ``meta["n_dropped"]``, the count of
    images without mocap.

    Raises:
        DatasetError: missing files, malformed csv/YAML lines (file and line named).
    """
    root = Path(folder)
    cc = _find_camchain(root, camchain)
    camera = load_camera(cc, camera=cam)
    T_cam_imu = _t_cam_imu(cc, cam)
    cam_dir = root / "mav0" / cam
    img_ts, img_rows, _ = read_euroc_csv(cam_dir / "data.csv", 2, "timestamp,filename")
    mpath = root / "mav0" / "mocap0" / "data.csv"
    mo_ts, mo_rows, mo_lines = read_euroc_csv(
        mpath, 8, "timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z"
    )
    if mo_ts.size == 0:
        raise fail(mpath, None, "no mocap samples")
    mo = np.stack(
        [
            parse_floats(mpath, ln, r, 7, "p_RS_R xyz, q_RS wxyz")
            for r, ln in zip(mo_rows, mo_lines, strict=True)
        ]
    )
    qn = np.linalg.norm(mo[:, 3:], axis=1)
    bad = np.flatnonzero(qn < 1e-8)
    if bad.size:
        raise fail(mpath, mo_lines[bad[0]], "quaternion q_RS is zero")
    pos, quat = mo[:, :3], mo[:, 3:] / qn[:, None]
    lim = int(round(max_dt * 1e9))
    k = np.searchsorted(mo_ts, img_ts)  # mo_ts[k-1] < ts <= mo_ts[k]
    k0 = np.clip(k - 1, 0, mo_ts.size - 1)
    k1 = np.clip(k, 0, mo_ts.size - 1)
    d0 = np.abs(img_ts - mo_ts[k0])
    d1 = np.abs(mo_ts[k1] - img_ts)
    keep = np.minimum(d0, d1) <= lim
    span = (mo_ts[k1] - mo_ts[k0]).astype(np.float64)
    alpha = np.where(
        span > 0, (img_ts - mo_ts[k0]).astype(np.float64) / np.where(span > 0, span, 1.0), 0.0
    )
    alpha = np.clip(alpha, 0.0, 1.0)
    p = pos[k0] + alpha[:, None] * (pos[k1] - pos[k0])
    q = slerp(quat[k0], quat[k1], alpha) if img_ts.size else np.zeros((0, 4))
    world_from_imu = np.tile(np.eye(4), (img_ts.size, 1, 1))
    world_from_imu[:, :3, :3] = quat_to_rot(q) if img_ts.size else np.zeros((0, 3, 3))
    world_from_imu[:, :3, 3] = p
    world_from_cam = world_from_imu @ invert_pose(T_cam_imu)
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        raise fail(
            mpath,
            None,
            f"no image of {cam_dir / 'data.csv'} has a mocap sample within {max_dt * 1e3:g} ms",
        )
    data = cam_dir / "data"
    return Sequence(
        name=name or f"{root.name}/{cam}",
        camera=camera,
        timestamps=img_ts[idx].astype(np.float64) * 1e-9,
        cam_from_world=invert_pose(world_from_cam[idx]),
        image_paths=[data / img_rows[i][0] for i in idx],
        meta={
            "source": str(root),
            "format": "tumvi",
            "camchain": str(cc),
            "n_dropped": int(img_ts.size - idx.size),
            "per_frame": {"timestamp_ns": img_ts[idx]},
        },
    )
