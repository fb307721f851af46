"""One adaptation step: the loss terms of a window, the optimiser step, and the objective of a
fixed adapter.

Part of :mod:`raytun3r_plugin.adaptation.train` (which re-exports the public names here).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from raytun3r_plugin.adaptation.config import (
    MODEL_REPROJECTION_SOURCES,
    POSE_TERM_SOURCES,
    TARGET_REPROJECTION_SOURCES,
    AdaptConfig,
)
from raytun3r_plugin.adaptation.losses import (
    backproject,
    depth_parallax_px,
    grouped_silog_loss,
    pe_correction_grid,
    pe_energy,
    pe_l2,
    pe_tv,
    pixel_optimal_scale,
    relative_pose,
    reprojection_loss,
    sample_bilinear,
    silog_loss,
    smoothness_loss,
    total_loss,
)
from raytun3r_plugin.adaptation.photometric import (
    blurred_gray,
    photometric_loss,
    photometric_optimal_scale,
)
from raytun3r_plugin.adaptation.pose_terms import (
    fit_translation_scale,
    pose_loss,
)
from raytun3r_plugin.adaptation.problem import AdaptationProblem, _Pair
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.errors import AlreadyAppliedError
from raytun3r_plugin.patching import apply, handle_of
from raytun3r_plugin.prediction import predict
from raytun3r_plugin.preprocess import InputLayout
from raytun3r_plugin.registry import spec_for

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

__all__ = [
    "adaptation_step",
    "objective_value",
    "optimiser_step",
    "prediction_terms",
    "problem_window_terms",
    "regulariser_scale",
    "window_of_step",
    "window_parallax",
    "window_terms",
]


@contextmanager
def _frozen(model: nn.Module) -> Iterator[None]:
    """Backbone parameters without gradients and every module in eval mode; restored after."""
    flags = [(parameter, parameter.requires_grad) for parameter in model.parameters()]
    modes = [(module, module.training) for module in model.modules()]
    try:
        for parameter, _ in flags:
            parameter.requires_grad_(False)
        model.eval()
        yield
    finally:
        for parameter, flag in flags:
            parameter.requires_grad_(flag)
        for module, mode in modes:
            module.training = mode


# --------------------------------------------------------------------------------------------
# Loss terms of one window
# --------------------------------------------------------------------------------------------


@contextmanager
def _evaluated(
    model: nn.Module, adapter: Adapter, problem: AdaptationProblem, config: AdaptConfig
) -> Iterator[None]:
    """``model`` frozen, in eval mode, without gradients and patched with ``adapter`` as the fit
    patches it; everything restored afterwards."""
    with (
        _frozen(model),
        torch.no_grad(),
        apply(
            model,
            problem.layout.native_camera,
            adapter,
            components=config.components,
            strict=False,
            mask=problem.mask,
        ),
    ):
        yield


def _subset(pair: _Pair, max_matches: int, generator: torch.Generator) -> tuple[torch.Tensor, ...]:
    count = pair.uv_i.shape[0]
    if max_matches and count > max_matches:
        index = torch.randperm(count, generator=generator)[:max_matches]
        return (
            pair.uv_i[index],
            pair.uv_j[index],
            pair.confidence[index],
            pair.rays_i[index],
            pair.rays_j[index],
        )
    return pair.uv_i, pair.uv_j, pair.confidence, pair.rays_i, pair.rays_j


def _matched_points(
    depth_i: torch.Tensor, uv_i: torch.Tensor, rays_i: torch.Tensor, convention: str
) -> tuple[torch.Tensor, torch.Tensor]:
    """(M, 3) points of the matches in camera i at the predicted depth, and (M,) where that depth
    is usable (finite, positive; the other points sit at depth 1)."""
    depth = sample_bilinear(depth_i, uv_i)
    usable = torch.isfinite(depth) & (depth > 0)
    points = backproject(torch.where(usable, depth, torch.ones_like(depth)), rays_i, convention)
    return points, usable


def _pose_scaled_to(
    pair: _Pair,
    points: torch.Tensor,
    usable: torch.Tensor,
    uv_j: torch.Tensor,
    confidence: torch.Tensor,
    rays_j: torch.Tensor,
    camera: Camera,
    config: AdaptConfig,
    scale: torch.Tensor | None = None,
) -> torch.Tensor:
    """``cam_j_from_cam_i`` from the MAGSAC++ target, translation scaled to ``points``
    (``config.scale``: pixel-optimal and detached, or the differentiable least-squares scale),
    or by ``scale`` where given (``config.scale="photometric"``: :func:`_photometric_scale`)."""
    rotation = pair.rotation.to(points.dtype)
    direction = pair.direction.to(points.dtype)
    if scale is None:
        scale = fit_translation_scale(
            points[usable], rays_j[usable], rotation, direction, confidence[usable]
        )
        if config.scale == "pixel":
            scale = pixel_optimal_scale(
                points[usable],
                uv_j[usable],
                rotation,
                direction,
                camera,
                confidence[usable],
                robust_px=config.robust_px or 1.0,
                initial=scale.detach(),
            )
    scale = scale.to(points.dtype)
    pose = torch.eye(4, dtype=points.dtype)
    return torch.cat((torch.cat((rotation, (scale * direction)[:, None]), dim=1), pose[3:]), dim=0)


def _targets_pose(
    pair: _Pair,
    depth_i: torch.Tensor,
    uv_i: torch.Tensor,
    uv_j: torch.Tensor,
    confidence: torch.Tensor,
    rays_i: torch.Tensor,
    rays_j: torch.Tensor,
    camera: Camera,
    config: AdaptConfig,
    scale: torch.Tensor | None = None,
) -> torch.Tensor:
    """``cam_j_from_cam_i`` from the MAGSAC++ target, translation scaled to the predicted depth
    (:func:`_pose_scaled_to`)."""
    points, usable = _matched_points(depth_i, uv_i, rays_i, config.depth_convention)
    return _pose_scaled_to(pair, points, usable, uv_j, confidence, rays_j, camera, config, scale)


def _valid_pixels(
    valid: torch.Tensor, camera: Camera, count: int, generator: torch.Generator, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """(K, 2) long (column, row) pixels, at most ``count`` drawn at random from ``valid``, and
    their (K, 3) unit rays (pixels without a ray left out)."""
    rows, cols = torch.nonzero(valid, as_tuple=True)
    pick = torch.randperm(rows.shape[0], generator=generator)[:count]
    pixels = torch.stack((cols[pick], rows[pick]), dim=-1)
    with torch.no_grad():
        rays, ok = camera.unproject(pixels.to(dtype))
    return pixels[ok], rays[ok]


def _photometric_scale(
    depth_i: torch.Tensor,
    gray_i: torch.Tensor,
    gray_j: torch.Tensor,
    pair: _Pair,
    camera: Camera,
    valid: torch.Tensor,
    config: AdaptConfig,
    generator: torch.Generator,
) -> torch.Tensor:
    """Translation length of ``pair``'s target for ``config.scale="photometric"``:
    :func:`photometric_optimal_scale` of frame ``i``'s predicted depth (detached) on
    ``config.photo_pixels`` random valid pixels."""
    with torch.no_grad():
        depth_i = depth_i.detach()
        pixels, rays = _valid_pixels(valid, camera, config.photo_pixels, generator, depth_i.dtype)
        points, usable = _matched_points(
            depth_i, pixels.to(depth_i.dtype), rays, config.depth_convention
        )
        return photometric_optimal_scale(
            points[usable],
            gray_i[pixels[:, 1], pixels[:, 0]][usable].to(depth_i.dtype),
            gray_j,
            pair.rotation,
            pair.direction,
            camera,
            valid,
        )


def window_terms(
    model: nn.Module,
    adapter: Adapter,
    images: torch.Tensor,
    pairs: list[_Pair],
    layout: InputLayout,
    valid: torch.Tensor,
    geometry: Any,
    config: AdaptConfig,
    generator: torch.Generator,
    *,
    pe_scale: float = 1.0,
    depth_targets: list[tuple[torch.Tensor, torch.Tensor]] | None = None,
    teacher_targets: list[tuple[torch.Tensor, ...]] | None = None,
    reproject: bool = True,
) -> tuple[dict[str, torch.Tensor], dict[str, int]]:
    """Forward one window through the patched model and compute every loss term.

    Args:
        images: (S, 3, h, w) network input in [0, 1].
        pairs: the window's ordered pairs (network-input pixels).
        valid: (h, w) bool valid region at the input size.
        geometry: :class:`raytun3r_plugin.geometry.SizeGeometry` at the input size.
        pe_scale: divisor of the L2 and TV terms (the backbone's PE energy for
            ``pe_regulariser="relative"``, 1 for ``"absolute"``).
        depth_targets: supervised mode: per frame of the window ``(uv (K, 2) input pixels,
            depth (K,))``; the terms are then ``depth`` (:func:`silog_loss`), ``l2`` and ``tv``.
        teacher_targets: per frame of the window ``(uv (K, 2) input pixels, range (K,), view
            (K,))`` of the pinhole-view teacher; adds the ``teacher`` term
            (:func:`grouped_silog_loss`, one scale per view).
        reproject: False leaves the window's matches out of the reprojection term (the
            parallax gate found no depth signal in them); the pose term stays.

    Returns:
        (terms, counts): 0-d tensors per term name (pose absent with ``pose_source="targets"``) and the
        numbers of reprojection matches / pose targets that entered them.
    """
    prediction = predict(model, images[None])
    # The network runs on its own device; the terms (a few thousand matches, the tables) are
    # computed on the CPU, where the matches, rays and targets live. ``.cpu()`` is differentiable,
    # so the gradient flows back into the network's device and on to the tables.
    return prediction_terms(
        prediction.depth[0].cpu(),
        prediction.cam_from_world[0].cpu(),
        adapter,
        images,
        pairs,
        layout,
        valid,
        geometry,
        config,
        generator,
        pe_scale=pe_scale,
        depth_targets=depth_targets,
        teacher_targets=teacher_targets,
        reproject=reproject,
    )


def prediction_terms(
    depth: torch.Tensor,
    poses: torch.Tensor,
    adapter: Adapter,
    images: torch.Tensor,
    pairs: list[_Pair],
    layout: InputLayout,
    valid: torch.Tensor,
    geometry: Any,
    config: AdaptConfig,
    generator: torch.Generator,
    *,
    pe_scale: float = 1.0,
    depth_targets: list[tuple[torch.Tensor, torch.Tensor]] | None = None,
    teacher_targets: list[tuple[torch.Tensor, ...]] | None = None,
    reproject: bool = True,
) -> tuple[dict[str, torch.Tensor], dict[str, int]]:
    """The loss terms of one window from its predicted ``depth`` (S, h, w) and ``poses``
    (S, 4, 4) ``cam_from_world``: :func:`window_terms` after its forward, so a rig fit
    (:func:`raytun3r_plugin.adaptation.rig.adapt_rig`) can score each camera's views of one
    joint forward. Arguments and result as :func:`window_terms`."""
    correction = pe_correction_grid(adapter, geometry)
    regularisers = {"l2": pe_l2(correction) / pe_scale, "tv": pe_tv(correction) / pe_scale}
    if depth_targets is not None:
        losses = [
            silog_loss(sample_bilinear(depth[k], uv), target)
            for k, (uv, target) in enumerate(depth_targets)
            if uv.shape[0]
        ]
        n_depth = sum(int(uv.shape[0]) for uv, _ in depth_targets)
        term = torch.stack(losses).mean() if losses else depth.sum() * 0.0
        return {"depth": term, **regularisers}, {"n_matches": 0, "n_pose": 0, "n_depth": n_depth}
    reproj, pose_terms, n_matches = [], [], 0
    photometric = config.scale == "photometric"
    gray = (
        blurred_gray(images.to(depth.dtype), config.photo_sigma)
        if photometric or config.weights.photo > 0
        else None
    )
    # Without a weight on the match terms (a teacher-only fit) the pairs are not visited.
    matched = config.weights.reproj > 0 or config.weights.pose > 0 or config.weights.photo > 0
    for pair in pairs if matched else []:
        relatives = []
        if config.pose_source in POSE_TERM_SOURCES:
            relative = relative_pose(poses, pair.a, pair.b)
            if pair.rotation is not None:
                pose_terms.append(pose_loss(relative, pair.rotation, pair.direction))
            if config.pose_source in MODEL_REPROJECTION_SOURCES:
                relatives.append(relative)
        if not reproject:
            relatives = []
        through_targets = (
            reproject
            and config.pose_source in TARGET_REPROJECTION_SOURCES
            and pair.rotation is not None
        )
        # A pair with nothing to reproject through draws no subset, so the generator's stream
        # (and every fit of the single-pose modes) is what it was before "both" existed.
        if pair.uv_i.shape[0] == 0 or not (relatives or through_targets):
            continue
        uv_i, uv_j, confidence, rays_i, rays_j = _subset(pair, config.max_matches, generator)
        if through_targets:
            scale = None
            if photometric:
                scale = _photometric_scale(
                    depth[pair.a],
                    gray[pair.a],
                    gray[pair.b],
                    pair,
                    layout.camera,
                    valid,
                    config,
                    generator,
                )
            relatives.append(
                _targets_pose(
                    pair,
                    depth[pair.a],
                    uv_i,
                    uv_j,
                    confidence,
                    rays_i,
                    rays_j,
                    layout.camera,
                    config,
                    scale,
                )
            )
        used = 0
        for relative in relatives:
            loss, count = reprojection_loss(
                depth[pair.a],
                relative,
                uv_i,
                uv_j,
                confidence,
                layout.camera,
                valid,
                config.depth_convention,
                rays_i=(rays_i, torch.ones_like(confidence, dtype=torch.bool)),
                robust_px=config.robust_px,
            )
            if count:
                reproj.append(loss)
                used = max(used, count)
        n_matches += used
    zero = depth.sum() * 0.0
    terms = {
        "reproj": torch.stack(reproj).mean() if reproj else zero,
        "smooth": smoothness_loss(depth, images.to(depth.dtype), valid),
        **regularisers,
    }
    if config.weights.photo > 0:
        terms["photo"] = _photometric_term(
            depth, gray, pairs, layout.camera, valid, config, generator
        )
    if config.pose_source in POSE_TERM_SOURCES:
        terms["pose"] = torch.stack(pose_terms).mean() if pose_terms else zero
    counts = {"n_matches": n_matches, "n_pose": len(pose_terms)}
    if config.weights.teacher > 0 and teacher_targets is not None:
        view_weights = config.view_weights()
        losses = [
            grouped_silog_loss(sample_bilinear(depth[k], uv), value, view, view_weights)
            for k, (uv, value, view) in enumerate(teacher_targets)
            if uv.shape[0]
        ]
        terms["teacher"] = torch.stack(losses).mean() if losses else zero
        counts["n_teacher"] = sum(int(uv.shape[0]) for uv, _, _ in teacher_targets)
    return terms, counts


def _photometric_term(
    depth: torch.Tensor,
    gray: torch.Tensor,
    pairs: list[_Pair],
    camera: Camera,
    valid: torch.Tensor,
    config: AdaptConfig,
    generator: torch.Generator,
) -> torch.Tensor:
    """Mean :func:`photometric_loss` over the window's pairs with a usable target, each on
    ``config.photo_pixels`` random valid pixels of its first frame; ``gray`` (S, h, w) are the
    window's blurred grey frames (:func:`blurred_gray`)."""
    losses = []
    for pair in pairs:
        if pair.rotation is None:
            continue
        pixels, rays = _valid_pixels(valid, camera, config.photo_pixels, generator, depth.dtype)
        loss, count = photometric_loss(
            depth[pair.a],
            rays,
            pixels,
            gray[pair.a],
            gray[pair.b],
            pair.rotation,
            pair.direction,
            camera,
            valid,
            config.depth_convention,
        )
        if count:
            losses.append(loss)
    return torch.stack(losses).mean() if losses else depth.sum() * 0.0


