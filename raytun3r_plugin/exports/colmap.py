"""A COLMAP sparse model of a prediction, with the real lens (``--export colmap``).

Writes ``colmap/images/<name>.png`` (the frames), ``colmap/sparse/0/{cameras,images,points3D}.bin``
and the same model as text in ``colmap/text/``. Conventions (COLMAP's ``Reconstruction``):

* one camera; the lens from :func:`raytun3r_plugin.exports.lens.colmap_lens` (exact, or a fitted
  OPENCV_FISHEYE with its error stated); cx, cy and every 2-D point get +0.5 (COLMAP's first
  pixel centre is (0.5, 0.5));
* images carry the predicted poses as ``cam_from_world`` (world to camera, OpenCV axes),
  quaternion ``QW QX QY QZ`` and ``TX TY TZ``;
* points3D are back-projected from the predicted depth (confidence-filtered, subsampled,
  coloured). Each is observed in the frame it came from and in every other frame where it
  projects inside the image and the predicted depth there agrees within
  :data:`TRACK_DEPTH_TOLERANCE`, so tracks span frames. Observations are projections through
  the written lens, so the model's reprojection error is 0 by construction; only rays within
  :data:`~raytun3r_plugin.exports.lens.COLMAP_MAX_ANGLE_DEG` of the axis are used (COLMAP
  projects through x / z).

COLMAP stores no depth maps; a depth convention does not apply to this export.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from raytun3r_plugin.atomic_files import atomic_write_bytes, atomic_write_text
from raytun3r_plugin.exports import ExportOptions, ExportPlan
from raytun3r_plugin.exports.files import write_frames
from raytun3r_plugin.exports.lens import COLMAP_MODEL_IDS, WrittenLens, colmap_lens
from raytun3r_plugin.exports.scene import ExportScene
from raytun3r_plugin.poses import rotation_to_quaternion

__all__ = ["TRACK_DEPTH_TOLERANCE", "ColmapModel", "build_model", "plan", "write_colmap"]

#: An observation in another frame counts when the predicted range there is within this
#: fraction of the point's distance from that camera (otherwise the point is occluded there).
TRACK_DEPTH_TOLERANCE = 0.05

_NO_POINT = 2**64 - 1  # COLMAP's invalid point3D id in images.bin


@dataclass
class ColmapModel:
    """A sparse model in COLMAP's terms (ids start at 1, pixels in COLMAP's convention).

    Attributes:
        lens: the written lens.
        points: (N, 3) float64 world points; colours (N, 3) uint8.
        tracks: per point, a list of (image index, point2D index).
        points2d: per image, (M, 2) float64 pixel positions (COLMAP convention, +0.5) and (M,)
            point ids (1-based).
    """

    lens: WrittenLens
    points: np.ndarray
    colours: np.ndarray
    tracks: list[list[tuple[int, int]]]
    points2d: list[tuple[np.ndarray, np.ndarray]]


def _observations(scene: ExportScene, lens: WrittenLens, xyz: np.ndarray, frame: int):
    """Pixels (raytun3r convention) of world points ``xyz`` in ``frame`` and where they count."""
    pose = scene.cam_from_world[frame]
    points = xyz @ pose[:3, :3].T + pose[:3, 3]
    uv, ok = lens.project(points)
    width, height = scene.camera.width, scene.camera.height
    ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] < width - 0.5) & (uv[:, 1] >= -0.5)
    ok &= uv[:, 1] < height - 0.5
    col = np.clip(np.round(uv[:, 0]).astype(np.int64), 0, width - 1)
    row = np.clip(np.round(uv[:, 1]).astype(np.int64), 0, height - 1)
    predicted = scene.depth[frame][row, col]
    distance = np.linalg.norm(points, axis=-1)
    agree = np.abs(predicted - distance) <= TRACK_DEPTH_TOLERANCE * distance
    return uv, ok, ok & scene.known(frame)[row, col] & agree


def build_model(scene: ExportScene, lens: WrittenLens, options: ExportOptions) -> ColmapModel:
    """Points, tracks and 2-D observations of ``scene`` through ``lens``."""
    sample = scene.sample_points(
        options.max_points, options.confidence_quantile, max_angle_deg=lens.max_angle_deg
    )
    count = len(sample)
    observed = np.zeros((len(scene), count), bool)
    pixels = np.zeros((len(scene), count, 2))
    for k in range(len(scene)):
        uv, in_view, seen = _observations(scene, lens, sample.xyz, k)
        own = sample.frame == k
        observed[k] = np.where(own, in_view, seen)
        pixels[k] = uv
    keep = observed[sample.frame, np.arange(count)]  # seen through the lens in its own frame
    points, colours = sample.xyz[keep], (np.clip(sample.rgb[keep], 0, 1) * 255 + 0.5)
    observed, pixels = observed[:, keep], pixels[:, keep]
    tracks: list[list[tuple[int, int]]] = [[] for _ in range(len(points))]
    points2d = []
    for k in range(len(scene)):
        ids = np.nonzero(observed[k])[0]
        for index, point in enumerate(ids):
            tracks[point].append((k, index))
        points2d.append((pixels[k, ids] + 0.5, ids + 1))
    return ColmapModel(lens, points, colours.astype(np.uint8), tracks, points2d)


def _camera_params(lens: WrittenLens) -> list[float]:
    params = list(lens.params)
    params[2] += 0.5  # COLMAP: the first pixel centre is (0.5, 0.5)
    params[3] += 0.5
    return params


def _pose(scene: ExportScene, k: int) -> tuple[np.ndarray, np.ndarray]:
    pose = scene.cam_from_world[k]
    return rotation_to_quaternion(pose[:3, :3]), pose[:3, 3]


def _text(scene: ExportScene, model: ColmapModel, names: list[str]) -> dict[str, str]:
    lens, width, height = model.lens, scene.camera.width, scene.camera.height
    cameras = "# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n"
    cameras += " ".join(["1", lens.model, str(width), str(height)])
    cameras += " " + " ".join(repr(float(v)) for v in _camera_params(lens)) + "\n"
    images = [
        "# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(scene)}",
    ]
    for k, name in enumerate(names):
        quaternion, translation = _pose(scene, k)
        numbers = " ".join(repr(float(v)) for v in (*quaternion, *translation))
        images.append(f"{k + 1} {numbers} 1 {name}")
        xy, ids = model.points2d[k]
        images.append(
            " ".join(
                f"{x!r} {y!r} {i}" for (x, y), i in zip(xy.tolist(), ids.tolist(), strict=True)
            )
        )
    points = [
        "# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
        f"# Number of points: {len(model.points)}",
    ]
    for index, (xyz, rgb, track) in enumerate(
        zip(model.points.tolist(), model.colours.tolist(), model.tracks, strict=True)
    ):
        elements = " ".join(f"{k + 1} {i}" for k, i in track)
        points.append(
            f"{index + 1} {' '.join(repr(v) for v in xyz)} {' '.join(map(str, rgb))} 0.0 {elements}"
        )
    return {
        "cameras.txt": cameras,
        "images.txt": "\n".join(images) + "\n",
        "points3D.txt": "\n".join(points) + "\n",
    }


def _binary(scene: ExportScene, model: ColmapModel, names: list[str]) -> dict[str, bytes]:
    lens = model.lens
    params = _camera_params(lens)
    cameras = struct.pack("<Q", 1) + struct.pack(
        f"<IiQQ{len(params)}d",
        1,
        COLMAP_MODEL_IDS[lens.model],
        scene.camera.width,
        scene.camera.height,
        *params,
    )
    images = [struct.pack("<Q", len(scene))]
    for k, name in enumerate(names):
        quaternion, translation = _pose(scene, k)
        images.append(struct.pack("<I7dI", k + 1, *quaternion, *translation, 1))
        images.append(name.encode("utf-8") + b"\0")
        xy, ids = model.points2d[k]
        record = np.zeros(len(ids), dtype=[("x", "<f8"), ("y", "<f8"), ("id", "<u8")])
        record["x"], record["y"], record["id"] = xy[:, 0], xy[:, 1], ids
        images.append(struct.pack("<Q", len(ids)) + record.tobytes())
    points = [struct.pack("<Q", len(model.points))]
    for index, (xyz, rgb, track) in enumerate(
        zip(model.points, model.colours, model.tracks, strict=True)
    ):
        points.append(struct.pack("<Q3d3BdQ", index + 1, *xyz, *rgb, 0.0, len(track)))
        points.append(np.asarray([(k + 1, i) for k, i in track], dtype="<u4").tobytes())
    return {
        "cameras.bin": cameras,
        "images.bin": b"".join(images),
        "points3D.bin": b"".join(points),
    }


def write_colmap(
    folder: str | Path, scene: ExportScene, lens: WrittenLens, options: ExportOptions
) -> dict:
    """Write the model (binary in ``sparse/0``, text in ``text``) and the frames in ``images``."""
    folder = Path(folder)
    model = build_model(scene, lens, options)
    names = write_frames(folder / "images", scene.names, scene.images)
    for file, data in _binary(scene, model, names).items():
        atomic_write_bytes(folder / "sparse" / "0" / file, data)
    for file, text in _text(scene, model, names).items():
        atomic_write_text(folder / "text" / file, text)
    track_lengths = [len(track) for track in model.tracks]
    return {
        "folder": str(folder),
        "camera_model": lens.model,
        "lens": "exact" if lens.exact else lens.fit,
        "images": len(scene),
        "points3D": len(model.points),
        "mean_track_length": float(np.mean(track_lengths)) if track_lengths else 0.0,
        "depth_convention": "none (COLMAP stores no depth maps)",
    }


def plan(scene: ExportScene, options: ExportOptions) -> ExportPlan:
    """Decide the lens (refusing a fit worse than ``options.max_fit_error_px``); write later."""
    lens = colmap_lens(scene.camera, options.max_fit_error_px, options.colmap_lens)
    return ExportPlan(
        "colmap", lambda out: write_colmap(Path(out) / "colmap", scene, lens, options), lens.notes
    )
