"""Network-size maps back at the frames' resolution, inside the camera's valid region.

The network sees the frames resized (after a stated crop, :mod:`raytun3r_plugin.preprocess`), so
an input pixel and the frame pixels it covers share one ray up to the resize. A map predicted at
the input size is brought back by bilinear interpolation in which only input pixels with a value
(inside the input camera's valid region, finite, > 0) take part, each weighted by its bilinear
weight and the sum renormalised: near the rim of the image circle no black outside pixel is
blended in. Frame pixels outside the frame camera's valid region, or with no valid neighbour,
get 0 ("unknown").
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.errors import InputError

__all__ = ["resample_maps"]


def _bilinear(maps: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of (S, 1, h, w) maps at normalised positions, zero outside."""
    return F.grid_sample(maps, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


def resample_maps(
    maps: np.ndarray | torch.Tensor,
    source_valid: np.ndarray | torch.Tensor,
    target: Camera,
) -> np.ndarray:
    """(S, h, w) maps on a network input -> (S, H, W) float32 on ``target``'s pixels.

    Args:
        maps: (S, h, w) values per input pixel (depth, confidence); non-finite or <= 0 = none.
        source_valid: (h, w) bool, the input camera's valid region.
        target: the camera of the frames (``W x H``), a pure resize of the input camera (the
            crop, if any, already applied: ``InputLayout.native_camera``).

    Returns:
        (S, H, W) float32; 0 where ``target`` has no valid ray or no valid input pixel is near.
    """
    values = torch.as_tensor(np.asarray(maps), dtype=torch.float64)
    if values.ndim != 3:
        raise InputError(f"maps must be (S, h, w), got shape {tuple(values.shape)}")
    valid = torch.as_tensor(np.asarray(source_valid), dtype=torch.bool)
    if tuple(valid.shape) != tuple(values.shape[1:]):
        raise InputError(
            f"valid mask {tuple(valid.shape)} does not match maps {tuple(values.shape)}"
        )
    usable = (valid[None] & torch.isfinite(values) & (values > 0)).to(torch.float64)
    weighted = torch.where(usable > 0, values, torch.zeros_like(values))
    height, width = target.height, target.width
    # align_corners=False maps pixel edges to -1 and 1 in both images, so the normalised position
    # of a frame pixel centre is the same whatever the input size: a pure resize.
    xs = (torch.arange(width, dtype=torch.float64) + 0.5) / width * 2 - 1
    ys = (torch.arange(height, dtype=torch.float64) + 0.5) / height * 2 - 1
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1)[None]  # (1, H, W, 2)
    grid = grid.expand(values.shape[0], -1, -1, -1)
    total = _bilinear((weighted * usable)[:, None], grid)[:, 0]
    weight = _bilinear(usable[:, None], grid)[:, 0]
    inside = target.valid_mask("cpu")[None] & (weight > 1e-9)
    out = torch.where(inside, total / weight.clamp_min(1e-12), torch.zeros_like(total))
    return out.to(torch.float32).numpy()
