"""Virtual pinhole views of a fisheye camera: the geometry that the pinhole-view teacher,
Center-PH and Multi-PH share.

A view is a pinhole of the fisheye image's size with ``fov_deg`` (110 degrees) across its width,
turned by a rotation ``R_v`` from the fisheye's optical axis (``X_v = R_v X``; OpenCV axes).
:func:`resample_to_view` renders a fisheye image into a view, :func:`view_depth_to_fisheye` and
:func:`view_lookup` carry a view's depth back, :func:`multi_pinhole_views` builds the five views
(centre, right, left, down, up) with the tilt rule of :func:`choose_tilt`, and
:func:`view_coverage` measures how much of the lens they see. Core geometry: the method
(:mod:`raytun3r_plugin.adaptation.teacher`) and the baselines
(:mod:`raytun3r_plugin.baselines.multi_ph`, Center-PH in ``apps/evaluation.py``) import it; it
imports neither.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import torch
import torch.nn.functional as F
from torch import Tensor

from raytun3r_plugin.cameras import Camera, Pinhole
from raytun3r_plugin.errors import InputError

__all__ = [
    "DEFAULT_FOV_DEG",
    "MAX_TILT_DEG",
    "MIN_COVERAGE",
    "TILT_STEP_DEG",
    "VIEW_NAMES",
    "PinholeView",
    "choose_tilt",
    "multi_pinhole_views",
    "resample_to_view",
    "view_coverage",
    "view_depth_to_fisheye",
    "view_lookup",
    "view_rotation",
    "view_validity",
    "virtual_pinhole",
]

#: Field of view of every virtual pinhole across its width, degrees (the paper's 110).
DEFAULT_FOV_DEG = 110.0
#: The tilt rule's grid and target: multiples of 5 degrees, at least 99.5 % of valid pixels.
TILT_STEP_DEG = 5.0
MIN_COVERAGE = 0.995
MAX_TILT_DEG = 85.0
#: View order: V0 the centre, then yaw +alpha, yaw -alpha, pitch +alpha, pitch -alpha.
VIEW_NAMES = ("centre", "right", "left", "down", "up")
#: Smallest cosine to a view's axis a fisheye ray may have to be looked up in that view.
_MIN_COS = 1e-6


@dataclass(frozen=True)
class PinholeView:
    """One virtual pinhole view of a fisheye.

    Attributes:
        name: one of :data:`VIEW_NAMES`.
        camera: the view's :class:`Pinhole` (pixels, focal length in px).
        rotation: (3, 3) float64 ``view_from_fisheye``: ``X_v = rotation @ X`` (same centre).
        yaw_deg, pitch_deg: where the view's axis points, degrees (+yaw right, +pitch down).
    """

    name: str
    camera: Pinhole
    rotation: Tensor
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0

    @property
    def axis(self) -> Tensor:
        """(3,) the view's optical axis in fisheye coordinates (``rotation^T e_z``)."""
        return self.rotation[2].clone()


def virtual_pinhole(camera: Camera, fov_deg: float = DEFAULT_FOV_DEG) -> Pinhole:
    """A pinhole of ``camera``'s size, centred, with ``fov_deg`` across the width (pixel edges).

    The focal length is ``(W / 2) / tan(fov_deg / 2)`` px and the principal point the image
    centre ``((W - 1) / 2, (H - 1) / 2)`` (pixel centres at integers, docs/conventions.md
    section 2); this is Center-PH's view and every Multi-PH view.
    """
    if not 0 < fov_deg < 180:
        raise InputError(f"a pinhole's field of view must lie in (0, 180) degrees, got {fov_deg}")
    focal = (camera.width / 2) / math.tan(math.radians(fov_deg) / 2)
    return Pinhole(
        camera.width,
        camera.height,
        {"fx": focal, "fy": focal, "cx": (camera.width - 1) / 2, "cy": (camera.height - 1) / 2},
    )


def view_rotation(yaw_deg: float = 0.0, pitch_deg: float = 0.0) -> Tensor:
    """(3, 3) float64 ``view_from_fisheye`` of a view whose axis is turned ``yaw_deg`` to the right
    (+x) and then ``pitch_deg`` down (+y), degrees.

    The rows are the view's axes in fisheye coordinates; the axis (third row) is
    ``(cos p sin y, sin p, cos p cos y)`` and the view's x axis stays horizontal (no roll).
    """
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    # R_y(yaw) then R_x(-pitch) applied to the view: X = R_y(yaw) R_x(-pitch) X_v.
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    ry = torch.tensor([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]], dtype=torch.float64)
    rx = torch.tensor([[1.0, 0.0, 0.0], [0.0, cp, sp], [0.0, -sp, cp]], dtype=torch.float64)
    return (ry @ rx).T.contiguous()


