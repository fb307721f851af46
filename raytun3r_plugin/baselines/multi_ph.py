"""Multi-PH: five virtual pinhole views of a fisheye, each through the unpatched model, fused back.

The paper's multi-pinhole baseline (docs/baselines.md, "Multi-PH"):

* **Views.** V0 is the Center-PH view (the fisheye's optical axis, a pinhole of the fisheye
  image's size with ``fov_deg`` = 110 degrees across the width); V1..V4 are the same pinhole
  turned by the tilt alpha to the right, left, down and up (OpenCV axes: +x right, +y down).
  ``R_v`` maps fisheye-camera coordinates to view coordinates, ``X_v = R_v X``.
* **Tilt rule** (:func:`choose_tilt`): the smallest multiple of 5 degrees, at least 5, whose
  five views cover at least 99.5 % of the fisheye's valid pixels (45 degrees for a 185-degree
  equidistant circle, 50 for 195 and 200 degrees).
* **Inference.** Each view is one stream: the window's frames resampled with the same ``R_v``
  and run through the *unpatched* model, so a frame costs five forward images instead of one.
* **Depth** (:func:`fuse_depth`): every fisheye pixel takes the range ``Z_v / q_z`` of the valid
  view whose axis is nearest (largest ``q_z = (R_v r)_z``, the cube-map rule), after a
  per-frame scale ``s_v = exp(median(log d_0 - log d_v))`` over the pixels V0 and V_v share.
* **Pose** (:func:`fuse_relative_poses`): each stream's relative pose is conjugated back to the
  fisheye frame (``R_v^T R R_v``, ``R_v^T t``); rotations are fused by the weighted chordal L2
  mean, translations by the weighted mean of their directions, with the centre view's length.

Everything here is geometry on torch tensors (float64 for rays and poses); the model is called
through :func:`raytun3r_plugin.prediction.predict` only. Center-PH is the special case of V0
alone, and ``apps/evaluation.py`` builds it from the same functions.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from raytun3r_plugin.cameras import Camera, Pinhole
from raytun3r_plugin.errors import AlreadyAppliedError, InputError
from raytun3r_plugin.poses import relative_pose
from raytun3r_plugin.prediction import Prediction, predict

__all__ = [
    "DEFAULT_FOV_DEG",
    "MIN_COVERAGE",
    "MIN_OVERLAP_FRACTION",
    "TILT_STEP_DEG",
    "VIEW_NAMES",
    "MultiPHPrediction",
    "PinholeView",
    "chain_relative_poses",
    "choose_tilt",
    "chordal_mean",
    "fuse_depth",
    "fuse_relative_poses",
    "multi_pinhole_views",
    "predict_multi_ph",
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
#: A side view's scale against V0 needs an overlap of at least 1 % of the valid fisheye pixels.
MIN_OVERLAP_FRACTION = 0.01
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


def fuse_depth(
    ranges: Tensor,
    inside: Tensor,
    cosines: Tensor,
    min_overlap: float = MIN_OVERLAP_FRACTION,
    valid: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Fuse per-view range maps into one, with per-frame scale alignment to view 0.

    Args:
        ranges: (V, S, H, W) range of each view at each fisheye pixel, frame by frame (any
            value where the view does not cover the pixel).
        inside: (V, H, W) bool, the pixels each view covers.
        cosines: (V, H, W) cosine between each pixel's ray and each view's axis.
        min_overlap: the overlap a side view needs with view 0, as a fraction of the valid
            pixels, for its scale to be estimated; below it the scale is 1 and flagged.
        valid: (H, W) the fisheye's valid pixels (the denominator of ``min_overlap``); default
            the union of ``inside``.

    Returns:
        fused (S, H, W) range (0 where no view covers the pixel), owner (H, W) int64 the view
        each pixel takes its depth from (the covering view with the largest cosine; -1 where
        none), scales (S, V) the factors applied to each view (1 for view 0), and flagged
        (S, V) bool where a scale fell back to 1.
    """
    if ranges.ndim != 4 or inside.shape != (ranges.shape[0], *ranges.shape[-2:]):
        raise InputError(
            f"ranges must be (V, S, H, W) and inside (V, H, W), got {tuple(ranges.shape)} and {tuple(inside.shape)}"
        )
    n_views, n_frames = ranges.shape[:2]
    valid = inside.any(0) if valid is None else valid
    needed = min_overlap * float(valid.sum())
    scales = torch.ones(n_frames, n_views, dtype=torch.float64)
    flagged = torch.zeros(n_frames, n_views, dtype=torch.bool)
    log_ranges = torch.log(ranges.double().clamp_min(1e-30))
    positive = torch.isfinite(ranges) & (ranges > 0)
    for v in range(1, n_views):
        for i in range(n_frames):
            shared = inside[0] & inside[v] & positive[0, i] & positive[v, i]
            if float(shared.sum()) < max(needed, 1.0):
                flagged[i, v] = True
                continue
            difference = (log_ranges[0, i] - log_ranges[v, i])[shared]
            # torch.median takes the lower middle value; the mean of the two middles is the
            # median the recipe states (and exact on an even count).
            ordered = difference.sort().values
            middle = (ordered[(len(ordered) - 1) // 2] + ordered[len(ordered) // 2]) / 2
            scales[i, v] = torch.exp(middle)
    score = torch.where(inside, cosines.double(), torch.full_like(cosines, -math.inf).double())
    owner = score.argmax(0)
    owner = torch.where(inside.any(0), owner, torch.full_like(owner, -1))
    scaled = ranges.double() * scales.T[:, :, None, None]
    picked = torch.gather(scaled, 0, owner.clamp_min(0)[None, None].expand(1, n_frames, -1, -1))
    fused = torch.where(owner >= 0, picked[0], torch.zeros_like(picked[0]))
    return fused.to(ranges.dtype), owner, scales, flagged


def chordal_mean(rotations: Tensor, weights: Tensor | None = None) -> Tensor:
    """Weighted chordal L2 mean of rotations (V, 3, 3): the rotation nearest ``sum w_v R_v`` in
    the Frobenius norm, ``U diag(1, 1, det(U V^T)) V^T`` from the SVD ``U S V^T``. Returns (3, 3)."""
    rotations = torch.as_tensor(rotations, dtype=torch.float64)
    if weights is None:
        weights = torch.ones(rotations.shape[0], dtype=torch.float64)
    weights = torch.as_tensor(weights, dtype=torch.float64)
    if rotations.ndim != 3 or rotations.shape[1:] != (3, 3) or weights.shape != rotations.shape[:1]:
        raise InputError(
            f"rotations must be (V, 3, 3) with weights (V,), got {tuple(rotations.shape)} and {tuple(weights.shape)}"
        )
    if not bool((weights >= 0).all()) or float(weights.sum()) <= 0:
        raise InputError(
            f"weights must be non-negative with a positive sum, got {weights.tolist()}"
        )
    total = (weights[:, None, None] * rotations).sum(0)
    u, _, vt = torch.linalg.svd(total)
    flip = torch.ones(3, dtype=torch.float64)
    flip[2] = torch.sign(torch.linalg.det(u @ vt))
    return u @ torch.diag(flip) @ vt


def fuse_relative_poses(
    relative: Tensor, rotations: Tensor, weights: Tensor, length_view: int = 0
) -> Tensor:
    """One relative pose in the fisheye frame from each view stream's.

    Args:
        relative: (V, 4, 4) ``cam_j_from_cam_i`` of each stream, in its own view frame.
        rotations: (V, 3, 3) ``view_from_fisheye`` of each view.
        weights: (V,) non-negative weights.
        length_view: the stream whose translation length the result keeps (the streams' scales
            differ, so only directions are averaged; V0's is the scale of the fused depth).

    Returns:
        (4, 4) float64 ``cam_j_from_cam_i`` of the fisheye camera: rotation the chordal mean of
        ``R_v^T R^v R_v``, translation the weighted mean of the unit ``R_v^T t^v`` times the
        length of stream ``length_view``'s.
    """
    relative = torch.as_tensor(relative, dtype=torch.float64)
    rotations = torch.as_tensor(rotations, dtype=torch.float64)
    weights = torch.as_tensor(weights, dtype=torch.float64)
    r_t = rotations.transpose(-1, -2)
    rotation = chordal_mean(r_t @ relative[:, :3, :3] @ rotations, weights)
    translations = (r_t @ relative[:, :3, 3:4])[..., 0]
    norms = torch.linalg.vector_norm(translations, dim=-1)
    units = translations / norms.clamp_min(1e-12)[:, None]
    direction = (weights[:, None] * units).sum(0)
    size = torch.linalg.vector_norm(direction)
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = rotation
    if float(size) > 0:
        out[:3, 3] = direction / size * norms[length_view]
    return out


def chain_relative_poses(relative: Tensor) -> Tensor:
    """Poses (S, 4, 4) with ``cam_from_world[0] = I`` and ``cam_from_world[k + 1] =
    relative[k] @ cam_from_world[k]`` from consecutive relative poses (S - 1, 4, 4), so the
    relative pose of each consecutive pair is exactly ``relative[k]``."""
    poses = [torch.eye(4, dtype=torch.float64)]
    for step in torch.as_tensor(relative, dtype=torch.float64):
        poses.append(step @ poses[-1])
    return torch.stack(poses)


@dataclass
class MultiPHPrediction:
    """Multi-PH outputs for one window of S frames, in the fisheye's frame and pixels.

    Attributes:
        depth: (S, H, W) range along the fisheye ray (0 where no view covers the pixel).
        covered: (H, W) bool, the pixels some view covers.
        cam_from_world: (S, 4, 4) float64, world = the fisheye camera of frame 0, chained from
            the fused consecutive relative poses.
        relative: (S - 1, 4, 4) float64 fused ``cam_{k+1}_from_cam_k``.
        owner: (H, W) int64 the view each pixel's depth comes from (-1: none).
        scales: (S, V) per-frame scale of each view's depth against V0; flagged (S, V) where it
            fell back to 1 (too little overlap with V0).
        pose_weights: (V,) weight of each stream in the pose fusion (valid-pixel fraction of the
            view x its mean predicted confidence).
        views: the views; tilt_deg their tilt.
        coverage: fraction of the fisheye's valid pixels covered.
        forward_images: images the model ran on (V x S).
        streams: per view, the raw prediction of its stream.
    """

    depth: Tensor
    covered: Tensor
    cam_from_world: Tensor
    relative: Tensor
    owner: Tensor
    scales: Tensor
    flagged: Tensor
    pose_weights: Tensor
    views: list[PinholeView]
    tilt_deg: float
    coverage: float
    forward_images: int
    streams: list = field(default_factory=list, repr=False)


def _on_cpu(prediction: Prediction) -> Prediction:
    """``prediction`` with its depth, pose and confidence on the CPU."""
    confidence = prediction.confidence
    return Prediction(
        depth=prediction.depth.cpu(),
        cam_from_world=prediction.cam_from_world.cpu(),
        confidence=None if confidence is None else confidence.cpu(),
        extras=prediction.extras,
    )


def predict_multi_ph(
    model: nn.Module,
    images: Tensor,
    camera: Camera,
    views: list[PinholeView] | None = None,
    tilt_deg: float | None = None,
    fov_deg: float = DEFAULT_FOV_DEG,
    min_overlap: float = MIN_OVERLAP_FRACTION,
    **predict_kwargs,
) -> MultiPHPrediction:
    """Run Multi-PH on one window of fisheye frames.

    Args:
        model: a registered backbone *without* a raytun3r patch (the baseline is the frozen
            model on pinhole images); it is not modified.
        images: (S, 3, H, W) or (1, S, 3, H, W) fisheye frames in [0, 1] at ``camera``'s size,
            a multiple of the patch size.
        camera: the fisheye camera of ``images``.
        views: the views (default :func:`multi_pinhole_views` with ``tilt_deg`` and
            ``fov_deg``); view 0 must be the centre view and the scale reference.
        min_overlap: see :func:`fuse_depth`.
        predict_kwargs: passed to :func:`raytun3r_plugin.prediction.predict`.

    Returns:
        :class:`MultiPHPrediction`.

    Raises:
        AlreadyAppliedError: the model carries a raytun3r patch.
        InputError: images of another size than the camera, or fewer than one frame.
    """
    from raytun3r_plugin.patching import handle_of

    if handle_of(model) is not None:
        raise AlreadyAppliedError(
            "Multi-PH runs the unpatched model; remove the raytun3r patch first"
        )
    if images.ndim == 5:
        if images.shape[0] != 1:
            raise InputError(
                f"Multi-PH takes one window at a time, got a batch of {images.shape[0]}"
            )
        images = images[0]
    if images.ndim != 4 or tuple(images.shape[-2:]) != (camera.height, camera.width):
        raise InputError(
            f"images must be (S, 3, {camera.height}, {camera.width}) for this camera, got {tuple(images.shape)}"
        )
    views = multi_pinhole_views(camera, tilt_deg, fov_deg) if views is None else views
    n_frames = images.shape[0]
    ranges, inside, cosines, relatives, weights, streams = [], [], [], [], [], []
    for view in views:
        virtual = resample_to_view(images, camera, view.camera, view.rotation)
        # The fusion below is geometry on the CPU tables of the views: outputs come back first.
        prediction = _on_cpu(predict(model, virtual, **predict_kwargs))
        streams.append(prediction)
        range_v, inside_v = view_depth_to_fisheye(
            prediction.depth[0], camera, view.camera, view.rotation
        )
        ranges.append(range_v)
        inside.append(inside_v)
        cosines.append(view_lookup(camera, view.camera, view.rotation)[1])
        poses = prediction.cam_from_world[0].double()
        relatives.append(
            torch.stack([relative_pose(poses, k, k + 1) for k in range(n_frames - 1)])
            if n_frames > 1
            else torch.zeros(0, 4, 4, dtype=torch.float64)
        )
        seen = view_validity(camera, view.camera, view.rotation)
        confidence = 1.0
        if prediction.confidence is not None and bool(seen.any()):
            confidence = float(prediction.confidence[0].double()[:, seen].mean())
        weights.append(float(seen.double().mean()) * max(confidence, 0.0))
    valid = camera.valid_mask()
    fused, owner, scales, flagged = fuse_depth(
        torch.stack(ranges), torch.stack(inside), torch.stack(cosines), min_overlap, valid
    )
    rotations = torch.stack([view.rotation for view in views])
    weight = torch.tensor(weights, dtype=torch.float64)
    if float(weight.sum()) <= 0:  # no confidence anywhere: every stream counts alike
        weight = torch.ones_like(weight)
    relative = (
        torch.stack(
            [
                fuse_relative_poses(torch.stack([r[k] for r in relatives]), rotations, weight)
                for k in range(n_frames - 1)
            ]
        )
        if n_frames > 1
        else torch.zeros(0, 4, 4, dtype=torch.float64)
    )
    covered = owner >= 0
    return MultiPHPrediction(
        depth=fused,
        covered=covered,
        cam_from_world=chain_relative_poses(relative),
        relative=relative,
        owner=owner,
        scales=scales,
        flagged=flagged,
        pose_weights=weight,
        views=list(views),
        tilt_deg=max(abs(view.yaw_deg) + abs(view.pitch_deg) for view in views),
        coverage=float((covered & valid).sum()) / max(int(valid.sum()), 1),
        forward_images=len(views) * n_frames,
        streams=streams,
    )
