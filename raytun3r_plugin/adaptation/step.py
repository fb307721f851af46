"""One adaptation step: the loss terms of a window, the optimiser step, and the objective of a
fixed adapter.

Part of :mod:`raytun3r_plugin.adaptation.train` (which re-exports the public names here).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from raytun3r_plugin.adaptation.config import AdaptConfig
from raytun3r_plugin.adaptation.evaluation import patched_for_evaluation
from raytun3r_plugin.adaptation.losses import (
    grouped_silog_loss,
    pe_correction_grid,
    pe_energy,
    pe_l2,
    pe_tv,
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
)
from raytun3r_plugin.adaptation.pose_terms import (
    pose_loss,
)
from raytun3r_plugin.adaptation.problem import AdaptationProblem, _Pair
from raytun3r_plugin.adaptation.settings_check import (
    MODEL_REPROJECTION_SOURCES,
    POSE_TERM_SOURCES,
    TARGET_REPROJECTION_SOURCES,
)
from raytun3r_plugin.adaptation.target_scale import (
    photometric_scale,
    sample_valid_pixels,
    subset_matches,
    targets_pose,
)
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.errors import AlreadyAppliedError
from raytun3r_plugin.patching import handle_of
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
    "window_terms",
]


# --------------------------------------------------------------------------------------------
# Loss terms of one window
# --------------------------------------------------------------------------------------------


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
        geometry: :class:`raytun3r_plugin.size_geometry.SizeGeometry` at the input size.
        pe_scale: divisor of the L2 and TV terms (the backbone's PE energy for
            ``pe_regulariser="relative"``, 1 for ``"absolute"``).
        depth_targets: supervised mode: per frame of the window ``(uv (K, 2) input pixels,
            depth (K,))``; the terms are then ``depth`` (:func:`silog_loss`), ``l2`` and ``tv``.
        teacher_targets: per frame of the window ``(uv (K, 2) input pixels, range (K,), view
            (K,))`` of the pinhole-view teacher; adds the ``teacher`` term
            (:func:`grouped_silog_loss`, one scale per view).
        reproject: False leaves the window's matches out of the reprojection term (the
            parallax gate found no depth signal in them); the pose term stays (and with
            ``config.pose_windows="unreprojected"`` is scored only on such windows).

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
    gray = (
        blurred_gray(images.to(depth.dtype), config.photo_sigma)
        if config.scale == "photometric" or config.weights.photo > 0
        else None
    )
    reproj, pose_terms, n_matches = _match_terms(
        depth, poses, gray, pairs, layout, valid, config, generator, reproject
    )
    zero = depth.sum() * 0.0
    terms = {
        "reproj": torch.stack(reproj).mean() if reproj else zero,
        "smooth": smoothness_loss(depth, images.to(depth.dtype), valid),
        **regularisers,
    }
    if config.weights.photo > 0 and gray is not None:  # gray is made whenever photo > 0
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


def _match_terms(
    depth: torch.Tensor,
    poses: torch.Tensor,
    gray: torch.Tensor | None,
    pairs: list[_Pair],
    layout: InputLayout,
    valid: torch.Tensor,
    config: AdaptConfig,
    generator: torch.Generator,
    reproject: bool,
) -> tuple[list[torch.Tensor], list[torch.Tensor], int]:
    """The window's match terms, pair by pair: (reprojection losses, pose losses, matches
    used). ``gray`` (S, h, w): the blurred grey frames where the photometric scale needs them.
    The pairs are visited in order and each draws its match subset from ``generator``, so a
    fit's random stream is the same for every caller."""
    reproj: list[torch.Tensor] = []
    pose_terms: list[torch.Tensor] = []
    n_matches = 0
    photometric = config.scale == "photometric"
    # Without a weight on the match terms (a teacher-only fit) the pairs are not visited.
    matched = config.weights.reproj > 0 or config.weights.pose > 0 or config.weights.photo > 0
    # ``pose_windows="unreprojected"``: where the matches enter the reprojection, the pose term
    # is left out; it scores only the windows the parallax gate keeps for the teacher alone.
    pose_scored = config.pose_windows == "all" or not reproject
    for pair in pairs if matched else []:
        relatives = []
        if config.pose_source in POSE_TERM_SOURCES:
            relative = relative_pose(poses, pair.a, pair.b)
            if pair.rotation is not None and pair.direction is not None and pose_scored:
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
        uv_i, uv_j, confidence, rays_i, rays_j = subset_matches(pair, config.max_matches, generator)
        if through_targets:
            scale = None
            if photometric and gray is not None:  # gray is made whenever the scale is photometric
                scale = photometric_scale(
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
                targets_pose(
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
    return reproj, pose_terms, n_matches


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
        if pair.rotation is None or pair.direction is None:  # both or neither (no target)
            continue
        pixels, rays = sample_valid_pixels(
            valid, camera, config.photo_pixels, generator, depth.dtype
        )
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
    with patched_for_evaluation(model, adapter, problem, config):
        for index in range(len(problem.windows)):
            generator = torch.Generator().manual_seed(int(seed) * 7_919 + index)
            terms, _ = problem_window_terms(model, adapter, problem, config, index, generator)
            terms = {**terms, "loss": total_loss(terms, config.weights)}
            for name, value in terms.items():
                sums[name] = sums.get(name, 0.0) + float(value) / len(problem.windows)
    return sums
