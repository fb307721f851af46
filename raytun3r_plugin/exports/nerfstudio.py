"""A nerfstudio / gsplat dataset of a prediction (``--export nerfstudio``).

Writes ``nerfstudio/transforms.json``, ``images/<name>.png``, ``depth/<name>.npy`` and, where
part of the image is no scene (outside the lens circle, or a ``--mask``), ``masks/mask.png``.
Conventions (docs.nerf.studio, "Data conventions"; nerfstudio's ``nerfstudio_dataparser``):

* shared intrinsics at the top level: ``camera_model`` (``OPENCV``, ``OPENCV_FISHEYE`` with
  ``k1..k4``, or ``FISHEYE624`` with ``distortion_params`` = k0..k5, p0, p1, s0..s3 and
  ``fisheye_crop_radius``), ``fl_x fl_y cx cy w h``; cx, cy with the first pixel centre at
  (0.5, 0.5) (nerfstudio casts rays through pixel + 0.5). Lenses nerfstudio has no model for are
  fitted as OPENCV_FISHEYE over the whole valid image (nerfstudio's fisheye rays use the angle
  itself, so beyond 90 degrees too) and the fit's error is stated;
* ``frames[i].transform_matrix``: camera-to-world with OpenGL camera axes (x right, y up,
  z back): the OpenCV ``world_from_cam`` with its y and z columns negated;
* ``depth_file_path``: float32 .npy in millimetres of the scene's unit (nerfstudio multiplies by
  its default ``depth_unit_scale_factor`` 1e-3), in the chosen convention, 0 = unknown.
  depth-nerfacto reads z-depth unless ``--pipeline.model.is-euclidean-depth True``, which
  range needs.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from raytun3r_plugin.atomic_files import atomic_path, atomic_write_bytes, atomic_write_text
from raytun3r_plugin.exports import ExportOptions, ExportPlan
from raytun3r_plugin.exports.files import write_frames
from raytun3r_plugin.exports.lens import WrittenLens, nerfstudio_lens
from raytun3r_plugin.exports.scene import ExportScene, depth_convention_text

__all__ = ["OPENGL_FROM_OPENCV", "plan", "transforms", "write_nerfstudio"]

#: Camera axes: OpenCV (x right, y down, z forward) -> OpenGL (x right, y up, z back).
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])

#: nerfstudio's default ``depth_unit_scale_factor``: depth files hold millimetres.
DEPTH_FILE_SCALE = 1000.0


def _crop_radius(scene: ExportScene) -> float:
    """Radius (px) of the largest circle about the principal point inside the valid region."""
    values = scene.camera.values
    rows, cols = np.nonzero(~scene.valid)
    if not len(rows):
        return float(np.hypot(scene.camera.width, scene.camera.height))
    return float(np.hypot(cols - values["cx"], rows - values["cy"]).min())


def _intrinsics(lens: WrittenLens, scene: ExportScene) -> dict:
    fx, fy, cx, cy, *rest = lens.params
    fields = {
        "camera_model": lens.model,
        "fl_x": fx,
        "fl_y": fy,
        "cx": cx + 0.5,  # nerfstudio's first pixel centre is (0.5, 0.5)
        "cy": cy + 0.5,
        "w": scene.camera.width,
        "h": scene.camera.height,
    }
    if lens.model == "OPENCV":
        fields |= dict(zip(("k1", "k2", "p1", "p2"), rest[:4], strict=True))
    elif lens.model == "OPENCV_FISHEYE":
        fields |= dict(zip(("k1", "k2", "k3", "k4"), rest, strict=True))
    elif lens.model == "FISHEYE624":
        fields["distortion_params"] = list(rest)
        fields["fisheye_crop_radius"] = _crop_radius(scene)
    return fields


def transforms(scene: ExportScene, lens: WrittenLens, options: ExportOptions, mask: bool) -> dict:
    """The ``transforms.json`` content (paths relative to its folder)."""
    meta = _intrinsics(lens, scene)
    meta["depth_convention"] = depth_convention_text(options.depth_convention)
    meta["depth_unit_scale_factor"] = 1.0 / DEPTH_FILE_SCALE
    if lens.fit is not None:
        meta["lens_fit"] = lens.fit
    frames = []
    for k, name in enumerate(scene.names):
        frame = {
            "file_path": f"images/{name}.png",
            "transform_matrix": (scene.world_from_cam(k) @ OPENGL_FROM_OPENCV).tolist(),
            "depth_file_path": f"depth/{name}.npy",
        }
        if mask:
            frame["mask_path"] = "masks/mask.png"
        frames.append(frame)
    meta["frames"] = frames
    return meta


def write_nerfstudio(
    folder: str | Path, scene: ExportScene, lens: WrittenLens, options: ExportOptions
) -> dict:
    """Write the dataset into ``folder``; returns a record of it."""
    import cv2

    folder = Path(folder)
    valid = scene.valid
    # nerfstudio refuses a mask with FISHEYE624 (it crops to fisheye_crop_radius instead).
    mask = (not valid.all()) and (lens.model != "FISHEYE624" or scene.mask is not None)
    write_frames(folder / "images", scene.names, scene.images)
    depth = scene.depth_as(options.depth_convention) * DEPTH_FILE_SCALE
    for name, values in zip(scene.names, depth, strict=True):
        with atomic_path(folder / "depth" / f"{name}.npy") as temporary, open(temporary, "wb") as f:
            np.save(f, values.astype(np.float32))
    if mask:
        ok, png = cv2.imencode(".png", valid.astype(np.uint8) * 255)
        atomic_write_bytes(folder / "masks" / "mask.png", png.tobytes())
    meta = transforms(scene, lens, options, mask)
    atomic_write_text(folder / "transforms.json", json.dumps(meta, indent=2))
    return {
        "folder": str(folder),
        "camera_model": lens.model,
        "lens": "exact" if lens.exact else lens.fit,
        "frames": len(scene),
        "depth_convention": options.depth_convention,
        "mask": mask,
    }


def plan(scene: ExportScene, options: ExportOptions) -> ExportPlan:
    """Decide the lens (refusing a fit worse than ``options.max_fit_error_px``); write later."""
    lens = nerfstudio_lens(scene.camera, options.max_fit_error_px)
    return ExportPlan(
        "nerfstudio",
        lambda out: write_nerfstudio(Path(out) / "nerfstudio", scene, lens, options),
        lens.notes,
    )
