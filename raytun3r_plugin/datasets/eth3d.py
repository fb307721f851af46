"""ETH3D low-res many-view scenes recorded with the multi-camera rig (COLMAP text calibration).

Layout of an extracted scene (``<scene>_rig_undistorted.7z`` / the distorted rig archive)::

    <scene>/rig_calibration/cameras.txt           THIN_PRISM_FISHEYE, one camera per rig camera
    <scene>/rig_calibration/images.txt            cam_from_world per image (ground truth)
    <scene>/rig_calibration_undistorted/...       the same for the PINHOLE-undistorted images
    <scene>/images/images_rig_cam4/<t_ns>.png     one folder per rig camera (cam4 .. cam7)
    <scene>/images/images_rig_cam4_undistorted/<t_ns>.png

Image NAMEs in ``images.txt`` are ``<camera folder>/<timestamp in ns>.png`` relative to
``<scene>/images``. One :class:`Sequence` per rig camera; the rig transform of each camera to the
reference camera (``images_rig_cam4``, the reference sensor of COLMAP's ETH3D rig example) is
computed from the frames both cameras share and recorded in ``meta["rig"]``.

Depth (optional): raw little-endian float32 files of H x W values in row-major order, non-finite
= no ground truth (the ETH3D depth-map format); whether the values are planar z or range is not
documented for the rig, so the caller must say (``depth_kind``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from raytun3r_plugin.datasets._common import fail, invert_pose, load_camera
from raytun3r_plugin.datasets.colmap import read_images_txt
from raytun3r_plugin.datasets.sequence import Sequence
from raytun3r_plugin.errors import DatasetError

__all__ = ["eth3d_rig_cameras", "load_eth3d_rig", "load_eth3d_rig_all"]

REF_CAMERA = "images_rig_cam4"


def _calib_dir(scene: Path, undistorted: bool) -> Path:
    d = scene / ("rig_calibration_undistorted" if undistorted else "rig_calibration")
    for f in ("cameras.txt", "images.txt"):
        if not (d / f).is_file():
            raise fail(d / f, None, "file not found (ETH3D rig calibration)")
    return d


def _grouped(images_txt: Path) -> dict[str, list[dict]]:
    """Images of ``images.txt`` grouped by camera folder (the NAME's first component)."""
    groups: dict[str, list[dict]] = {}
    for im in read_images_txt(images_txt):
        parts = im["name"].replace("\\", "/").split("/")
        if len(parts) != 2 or not parts[0] or not parts[1]:
            raise fail(
                images_txt,
                im["line"],
                f"NAME {im['name']!r} is not '<camera folder>/<timestamp_ns>.png'",
            )
        stem = parts[1].rsplit(".", 1)[0]
        if not stem.isdigit():
            raise fail(
                images_txt,
                im["line"],
                f"NAME {im['name']!r}: file name is not an integer timestamp in ns",
            )
        im["timestamp_ns"] = int(stem)
        groups.setdefault(parts[0], []).append(im)
    if not groups:
        raise fail(images_txt, None, "no images listed")
    return groups


def eth3d_rig_cameras(scene: str | Path, undistorted: bool = False) -> list[str]:
    """The camera folder names (``images_rig_cam4`` ...) listed in the rig ``images.txt``."""
    d = _calib_dir(Path(scene), undistorted)
    return sorted(_grouped(d / "images.txt"))


def _read_depth(path: Path, h: int, w: int) -> np.ndarray:
    if not path.is_file():
        raise fail(path, None, "depth file not found")
    raw = np.fromfile(path, dtype="<f4")
    if raw.size != h * w:
        raise fail(path, None, f"depth file holds {raw.size} float32 values, expected {h}x{w}")
    d = raw.reshape(h, w).astype(np.float32)
    return np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)