def window_parallax(
    model: nn.Module, adapter: Adapter, problem: AdaptationProblem, config: AdaptConfig
) -> list[float]:
    """Median depth parallax (px per unit log depth, :func:`depth_parallax_px`) of each window's
    matches, NaN for a window without a pair that has a usable pose target.

    Each used frame is predicted once, alone, through ``model`` patched with ``adapter`` (frozen,
    in eval mode, restored afterwards); each pair's translation is scaled to that depth as the fit
    scales it (:func:`_targets_pose`).
    """
    camera = problem.layout.camera
    frames = sorted({frame for window, _ in problem.windows for frame in window.frames})
    with _evaluated(model, adapter, problem, config):
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
                points, usable = _matched_points(
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
                    scale = _photometric_scale(
                        depth[i].double(),
                        gray[i],
                        gray[j],
                        pair,
                        camera,
                        problem.valid,
                        config,
                        generator,
                    )
                pose = _pose_scaled_to(
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


# --------------------------------------------------------------------------------------------
# One optimisation step
# --------------------------------------------------------------------------------------------


def window_of_step(step: int, n_windows: int, seed: int) -> int:
    """Window index of a step: a seeded permutation of the windows per pass (epoch)."""
    epoch, position = divmod(step, n_windows)
    generator = torch.Generator().manual_seed(int(seed) * 1_000_003 + epoch)
    return int(torch.randperm(n_windows, generator=generator)[position])


def problem_window_terms(
    model: nn.Module,
    adapter: Adapter,
    problem: AdaptationProblem,
    config: AdaptConfig,
    index: int,
    generator: torch.Generator,
) -> tuple[dict[str, torch.Tensor], dict[str, int]]:
    """:func:`window_terms` of window ``index`` of a prepared problem (its frames, pairs, layout,
    valid region, geometry, PE scale and, in supervised mode, depth samples)."""
    _, pairs = problem.windows[index]
    return window_terms(
        model,
        adapter,
        problem.batch(index),
        pairs,
        problem.layout,
        problem.valid,
        problem.geometry,
        config,
        generator,
        pe_scale=problem.pe_scale,
        depth_targets=problem.window_depth(index),
        teacher_targets=problem.window_teacher(index),
        reproject=problem.window_reprojects(index),
    )


def adaptation_step(
    model: nn.Module,
    adapter: Adapter,
    optimizer: torch.optim.Optimizer,
    problem: AdaptationProblem,
    config: AdaptConfig,
    step: int,
    index: int | None = None,
) -> dict[str, Any]:
    """One step on a model already patched with ``adapter``: forward a window, every loss term,
    backward, gradient clipping, Adam step. A non-finite loss or gradient skips the update.

    Args:
        step: global step number (selects the window unless ``index`` is given, and seeds the
            match subsets).
        index: window index to use instead of the scheduled one.

    Returns:
        The step's log record: loss, every term, gradient norm, counts, wall time.
    """
    began = time.perf_counter()
    index = window_of_step(step, len(problem.windows), config.seed) if index is None else index
    window = problem.windows[index][0]
    generator = torch.Generator().manual_seed(int(config.seed) * 7_919 + step)
    terms, counts = problem_window_terms(model, adapter, problem, config, index, generator)
    loss = total_loss(terms, config.weights)
    grad_norm = optimiser_step(loss, optimizer, config.clip)
    return {
        "step": step,
        "window": index,
        "frames": list(window.frames),
        "loss": float(loss.detach()),
        **{name: float(value.detach()) for name, value in terms.items()},
        "grad_norm": grad_norm,
        "skipped": not math.isfinite(grad_norm),
        **counts,
        "time_s": round(time.perf_counter() - began, 4),
    }


def optimiser_step(
    loss: torch.Tensor, optimizer: torch.optim.Optimizer, clip: float | None
) -> float:
    """Backward, gradient clipping at ``clip`` (None: none) and one step; returns the gradient
    norm. A non-finite loss or gradient norm skips the update (the norm is then NaN or inf)."""
    parameters = [p for group in optimizer.param_groups for p in group["params"]]
    optimizer.zero_grad(set_to_none=True)
    grad_norm = float("nan")
    if bool(torch.isfinite(loss)):
        loss.backward()
        grads = [p.grad for p in parameters if p.grad is not None]
        if clip is not None:
            grad_norm = float(torch.nn.utils.clip_grad_norm_(parameters, clip))
        elif grads:
            grad_norm = float(
                torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads]))
            )
        if math.isfinite(grad_norm):
            optimizer.step()
    return grad_norm


