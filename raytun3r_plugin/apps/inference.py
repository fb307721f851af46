"""Run a (patched) backbone on fisheye frames and write depth, poses, a point cloud and exports."""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from raytun3r_plugin.atomic_files import atomic_path, atomic_write_bytes, atomic_write_text
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.exports import ExportOptions, ExportScene, plan_exports
from raytun3r_plugin.exports.files import depth_panel, write_ply, write_tum
from raytun3r_plugin.exports.resample import resample_maps
from raytun3r_plugin.exports.scene import check_depth_convention
from raytun3r_plugin.patching import apply
from raytun3r_plugin.poses import backproject
from raytun3r_plugin.prediction import Prediction, predict

#: Back-projection of (..., H, W) depth along (H, W, 3) unit rays; kept under its old name.
points_from_depth = backproject


def predict_with_camera(
    model,
    camera,
    adapter,
    images: torch.Tensor,
    components=None,
    strict: bool = True,
    mask: torch.Tensor | None = None,
) -> Prediction:
    """Apply raytun3r for ``camera`` (+ ``adapter``, + an optional (h, w) scene ``mask``), predict,
    remove again."""
    with (
        apply(model, camera, adapter, components=components, strict=strict, mask=mask),
        torch.no_grad(),
    ):
        return predict(model, images)


def scene_from_prediction(
    prediction: Prediction,
    images: torch.Tensor,
    camera,
    names: list[str],
    timestamps: np.ndarray | None = None,
    depth_unit: str = "units",
    frames: np.ndarray | None = None,
    frames_camera=None,
    mask: np.ndarray | torch.Tensor | None = None,
) -> ExportScene:
    """The prediction as an :class:`~raytun3r_plugin.exports.ExportScene`.

    images: (1, S, 3, h, w) network input in [0, 1]; camera: the camera of that input. With
    ``frames`` ((S, H, W, 3) RGB in [0, 1], already cropped as the layout crops) and
    ``frames_camera`` (their camera, ``InputLayout.native_camera``) depth and confidence are
    resampled to the frames' resolution inside the camera's valid region
    (:func:`~raytun3r_plugin.exports.resample.resample_maps`); without them the scene stays at the
    network's size. ``mask``: optional (H, W) scene mask at the scene's resolution.
    """
    depth = prediction.depth[0].detach().double().cpu().numpy()
    confidence = prediction.confidence
    conf = None if confidence is None else confidence[0].detach().double().cpu().numpy()
    cam_from_world = prediction.cam_from_world[0].detach().double().cpu().numpy()
    if frames is None:
        scene_camera, resolution = camera, "network"
        pictures = images[0].permute(0, 2, 3, 1).detach().float().cpu().numpy()
    else:
        if frames_camera is None:
            raise InputError("frames need their camera (frames_camera) to resample depth to them")
        valid = camera.valid_mask("cpu").numpy()
        depth = resample_maps(depth, valid, frames_camera)
        conf = None if conf is None else resample_maps(conf, valid, frames_camera)
        scene_camera, resolution, pictures = frames_camera, "frames", np.asarray(frames)
    return ExportScene(
        camera=scene_camera,
        images=np.ascontiguousarray(pictures, dtype=np.float32),
        depth=np.asarray(depth, dtype=np.float32),
        cam_from_world=cam_from_world,
        names=list(names),
        confidence=None if conf is None else np.asarray(conf, dtype=np.float32),
        mask=None if mask is None else np.asarray(mask, dtype=bool),
        timestamps=None if timestamps is None else np.asarray(timestamps, dtype=np.float64),
        depth_unit=depth_unit,
        resolution=resolution,
    )


def write_outputs(
    out_dir: str | os.PathLike,
    prediction: Prediction,
    images: torch.Tensor,
    camera,
    names: list[str],
    timestamps: np.ndarray | None = None,
    max_points: int = 500_000,
    depth_unit: str = "units",
    *,
    frames: np.ndarray | None = None,
    frames_camera=None,
    mask: np.ndarray | torch.Tensor | None = None,
    depth_convention: str = "range",
    exports: tuple[str, ...] | list[str] = (),
    export_options: ExportOptions | None = None,
) -> dict:
    """Write ``depth/<name>.npy`` + ``.png``, ``trajectory.txt`` (TUM), ``points.ply``,
    ``summary.json`` and the ``exports`` asked for (:data:`raytun3r_plugin.exports.FORMATS`).

    The scene is built by :func:`scene_from_prediction` (the frames' resolution when ``frames``
    and ``frames_camera`` are given, else the network's). The .npy is (H, W) float32 depth in
    ``depth_convention`` (``range`` or ``z``, :data:`~raytun3r_plugin.exports.DEPTH_CONVENTIONS`),
    0 where unknown; the PNG shows the input frame, the colourised depth and a colour bar
    labelled in ``depth_unit`` (:func:`raytun3r_plugin.exports.files.depth_panel`).
    ``summary.json`` says which resolution and convention were written. Every option is checked
    (and each export's camera decided) before the first file is written.
    """
    check_depth_convention(depth_convention)
    options = export_options or ExportOptions()
    scene = scene_from_prediction(
        prediction, images, camera, names, timestamps, depth_unit, frames, frames_camera, mask
    )
    plans = plan_exports(scene, exports, replace(options, depth_convention=depth_convention))
    out = Path(out_dir)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    import cv2

    depth = scene.depth_as(depth_convention)
    valid = scene.valid
    # z-depth tends to 0 towards 90 degrees: its picture takes the colour scale from rays within
    # 75 degrees of the axis (the files hold every value).
    central = scene.rays[..., 2] > np.cos(np.radians(75.0)) if depth_convention == "z" else None
    for name, frame_depth, frame in zip(scene.names, depth, scene.images, strict=True):
        with atomic_path(out / "depth" / f"{name}.npy") as temporary, open(temporary, "wb") as f:
            np.save(f, frame_depth.astype(np.float32))
        ok, png = cv2.imencode(
            ".png",
            depth_panel(
                frame, frame_depth, valid, depth_unit, label=depth_convention, scale_region=central
            ),
        )
        if not ok:
            raise OSError(f"could not encode the depth picture of frame {name!r}")
        atomic_write_bytes(out / "depth" / f"{name}.png", png.tobytes())
    write_tum(out / "trajectory.txt", scene.timestamps, scene.cam_from_world)
    points = scene.sample_points(max_points=max_points, confidence_quantile=0.0)
    write_ply(out / "points.ply", points.xyz, points.rgb)
    written = {name: plan.write(out) for name, plan in plans.items()}
    summary = {
        "frames": len(scene),
        "points": int(len(points)),
        "input_size": [camera.width, camera.height],
        "camera": json.loads(camera.to_json()),
        "depth": scene.record(depth_convention),
        "exports": written,
        "notes": [note for plan in plans.values() for note in plan.notes],
    }
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2))
    return summary
