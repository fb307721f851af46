"""The parallax gate's measurement: how far each window's matches move per unit of log depth.

Matches that move less than ``AdaptConfig.min_parallax_px`` input pixels per unit log depth
cannot tell near from far; the fit leaves such windows out of the reprojection term
(docs/adaptation.md section 6).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from raytun3r_plugin.adaptation.config import AdaptConfig
from raytun3r_plugin.adaptation.evaluation import patched_for_evaluation
from raytun3r_plugin.adaptation.losses import depth_parallax_px
from raytun3r_plugin.adaptation.photometric import blurred_gray
from raytun3r_plugin.adaptation.problem import AdaptationProblem
from raytun3r_plugin.adaptation.target_scale import (
    matched_points,
    photometric_scale,
    pose_scaled_to,
)
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.prediction import predict

__all__ = ["window_parallax"]


def window_parallax(
    model: nn.Module, adapter: Adapter, problem: AdaptationProblem, config: AdaptConfig
) -> list[float]:
    """Median depth parallax (px per unit log depth, :func:`depth_parallax_px`) of each window's
    matches, NaN for a window without a pair that has a usable pose target.

    Each used frame is predicted once, alone, through ``model`` patched with ``adapter`` (frozen,
    in eval mode, restored afterwards); each pair's translation is scaled to that depth as the fit
    scales it (:func:`targets_pose`).
    """
    camera = problem.layout.camera
    frames = sorted({frame for window, _ in problem.windows for frame in window.frames})
    with patched_for_evaluation(model, adapter, problem, config):
        depth = {
            frame: predict(model, problem.inputs[frame][None, None]).depth[0, 0].cpu()
            for frame in frames
        }
    medians = []
    photometric = config.scale == "photometric"
    generator = torch.Generator().manual_seed(int(config.seed))
    with torch.no_grad():
        if photometric:
            gray = {
                frame: blurred_gray(problem.inputs[frame][None].double(), config.photo_sigma)[0]
                for frame in frames
            }
        for window, pairs in problem.windows:
            values = []
            for pair in pairs:
                if pair.rotation is None or pair.uv_i.shape[0] == 0:
                    continue
                points, usable = matched_points(
                    depth[window.frames[pair.a]].double(),
                    pair.uv_i.double(),
                    pair.rays_i.double(),
                    config.depth_convention,
                )
                if not usable.any():
                    continue
                scale = None
                if photometric:
                    i, j = window.frames[pair.a], window.frames[pair.b]
                    scale = photometric_scale(
                        depth[i].double(),
                        gray[i],
                        gray[j],
                        pair,
                        camera,
                        problem.valid,
                        config,
                        generator,
                    )
                pose = pose_scaled_to(
                    pair,
                    points,
                    usable,
                    pair.uv_j.double(),
                    pair.confidence.double(),
                    pair.rays_j.double(),
                    camera,
                    config,
                    scale,
                )
                points = points[usable]
                values.append(float(depth_parallax_px(points, pose, camera).median()))
            medians.append(float(torch.tensor(values).median()) if values else math.nan)
    return medians
