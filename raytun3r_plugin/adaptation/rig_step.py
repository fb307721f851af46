"""One joint step of a rig fit (:func:`~raytun3r_plugin.adaptation.rig.adapt_rig`) and its
cross-camera terms: a window of every camera laid out instant-major, one multi-view forward, each
camera's terms on its own views, and (``cross_camera``) reprojection between the cameras at one
instant with the rig's known relative poses.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from raytun3r_plugin.adaptation.config import AdaptConfig
from raytun3r_plugin.adaptation.losses import (
    inside_mask,
    pe_correction_grid,
    pe_l2,
    pe_tv,
    reprojection_loss,
    total_loss,
)
from raytun3r_plugin.adaptation.problem import AdaptationProblem, _Pair
from raytun3r_plugin.adaptation.step import (
    optimiser_step,
    prediction_terms,
    window_of_step,
)
from raytun3r_plugin.adaptation.target_scale import subset_matches, targets_pose
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.poses import invert_rigid
from raytun3r_plugin.prediction import predict

if TYPE_CHECKING:
    from raytun3r_plugin.datasets.rig import Rig

__all__ = ["cross_pairs", "rig_step", "rig_views"]


def rig_views(batches: dict[str, torch.Tensor], names: list[str]) -> torch.Tensor:
    """Every camera's views of one window as one forward's views, instant-major.

    Args:
        batches: camera name -> (T, 3, H, W) network inputs of its window (the same T for all).
        names: the rig's camera order.

    Returns:
        (T x V, 3, H, W): view ``t V + c`` is camera ``c`` at instant ``t``, the order
        ``apply(model, cameras, adapters)`` expects.
    """
    count = min(int(batches[name].shape[0]) for name in names)
    return torch.stack([batches[name][t] for t in range(count) for name in names])


def _window_depth(
    problem: AdaptationProblem, index: int, frames_per_view: int
) -> list[tuple[torch.Tensor, torch.Tensor]] | None:
    """Supervised rig fit: the depth samples of the window's first ``frames_per_view`` frames."""
    samples = problem.window_depth(index)
    return None if samples is None else samples[:frames_per_view]


def rig_step(
    model: nn.Module,
    fitted: dict[str, Adapter],
    problems: dict[str, AdaptationProblem],
    names: list[str],
    optimizer: torch.optim.Optimizer,
    config: AdaptConfig,
    step: int,
    frames_per_view: int,
    scored: dict[str, list[int]],
    cross: dict[int, list[tuple[int, int, _Pair]]] | None = None,
) -> dict[str, Any]:
    """One joint step: a window of every camera, one forward, each camera's terms, one update.

    ``scored``: per camera, the windows the loss may use (the parallax gate's); a camera with
    none takes part in the forward with its own windows but adds no loss. ``cross`` (a
    cross-camera fit): frame -> ``(camera i, camera j, pair)``; the step then takes the
    reference camera's window and each other camera's window of the same frames (when it has
    one) and adds the cross-camera reprojection terms of those frames.
    """
    began = time.perf_counter()
    count = len(names)
    windows, batches, frames, aligned = _step_windows(
        problems, names, config, step, frames_per_view, scored, cross
    )
    views = rig_views(batches, names)
    prediction = predict(model, views[None])
    # Terms on the CPU, as in step.window_terms (the network may run on a GPU).
    depth, poses = prediction.depth[0].cpu(), prediction.cam_from_world[0].cpu()
    losses: list[torch.Tensor] = []
    record: dict[str, Any] = {"step": step}
    for offset, name in enumerate(names):
        problem = problems[name]
        if windows[name] not in scored[name]:
            if cross is not None:  # its tables still move through the cross terms: regularise
                correction = pe_correction_grid(fitted[name], problem.geometry)
                losses.append(
                    total_loss(
                        {
                            "l2": pe_l2(correction) / problem.pe_scale,
                            "tv": pe_tv(correction) / problem.pe_scale,
                        },
                        config.weights,
                    )
                )
            continue
        _window, pairs = problem.windows[windows[name]]
        kept = [pair for pair in pairs if pair.a < frames_per_view and pair.b < frames_per_view]
        generator = torch.Generator().manual_seed(int(config.seed) * 7_919 + step * 31 + offset)
        terms, counts = prediction_terms(
            depth[offset::count],
            poses[offset::count],
            fitted[name],
            batches[name],
            kept,
            problem.layout,
            problem.valid,
            problem.geometry,
            config,
            generator,
            pe_scale=problem.pe_scale,
            depth_targets=_window_depth(problem, windows[name], frames_per_view),
        )
        loss = total_loss(terms, config.weights)
        losses.append(loss)
        record[f"{name}:loss"] = float(loss.detach())
        record.update({f"{name}:{term}": float(value.detach()) for term, value in terms.items()})
        record[f"{name}:window"] = windows[name]
        record[f"{name}:n_matches"] = counts["n_matches"]
    if cross is not None and aligned:
        cross_loss = _cross_loss(depth, frames, cross, problems, names, config, step)
        if cross_loss is not None:
            record["cross"] = float(cross_loss.detach())
            losses.append(config.weights.reproj * cross_loss)
    record["aligned"] = bool(cross is not None and aligned)
    loss = torch.stack(losses).mean() if losses else depth.sum() * 0.0
    grad_norm = optimiser_step(loss, optimizer, config.clip)
    record.update(
        {
            "loss": float(loss.detach()),
            "grad_norm": grad_norm,
            "skipped": not math.isfinite(grad_norm),
            "views": int(views.shape[0]),
            "time_s": round(time.perf_counter() - began, 4),
        }
    )
    return record


