"""Depth as ``raytun3r infer`` writes it: at the frames' resolution, in a stated convention."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from raytun3r_plugin.apps.inference import write_outputs
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.exports.resample import resample_maps
from raytun3r_plugin.prediction import Prediction
from raytun3r_plugin.preprocess import input_layout
from tests.export_scenes import rendered
from tests.helpers import fisheye


def _prediction(seq) -> Prediction:
    depth = torch.from_numpy(np.asarray(seq.depth, dtype=np.float32))[None]
    poses = torch.from_numpy(np.asarray(seq.cam_from_world, dtype=np.float32))[None]
    return Prediction(depth=depth, cam_from_world=poses, confidence=None, extras={})


def _images(seq) -> torch.Tensor:
    return torch.from_numpy(np.asarray(seq.images, dtype=np.float32)).permute(0, 3, 1, 2)[None]


def test_constant_depth_stays_constant_up_to_the_rim():
    """Only valid input pixels take part: a constant map is that constant everywhere inside the
    frames' lens circle (a plain bilinear resize would darken the rim with the black outside)."""
    native = fisheye(160, 128, 190.0)
    layout = input_layout(native, 84)
    valid_in = layout.camera.valid_mask().numpy()
    maps = np.where(valid_in, 2.5, 0.0)[None]
    out = resample_maps(maps, valid_in, layout.native_camera)
    inside = layout.native_camera.valid_mask().numpy()
    assert out.shape == (1, layout.native_camera.height, layout.native_camera.width)
    assert np.all(out[0][~inside] == 0)
    reached = inside & (out[0] > 0)
    assert reached.sum() > 0.99 * inside.sum()
    assert np.allclose(out[0][reached], 2.5, atol=1e-6)


def test_resampling_follows_the_resize_pixel_convention():
    """A map linear in the input's u is read back at each frame pixel's input position,
    ``u_in = (u + 0.5) * w / W - 0.5`` (the mapping of Camera.resized)."""
    native = fisheye(160, 128, 190.0)
    layout = input_layout(native, 84)
    height, width = layout.height, layout.width
    u_in = np.arange(width, dtype=np.float64)[None, :].repeat(height, 0)
    valid_in = np.ones((height, width), bool)
    out = resample_maps((3.0 + 0.1 * u_in)[None], valid_in, layout.native_camera)[0]
    native_w = layout.native_camera.width
    expected = 3.0 + 0.1 * ((np.arange(native_w) + 0.5) * width / native_w - 0.5)
    inside = layout.native_camera.valid_mask().numpy()
    columns = (np.arange(native_w) > 2) & (np.arange(native_w) < native_w - 3)  # not the edges
    rows, cols = np.nonzero(inside & columns[None, :])
    assert np.abs(out[rows, cols] - expected[cols]).max() < 1e-5


def test_frames_resolution_is_close_to_the_native_ground_truth(tmp_path):
    """Depth predicted at the input size and written at the frames' size agrees with the
    native-size truth inside the lens circle, and summary.json says which size it is."""
    native = fisheye(160, 128, 190.0)
    layout = input_layout(native, 84)
    small = rendered(layout.camera.to_json(), 2)
    large = rendered(layout.native_camera.to_json(), 2)
    summary = write_outputs(
        tmp_path,
        _prediction(small),
        _images(small),
        layout.camera,
        ["a", "b"],
        frames=np.asarray(large.images),
        frames_camera=layout.native_camera,
    )
    depth = np.load(tmp_path / "depth" / "a.npy")
    assert depth.shape == (layout.native_camera.height, layout.native_camera.width)
    truth = np.asarray(large.depth[0])
    both = (depth > 0) & (truth > 0)
    assert both.sum() > 0.9 * (truth > 0).sum()
    relative = np.abs(depth[both] - truth[both]) / truth[both]
    assert np.median(relative) < 0.02
    record = json.loads((tmp_path / "summary.json").read_text())["depth"]
    assert record["resolution"] == "frames" and record["width"] == layout.native_camera.width
    assert record == summary["depth"] and record["convention"] == "range"
    # --depth-resolution network: the network's size, said so.
    network = write_outputs(
        tmp_path / "net", _prediction(small), _images(small), layout.camera, ["a", "b"]
    )
    assert network["depth"]["resolution"] == "network"
    assert np.load(tmp_path / "net" / "depth" / "a.npy").shape == (layout.height, layout.width)


