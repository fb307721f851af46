"""COLMAP models (``cameras.txt`` + ``images.txt``, as shipped by ETH3D and ScanNet++ DSLR; and
the binary ``images.bin``, as FIORD ships it).

``images.txt`` holds two lines per image::

    IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME
    POINTS2D[] as (X, Y, POINT3D_ID)        (may be empty)

(q, t) is the world-to-camera transform (``cam_from_world``), quaternion in (w, x, y, z) order.
The camera comes from ``cameras.txt`` through ``raytun3r_plugin.cameras.load`` (which moves the
principal point by -0.5 px to raytun3r's pixel-centre convention).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from raytun3r_plugin.datasets._common import fail, load_camera, parse_floats, quat_to_rot
from raytun3r_plugin.datasets.sequence import Sequence

__all__ = ["load_colmap", "read_images_bin", "read_images_txt"]


def read_images_txt(path: str | Path) -> list[dict]:
    """Parse a COLMAP ``images.txt``: a list of ``{"image_id", "camera_id", "name",
    "cam_from_world" (4, 4) float64, "line"}`` in file order.

    Raises:
        DatasetError: malformed line (message ``<file>:<line>: ...``), duplicate image id.
    """
    p = Path(path)
    if not p.is_file():
        raise fail(p, None, "file not found")
    lines = p.read_text(encoding="utf-8").splitlines()
    out: list[dict] = []
    ids: set[int] = set()
    k = 0
    while k < len(lines):
        lineno = k + 1
        s = lines[k].strip()
        k += 1
        if not s or s.startswith("#"):
            continue
        tok = s.split(maxsplit=9)
        if len(tok) < 10:
            raise fail(
                p,
                lineno,
                f"expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', got {len(tok)} fields",
            )
        try:
            image_id = int(tok[0])
            camera_id = int(tok[8])
        except ValueError:
            raise fail(
                p, lineno, f"IMAGE_ID and CAMERA_ID must be integers, got {tok[0]!r}, {tok[8]!r}"
            ) from None
        vals = parse_floats(p, lineno, tok[1:8], 7, "QW QX QY QZ TX TY TZ")
        q, t = vals[:4], vals[4:]
        if np.linalg.norm(q) < 1e-8:
            raise fail(p, lineno, "quaternion (QW, QX, QY, QZ) is zero")
        if abs(np.linalg.norm(q) - 1.0) > 1e-2:
            raise fail(p, lineno, f"quaternion is not unit length (norm {np.linalg.norm(q):.6g})")
        if image_id in ids:
            raise fail(p, lineno, f"IMAGE_ID {image_id} appears twice")
        ids.add(image_id)
        T = np.eye(4)
        T[:3, :3] = quat_to_rot(q)
        T[:3, 3] = t
        out.append(
            {
                "image_id": image_id,
                "camera_id": camera_id,
                "name": tok[9].strip(),
                "cam_from_world": T,
                "line": lineno,
            }
        )
        # The POINTS2D line follows unconditionally (it is empty for images without points).
        if k < len(lines):
            pts = lines[k].split()
            if pts and (len(pts) % 3 != 0 or lines[k].lstrip().startswith("#")):
                raise fail(
                    p,
                    k + 1,
                    f"expected the POINTS2D line of image {image_id} (X Y POINT3D_ID triples), got {len(pts)} fields",
                )
            k += 1
    return out


def read_images_bin(path: str | Path) -> list[dict]:
    """Parse a COLMAP binary ``images.bin`` (little-endian: uint64 image count; per image int32
    IMAGE_ID, 4 float64 QW QX QY QZ, 3 float64 TX TY TZ, int32 CAMERA_ID, NUL-terminated NAME,
    uint64 point count, then (float64 X, float64 Y, int64 POINT3D_ID) per point).

    Returns the same records as :func:`read_images_txt`
    (``image_id``, ``camera_id``, ``name``, ``cam_from_world`` (4, 4) float64), in file order,
    with ``"line"`` the image's index in the file.

    Raises:
        DatasetError: missing file, truncated or malformed record, zero or non-unit quaternion,
            duplicate image id.
    """
    p = Path(path)
    if not p.is_file():
        raise fail(p, None, "file not found")
    data = p.read_bytes()
    offset = 0

    def take(fmt: str, what: str) -> tuple:
        nonlocal offset
        size = struct.calcsize(fmt)
        if offset + size > len(data):
            raise fail(p, None, f"truncated at byte {offset} while reading {what}")
        values = struct.unpack_from(fmt, data, offset)
        offset += size
        return values

    (count,) = take("<Q", "the image count")
    out: list[dict] = []
    ids: set[int] = set()
    for index in range(count):
        image_id, *vals = take("<i7d", f"image {index}")
        (camera_id,) = take("<i", f"the camera id of image {image_id}")
        end = data.find(b"\0", offset)
        if end < 0:
            raise fail(p, None, f"truncated in the name of image {image_id}")
        try:
            name = data[offset:end].decode("utf-8")
        except UnicodeDecodeError:
            raise fail(p, None, f"the name of image {image_id} is not UTF-8") from None
        offset = end + 1
        (points,) = take("<Q", f"the point count of image {image_id}")
        if offset + 24 * points > len(data):
            raise fail(p, None, f"truncated in the {points} points of image {image_id}")
        offset += 24 * points
        q = np.asarray(vals[:4], dtype=np.float64)
        if not np.all(np.isfinite(vals)) or abs(np.linalg.norm(q) - 1.0) > 1e-2:
            raise fail(p, None, f"image {image_id}: quaternion {q.tolist()} is not a unit vector")
        if image_id in ids:
            raise fail(p, None, f"IMAGE_ID {image_id} appears twice")
        ids.add(image_id)
        pose = np.eye(4)
        pose[:3, :3] = quat_to_rot(q)
        pose[:3, 3] = vals[4:]
        out.append(
            {
                "image_id": image_id,
                "camera_id": camera_id,
                "name": name,
                "cam_from_world": pose,
                "line": index,
            }
        )
    if offset != len(data):
        raise fail(p, None, f"{len(data) - offset} bytes after the last of {count} images")
    return out


def _find_colmap_dir(folder: Path) -> Path:
    for cand in (
        folder,
        folder / "sparse" / "0",
        folder / "sparse",
        folder / "colmap",
        folder / "dslr_calibration_jpg",
    ):
        if (cand / "cameras.txt").is_file() and (cand / "images.txt").is_file():
            return cand
    missing = "cameras.txt" if not (folder / "cameras.txt").is_file() else "images.txt"
    raise fail(
        folder / missing,
        None,
        "file not found (looked in ., sparse/0, sparse, colmap, dslr_calibration_jpg)",
    )


def _find_image_root(model_dir: Path, first_name: str, given: str | Path | None) -> Path:
    if given is not None:
        root = Path(given)
        if not (root / first_name).is_file():
            raise fail(root / first_name, None, "image file not found (image_dir given)")
        return root
    cands = [
        model_dir / "images",
        model_dir.parent / "images",
        model_dir.parent / "resized_images",
        model_dir.parent / "resized_anon_images",
        model_dir.parent.parent / "images",
        model_dir,
        model_dir.parent,
    ]
    for c in cands:
        if (c / first_name).is_file():
            return c
    tried = ", ".join(str(c) for c in cands)
    raise fail(
        model_dir / "images.txt",
        None,
        f"image {first_name!r} not found under any of: {tried}; pass image_dir=",
    )


def load_colmap(
    folder: str | Path,
    image_dir: str | Path | None = None,
    camera_id: int | None = None,
    name: str | None = None,
) -> Sequence:
    """Read a COLMAP text model as a :class:`Sequence`.

    Args:
        folder: directory holding ``cameras.txt`` and ``images.txt`` (or a COLMAP project with
            them in ``sparse/0``, ``sparse``, ``colmap`` or ``dslr_calibration_jpg``).
        image_dir: root the image NAMEs are relative to; by default the first of ``images``
            next to the model, ``../images``, ``../resized_images``, ``../resized_anon_images``
            (ScanNet++ DSLR), ``../../images`` (ETH3D), the model folder or its parent that
            contains the first image.
        camera_id: which camera to use when images of several cameras are listed (a sequence
            has one camera); by default the only one used.
        name: sequence name (default: the folder name).

    Frames are ordered by image NAME; timestamps are the frame indices (COLMAP has no time).
    ``meta["per_frame"]`` holds ``image_id`` and ``name``.

    Raises:
        DatasetError: missing files, malformed lines (file and line named), several cameras
            without ``camera_id``.
    """
    root = Path(folder)
    model = _find_colmap_dir(root)
    images = read_images_txt(model / "images.txt")
    if not images:
        raise fail(model / "images.txt", None, "no images listed")
    used = sorted({im["camera_id"] for im in images})
    if camera_id is None:
        if len(used) > 1:
            raise fail(
                model / "images.txt", None, f"images use several cameras {used}; pass camera_id="
            )
        camera_id = used[0]
    elif camera_id not in used:
        raise fail(
            model / "images.txt", None, f"no image uses camera_id {camera_id} (used: {used})"
        )
    images = sorted(
        (im for im in images if im["camera_id"] == camera_id), key=lambda im: im["name"]
    )
    camera = load_camera(model / "cameras.txt", camera=int(camera_id))
    img_root = _find_image_root(model, images[0]["name"], image_dir)
    n = len(images)
    return Sequence(
        name=name or root.name,
        camera=camera,
        timestamps=np.arange(n, dtype=np.float64),
        cam_from_world=np.stack([im["cam_from_world"] for im in images]),
        image_paths=[img_root / im["name"] for im in images],
        meta={
            "source": str(model),
            "format": "colmap",
            "camera_id": int(camera_id),
            "per_frame": {
                "image_id": np.array([im["image_id"] for im in images], dtype=np.int64),
                "name": np.array([im["name"] for im in images]),
            },
        },
    )