def _step_windows(
    problems: dict[str, AdaptationProblem],
    names: list[str],
    config: AdaptConfig,
    step: int,
    frames_per_view: int,
    scored: dict[str, list[int]],
    cross: dict[int, list[tuple[int, int, _Pair]]] | None,
) -> tuple[dict[str, int], dict[str, torch.Tensor], tuple[int, ...], bool]:
    """Each camera's window of this step and its views: (window index by camera, views by
    camera, the reference camera's frames, whether every camera has a window of those
    frames). With ``cross``, the frames are the reference camera's; else each camera draws
    from the windows the gate scores."""
    windows, batches = {}, {}
    aligned = cross is not None
    frames: tuple[int, ...] = ()
    if cross is not None:
        reference = problems[names[0]]
        first = window_of_step(step, len(reference.windows), config.seed)
        frames = tuple(reference.windows[first][0].frames[:frames_per_view])
    for offset, name in enumerate(names):
        problem = problems[name]
        if cross is not None:
            same = [
                i
                for i, (window, _) in enumerate(problem.windows)
                if tuple(window.frames[:frames_per_view]) == frames
            ]
            index = same[0] if same else window_of_step(step, len(problem.windows), config.seed)
            aligned = aligned and bool(same)
        else:
            # Each camera draws its own window order (its seed offset by its place in the rig).
            usable = scored[name] or list(range(len(problem.windows)))
            index = usable[window_of_step(step, len(usable), config.seed + offset)]
        windows[name] = index
        batches[name] = problem.batch(index)[:frames_per_view]
    return windows, batches, frames, aligned


def _cross_loss(
    depth: torch.Tensor,
    frames: tuple[int, ...],
    cross: dict[int, list[tuple[int, int, _Pair]]],
    problems: dict[str, AdaptationProblem],
    names: list[str],
    config: AdaptConfig,
    step: int,
) -> torch.Tensor | None:
    """Mean cross-camera reprojection term over the step's frames (``depth``: every view of
    the joint forward, instant-major); None when no pair gives one."""
    count = len(names)
    cross_terms: list[torch.Tensor] = []
    for position, frame in enumerate(frames):
        for offset_i, offset_j, pair in cross.get(frame, []):
            if pair.uv_i.shape[0] == 0:
                continue
            term = _cross_term(
                depth[position * count + offset_i],
                pair,
                problems[names[offset_i]],
                problems[names[offset_j]],
                config,
                torch.Generator().manual_seed(int(config.seed) * 7_919 + step * 31 + 17),
            )
            if term is not None:
                cross_terms.append(term)
    return torch.stack(cross_terms).mean() if cross_terms else None