def load_eth3d_rig(
    scene: str | Path,
    camera: str | None = None,
    undistorted: bool = False,
    depth_dir: str | Path | None = None,
    depth_kind: str | None = None,
    name: str | None = None,
) -> Sequence:
    """Read one camera of an ETH3D multi-camera-rig scene as a :class:`Sequence`.

    Args:
        scene: the scene folder (holding ``rig_calibration/`` and ``images/``).
        camera: camera folder name, e.g. ``"images_rig_cam5"`` (``_undistorted`` is appended
            for ``undistorted=True`` if missing); required when the scene has several cameras.
        undistorted: read ``rig_calibration_undistorted`` (PINHOLE) instead of the
            THIN_PRISM_FISHEYE calibration.
        depth_dir: folder holding one raw float32 depth file per image at ``<depth_dir>/<NAME>``
            (metres, H x W row-major, non-finite = unknown -> 0).
        depth_kind: "z" or "range": required with ``depth_dir`` (the rig depth convention is not
            documented, so it is never guessed).
        name: sequence name (default ``<scene>/<camera>``).

    Frames are ordered by timestamp (the image file name, ns); ``timestamps`` are seconds.
    ``meta["rig"]``: ``ref_camera``, ``cam_from_ref`` (4, 4) float64, the transform from the
    reference camera to this one taken from the first shared timestamp, ``n_shared`` (frames
    both cameras have), ``max_dev_m`` / ``max_dev_deg`` (how far the other shared frames'
    transforms deviate from it: a check that the ground truth is a rigid rig).
    ``meta["per_frame"]``: ``image_id``, ``name``, ``timestamp_ns``.

    Raises:
        DatasetError: missing files, malformed ``images.txt`` lines or NAMEs, one camera folder
            using several COLMAP cameras, unknown camera, depth without ``depth_kind``.
    """
    root = Path(scene)
    calib = _calib_dir(root, undistorted)
    groups = _grouped(calib / "images.txt")
    if camera is None:
        if len(groups) > 1:
            raise fail(
                calib / "images.txt", None, f"several rig cameras {sorted(groups)}; pass camera="
            )
        camera = next(iter(groups))
    if undistorted and camera not in groups and f"{camera}_undistorted" in groups:
        camera = f"{camera}_undistorted"
    if camera not in groups:
        raise fail(
            calib / "images.txt", None, f"no images of camera {camera!r} (have {sorted(groups)})"
        )
    if depth_dir is not None and depth_kind not in ("z", "range"):
        raise DatasetError(
            f"{depth_dir}: depth_kind must be 'z' or 'range' (the ETH3D rig depth convention is "
            f"not documented, so it is not guessed), got {depth_kind!r}"
        )
    ims = sorted(groups[camera], key=lambda im: im["timestamp_ns"])
    cam_ids = sorted({im["camera_id"] for im in ims})
    if len(cam_ids) != 1:
        raise fail(
            calib / "images.txt", None, f"camera folder {camera!r} uses COLMAP cameras {cam_ids}"
        )
    cam = load_camera(calib / "cameras.txt", camera=cam_ids[0])
    ts = np.array([im["timestamp_ns"] for im in ims], dtype=np.int64)
    if np.any(np.diff(ts) == 0):
        raise fail(calib / "images.txt", None, f"camera {camera!r} lists a timestamp twice")
    cfw = np.stack([im["cam_from_world"] for im in ims])
    img_root = root / "images"
    depth = None
    if depth_dir is not None:
        depth = np.stack(
            [_read_depth(Path(depth_dir) / im["name"], cam.height, cam.width) for im in ims]
        )
    ref = REF_CAMERA + ("_undistorted" if camera.endswith("_undistorted") else "")
    return Sequence(
        name=name or f"{root.name}/{camera}",
        camera=cam,
        timestamps=ts.astype(np.float64) * 1e-9,
        cam_from_world=cfw,
        image_paths=[img_root / im["name"] for im in ims],
        depth=depth,
        depth_kind=depth_kind or "range",
        meta={
            "source": str(calib),
            "format": "eth3d_rig",
            "camera": camera,
            "camera_id": int(cam_ids[0]),
            "rig": _rig(groups, camera, ref, cfw, ts),
            "per_frame": {
                "image_id": np.array([im["image_id"] for im in ims], dtype=np.int64),
                "name": np.array([im["name"] for im in ims]),
                "timestamp_ns": ts,
            },
        },
    )


def _rig(
    groups: dict[str, list[dict]], camera: str, ref: str, cfw: np.ndarray, ts: np.ndarray
) -> dict:
    """Transform of ``camera`` relative to the reference camera from shared timestamps."""
    if ref not in groups:
        return {"ref_camera": None, "cam_from_ref": None, "n_shared": 0}
    ref_by_t = {im["timestamp_ns"]: im["cam_from_world"] for im in groups[ref]}
    rel = [cfw[k] @ invert_pose(ref_by_t[t]) for k, t in enumerate(ts.tolist()) if t in ref_by_t]
    if not rel:
        return {"ref_camera": ref, "cam_from_ref": None, "n_shared": 0}
    T0 = rel[0]
    dev_m = max(float(np.linalg.norm(T[:3, 3] - T0[:3, 3])) for T in rel)
    dev_deg = max(
        float(
            np.degrees(
                np.arccos(np.clip((np.trace(T[:3, :3] @ T0[:3, :3].T) - 1.0) / 2.0, -1.0, 1.0))
            )
        )
        for T in rel
    )
    return {
        "ref_camera": ref,
        "cam_from_ref": T0,
        "n_shared": len(rel),
        "max_dev_m": dev_m,
        "max_dev_deg": dev_deg,
    }


def load_eth3d_rig_all(
    scene: str | Path, undistorted: bool = False, **kw: Any
) -> dict[str, Sequence]:
    """Every camera of the rig: ``{camera folder: Sequence}`` (see :func:`load_eth3d_rig`)."""
    return {
        c: load_eth3d_rig(scene, camera=c, undistorted=undistorted, **kw)
        for c in eth3d_rig_cameras(scene, undistorted)
    }