def test_one_pixels_point_under_range_and_z(tmp_path):
    """The same pixel's 3-D point from the written range (X = D ray) and the written z-depth
    (X = D ray / ray_z) is the one point of the renderer's independent z-depth; beyond 90
    degrees only range exists."""
    camera = fisheye(96, 80, 190.0)
    seq = rendered(camera.to_json(), 2)
    written = {}
    for convention in ("range", "z"):
        summary = write_outputs(
            tmp_path / convention,
            _prediction(seq),
            _images(seq),
            camera,
            ["a", "b"],
            depth_convention=convention,
        )
        assert summary["depth"]["convention"] == convention
        assert convention in summary["depth"]["meaning"]
        written[convention] = np.load(tmp_path / convention / "depth" / "b.npy")
    rays, valid = camera.ray_table(dtype=torch.float64)
    rays = rays.numpy()
    truth_z = np.asarray(seq.meta["per_frame"]["z_depth"][1], dtype=np.float64)
    row, col = 25, 62  # about 40 degrees off-axis
    ray = rays[row, col]
    assert valid[row, col] and 0.5 < ray[2] < 0.9 and truth_z[row, col] > 0
    from_range = written["range"][row, col] * ray
    from_z = written["z"][row, col] * ray / ray[2]
    expected = truth_z[row, col] * ray / ray[2]
    assert np.abs(from_range - expected).max() < 1e-4 * np.linalg.norm(expected)
    assert np.abs(from_z - expected).max() < 1e-4 * np.linalg.norm(expected)
    assert abs(written["z"][row, col] - truth_z[row, col]) < 1e-4 * truth_z[row, col]
    # A ray beyond 90 degrees (a 190-degree lens has them): range > 0, no z-depth (0).
    behind = valid.numpy() & (rays[..., 2] < -0.02) & (written["range"] > 0)
    assert behind.any()
    assert np.all(written["z"][behind] == 0)


def test_an_unknown_convention_is_refused_before_anything_is_written(tmp_path):
    camera = fisheye(96, 80, 190.0)
    seq = rendered(camera.to_json(), 2)
    with pytest.raises(InputError, match="range"):
        write_outputs(
            tmp_path / "out",
            _prediction(seq),
            _images(seq),
            camera,
            ["a", "b"],
            depth_convention="ray",
        )
    assert not (tmp_path / "out").exists()


def test_a_z_depth_picture_takes_its_scale_from_the_centre():
    """z-depth near 90 degrees is close to 0: without a scale region the rim takes the whole
    colour scale and the centre is one colour; with it the centre's gradient shows."""
    from raytun3r_plugin.exports.files import depth_panel

    height, width = 60, 80
    depth = np.tile(np.linspace(2.0, 3.0, width, dtype=np.float32), (height, 1))
    rim = np.zeros((height, width), bool)
    rim[:12], rim[-12:] = True, True
    depth[rim] = 0.01
    frame = np.zeros((height, width, 3), np.float32)
    scale = 240 // height

    def centre_spread(panel):
        coloured = panel[:, width * scale : 2 * width * scale].astype(np.float32)
        return coloured[20 * scale : 40 * scale].reshape(-1, 3).std(0).sum()

    plain = depth_panel(frame, depth, label="z")
    scaled = depth_panel(frame, depth, label="z", scale_region=~rim)
    assert centre_spread(scaled) > 5 * centre_spread(plain) + 1
