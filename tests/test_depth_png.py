"""The depth PNG of ``raytun3r infer``: input frame, colourised depth, colour bar with its scale."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from raytun3r_plugin.apps.inference import write_outputs
from raytun3r_plugin.exports.files import depth_panel
from raytun3r_plugin.prediction import Prediction
from tests.helpers import fisheye

H, W = 70, 84


def _inputs(frames: int = 2):
    generator = torch.Generator().manual_seed(0)
    images = torch.rand(1, frames, 3, H, W, generator=generator)
    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij"
    )
    depth = (
        (1.0 + xs / W * 4.0 + ys / H)[None, None].expand(1, frames, H, W).contiguous()
    )  # 1 .. 6 m
    pose = torch.eye(4).expand(1, frames, 4, 4).contiguous()
    return images, Prediction(depth=depth, cam_from_world=pose, confidence=None, extras={})


def test_infer_png_shows_the_input_beside_the_depth_with_a_colour_bar(tmp_path):
    images, prediction = _inputs()
    write_outputs(tmp_path, prediction, images, fisheye(W, H), ["0000", "0001"])
    png = cv2.imread(str(tmp_path / "depth" / "0000.png"), cv2.IMREAD_COLOR)
    assert png is not None and png.ndim == 3
    height, width = png.shape[:2]
    # two panels of the frame's aspect side by side, plus the bar and its labels
    assert height >= H and width > 2 * W * height / H
    assert png.std() > 10 and len(np.unique(png.reshape(-1, 3), axis=0)) > 100  # not constant
    npy = np.load(tmp_path / "depth" / "0000.npy")
    assert npy.shape == (H, W)  # the raw depth stays at the network's size


def test_depth_panel_layout_scale_and_input():
    images, prediction = _inputs(1)
    frame = images[0, 0].permute(1, 2, 0).numpy()
    depth = prediction.depth[0, 0].numpy()
    panel = depth_panel(frame, depth, unit="m")
    scale = panel.shape[0] / H
    panel_w = round(W * scale)
    assert panel.dtype == np.uint8 and panel.shape[2] == 3 and panel.shape[0] >= 240
    # left: the input frame (RGB -> BGR), resized
    left = cv2.resize(panel[:, :panel_w], (W, H), interpolation=cv2.INTER_AREA)
    expected = (frame[..., ::-1] * 255).astype(np.float32)
    assert np.abs(left.astype(np.float32) - expected).mean() < 25
    # middle: the depth colours vary across the image (depth grows to the right)
    middle = panel[:, panel_w : 2 * panel_w].astype(np.float32)
    assert (
        np.abs(
            middle[:, : panel_w // 4].mean(axis=(0, 1))
            - middle[:, -panel_w // 4 :].mean(axis=(0, 1))
        ).sum()
        > 50
    )
    # right: a colour bar whose rows change colour from top to bottom, then text
    bar = panel[:, 2 * panel_w :].astype(np.float32)
    assert bar.shape[1] >= 60
    column = bar[panel.shape[0] // 8 : -panel.shape[0] // 8, 8]
    assert np.abs(np.diff(column, axis=0)).sum() > 200


def test_depth_panel_without_valid_pixels_is_not_an_error():
    frame = np.zeros((H, W, 3), np.float32)
    panel = depth_panel(frame, np.zeros((H, W), np.float32))
    assert panel.shape[0] >= H