def _rotated(rays: Tensor, rotation: Tensor | None) -> Tensor:
    """``rotation @ ray`` for rays (..., 3); no arithmetic at all without a rotation, so the
    Center-PH path stays bit for bit what it was."""
    if rotation is None:
        return rays
    return rays @ rotation.to(dtype=rays.dtype, device=rays.device).T


_Table = TypeVar("_Table")


def _cached(
    build: Callable[[Camera, Pinhole, Tensor | None], _Table],
) -> Callable[[Camera, Pinhole, Tensor | None], _Table]:
    """Cache a geometry table per (fisheye, view, rotation) by value: every window of a sequence
    asks for the same ones. Cameras whose parameters carry a graph are not cached. The cached
    tensors are shared; nothing modifies them in place."""
    cache = functools.lru_cache(maxsize=16)(
        lambda camera, view, key: build(
            camera, view, None if key is None else torch.tensor(key, dtype=torch.float64).view(3, 3)
        )
    )

    @functools.wraps(build)
    def tables(camera: Camera, view: Pinhole, rotation: Tensor | None = None) -> _Table:
        if camera.requires_grad or view.requires_grad:
            return build(camera, view, rotation)
        key = None if rotation is None else tuple(rotation.double().flatten().tolist())
        return cache(camera, view, key)

    return tables


@_cached
def _view_sampling(camera: Camera, view: Pinhole, rotation: Tensor | None) -> Tensor:
    """(h, w, 2) float32 ``grid_sample`` grid of the fisheye image for each view pixel."""
    rays, _ = view.ray_table(dtype=torch.float64)
    # A view pixel's ray in fisheye coordinates is R^T ray, i.e. the row vector ray @ R.
    rays = rays if rotation is None else rays @ rotation.to(torch.float64)
    uv, valid = camera.project(rays)
    grid = torch.stack(
        ((2 * uv[..., 0] + 1) / camera.width - 1, (2 * uv[..., 1] + 1) / camera.height - 1), -1
    )
    return torch.where(valid[..., None], grid, torch.full_like(grid, 2.0)).float()


def resample_to_view(
    images: Tensor, camera: Camera, view: Pinhole, rotation: Tensor | None = None
) -> Tensor:
    """Resample fisheye images (..., 3, H, W) into a virtual pinhole view (bilinear).

    Args:
        images: fisheye images in [0, 1], the last three dimensions (3, H, W) at ``camera``'s size.
        camera: the fisheye camera of ``images``.
        view: the pinhole (its size is the output's size).
        rotation: (3, 3) ``view_from_fisheye``; None for the fisheye's own axis (Center-PH).

    Returns:
        (..., 3, h, w) images of the view; pixels whose ray the fisheye does not see are black.
    """
    grid = _view_sampling(camera, view, rotation).to(images.device)
    flat = images.reshape(-1, *images.shape[-3:])
    out = F.grid_sample(
        flat,
        grid[None].expand(flat.shape[0], -1, -1, -1),
        mode="bilinear",
        padding_mode="zeros",
        align_corners=False,
    )
    return out.reshape(*images.shape[:-2], view.height, view.width)


@_cached
def view_validity(camera: Camera, view: Pinhole, rotation: Tensor | None = None) -> Tensor:
    """(h, w) bool: view pixels whose ray lands on a valid fisheye pixel (the rest is black)."""
    rays, _ = view.ray_table(dtype=torch.float64)
    rays = rays if rotation is None else rays @ rotation.to(torch.float64)
    uv, valid = camera.project(rays)
    col, row = torch.round(uv[..., 0]), torch.round(uv[..., 1])
    inside = (
        valid & (col >= 0) & (col <= camera.width - 1) & (row >= 0) & (row <= camera.height - 1)
    )
    mask = camera.valid_mask()
    index_r = row.clamp(0, camera.height - 1).long()
    index_c = col.clamp(0, camera.width - 1).long()
    return inside & mask[index_r, index_c]


@_cached
def view_lookup(
    camera: Camera, view: Pinhole, rotation: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Where each fisheye pixel's ray falls in a view.

    Returns:
        uv (H, W, 2) float64 view pixel coordinates, q_z (H, W) float64 the cosine between the
        ray and the view's axis, and inside (H, W) bool: the fisheye pixel is valid, in front of
        the view and its projection lies within the view's pixel centres. Cached per (camera,
        view, rotation); do not modify the tensors in place.
    """
    rays, valid = camera.ray_table(dtype=torch.float64)
    q = _rotated(rays, rotation)
    uv, in_front = view.project(q)
    inside = (
        valid
        & in_front
        & (q[..., 2] > _MIN_COS)
        & (uv[..., 0] >= 0)
        & (uv[..., 0] <= view.width - 1)
        & (uv[..., 1] >= 0)
        & (uv[..., 1] <= view.height - 1)
    )
    return uv, q[..., 2], inside


@_cached
def _fisheye_sampling(camera: Camera, view: Pinhole, rotation: Tensor | None) -> Tensor:
    """(H, W, 2) float32 ``grid_sample`` grid of the view's maps for each fisheye pixel."""
    uv, _, inside = view_lookup(camera, view, rotation)
    grid = torch.stack(
        ((2 * uv[..., 0] + 1) / view.width - 1, (2 * uv[..., 1] + 1) / view.height - 1), -1
    )
    return torch.where(inside[..., None], grid, torch.zeros_like(grid)).float()


