"""Fit the adapters of every camera of a rig together, from one rig sequence (docs/rigs.md).

Each camera keeps its own adapter (shareable per camera, as a single-camera fit's), and each
camera's segment is prepared as :func:`~raytun3r_plugin.adaptation.train.adapt` prepares one
(windows, matches, pose targets, input layout). What is joint is the forward: every step takes
one window of every camera, lays the views out instant-major (``apply(model, cameras,
adapters)``'s order), runs them through the patched model *in one multi-view forward*, scores
each camera's views with that camera's pairs (:func:`~raytun3r_plugin.adaptation.step.
prediction_terms`) and steps one Adam optimiser over every camera's tables on the mean of the
cameras' losses. So each camera's tables are fitted while the network sees the other cameras'
views, as it will at inference.

The parallax gate (``AdaptConfig.min_parallax_px``) works per camera as in :func:`adapt`: a
camera's windows whose matches carry no depth signal are dropped from its loss, and a camera
left with none still gives its views to every forward but is not scored (its tables stay as they
started, ``training_info["verdict"]`` "no signal").

Not here (single-camera :func:`adapt` has them): pairs across cameras (the reprojection terms
are within one camera), the collapse guard, checkpoints and resuming, the supervised mode.
``training_info["rig"]`` says so.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from raytun3r_plugin.adaptation.checkpoint import write_loss_artifacts
from raytun3r_plugin.adaptation.config import TERMS, AdaptConfig
from raytun3r_plugin.adaptation.losses import (
    inside_mask,
    pe_correction_grid,
    pe_l2,
    pe_tv,
    reprojection_loss,
    total_loss,
)
from raytun3r_plugin.adaptation.problem import (
    AdaptationProblem,
    _Pair,
    prepare_problem,
)
from raytun3r_plugin.adaptation.step import (
    _frozen,
    _subset,
    _targets_pose,
    optimiser_step,
    prediction_terms,
    regulariser_scale,
    window_of_step,
    window_parallax,
)
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.errors import AlreadyAppliedError, InputError
from raytun3r_plugin.patching import apply, handle_of
from raytun3r_plugin.poses import invert_rigid
from raytun3r_plugin.prediction import predict

if TYPE_CHECKING:
    from raytun3r_plugin.datasets.rig import Rig

__all__ = ["adapt_rig", "rig_artifact_paths"]

#: What a rig fit leaves out, recorded in every adapter's ``training_info["rig"]``.
NOT_IN_A_RIG_FIT = (
    "cross-camera pairs",
    "collapse guard",
    "checkpoint and resume",
    "supervised mode",
)


def rig_artifact_paths(out_dir: str | os.PathLike, names: list[str]) -> dict[str, Path]:
    """Files a rig fit writes into ``out_dir``: one adapter per camera, one log and loss curve."""
    folder = Path(out_dir)
    paths = {f"adapter:{name}": folder / f"{name}.safetensors" for name in names}
    paths.update(
        {
            "log": folder / "rig.log.jsonl",
            "csv": folder / "rig.losses.csv",
            "curve": folder / "rig.losses.png",
        }
    )
    return paths


def adapt_rig(
    model: nn.Module,
    rig: Rig,
    config: AdaptConfig | None = None,
    *,
    adapters: Mapping[str, Adapter] | None = None,
    out_dir: str | os.PathLike | None = None,
    progress: bool = True,
    cross_camera: bool = False,
) -> dict[str, Adapter]:
    """Fit one adapter per camera of ``rig``, all cameras' views in each forward.

    Args:
        model: a supported backbone, not patched; its weights are never changed.
        rig: a :class:`~raytun3r_plugin.datasets.rig.Rig` (time-aligned sequences, one image
            size); its :attr:`~raytun3r_plugin.datasets.rig.Rig.names` order is the view order.
        config: :class:`AdaptConfig` for every camera (None: the ``rig`` recipe, which is the
            ``default`` one without the teacher term; an ``input_size`` of None is the
            backbone's own); ``window_size``
            frames of each camera per step, so ``window_size x V`` views per forward.
        adapters: start from these (copied), by camera name; default zero adapters.
        out_dir: write ``<camera>.safetensors`` per camera, ``rig.log.jsonl`` (one JSON object
            per step) and the loss curves (``rig.losses.csv``, ``.png`` with matplotlib).
        progress: a line to stderr every ~5 % of the run.
        cross_camera: add a reprojection term between the cameras at each instant (matches
            between camera i and camera j at one instant, the rig's known rotation and
            translation direction, the translation scale chosen for the pixel residual as for
            temporal pairs; :func:`_cross_pairs`). Every step then takes the reference
            camera's window and, for the other cameras, their window of the same frames; the
            temporal terms still need the gate's windows, the cross terms do not.

    Returns:
        ``{camera name: Adapter}``, each with its camera and ``training_info`` (the single-camera
        fields for its segment, plus ``"rig"``: the cameras, views per forward, and what a rig
        fit leaves out, :data:`NOT_IN_A_RIG_FIT`).

    Raises:
        AlreadyAppliedError: the model carries a raytun3r patch.
        InputError: a camera without a usable window, or cameras whose input layouts differ.
    """
    config = (AdaptConfig.from_recipe("rig", model=model) if config is None else config).sized_for(
        model
    )
    if handle_of(model) is not None:
        raise AlreadyAppliedError(
            "adapt_rig needs an unpatched model; remove the existing raytun3r patch first"
        )
    if config.weights.teacher > 0:
        raise InputError(
            "adapt_rig has no pinhole-view teacher term yet: use the 'rig' recipe "
            "(AdaptConfig.from_recipe('rig')), set weights.teacher to 0, or fit each camera "
            "with adapt() for the teacher"
        )
    names = rig.names
    start = {} if adapters is None else dict(adapters)
    fitted = {
        name: (
            Adapter.for_model(model, None, components=config.components)
            if name not in start
            else copy.deepcopy(start[name])
        )
        for name in names
    }
    patch = fitted[names[0]].patch_size
    problems: dict[str, AdaptationProblem] = {}
    for name in names:
        seq = rig.sequences[name]
        problem = prepare_problem(
            seq.camera, seq, _for_camera(config, rig, name), patch, mask=_static_mask(seq)
        )
        problem.pe_scale = regulariser_scale(model, config)
        problems[name] = problem
        fitted[name].camera = problem.layout.native_camera
    sizes = {name: (p.layout.height, p.layout.width) for name, p in problems.items()}
    if len(set(sizes.values())) != 1:
        raise InputError(
            f"the rig's cameras give different network inputs {sizes}: a rig forward needs one"
        )
    frames_per_view = min(len(p.windows[0][0].frames) for p in problems.values())
    # Per camera, measured with the starting tables: (windows to score, the gate's record).
    scored: dict[str, list[int]] = {}
    gates: dict[str, dict[str, Any] | None] = {}
    for name in names:
        problem = problems[name]
        everything = list(range(len(problem.windows)))
        if config.min_parallax_px <= 0:
            scored[name], gates[name] = everything, None
            continue
        medians = window_parallax(model, fitted[name], problem, config)
        scored[name] = [
            i for i, m in zip(everything, medians, strict=True) if not m < config.min_parallax_px
        ]
        gates[name] = {
            "min_parallax_px": config.min_parallax_px,
            "window_median_px": [round(m, 4) if math.isfinite(m) else None for m in medians],
            "windows_kept": len(scored[name]),
            "windows_dropped": len(medians) - len(scored[name]),
        }
    cross: dict[int, list[tuple[int, int, _Pair]]] = {}
    if cross_camera and len(names) > 1:
        frames = sorted({f for window, _ in problems[names[0]].windows for f in window.frames})
        cross = _cross_pairs(rig, problems, names, frames, config)
    has_signal = any(scored.values()) or any(
        pair.uv_i.shape[0] for pairs in cross.values() for *_, pair in pairs
    )
    trainable = [table for name in names for table in fitted[name].parameters()]
    optimizer = torch.optim.Adam(trainable, lr=config.lr)
    history: list[dict[str, Any]] = []
    paths = rig_artifact_paths(out_dir, names) if out_dir is not None else None
    log = None
    if paths is not None:
        paths["log"].parent.mkdir(parents=True, exist_ok=True)
        log = open(paths["log"], "w", encoding="utf-8")  # noqa: SIM115 (closed in finally)
    began = time.perf_counter()
    every = max(1, config.steps // 20)
    try:
        with _frozen(model), torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed)
            handle = apply(
                model,
                [problems[name].layout.native_camera for name in names],
                [fitted[name] for name in names],
                components=config.components,
                strict=False,
                mask=[problems[name].mask for name in names],
            )
            try:
                for step in range(config.steps if has_signal else 0):
                    record = _rig_step(
                        model,
                        fitted,
                        problems,
                        names,
                        optimizer,
                        config,
                        step,
                        frames_per_view,
                        scored,
                        cross if cross_camera else None,
                    )
                    history.append(record)
                    if log is not None:
                        log.write(json.dumps(record) + "\n")
                        log.flush()
                    if progress and ((step + 1) % every == 0 or step + 1 == config.steps):
                        print(
                            f"adapt_rig: step {step + 1}/{config.steps} loss {record['loss']:.4g}",
                            file=sys.stderr,
                            flush=True,
                        )
            finally:
                handle.remove()
    finally:
        if log is not None:
            log.close()
    seconds = time.perf_counter() - began
    for index, name in enumerate(names):
        info = _training_info(
            config, problems[name], history, name, index, names, frames_per_view, seconds
        )
        info["recipe"] = config.recipe_record(model)
        if gates[name] is not None:
            info["parallax_gate"] = gates[name]
        if cross_camera:
            info["rig"]["cross_camera"] = {
                "pairs": sum(1 for pairs in cross.values() for p in pairs if p[0] == index),
                "median_matches": float(
                    np.median(
                        [
                            p[2].uv_i.shape[0]
                            for pairs in cross.values()
                            for p in pairs
                            if p[0] == index
                        ]
                    )
                )
                if cross
                else 0.0,
                "aligned_steps": sum(1 for r in history if r.get("aligned", False)),
            }
            info["rig"]["left_out"] = [
                x for x in info["rig"]["left_out"] if x != "cross-camera pairs"
            ]
        info["verdict"] = _verdict(
            info, bool(scored[name]) or bool(history and cross_camera), history
        )
        fitted[name].training_info = info
    if paths is not None:
        for name in names:
            fitted[name].save(paths[f"adapter:{name}"])
        per_camera = [
            f"{name}:{term}"
            for name in names
            for term in ("loss", *TERMS)
            if history and f"{name}:{term}" in history[0]
        ]
        write_loss_artifacts(
            paths,
            history,
            terms=per_camera,
            plotted=[column for column in per_camera if column.endswith(":loss")],
            title=f"rig adaptation losses ({len(history)} steps, {len(names)} cameras)",
        )
    return fitted


def _for_camera(config: AdaptConfig, rig: Rig, name: str) -> AdaptConfig:
    """The camera's config: its own cache entry (``sequence_id``) when the config has one."""

    if config.sequence_id is None:
        return config
    return dataclasses.replace(config, sequence_id=f"{config.sequence_id}/{name}")


def _static_mask(seq) -> np.ndarray | None:
    """A sequence's fixed (H, W) mask (a vehicle body), passed on; per-frame masks are not."""
    mask = getattr(seq, "mask", None)
    if mask is None or np.ndim(mask) != 2:
        return None
    return np.asarray(mask, dtype=bool)


def _rig_step(
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
    windows, batches = {}, {}
    aligned = cross is not None
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
    views = torch.stack(
        [batches[name][t] for t in range(frames_per_view) for name in names]
    )  # instant-major: view t V + c is camera c
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
        )
        loss = total_loss(terms, config.weights)
        losses.append(loss)
        record[f"{name}:loss"] = float(loss.detach())
        record.update({f"{name}:{term}": float(value.detach()) for term, value in terms.items()})
        record[f"{name}:window"] = windows[name]
        record[f"{name}:n_matches"] = counts["n_matches"]
    cross_terms: list[torch.Tensor] = []
    if cross is not None and aligned:
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
    if cross_terms:
        cross_loss = torch.stack(cross_terms).mean()
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


def _cross_pairs(
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
    uv_i, uv_j, confidence, rays_i, rays_j = _subset(pair, config.max_matches, generator)
    camera_j = problem_j.layout.camera
    relative = _targets_pose(
        pair, depth_i, uv_i, uv_j, confidence, rays_i, rays_j, camera_j, config
    )
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


def _verdict(
    info: dict[str, Any], has_signal: bool, history: list[dict[str, Any]]
) -> dict[str, Any]:
    """What the fit of one camera came to, as a sentence (``status`` and ``summary``).

    A camera with no temporal window of its own (cross-camera terms only) is judged by the
    cross-camera loss of the first and last pass.
    """
    if not has_signal:
        return {
            "status": "no signal",
            "summary": "no signal: every window of this camera was dropped by the parallax "
            "gate (its matches carry no depth signal); the tables stay as they started",
        }
    first, last = info.get("first_pass_loss"), info["final_losses"].get("loss")
    if first is None and last is None and any("cross" in r for r in history):
        crossed = [r["cross"] for r in history if "cross" in r]
        window = max(1, len(crossed) // 10)
        first, last = float(np.mean(crossed[:window])), float(np.mean(crossed[-window:]))
    if first is None or last is None or not (math.isfinite(first) and math.isfinite(last)):
        return {"status": "diverged", "summary": "diverged: the loss is not finite"}
    return {
        "status": "ok",
        "summary": f"ok: loss {first:.4g} -> {last:.4g} over {info['steps']} joint steps",
        "first_pass_loss": first,
        "last_pass_loss": last,
    }


def _training_info(
    config: AdaptConfig,
    problem: AdaptationProblem,
    history: list[dict[str, Any]],
    name: str,
    index: int,
    names: list[str],
    frames_per_view: int,
    seconds: float,
) -> dict[str, Any]:
    tail = history[-len(problem.windows) :]
    final = {
        term: float(np.mean([r[f"{name}:{term}"] for r in tail]))
        for term in ("loss", *TERMS)
        if tail and f"{name}:{term}" in tail[0]
    }
    first, key = history[: len(problem.windows)], f"{name}:loss"
    return {
        "method": "raytun3r rig adaptation",
        "supervision": {"kind": "self-supervised"},
        "steps": len(history),
        "requested_steps": config.steps,
        "final_losses": final,
        "first_pass_loss": float(np.mean(losses))
        if (losses := [r[key] for r in first if key in r])
        else None,
        "segment": {
            **problem.segment,
            "windows": [list(w.frames) for w in problem.adaptation.windows],
        },
        "input": problem.layout.record(),
        "adaptation_set": problem.adaptation.cache_key,
        "config": config.to_dict(),
        "wall_time_s": round(seconds, 3),
        "rig": {
            "cameras": list(names),
            "camera_index": index,
            "camera": name,
            "views_per_forward": frames_per_view * len(names),
            "left_out": list(NOT_IN_A_RIG_FIT),
        },
    }
