"""Scoring a method on a sequence (docs/conventions.md section 8): vanilla, Center-PH, Multi-PH,
raytun3r.

Every method is run on the same frame windows and scored on the same pair list. The network sees
non-overlapping windows of consecutive frames (``window`` views per forward); relative poses are
scored on consecutive pairs inside a window, depth on every frame. On a fisheye the depth channel
is read as range along the ray for every method (docs/conventions.md section 2), so all methods are scored
alike; AbsRel and delta < 1.25 use a per-image median scale.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from raytun3r_plugin import metrics
from raytun3r_plugin.baselines.multi_ph import predict_multi_ph
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.patching import apply
from raytun3r_plugin.pinhole_views import (
    multi_pinhole_views,
    resample_to_view,
    view_depth_to_fisheye,
    virtual_pinhole,
)
from raytun3r_plugin.poses import relative_pose
from raytun3r_plugin.prediction import predict

METHODS = ("vanilla", "center-ph", "multi-ph", "raytun3r")
#: What identifies a row and what it scores, in the order every table shows them (the benchmark,
#: the demo and the report page add their own columns after these).
METRIC_COLUMNS = (
    "camera",
    "scene",
    "method",
    "rot_deg",
    "trans_deg",
    "d_reproj_px",
    "abs_rel",
    "delta_1.25",
    "coverage",
)
CENTER_PH_FOV_DEG = 110.0


@dataclass
class MethodOutput:
    """Per-frame predictions of one method over a sequence (at the network input size).

    depth: (N, h, w) range along the ray (0 where the method gives none);
    window_poses: list of (frame indices, cam_from_world (S, 4, 4)) per forward window;
    coverage: fraction of valid fisheye pixels that received a depth.
    """

    depth: np.ndarray
    window_poses: list[tuple[list[int], np.ndarray]]
    coverage: float = 1.0
    seconds: float = 0.0
    extras: dict = field(default_factory=dict)


def frame_windows(indices: list[int], window: int, stride: int = 1) -> list[list[int]]:
    """Non-overlapping windows of ``window`` indices ``stride`` apart; a short tail joins the
    previous window. With ``stride`` s the indices are split into s interleaved runs
    (``indices[r::s]``), so every frame is in one window and scored pairs are s frames apart."""
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise InputError(f"pair stride must be a positive integer, got {stride!r}")
    windows: list[list[int]] = []
    for start in range(min(stride, len(indices))):
        run = indices[start::stride]
        part = [run[k : k + window] for k in range(0, len(run), window)]
        if len(part) > 1 and len(part[-1]) < 2:
            part[-2].extend(part.pop())
        windows.extend(part)
    return windows


#: ``choose_pair_stride``: the baseline a pair needs, as a fraction of the median scene depth
#: (or in metres without depth), for its relative pose to be measurable: at stride 1 a
#: 30 Hz sequence moves about a centimetre, where pose targets and d_reproj stop depending on
#: depth.
MIN_BASELINE_FRACTION = 0.03
MIN_BASELINE_M = 0.05


def choose_pair_stride(seq, frames: list[int] | None = None, max_stride: int = 20) -> dict:
    """The smallest frame stride whose median ground-truth baseline is measurable.

    Returns ``{"stride", "median_baseline", "threshold", "rule"}``: the stride s is the smallest
    with median |t| of the relative poses (k, k + s) at least :data:`MIN_BASELINE_FRACTION` x
    the median ground-truth depth (or :data:`MIN_BASELINE_M` metres without depth), capped at
    ``max_stride`` and at a third of the frames.
    """
    if seq.cam_from_world is None:
        raise InputError(f"{seq.name}: no ground-truth poses to choose a pair stride from")
    frames = list(range(len(seq))) if frames is None else list(frames)
    poses = np.asarray(seq.cam_from_world, dtype=np.float64)[frames]
    centres = np.einsum("nij,nj->ni", -np.transpose(poses[:, :3, :3], (0, 2, 1)), poses[:, :3, 3])
    if seq.depth is not None and bool((seq.depth[frames] > 0).any()):
        depth = seq.depth[frames]
        threshold = MIN_BASELINE_FRACTION * float(np.median(depth[depth > 0]))
        rule = f"{MIN_BASELINE_FRACTION:g} x median depth"
    else:
        threshold, rule = MIN_BASELINE_M, f"{MIN_BASELINE_M:g} m"
    limit = max(1, min(max_stride, len(frames) // 3))
    baseline = 0.0
    for stride in range(1, limit + 1):
        baseline = float(np.median(np.linalg.norm(centres[stride:] - centres[:-stride], axis=1)))
        if baseline >= threshold:
            break
    return {"stride": stride, "median_baseline": baseline, "threshold": threshold, "rule": rule}


def _input_images(seq, frames: list[int]) -> torch.Tensor:
    images = np.stack([seq.image(k) for k in frames])
    return torch.from_numpy(images).permute(0, 3, 1, 2)[None].float()


def center_pinhole(camera, fov_deg: float = CENTER_PH_FOV_DEG):
    """The virtual pinhole of Center-PH: same optical axis and size, ``fov_deg`` across the width."""
    return virtual_pinhole(camera, fov_deg)


def fisheye_to_center_pinhole(images: torch.Tensor, camera, pinhole) -> torch.Tensor:
    """Resample fisheye images (..., 3, H, W) into the virtual pinhole view (bilinear)."""
    return resample_to_view(images, camera, pinhole)


def center_pinhole_depth_to_fisheye(
    depth_z: torch.Tensor, camera, pinhole
) -> tuple[torch.Tensor, torch.Tensor]:
    """Map pinhole z-depth (..., h, w) back to the fisheye pixels it covers, as range.

    Returns range depth (..., H, W) (0 where uncovered) and the coverage mask (H, W).
    """
    return view_depth_to_fisheye(depth_z, camera, pinhole)


def run_method(
    model,
    seq,
    method: str,
    adapter=None,
    frames: list[int] | None = None,
    window: int = 3,
    components=None,
    stride: int = 1,
) -> MethodOutput:
    """Run ``method`` on ``frames`` of ``seq`` (images already at the network input size), in
    windows of ``window`` frames ``stride`` apart (:func:`frame_windows`)."""
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; choose from {METHODS}")
    camera = seq.camera
    frames = list(range(len(seq))) if frames is None else list(frames)
    depth = np.zeros((len(seq), camera.height, camera.width), np.float32)
    poses: list[tuple[list[int], np.ndarray]] = []
    coverage = 1.0
    pinhole = center_pinhole(camera) if method == "center-ph" else None
    # Multi-PH's views (and its tilt rule's coverage search) once per sequence, not per window.
    views = multi_pinhole_views(camera, fov_deg=CENTER_PH_FOV_DEG) if method == "multi-ph" else None
    extras: dict = {}
    start = time.perf_counter()
    handle = (
        apply(model, camera, adapter, components=components, strict=False)
        if method == "raytun3r"
        else None
    )
    try:
        with torch.no_grad():
            for group in frame_windows(frames, window, stride):
                images = _input_images(seq, group)
                if method == "center-ph":
                    prediction = predict(model, fisheye_to_center_pinhole(images, camera, pinhole))
                    window_depth, covered = center_pinhole_depth_to_fisheye(
                        prediction.depth[0].cpu(), camera, pinhole
                    )
                    coverage = float(covered.sum() / camera.valid_mask().sum())
                elif method == "multi-ph":
                    fused = predict_multi_ph(model, images, camera, views=views)
                    depth[group] = fused.depth.float().numpy()
                    poses.append((group, fused.cam_from_world.numpy()))
                    coverage = fused.coverage
                    extras["tilt_deg"] = fused.tilt_deg
                    extras["forward_images"] = (
                        extras.get("forward_images", 0) + fused.forward_images
                    )
                    extras["scale_fallbacks"] = extras.get("scale_fallbacks", 0) + int(
                        fused.flagged.sum()
                    )
                    continue
                else:
                    prediction = predict(model, images)
                    window_depth = prediction.depth[0]
                depth[group] = window_depth.float().cpu().numpy()
                poses.append((group, prediction.cam_from_world[0].double().cpu().numpy()))
    finally:
        if handle is not None:
            handle.remove()
    return MethodOutput(
        depth=depth,
        window_poses=poses,
        coverage=coverage,
        seconds=time.perf_counter() - start,
        extras=extras,
    )


def score(
    seq, output: MethodOutput, min_translation: float = 1e-3, correspondence_stride: int = 4
) -> dict[str, Any]:
    """Metrics of one method's output against the sequence's ground truth."""
    from raytun3r_plugin.synthetic import correspondences

    gt_poses = np.asarray(seq.cam_from_world, dtype=np.float64)
    rotation, translation, pairs = [], [], []
    n_skipped = 0
    for group, predicted in output.window_poses:
        local_pairs = [(a, a + 1) for a in range(len(group) - 1)]
        errors = metrics.relative_pose_errors(
            predicted, gt_poses[group], local_pairs, min_translation=min_translation
        )
        rotation.extend(errors["rotation_deg"].tolist())
        translation.extend(errors["translation_deg"].tolist())
        pairs.extend((group[a], group[b]) for a, b in errors["pairs"])
        n_skipped += errors["n_skipped"]
    pose_errors = {
        "rotation_deg": np.array(rotation),
        "translation_deg": np.array(translation),
        "pairs": np.array(pairs).reshape(-1, 2),
        "n_pairs": len(pairs),
        "n_skipped": n_skipped,
        "folded": False,
    }
    d_values = []
    sky = (getattr(seq, "meta", None) or {}).get("per_frame", {}).get("sky")
    if seq.depth is not None:
        for i, j in pairs:
            uv_i, uv_j, visible = correspondences(seq, i, j, stride=correspondence_stride)
            keep = visible & np.isfinite(uv_j).all(-1)
            if sky is not None:
                rows, cols = np.round(uv_i[:, 1]).astype(int), np.round(uv_i[:, 0]).astype(int)
                keep &= ~np.asarray(sky, bool)[i][rows, cols]
            relative = relative_pose(gt_poses, i, j)
            d_values.append(
                metrics.d_reproj(output.depth[i], seq.camera, uv_i[keep], uv_j[keep], relative)
            )
    abs_rel = delta = None
    if seq.depth is not None:
        scored = sorted({k for group, _ in output.window_poses for k in group})
        valid = seq.camera.valid_mask().numpy()[None] & (seq.depth[scored] > 0)
        if seq.mask is not None:
            valid &= np.broadcast_to(seq.mask, seq.depth.shape)[scored]
        valid &= output.depth[scored] > 0
        if sky is not None:  # synthetic sky sits at ~2 km: not a depth to score
            valid &= ~np.asarray(sky, bool)[scored]
        abs_rel = metrics.abs_rel(output.depth[scored], seq.depth[scored], valid)
        delta = metrics.delta_125(output.depth[scored], seq.depth[scored], valid)
    summary = metrics.summarize(
        pose_errors=pose_errors, d_reproj=d_values, abs_rel=abs_rel, delta_125=delta, name=seq.name
    )
    summary["coverage"] = output.coverage
    summary["seconds"] = output.seconds
    return summary


def headline(summary: dict[str, Any]) -> dict[str, float]:
    """The numbers a results table shows: means of rotation / translation error (deg; signed
    0-180 as ``trans_deg``, folded 0-90 as ``trans_folded_deg``), d_reproj (px), AbsRel,
    delta < 1.25, coverage, and the counts of scored and skipped pairs."""

    def mean(key: str) -> float:
        value = summary.get(key)
        return float(value["mean"]) if isinstance(value, dict) and "mean" in value else math.nan

    return {
        "rot_deg": mean("rotation_deg"),
        "trans_deg": mean("translation_deg"),
        "trans_folded_deg": mean("translation_folded_deg"),
        "d_reproj_px": mean("d_reproj"),
        "abs_rel": mean("abs_rel"),
        "delta_1.25": mean("delta_125"),
        "coverage": float(summary.get("coverage", math.nan)),
        "pairs": summary.get("n_pairs", 0),
        "skipped_pairs": summary.get("n_skipped", 0),
    }


def format_table(rows: list[dict[str, Any]], columns: list[str]) -> str:
    """Markdown table of ``rows`` (dicts) over ``columns``; floats with 3 significant digits."""

    def cell(value: Any) -> str:
        if isinstance(value, float):
            return "-" if math.isnan(value) else f"{value:.3g}"
        return str(value)

    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(cell(row.get(c, "")) for c in columns) + " |" for row in rows]
    return "\n".join(lines)


def fit_sequence(seq, long_side: int, patch: int = 14, max_frames: int | None = None):
    """A copy of ``seq`` (its first ``max_frames`` frames) prepared for a network input of long
    side ``long_side`` px by :class:`raytun3r_plugin.preprocess.InputLayout`, the preparation
    ``raytun3r adapt`` and ``raytun3r infer`` use, so eval scores the network on the pixels an
    adapter was fitted on.

    Images: (N, h, w, 3) float32, bilinear antialiased; depth (N, h, w) and masks (N, h, w)
    nearest neighbour; the camera is the layout's input camera (a stated crop, then a pure
    resize), so it describes the new images exactly. Poses are unchanged.
    """
    from raytun3r_plugin.datasets import Sequence
    from raytun3r_plugin.preprocess import InputLayout

    count = len(seq) if max_frames is None else min(len(seq), max_frames)
    layout = InputLayout.for_camera(seq.camera, long_side, patch)
    # One frame at a time: a dataset sequence may be long and its native frames large.
    images = np.stack(
        [layout.frames(seq.image(k)[None])[0].permute(1, 2, 0).numpy() for k in range(count)]
    )
    depth = (
        None
        if seq.depth is None
        else layout.depth(np.asarray(seq.depth[:count], dtype=np.float32)).numpy()
    )
    mask = None
    if seq.mask is not None:
        native = np.asarray(seq.mask, dtype=bool)
        mask = (
            layout.mask(native[:count]).numpy()
            if native.ndim == 3
            else np.repeat(layout.mask(native).numpy()[None], count, axis=0)
        )
    poses = None if seq.cam_from_world is None else np.asarray(seq.cam_from_world)[:count]
    return Sequence(
        name=seq.name,
        camera=layout.camera,
        timestamps=np.asarray(seq.timestamps)[:count],
        cam_from_world=poses,
        images=images,
        depth=depth,
        depth_kind=seq.depth_kind,
        mask=mask,
    )