def regulariser_scale(model: nn.Module, config: AdaptConfig) -> float:
    """Divisor of the PE regularisers for ``model`` under ``config``: the backbone's PE energy
    (:func:`~raytun3r_plugin.adaptation.losses.pe_energy`) for ``pe_regulariser="relative"``,
    1 for ``"absolute"``."""
    if config.pe_regulariser != "relative":
        return 1.0
    spec, root = spec_for(model)
    return pe_energy(spec.describe(root).pos_embed)


def objective_value(
    model: nn.Module,
    adapter: Adapter,
    problem: AdaptationProblem,
    config: AdaptConfig,
    seed: int = 0,
) -> dict[str, float]:
    """The objective of ``config`` for ``adapter``, averaged over every window of ``problem``.

    Runs the model patched with ``adapter`` (the model must be unpatched; it is again
    afterwards), without gradients; the PE regularisers are scaled for ``model``
    (:func:`regulariser_scale`), as :func:`adapt` scales them. Match subsets come from a generator seeded by ``seed`` and
    the window index, so two adapters are scored on the same samples. Used to check that the
    objective ranks a better adapter lower (``tests``, ``docs/adaptation.md``).

    Returns:
        ``{"loss": total, <term>: mean value, ...}``.
    """
    if handle_of(model) is not None:
        raise AlreadyAppliedError("objective_value needs an unpatched model")
    problem = dataclasses.replace(problem, pe_scale=regulariser_scale(model, config))
    sums: dict[str, float] = {}
    with _evaluated(model, adapter, problem, config):
        for index in range(len(problem.windows)):
            generator = torch.Generator().manual_seed(int(seed) * 7_919 + index)
            terms, _ = problem_window_terms(model, adapter, problem, config, index, generator)
            terms = {**terms, "loss": total_loss(terms, config.weights)}
            for name, value in terms.items():
                sums[name] = sums.get(name, 0.0) + float(value) / len(problem.windows)
    return sums
