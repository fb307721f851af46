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

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from raytun3r_plugin.cameras import Camera
from raytun3r_plugin.errors import AlreadyAppliedError, InputError
from raytun3r_plugin.pinhole_views import (  # the views' geometry, shared with the teacher
    DEFAULT_FOV_DEG,
    MIN_COVERAGE,
    TILT_STEP_DEG,
    VIEW_NAMES,
    PinholeView,
    choose_tilt,
    multi_pinhole_views,
    resample_to_view,
    view_coverage,
    view_depth_to_fisheye,
    view_lookup,
    view_rotation,
    view_validity,
    virtual_pinhole,
)
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

#: A side view's scale against V0 needs an overlap of at least 1 % of the valid fisheye pixels.
MIN_OVERLAP_FRACTION = 0.01


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