def view_depth_to_fisheye(
    depth_z: Tensor, camera: Camera, view: Pinhole, rotation: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Map a view's z-depth (..., h, w) back to the fisheye pixels it covers, as range.

    A fisheye pixel with unit ray r sees the view's z-depth ``Z`` at ``q = R r`` (bilinear), and
    its range is ``Z / q_z``.

    Returns:
        range depth (..., H, W) (0 where the view does not cover the pixel) and the view's
        coverage mask (H, W) bool.
    """
    device = depth_z.device
    grid = _fisheye_sampling(camera, view, rotation).to(device)
    _, q_z, inside = view_lookup(camera, view, rotation)
    q_z, inside = q_z.to(device), inside.to(device)
    flat = depth_z.reshape(-1, 1, *depth_z.shape[-2:]).float()
    sampled = F.grid_sample(
        flat, grid[None].expand(flat.shape[0], -1, -1, -1), mode="bilinear", align_corners=False
    )[:, 0]
    range_depth = sampled / q_z.clamp_min(_MIN_COS).float()
    range_depth = torch.where(inside, range_depth, torch.zeros_like(range_depth))
    return range_depth.reshape(*depth_z.shape[:-2], *range_depth.shape[-2:]), inside


def multi_pinhole_views(
    camera: Camera, tilt_deg: float | None = None, fov_deg: float = DEFAULT_FOV_DEG
) -> list[PinholeView]:
    """The five Multi-PH views of ``camera``: centre, right, left, down, up.

    Args:
        camera: the fisheye (its size is every view's size).
        tilt_deg: how far the side views turn from the axis, degrees; None applies the rule of
            :func:`choose_tilt`.
        fov_deg: each view's field of view across its width, degrees.

    Returns:
        Five :class:`PinholeView` in :data:`VIEW_NAMES` order; V0's rotation is the identity.
    """
    pinhole = virtual_pinhole(camera, fov_deg)
    if tilt_deg is None:
        tilt_deg = choose_tilt(camera, fov_deg)
    if not math.isfinite(tilt_deg) or not 0 <= tilt_deg < 90:
        raise InputError(f"tilt must lie in [0, 90) degrees, got {tilt_deg}")
    directions = ((0.0, 0.0), (tilt_deg, 0.0), (-tilt_deg, 0.0), (0.0, tilt_deg), (0.0, -tilt_deg))
    return [
        PinholeView(name, pinhole, view_rotation(yaw, pitch), yaw, pitch)
        for name, (yaw, pitch) in zip(VIEW_NAMES, directions, strict=True)
    ]


def view_coverage(camera: Camera, views: list[PinholeView]) -> float:
    """Fraction of ``camera``'s valid pixels that at least one of ``views`` covers."""
    covered = torch.zeros(camera.height, camera.width, dtype=torch.bool)
    for view in views:
        covered |= view_lookup(camera, view.camera, view.rotation)[2]
    return float(covered.sum()) / max(int(camera.valid_mask().sum()), 1)


def choose_tilt(
    camera: Camera,
    fov_deg: float = DEFAULT_FOV_DEG,
    min_coverage: float = MIN_COVERAGE,
    step_deg: float = TILT_STEP_DEG,
    max_tilt_deg: float = MAX_TILT_DEG,
) -> float:
    """The tilt rule, degrees: the smallest multiple of ``step_deg`` (from ``step_deg`` up to
    ``max_tilt_deg``) whose five views cover at least ``min_coverage`` of the valid pixels.

    The side views always turn by at least one step (at 0 they would repeat V0). A lens no tilt
    covers well enough (beyond about 230 degrees with 110-degree views) gets the tilt of the
    largest coverage, the smallest one on ties.
    """
    best, best_tilt = -1.0, step_deg
    steps = int(math.floor(max_tilt_deg / step_deg + 1e-9))
    for k in range(1, steps + 1):
        tilt = k * step_deg
        coverage = view_coverage(camera, multi_pinhole_views(camera, tilt, fov_deg))
        if coverage >= min_coverage:
            return tilt
        if coverage > best:
            best, best_tilt = coverage, tilt
    return best_tilt
