"""raytun3r's own sequence folder format (written for synthetic sequences, readable for any).

Layout (format ``raytun3r-sequence``, version 1)::

    <folder>/
      meta.json          {"format": "raytun3r-sequence", "format_version": 1, "name": str,
                          "n_frames": N, "width": W, "height": H, "has_poses": bool,
                          "depth_kind": "range" | "z", "depth_format": "npy" | "png16" | null,
                          "depth_scale": float (png16: metres = value / depth_scale),
                          "mask": "per_frame" | "static" | null,
                          "synthetic": {generator parameters and camera path} (optional)}
      camera.json        the camera, raytun3r JSON (raytun3r_plugin.cameras.save)
      poses.txt          one line per frame: "index timestamp_s" + 12 numbers, the 3x4 top rows
                         of cam_from_world, row-major, written with 17 significant digits
                         (exact float64 round trip); only "index timestamp_s" without poses
      images/%06d.png    8-bit RGB
      depth/%06d.npy     (H, W) float32, metres, 0 = unknown   (depth_format "npy", exact)
      depth/%06d.png     (H, W) uint16, metres * depth_scale   (depth_format "png16")
      mask/%06d.png      (H, W) uint8, 255 = valid             (mask "per_frame")
      mask.png           (H, W) uint8, 255 = valid             (mask "static")

Lines of ``poses.txt`` starting with ``#`` are comments.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from raytun3r_plugin.datasets._common import fail, load_camera, parse_floats
from raytun3r_plugin.datasets.sequence import Sequence
from raytun3r_plugin.errors import DatasetError, InputError

__all__ = ["FORMAT", "FORMAT_VERSION", "load_synthetic", "write_sequence"]

FORMAT = "raytun3r-sequence"
FORMAT_VERSION = 1


def _write_png(path: Path, arr: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), arr):
        raise DatasetError(f"{path}: cannot write image")


def write_sequence(seq: Sequence, folder: str | Path, depth_format: str = "npy") -> Path:
    """Write ``seq`` in the folder format above; returns the folder.

    Args:
        seq: any :class:`Sequence` (images in memory or on disk).
        folder: output folder (created; existing files of the same names are overwritten).
        depth_format: "npy" (float32, exact) or "png16" (16-bit PNG, quantised; the scale is
            1000 per metre (millimetres) unless the largest depth needs a coarser one).
    """
    import cv2

    from raytun3r_plugin import cameras

    if depth_format not in ("npy", "png16"):
        raise DatasetError(f"depth_format must be 'npy' or 'png16', got {depth_format!r}")
    out = Path(folder)
    (out / "images").mkdir(parents=True, exist_ok=True)
    n = len(seq)
    cameras.save(seq.camera, out / "camera.json")
    lines = ["# index timestamp_s cam_from_world[0:3, 0:4] row-major (12 numbers)"]
    for k in range(n):
        row = [str(k), repr(float(seq.timestamps[k]))]
        if seq.cam_from_world is not None:
            row += [f"{v:.17g}" for v in seq.cam_from_world[k, :3, :4].reshape(-1)]
        lines.append(" ".join(row))
    (out / "poses.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
    for k in range(n):
        img = np.clip(np.rint(seq.image(k) * 255.0), 0, 255).astype(np.uint8)
        _write_png(out / "images" / f"{k:06d}.png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    depth_scale = None
    if seq.depth is not None:
        (out / "depth").mkdir(exist_ok=True)
        if depth_format == "png16":
            dmax = float(np.max(seq.depth)) if seq.depth.size else 0.0
            depth_scale = (
                1000.0 if dmax * 1000.0 <= 65535.0 else math.floor(65535.0 / dmax * 1e6) / 1e6
            )
        for k in range(n):
            d = np.asarray(seq.depth[k], dtype=np.float32)
            if depth_format == "npy":
                np.save(out / "depth" / f"{k:06d}.npy", d)
            else:
                q = np.clip(np.rint(d.astype(np.float64) * depth_scale), 0, 65535).astype(np.uint16)
                _write_png(out / "depth" / f"{k:06d}.png", q)
    mask_kind = None
    if seq.mask is not None:
        if seq.mask.ndim == 2:
            mask_kind = "static"
            _write_png(out / "mask.png", seq.mask.astype(np.uint8) * 255)
        else:
            mask_kind = "per_frame"
            (out / "mask").mkdir(exist_ok=True)
            for k in range(n):
                _write_png(out / "mask" / f"{k:06d}.png", seq.mask[k].astype(np.uint8) * 255)
    meta: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "name": seq.name,
        "n_frames": n,
        "width": seq.width,
        "height": seq.height,
        "has_poses": seq.cam_from_world is not None,
        "depth_kind": seq.depth_kind,
        "depth_format": depth_format if seq.depth is not None else None,
        "depth_scale": depth_scale,
        "mask": mask_kind,
    }
    if "synthetic" in seq.meta:
        meta["synthetic"] = seq.meta["synthetic"]
    (out / "meta.json").write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    return out


def _read_meta(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise fail(path, None, "meta.json not found (not a raytun3r sequence folder)")
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise fail(path, e.lineno, f"invalid JSON: {e.msg}") from None
    if not isinstance(meta, dict):
        raise fail(path, 1, "expected a JSON object")
    if meta.get("format") != FORMAT:
        raise fail(path, None, f"field 'format' is {meta.get('format')!r}, expected {FORMAT!r}")
    if meta.get("format_version") != FORMAT_VERSION:
        raise fail(path, None, f"unsupported format_version {meta.get('format_version')!r}")
    for key in ("n_frames", "width", "height"):
        v = meta.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise fail(path, None, f"field '{key}' must be a non-negative integer, got {v!r}")
    return meta


def load_synthetic(folder: str | Path, load_images: bool = False) -> Sequence:
    """Read a folder written by :func:`write_sequence` (format in the module docstring).

    Poses round-trip exactly, depth exactly for ``npy`` (to 1 / depth_scale for ``png16``),
    images to 8 bits. Images are read lazily (``image_paths``) unless ``load_images``.

    Raises:
        DatasetError: missing or malformed files (the message names the file and the line).
    """

    root = Path(folder)
    meta = _read_meta(root / "meta.json")
    n, w, h = meta["n_frames"], meta["width"], meta["height"]
    camera = load_camera(root / "camera.json")
    if (camera.width, camera.height) != (w, h):
        raise fail(
            root / "camera.json",
            None,
            f"camera is {camera.width}x{camera.height} px, meta.json says {w}x{h}",
        )
    stamps, poses = _read_poses(root / "poses.txt", n, bool(meta.get("has_poses", True)))
    image_paths = [root / "images" / f"{k:06d}.png" for k in range(n)]
    missing = [p for p in image_paths if not p.is_file()]
    if missing:
        raise fail(missing[0], None, "image file not found")
    depth = _read_depth(root, meta, n, h, w)
    mask = _read_masks(root, meta.get("mask"), n, h, w)
    seq = Sequence(
        name=str(meta.get("name", root.name)),
        camera=camera,
        timestamps=stamps,
        cam_from_world=poses,
        image_paths=image_paths,
        depth=depth,
        depth_kind=str(meta.get("depth_kind", "range")),
        mask=mask,
        meta={"source": str(root), "format": FORMAT},
    )
    if "synthetic" in meta:
        seq.meta["synthetic"] = meta["synthetic"]
    if load_images and n:
        seq.images = np.stack([seq.image(k) for k in range(n)])
    return seq


def _read_poses(ppath: Path, n: int, has_poses: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """``poses.txt``: (n,) timestamps and (n, 4, 4) cam_from_world (None without poses)."""
    if not ppath.is_file():
        raise fail(ppath, None, "file not found")
    stamps = np.zeros(n)
    poses = np.tile(np.eye(4), (n, 1, 1)) if has_poses else None
    seen = np.zeros(n, dtype=bool)
    for lineno, raw in enumerate(ppath.read_text(encoding="utf-8").splitlines(), start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        tok = s.split()
        vals = parse_floats(
            ppath,
            lineno,
            tok,
            14 if has_poses else 2,
            "index timestamp" + (" + 12 pose numbers" if has_poses else ""),
        )
        k = int(vals[0])
        if vals[0] != k or not 0 <= k < n:
            raise fail(ppath, lineno, f"frame index {tok[0]!r} is not an integer in [0, {n})")
        if seen[k]:
            raise fail(ppath, lineno, f"frame {k} listed twice")
        seen[k] = True
        stamps[k] = vals[1]
        if poses is not None:
            poses[k, :3, :4] = vals[2:].reshape(3, 4)
    if not seen.all():
        raise fail(ppath, None, f"frames {np.flatnonzero(~seen)[:5].tolist()} have no line")
    return stamps, poses


def _read_depth(root: Path, meta: dict, n: int, h: int, w: int) -> np.ndarray | None:
    """The (n, h, w) float32 depth maps of ``depth/``, or None where the folder has none."""
    import cv2

    fmt = meta.get("depth_format")
    if fmt is None:
        return None
    depth = np.zeros((n, h, w), dtype=np.float32)
    for k in range(n):
        if fmt == "npy":
            p = root / "depth" / f"{k:06d}.npy"
            if not p.is_file():
                raise fail(p, None, "depth file not found")
            try:
                d = np.load(p, allow_pickle=False)
            except (ValueError, OSError) as e:
                raise fail(p, None, f"cannot read depth: {e}") from None
        elif fmt == "png16":
            p = root / "depth" / f"{k:06d}.png"
            q = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if q is None or q.dtype != np.uint16 or q.ndim != 2:
                raise fail(p, None, "missing or not a single-channel 16-bit PNG")
            scale = meta.get("depth_scale")
            if not isinstance(scale, (int, float)) or isinstance(scale, bool) or scale <= 0:
                raise fail(
                    root / "meta.json",
                    None,
                    f"field 'depth_scale' must be positive, got {scale!r}",
                )
            d = (q.astype(np.float64) / float(scale)).astype(np.float32)
        else:
            raise fail(root / "meta.json", None, f"unknown depth_format {fmt!r}")
        if d.shape != (h, w):
            raise fail(p, None, f"depth has shape {d.shape}, expected {(h, w)}")
        depth[k] = d
    return depth


def _read_masks(root: Path, mk: str | None, n: int, h: int, w: int) -> np.ndarray | None:
    """The valid-pixel mask: (h, w) for ``static``, (n, h, w) for ``per_frame``, or None."""
    mask = None
    if mk == "static":
        mask = _read_mask(root / "mask.png", h, w)
    elif mk == "per_frame":
        mask = (
            np.stack([_read_mask(root / "mask" / f"{k:06d}.png", h, w) for k in range(n)])
            if n
            else None
        )
    elif mk is not None:
        raise fail(root / "meta.json", None, f"unknown mask kind {mk!r}")
    return mask


def _read_mask(path: Path, h: int, w: int) -> np.ndarray:
    from raytun3r_plugin.images import read_mask

    try:
        return read_mask(path, w, h)
    except InputError as error:
        raise fail(path, None, str(error).removeprefix(f"{path}: ")) from error