def cross_pairs(
    rig: Rig,
    problems: dict[str, AdaptationProblem],
    names: list[str],
    frames: list[int],
    config: AdaptConfig,
) -> dict[int, list[tuple[int, int, _Pair]]]:
    """frame -> ``(camera i, camera j, pair)`` for every ordered pair of cameras at one instant.

    Matched on the network inputs (one size for the whole rig) by the configured matcher inside
    both cameras' valid regions; the pose target is the rig's ``cam_j_from_cam_i`` (rotation
    and unit translation; the scale is chosen for the pixel residual in the fit, as the
    predicted depth has none). Frames a camera has no input for are skipped.
    """
    from raytun3r_plugin.adaptation.matchers import get_matcher

    matcher = get_matcher(config.matcher, **config.matcher_options)
    out: dict[int, list[tuple[int, int, _Pair]]] = {}
    for frame in frames:
        for offset_i, name_i in enumerate(names):
            for offset_j, name_j in enumerate(names):
                problem_i, problem_j = problems[name_i], problems[name_j]
                if (
                    offset_i == offset_j
                    or frame not in problem_i.inputs
                    or frame not in problem_j.inputs
                ):
                    continue
                j_from_i = rig.cam_from_rig[name_j] @ invert_rigid(rig.cam_from_rig[name_i])
                baseline = float(np.linalg.norm(j_from_i[:3, 3]))
                if baseline < 1e-9:
                    continue
                valid = problem_i.valid & problem_j.valid
                image_i = problem_i.inputs[frame].permute(1, 2, 0).numpy()
                image_j = problem_j.inputs[frame].permute(1, 2, 0).numpy()
                matches = matcher.match(image_i, image_j, valid.numpy())
                uv_i, uv_j = torch.from_numpy(matches.uv_i), torch.from_numpy(matches.uv_j)
                with torch.no_grad():
                    rays_i, ok_i = problem_i.layout.camera.unproject(uv_i)
                    rays_j, ok_j = problem_j.layout.camera.unproject(uv_j)
                keep = ok_i & ok_j & inside_mask(uv_i, valid) & inside_mask(uv_j, valid)
                pair = _Pair(
                    offset_i,
                    offset_j,
                    uv_i[keep],
                    uv_j[keep],
                    torch.from_numpy(matches.confidence).float()[keep],
                    rays_i[keep].float(),
                    rays_j[keep].float(),
                    torch.from_numpy(j_from_i[:3, :3]).double(),
                    torch.from_numpy(j_from_i[:3, 3] / baseline).double(),
                )
                out.setdefault(frame, []).append((offset_i, offset_j, pair))
    return out


def _cross_term(
    depth_i: torch.Tensor,
    pair: _Pair,
    problem_i: AdaptationProblem,
    problem_j: AdaptationProblem,
    config: AdaptConfig,
    generator: torch.Generator,
) -> torch.Tensor | None:
    """The reprojection term of one cross-camera pair: camera i's depth, projected into camera j."""
    uv_i, uv_j, confidence, rays_i, rays_j = subset_matches(pair, config.max_matches, generator)
    camera_j = problem_j.layout.camera
    relative = targets_pose(pair, depth_i, uv_i, uv_j, confidence, rays_i, rays_j, camera_j, config)
    loss, count = reprojection_loss(
        depth_i,
        relative,
        uv_i,
        uv_j,
        confidence,
        camera_j,
        problem_i.valid & problem_j.valid,
        config.depth_convention,
        rays_i=(rays_i, torch.ones_like(confidence, dtype=torch.bool)),
        robust_px=config.robust_px,
    )
    return loss if count else None
