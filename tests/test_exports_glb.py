"""``--export glb``: the point cloud and camera frusta, read back with trimesh."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from raytun3r_plugin.errors import MissingDependencyError
from raytun3r_plugin.exports import ExportOptions, plan_exports
from raytun3r_plugin.exports.glb import GLTF_FROM_WORLD
from tests.export_scenes import scene_of
from tests.helpers import fisheye

trimesh = pytest.importorskip("trimesh")


def test_points_and_frusta_read_back(tmp_path):
    scene = scene_of(fisheye(96, 80, 190.0), frames=3)
    options = ExportOptions(max_points=3000, confidence_quantile=0.3)
    record = plan_exports(scene, ["glb"], options)["glb"].write(tmp_path)
    loaded = trimesh.load(tmp_path / "scene.glb", force="scene")
    assert set(loaded.geometry) == {"points", *(f"camera_{name}" for name in scene.names)}
    cloud = loaded.geometry["points"]
    assert isinstance(cloud, trimesh.PointCloud) and len(cloud.vertices) == record["points"] == 3000
    # Back in the world frame, the points are the confidence-filtered back-projection.
    expected = scene.sample_points(3000, 0.3)
    world = np.asarray(cloud.vertices) @ GLTF_FROM_WORLD  # the flip is its own inverse
    assert np.abs(world - expected.xyz).max() < 1e-5 * np.abs(expected.xyz).max()
    assert np.abs(cloud.colors[:, :3].astype(int) - np.round(expected.rgb * 255)).max() <= 1
    # Confidence filter: no point from a frame's lowest 30 % of confidence.
    for k in range(3):
        known = scene.known(k)
        floor = np.quantile(scene.confidence[k][known], 0.3)
        assert expected.confidence[expected.frame == k].min() >= floor
    for k, name in enumerate(scene.names):
        vertices = np.asarray(loaded.geometry[f"camera_{name}"].vertices) @ GLTF_FROM_WORLD
        pose = scene.world_from_cam(k)
        assert np.abs(vertices[0] - pose[:3, 3]).max() < 1e-5  # apex at the camera centre
        axis = vertices[1:].mean(0) - vertices[0]
        assert axis @ pose[:3, 2] > 0.999 * np.linalg.norm(axis)  # looking along its z


def test_a_missing_trimesh_names_the_extra(monkeypatch):
    scene = scene_of(fisheye(96, 80, 190.0), frames=1)
    monkeypatch.setitem(sys.modules, "trimesh", None)
    with pytest.raises(MissingDependencyError, match=r"raytun3r\[viz\]"):
        plan_exports(scene, ["glb"], ExportOptions())
