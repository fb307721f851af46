"""``--export nerfstudio``: transforms.json read back by a reader written from nerfstudio's
documented schema and conventions (docs.nerf.studio "Data conventions"; the dataparser's keys),
not from raytun3r's writer."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from raytun3r_plugin import cameras
from raytun3r_plugin.exports import ExportOptions, plan_exports
from tests.export_scenes import scene_of
from tests.helpers import fisheye

W, H = 96, 80


# ------------------------------------------------------------------ the reader
def read_transforms(folder):
    meta = json.loads((folder / "transforms.json").read_text())
    for key in ("camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h", "frames"):
        assert key in meta, key
    return meta


def opencv_cam_from_world(frame) -> np.ndarray:
    """transform_matrix is camera-to-world with OpenGL camera axes (+X right, +Y up, +Z back)."""
    c2w_gl = np.asarray(frame["transform_matrix"], dtype=np.float64)
    c2w_cv = c2w_gl @ np.diag([1.0, -1.0, -1.0, 1.0])  # back to +Y down, +Z forward
    return np.linalg.inv(c2w_cv)


def _undistort_kb(theta_d: float, k: list[float]) -> float:
    theta = theta_d
    for _ in range(50):
        t2 = theta * theta
        f = theta * (1 + k[0] * t2 + k[1] * t2**2 + k[2] * t2**3 + k[3] * t2**4) - theta_d
        df = 1 + 3 * k[0] * t2 + 5 * k[1] * t2**2 + 7 * k[2] * t2**3 + 9 * k[3] * t2**4
        theta -= f / df
    return theta


def pixel_ray(meta, frame, row: int, col: int) -> tuple[np.ndarray, np.ndarray]:
    """World origin and unit direction of the ray through the centre of pixel (row, col).

    nerfstudio casts rays through (col + 0.5, row + 0.5) with cx, cy in those coordinates and
    builds the camera direction with +Y up and -Z forward.
    """
    x = (col + 0.5 - meta["cx"]) / meta["fl_x"]
    y = (row + 0.5 - meta["cy"]) / meta["fl_y"]
    if meta["camera_model"] == "OPENCV_FISHEYE":
        theta_d = math.hypot(x, y)
        theta = _undistort_kb(theta_d, [meta[f"k{i}"] for i in range(1, 5)])
        s = math.sin(theta) / theta_d if theta_d > 0 else 1.0
        direction_gl = np.array([s * x, -s * y, -math.cos(theta)])
    else:
        assert meta["camera_model"] == "OPENCV" and meta["k1"] == meta["p1"] == 0.0
        direction_gl = np.array([x, -y, -1.0])
        direction_gl /= np.linalg.norm(direction_gl)
    c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
    return c2w[:3, 3], c2w[:3, :3] @ direction_gl


# ------------------------------------------------------------------ the tests
def _export(tmp_path, scene, **options):
    plans = plan_exports(scene, ["nerfstudio"], ExportOptions(**options))
    record = plans["nerfstudio"].write(tmp_path)
    return tmp_path / "nerfstudio", record, plans["nerfstudio"]


def test_kb4_pose_pixel_ray_and_depth_round_trip(tmp_path):
    camera = fisheye(W, H, 190.0)
    scene = scene_of(camera, frames=2)
    folder, record, _ = _export(tmp_path, scene)
    meta = read_transforms(folder)
    assert meta["camera_model"] == "OPENCV_FISHEYE" and record["lens"] == "exact"
    assert (meta["w"], meta["h"]) == (W, H)
    assert [meta[f"k{i}"] for i in range(1, 5)] == [camera.values[f"k{i}"] for i in range(1, 5)]
    frame = meta["frames"][1]
    assert (folder / frame["file_path"]).is_file() and (folder / frame["mask_path"]).is_file()
    # One frame's pose, back through nerfstudio's convention.
    assert np.abs(opencv_cam_from_world(frame) - scene.cam_from_world[1]).max() < 1e-9
    # One pixel's ray, ~40 degrees off-axis, and one beyond 90 degrees (a 190-degree lens).
    world = scene.world_from_cam(1)
    for row, col in ((25, 62), (40, 1)):
        origin, direction = pixel_ray(meta, frame, row, col)
        ours = camera.unproject(torch.tensor([float(col), float(row)], dtype=torch.float64))[0]
        expected = world[:3, :3] @ ours.numpy()
        assert np.abs(origin - world[:3, 3]).max() < 1e-12
        assert np.abs(direction - expected).max() < 1e-9
    assert (world[:3, :3].T @ direction)[2] < 0  # the second ray looks backwards: theta > 90
    # The depth file (mm, range by default) puts the pixel's point where raytun3r's depth does.
    depth = np.load(folder / frame["depth_file_path"]) * meta["depth_unit_scale_factor"]
    assert meta["depth_convention"].startswith("range")
    origin, direction = pixel_ray(meta, frame, 25, 62)
    point = origin + depth[25, 62] * direction
    ours = world[:3, :3] @ (scene.depth[1, 25, 62] * scene.rays[25, 62]) + world[:3, 3]
    assert np.abs(point - ours).max() < 1e-5
    # The mask is the lens circle: nerfstudio samples no ray outside it.
    mask = cv2.imread(str(folder / frame["mask_path"]), cv2.IMREAD_GRAYSCALE) > 0
    assert np.array_equal(mask, camera.valid_mask().numpy())


def test_z_depth_files_hold_z(tmp_path):
    camera = fisheye(W, H, 190.0)
    scene = scene_of(camera, frames=2)
    folder, record, _ = _export(tmp_path, scene, depth_convention="z")
    meta = read_transforms(folder)
    assert record["depth_convention"] == "z" and meta["depth_convention"].startswith("z")
    depth = np.load(folder / meta["frames"][0]["depth_file_path"]) * meta["depth_unit_scale_factor"]
    expected = scene.depth[0] * scene.rays[..., 2]
    front = (scene.rays[..., 2] > 0.05) & scene.known(0)
    assert np.allclose(depth[front], expected[front], rtol=1e-6)


def test_double_sphere_is_fitted_and_its_rays_agree(tmp_path):
    camera = cameras.fisheye((W, H), 195.0, "ds")
    scene = scene_of(camera, frames=1)
    folder, record, plan = _export(tmp_path, scene)
    meta = read_transforms(folder)
    assert meta["camera_model"] == "OPENCV_FISHEYE" and meta["lens_fit"]["fitted_to"] == "ds"
    assert record["lens"]["worst_px"] < 0.1 and any("fitted" in note for note in plan.notes)
    world = scene.world_from_cam(0)
    for row, col in ((25, 62), (40, 10)):
        _, direction = pixel_ray(meta, meta["frames"][0], row, col)
        ours = world[:3, :3] @ scene.rays[row, col]
        # an error of worst_px pixels is at most about worst_px / focal radians
        assert np.arccos(np.clip(direction @ ours, -1, 1)) < 2 * record["lens"]["worst_px"] / 20


def test_fisheye624_keeps_its_own_model_and_a_given_mask(tmp_path):
    camera = cameras.Fisheye624(
        W,
        H,
        {"fx": 40.0, "fy": 40.0, "cx": 47.3, "cy": 39.6, "k0": 0.01, "k1": -0.002, "k2": 3e-4}
        | {"k3": 0.0, "k4": 0.0, "k5": 0.0, "p0": 1e-4, "p1": -2e-4, "s0": 1e-4, "s1": 0.0}
        | {"s2": -1e-4, "s3": 0.0},
    )
    scene = scene_of(camera, frames=1)
    folder, _, _ = _export(tmp_path, scene)
    meta = read_transforms(folder)
    assert meta["camera_model"] == "FISHEYE624"
    assert meta["distortion_params"] == [camera.values[n] for n in camera.param_names[4:]]
    assert meta["cx"] == camera.values["cx"] + 0.5 and meta["fisheye_crop_radius"] > 10
    assert "mask_path" not in meta["frames"][0]  # nerfstudio crops FISHEYE624 by the radius
    # A mask the user gave is written with the frames.
    scene.mask = np.ones((H, W), bool)
    scene.mask[:, : W // 3] = False
    folder, record, _ = _export(tmp_path / "masked", scene)
    meta = read_transforms(folder)
    mask = cv2.imread(str(folder / meta["frames"][0]["mask_path"]), cv2.IMREAD_GRAYSCALE) > 0
    assert record["mask"] and np.array_equal(mask, scene.valid) and not mask[:, : W // 3].any()


@pytest.mark.parametrize("camera", [cameras.Pinhole(W, H, [60.0, 61.0, 47.3, 39.6])])
def test_pinhole_is_written_as_undistorted_opencv(tmp_path, camera):
    scene = scene_of(camera, frames=1)
    folder, _, _ = _export(tmp_path, scene)
    meta = read_transforms(folder)
    assert meta["camera_model"] == "OPENCV" and meta["k1"] == meta["k2"] == 0.0
    origin, direction = pixel_ray(meta, meta["frames"][0], 10, 70)
    world = scene.world_from_cam(0)
    ours = camera.unproject(torch.tensor([70.0, 10.0], dtype=torch.float64))[0].numpy()
    assert np.abs(direction - world[:3, :3] @ ours).max() < 1e-9
