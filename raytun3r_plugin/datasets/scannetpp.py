"""ScanNet++ DSLR ``nerfstudio/transforms.json`` (nerfstudio camera format).

Fields used: ``camera_model`` ("OPENCV_FISHEYE" -> Kannala-Brandt 4, "PINHOLE" -> pinhole),
``w``, ``h``, ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``k1`` .. ``k4`` and the frame lists ``frames``
and (optionally) ``test_frames``; per frame ``file_path``, ``transform_matrix`` (4x4 camera-to-world
in nerfstudio/OpenGL camera axes: x right, y up, z backwards) and optionally ``is_bad``.

Conversions: ``world_from_cam_opencv = transform_matrix @ diag(1, -1, -1, 1)`` (flip y and z of
the camera axes; the world frame is kept), ``cam_from_world = inv(world_from_cam_opencv)``.
nerfstudio places pixel centres at +0.5 (its rays go through ``pixel + 0.5``, and ScanNet++ copies
cx, cy from its COLMAP model), so ``pixel_offset`` = 0.5 is subtracted from cx, cy.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from raytun3r_plugin.datasets._common import check_rigid, fail, invert_pose
from raytun3r_plugin.datasets.sequence import Sequence
from raytun3r_plugin.errors import CameraError, DatasetError

__all__ = ["load_scannetpp_transforms"]

_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _line_of(text: str, needle: str, start: int = 0) -> int | None:
    """1-based line number of the first occurrence of ``needle`` at or after ``start``."""
    i = text.find(needle, start)
    return None if i < 0 else text.count("\n", 0, i) + 1


def _number(path: Path, text: str, d: dict, key: str) -> float:
    if key not in d:
        raise fail(path, None, f"field '{key}' is missing")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise fail(
            path, _line_of(text, f'"{key}"'), f"field '{key}' must be a finite number, got {v!r}"
        )
    return float(v)


def _camera(path: Path, text: str, d: dict, pixel_offset: float):
    from raytun3r_plugin import cameras

    model = d.get("camera_model", "OPENCV_FISHEYE")
    w = _number(path, text, d, "w")
    h = _number(path, text, d, "h")
    if w != int(w) or h != int(h) or w <= 0 or h <= 0:
        raise fail(
            path, _line_of(text, '"w"'), f"image size w, h must be positive integers, got {w}, {h}"
        )
    p = {
        "fx": _number(path, text, d, "fl_x"),
        "fy": _number(path, text, d, "fl_y"),
        "cx": _number(path, text, d, "cx") - pixel_offset,
        "cy": _number(path, text, d, "cy") - pixel_offset,
    }
    try:
        if model == "OPENCV_FISHEYE":
            for k in ("k1", "k2", "k3", "k4"):
                p[k] = _number(path, text, d, k) if k in d else 0.0
            return cameras.KannalaBrandt4(int(w), int(h), p)
        if model == "PINHOLE":
            return cameras.Pinhole(int(w), int(h), p)
    except CameraError as e:
        raise fail(path, None, f"invalid camera: {e}") from e
    raise fail(
        path,
        _line_of(text, '"camera_model"'),
        f"unsupported camera_model {model!r} (OPENCV_FISHEYE or PINHOLE)",
    )


def _frame_entries(
    p: Path, text: str, frames: Any, key: str, is_test: bool, skip_bad: bool
) -> list[tuple[str, bool, np.ndarray, str | None]]:
    """The usable frames of the JSON's list ``key``: ``(file_path, is_test, world_from_cam in
    OpenCV axes, mask_path)`` each; a malformed entry is refused with the line it is on."""
    entries: list[tuple[str, bool, np.ndarray, str | None]] = []
    if not isinstance(frames, list):
        raise fail(p, _line_of(text, f'"{key}"'), f"field '{key}' must be a list")
    search = text.find(f'"{key}"')
    for i, fr in enumerate(frames):
        where = f"{key}[{i}]"
        if not isinstance(fr, dict):
            raise fail(p, _line_of(text, "{", search + 1), f"{where} must be an object")
        fpath = fr.get("file_path")
        line = _line_of(text, json.dumps(fpath), search) if isinstance(fpath, str) else None
        if line is not None:
            search = text.find(json.dumps(fpath), search) + 1
        if not isinstance(fpath, str) or not fpath:
            raise fail(p, line, f"{where}.file_path must be a non-empty string, got {fpath!r}")
        if skip_bad and fr.get("is_bad", False) is True:
            continue
        m = fr.get("transform_matrix")
        try:
            M = np.asarray(m, dtype=np.float64)
        except (TypeError, ValueError):
            raise fail(p, line, f"{where}.transform_matrix is not a numeric matrix") from None
        if M.shape == (3, 4):
            M = np.vstack([M, [0.0, 0.0, 0.0, 1.0]])
        if M.shape != (4, 4):
            raise fail(
                p, line, f"{where}.transform_matrix must be 4x4 (or 3x4), got shape {M.shape}"
            )
        check_rigid(p, line, M, f"{where}.transform_matrix")
        mpath = fr.get("mask_path")
        if mpath is not None and (not isinstance(mpath, str) or not mpath):
            raise fail(p, line, f"{where}.mask_path must be a non-empty string, got {mpath!r}")
        entries.append((fpath, is_test, M @ _GL_TO_CV, mpath))
    return entries


def load_scannetpp_transforms(
    path: str | Path,
    split: str = "all",
    image_dir: str | Path | None = None,
    skip_bad: bool = True,
    pixel_offset: float = 0.5,
    name: str | None = None,
    mask_dir: str | Path | None = None,
) -> Sequence:
    """Read a nerfstudio ``transforms.json`` (ScanNet++ DSLR) as a :class:`Sequence`.

    Args:
        path: the JSON file, or a folder containing ``transforms.json``.
        split: "train" (``frames``), "test" (``test_frames``) or "all" (both).
        image_dir: folder the ``file_path`` entries are relative to; by default the first of
            the JSON's folder, ``../resized_images``, ``../resized_anon_images``, ``../images``
            that holds the first image.
        skip_bad: drop frames flagged ``"is_bad": true``.
        pixel_offset: subtracted from cx, cy (see module docstring).
        name: sequence name (default: the scene folder name).
        mask_dir: folder the frames' ``mask_path`` entries are relative to; by default the
            first of the JSON's folder, ``../resized_anon_masks``, ``../resized_masks``,
            ``../masks`` that holds the first mask.

    Frames with ``mask_path`` (all or none of the kept frames) give ``mask`` (N, H, W) bool:
    the mask image (8-bit grey) is valid where its value is >= 128 (ScanNet++ writes 255 =
    valid, 0 = anonymised / invalid). Frames are ordered by ``file_path``; timestamps are frame indices. ``meta["per_frame"]``
    holds ``file_path`` and ``is_test``.

    Raises:
        DatasetError: invalid JSON (line given), missing or bad fields (field named, with the
            line of the offending entry where it can be located).
    """
    p = Path(path)
    if p.is_dir():
        p = p / "transforms.json"
    if not p.is_file():
        raise fail(p, None, "file not found")
    if split not in ("all", "train", "test"):
        raise DatasetError(f"split must be 'all', 'train' or 'test', got {split!r}")
    text = p.read_text(encoding="utf-8")
    try:
        d = json.loads(text)
    except json.JSONDecodeError as e:
        raise fail(p, e.lineno, f"invalid JSON: {e.msg}") from None
    if not isinstance(d, dict):
        raise fail(p, 1, "expected a JSON object")
    camera = _camera(p, text, d, pixel_offset)
    lists = []
    if split in ("all", "train"):
        if "frames" not in d:
            raise fail(p, None, "field 'frames' is missing")
        lists.append(("frames", False))
    if split in ("all", "test") and "test_frames" in d:
        lists.append(("test_frames", True))
    if split == "test" and "test_frames" not in d:
        raise fail(p, None, "field 'test_frames' is missing")
    entries = [
        entry
        for key, is_test in lists
        for entry in _frame_entries(p, text, d[key], key, is_test, skip_bad)
    ]
    if not entries:
        raise fail(p, None, f"no usable frames for split {split!r}")
    entries.sort(key=lambda e: e[0])
    img_root = _image_root(p, entries[0][0], image_dir)
    n = len(entries)
    world_from_cam = np.stack([e[2] for e in entries])
    mask = _masks(p, entries, camera, mask_dir)
    return Sequence(
        name=name
        or (p.parent.parent.parent.name if p.parent.name == "nerfstudio" else p.parent.name),
        camera=camera,
        timestamps=np.arange(n, dtype=np.float64),
        cam_from_world=invert_pose(world_from_cam),
        image_paths=[img_root / e[0] for e in entries],
        mask=mask,
        meta={
            "source": str(p),
            "format": "nerfstudio",
            "per_frame": {
                "file_path": np.array([e[0] for e in entries]),
                "is_test": np.array([e[1] for e in entries], dtype=bool),
            },
        },
    )


def _masks(p: Path, entries: list, camera, given: str | Path | None) -> np.ndarray | None:
    """(N, H, W) bool masks from the frames' ``mask_path`` (None if no frame has one)."""
    import cv2

    with_mask = [e[3] is not None for e in entries]
    if not any(with_mask):
        return None
    if not all(with_mask):
        missing = next(e[0] for e in entries if e[3] is None)
        raise fail(p, None, f"frame {missing!r} has no mask_path while other frames have one")
    first = entries[0][3]
    if given is not None:
        root = Path(given)
    else:
        cands = [
            p.parent,
            p.parent.parent / "resized_anon_masks",
            p.parent.parent / "resized_masks",
            p.parent.parent / "masks",
        ]
        root = next((c for c in cands if (c / first).is_file()), None)
        if root is None:
            raise DatasetError(
                f"{p}: mask {first!r} not found under any of: "
                f"{', '.join(str(c) for c in cands)}; pass mask_dir="
            )
    out = np.zeros((len(entries), camera.height, camera.width), dtype=bool)
    for k, e in enumerate(entries):
        mp = root / e[3]
        if not mp.is_file():
            raise fail(mp, None, f"mask file not found (mask_path of {e[0]!r})")
        m = cv2.imread(str(mp), cv2.IMREAD_UNCHANGED)
        if m is None:
            raise fail(mp, None, "cannot decode mask image")
        if m.ndim == 3:
            m = m[..., 0]
        if m.dtype != np.uint8:
            raise fail(mp, None, f"mask must be 8-bit (255 = valid), got {m.dtype}")
        if m.shape != (camera.height, camera.width):
            raise fail(
                mp,
                None,
                f"mask is {m.shape[1]}x{m.shape[0]} px, camera is {camera.width}x{camera.height}",
            )
        out[k] = m >= 128
    return out


def _image_root(p: Path, first: str, given: str | Path | None) -> Path:
    if given is not None:
        root = Path(given)
        if not (root / first).is_file():
            raise fail(root / first, None, "image file not found (image_dir given)")
        return root
    cands = [
        p.parent,
        p.parent.parent / "resized_images",
        p.parent.parent / "resized_anon_images",
        p.parent / "images",
    ]
    for c in cands:
        if (c / first).is_file():
            return c
    raise DatasetError(
        f"{p}: image {first!r} not found under any of: {', '.join(str(c) for c in cands)}; pass image_dir="
    )
