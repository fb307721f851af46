"""Run a (patched) backbone on fisheye frames and write depth, poses and a point cloud."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch

from raytun3r_plugin.apps.export import depth_panel, write_ply, write_tum
from raytun3r_plugin.patching import apply
from raytun3r_plugin.poses import backproject, invert_rigid
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


def write_outputs(
    out_dir: str | os.PathLike,
    prediction: Prediction,
    images: torch.Tensor,
    camera,
    names: list[str],
    timestamps: np.ndarray | None = None,
    max_points: int = 500_000,
    depth_unit: str = "units",
) -> dict:
    """Write ``depth/<name>.npy`` + ``.png``, ``trajectory.txt`` (TUM) and ``points.ply``.

    images: (1, S, 3, h, w) network input in [0, 1]; camera: the camera of that input. The PNG
    shows the input frame, the colourised depth and a colour bar labelled in ``depth_unit``
    (see :func:`raytun3r_plugin.apps.export.depth_panel`); the .npy is the raw (h, w) float32 depth.
    """
    out = Path(out_dir)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    import cv2

    depth = prediction.depth[0].detach().float().cpu().numpy()
    cam_from_world = prediction.cam_from_world[0].detach().double().cpu().numpy()
    rays, valid = camera.ray_table(dtype=torch.float32)
    valid_np = valid.cpu().numpy()
    frames = images[0].permute(0, 2, 3, 1).detach().float().cpu().numpy()
    for name, frame_depth, frame in zip(names, depth, frames, strict=True):
        np.save(out / "depth" / f"{name}.npy", frame_depth.astype(np.float32))
        cv2.imwrite(
            str(out / "depth" / f"{name}.png"),
            depth_panel(frame, frame_depth, valid_np, unit=depth_unit),
        )
    stamps = (
        np.arange(len(names), dtype=np.float64)
        if timestamps is None
        else np.asarray(timestamps, dtype=np.float64)
    )
    write_tum(out / "trajectory.txt", stamps, cam_from_world)
    points_cam = points_from_depth(torch.from_numpy(depth), rays.cpu()).numpy()  # (S, h, w, 3)
    colours = images[0].permute(0, 2, 3, 1).cpu().numpy()
    world_points, world_colours = [], []
    for pose, points, colour in zip(cam_from_world, points_cam, colours, strict=True):
        world_from_cam = invert_rigid(pose)
        keep = valid_np & np.isfinite(points).all(-1)
        world_points.append(points[keep] @ world_from_cam[:3, :3].T + world_from_cam[:3, 3])
        world_colours.append(colour[keep])
    all_points, all_colours = np.concatenate(world_points), np.concatenate(world_colours)
    if len(all_points) > max_points:
        pick = np.random.default_rng(0).choice(len(all_points), max_points, replace=False)
        all_points, all_colours = all_points[pick], all_colours[pick]
    write_ply(out / "points.ply", all_points, all_colours)
    summary = {
        "frames": len(names),
        "points": int(len(all_points)),
        "input_size": [camera.width, camera.height],
        "camera": json.loads(camera.to_json()),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary
