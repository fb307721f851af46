"""Patch resampling's local maps (docs/conventions.md, "Patch resampling"; docs/decisions.md,
"Patch resampling's local map"): with ``"turned"`` each patch becomes a pinhole crop from its own
viewing direction and every pixel of the lens reaches some patch; the default ``"central"`` map
leaves much of the rim unread."""

from __future__ import annotations

import math

import pytest
import torch

from raytun3r_plugin import cameras as C
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.geometry import patch_resample_grid, resampled_share, token_centres

SIZE, PATCH = 112, 14


def _pixels(grid: torch.Tensor) -> torch.Tensor:
    """(H, W, 2) input pixel positions of a normalised ``align_corners=False`` grid."""
    return (grid[0] + 1) * torch.tensor([SIZE, SIZE], dtype=grid.dtype) / 2 - 0.5


def _local_maps(grid: torch.Tensor) -> torch.Tensor:
    """(hw, 2, 2) linear map A of every patch, fitted to where its pixels sample (c + A e)."""
    pixels = _pixels(grid).to(torch.float64)
    h = SIZE // PATCH
    per_patch = pixels.reshape(h, PATCH, h, PATCH, 2).permute(0, 2, 1, 3, 4).reshape(h * h, -1, 2)
    offsets_1d = torch.arange(PATCH, dtype=torch.float64) - (PATCH - 1) / 2
    oy, ox = torch.meshgrid(offsets_1d, offsets_1d, indexing="ij")
    offsets = torch.stack((ox, oy), dim=-1).reshape(-1, 2)
    design = torch.cat((offsets, torch.ones(len(offsets), 1, dtype=torch.float64)), dim=1)
    solution = torch.linalg.lstsq(design.expand(h * h, -1, -1), per_patch).solution
    return solution[:, :2].transpose(1, 2)


def test_each_patch_is_a_pinhole_crop_from_its_own_viewing_direction():
    # An ideal equidistant lens (r = f theta): against a pinhole of focal f turned to a ray at
    # angle theta, its local scale is 1 along the radius and theta / sin(theta) across it.
    camera = C.fisheye(SIZE, 185.0, model="kb4", k=(0.0, 0.0, 0.0, 0.0))
    grid = patch_resample_grid(camera, SIZE, SIZE, PATCH, local_map="turned")
    assert grid is not None
    maps = _local_maps(grid)
    centres = token_centres(SIZE, SIZE, PATCH)
    rays, valid = camera.unproject(centres)
    angle = torch.atan2(rays[:, :2].norm(dim=-1), rays[:, 2]).to(torch.float64)
    checked = 0
    for a, theta, ok in zip(maps, angle, valid.tolist(), strict=True):
        if not ok or theta < 0.05:
            continue
        expected = sorted((1.0, min(float(theta / math.sin(theta)), 2.0)), reverse=True)
        assert torch.linalg.svdvals(a).tolist() == pytest.approx(expected, abs=0.01)
        checked += 1
    assert checked >= 40


@pytest.mark.parametrize(
    "camera",
    [C.fisheye(SIZE, 185.0, model="kb4"), C.fisheye(SIZE, 195.0, model="ds")],
    ids=["KB4 185", "DS 195"],
)
def test_every_lens_pixel_reaches_a_patch(camera):
    assert resampled_share(camera, SIZE, SIZE, PATCH, "turned") == 1.0
    # The map to the pinhole on the lens axis zooms rim patches in: most of the rim is unread.
    assert resampled_share(camera, SIZE, SIZE, PATCH, "central") < 0.6
    # A pinhole camera is not resampled: all of it is read.
    lens = C.Pinhole(SIZE, SIZE, [80.0, 80.0, (SIZE - 1) / 2, (SIZE - 1) / 2])
    assert resampled_share(lens, SIZE, SIZE, PATCH) == 1.0
    assert resampled_share(lens, SIZE, SIZE, PATCH, "turned") == 1.0


def test_an_unknown_local_map_is_refused():
    with pytest.raises(InputError, match="local_map"):
        patch_resample_grid(C.fisheye(SIZE, 185.0), SIZE, SIZE, PATCH, local_map="tangent")
