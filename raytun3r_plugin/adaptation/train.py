"""Online adaptation: fit an adapter to a fisheye segment without ground truth.

``adapt(model, camera, frames, config)`` (docs/conventions.md section 7, paper "Adapter training"):

1. picks the network input size (long side ``config.input_size``, multiples of the patch size;
   a centred crop only when a pure resize would change the aspect ratio by more than 1%);
2. prepares the adaptation set once (windows of 3 frames, matches and MAGSAC++ targets for every
   ordered pair, cached on disk with ``config.cache_dir``);
3. patches the model with a zero adapter, freezes every backbone parameter and runs Adam on the
   adapter tables only, one window per step, with gradient clipping;
4. logs every loss term per step (JSON lines), checkpoints (safetensors + JSON metadata, never
   pickle) and resumes, saves what it has on Ctrl-C, and finally removes the patch and restores
   the model's ``requires_grad`` flags and train/eval modes.

Files next to ``out_path`` (e.g. ``run/indoor.safetensors``): the adapter itself,
``run/indoor.log.jsonl`` (one JSON object per step) and ``run/indoor.ckpt.safetensors`` (adapter
tables, Adam moments and step counters as tensors; step, configuration and identity checks as
string metadata).

Determinism: the window of step ``k`` and the match subset it uses are functions of
``(seed, k)`` only, so the same seed gives identical tables, and a resumed run continues exactly
where the interrupted one stopped.

The run is split at its seams; each name lives in one module and is imported from there:

* :mod:`~raytun3r_plugin.adaptation.config`: :class:`AdaptConfig` and the default loss weights;
* :mod:`~raytun3r_plugin.adaptation.problem`: :func:`prepare_problem` (frames, masks, pairs,
  depth targets) and :class:`AdaptationProblem`;
* :mod:`~raytun3r_plugin.adaptation.step`: :func:`window_terms`, :func:`adaptation_step`,
  :func:`objective_value`;
* :mod:`~raytun3r_plugin.adaptation.target_scale`: a pair's MAGSAC++ target at the predicted
  depth's scale; :mod:`~raytun3r_plugin.adaptation.evaluation`: the backbone frozen (and patched)
  as a fit runs it;
* :mod:`~raytun3r_plugin.adaptation.parallax` and :mod:`~raytun3r_plugin.adaptation.pose_gate`:
  the two gates measured with the starting tables before a fit;
* :mod:`~raytun3r_plugin.adaptation.checkpoint`: artefact paths, loss log, checkpoint;
* :mod:`~raytun3r_plugin.adaptation.guard`: the collapse guard and :func:`fit_verdict`;
* :mod:`~raytun3r_plugin.adaptation.loop`: the optimisation loop :func:`adapt` and
  :func:`~raytun3r_plugin.adaptation.rig.adapt_rig` share;
* this module: :func:`adapt`, which prepares a camera's fit and runs it on that loop.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from raytun3r_plugin.adaptation.check import judge_on_check, split_off_check
from raytun3r_plugin.adaptation.checkpoint import (
    _restore_checkpoint,
    _save_checkpoint,
    artifact_paths,
    read_loss_log,
    write_loss_artifacts,
)
from raytun3r_plugin.adaptation.config import (
    TERMS,
    AdaptConfig,
)
from raytun3r_plugin.adaptation.evaluation import patched_as_fitted
from raytun3r_plugin.adaptation.guard import (
    GUARD_MIN_CORRELATION,
    GUARD_SPREAD_RANGE,
    _CollapseGuard,
    fit_verdict,
)
from raytun3r_plugin.adaptation.loop import LoopOutcome, run_fit_loop
from raytun3r_plugin.adaptation.parallax import window_parallax
from raytun3r_plugin.adaptation.pose_gate import gate_pose_term
from raytun3r_plugin.adaptation.problem import (
    AdaptationProblem,
    prepare_problem,
    split_segments,
    with_pose_targets,
)
from raytun3r_plugin.adaptation.step import (
    adaptation_step,
    regulariser_scale,
)
from raytun3r_plugin.adaptation.teacher import teacher_coverage, teacher_targets
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.errors import AlreadyAppliedError, InputError
from raytun3r_plugin.patching import handle_of

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

__all__ = ["adapt"]


# --------------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------------


def adapt(
    model: nn.Module,
    camera: Camera,
    frames: Any,
    config: AdaptConfig | None = None,
    *,
    out_path: str | os.PathLike | None = None,
    adapter: Adapter | None = None,
    resume: bool = True,
    progress: bool = True,
    mask: Any = None,
    depth: Any = None,
    poses: Any = None,
    tune: nn.Module | None = None,
) -> Adapter:
    """Fit an adapter for ``model`` on a fisheye segment, without ground truth (or with it).

    Args:
        model: a supported backbone (not already patched); its weights are never changed.
        camera: camera of the native frames.
        frames: (N, H, W, 3) float32 RGB in [0, 1] (numpy or torch), or a
            ``raytun3r_plugin.datasets.Sequence``; or a list of such segments, all seen by
            ``camera``, fitted together into one adapter (each segment gets
            ``config.n_windows`` windows of its own, and no window spans two segments; the
            steps are shared, so raise ``config.steps`` with the number of windows). A camera's
            adapter file is meant for every segment the camera records, and a fit on several
            segments learns the camera, less any one scene.
        config: :class:`AdaptConfig`; None: the ``default`` recipe (``supervised`` with
            ``depth``) for this model (:meth:`AdaptConfig.from_recipe`). What a config leaves to
            the backbone is resolved for ``model`` (:meth:`AdaptConfig.resolved_for`): an
            ``input_size`` of None is its own, an ``lr`` of None its family's step.
        out_path: adapter file to write (``.safetensors``); the loss log and the checkpoint go
            next to it (:func:`artifact_paths`). None keeps everything in memory (no log file,
            no checkpoint).
        adapter: start from this adapter (copied) instead of a zero one.
        resume: continue from the checkpoint next to ``out_path`` when there is one.
        progress: show progress: a tqdm bar on a terminal, else a line to stderr every 5 s.
        mask: optional (H, W) bool (or 0/non-zero) mask of the native frames, True where the
            scene is seen: pixels it excludes (a vehicle's body, a lens mount) get no matches,
            no reprojection or smoothness terms, and their patches count as border tokens, as
            ``apply(mask=...)`` does. The adapter file records its valid fraction and digest
            (``training_info["segment"]["mask"]``), not the mask: pass the same mask to
            ``apply`` at inference.
        depth: optional (N, H, W) ground-truth depth of the frames (range along the ray, or z
            with ``depth_convention="z"``; any unit, only its log-differences count), dense (a
            depth sensor, a renderer) or sparse (LiDAR points projected into the frames); 0,
            negative or NaN marks pixels without a value. Switches to the **supervised fit**:
            the same tables fitted with the scale-invariant log depth loss
            (:func:`~raytun3r_plugin.adaptation.losses.silog_loss`); with ``config=None`` its
            settings are :meth:`AdaptConfig.supervised`. ``training_info["supervision"]``
            records the kind and the coverage (fraction of lens pixels with a value). With
            several segments, a list of one depth per segment.

        poses: optional (N, 4, 4) ground-truth ``cam_from_world`` of the frames (one segment):
            every pair's pose target becomes the true relative pose, so the pose term measures
            the network's own pose against the truth. With the ``pose-oracle`` recipe (the pose
            term alone) this is the **pose oracle**: what the tables can do for pose, as the
            supervised fit is for depth. ``training_info["supervision"]`` is ``{"kind":
            "poses"}``; with ``config=None`` the recipe is ``pose-oracle``.

    Without ``depth``, ``config.weights.teacher > 0`` adds the pinhole-view teacher: before the
    patch is applied, the model's own depth on virtual pinhole views of every window
    (:func:`~raytun3r_plugin.adaptation.teacher.teacher_targets`) becomes a per-view
    scale-invariant target, on lenses of which no view covers more than
    ``config.teacher_max_coverage`` (``training_info["teacher"]`` records the largest view's
    coverage and whether the term was used).

    With ``config.check_frames`` (``"auto"``: a fifth of the last segment when it has at least
    15 frames), the trailing frames of the last segment are kept out of the fit and scored after
    it with the starting and the fitted tables
    (:func:`~raytun3r_plugin.adaptation.check.held_out_reprojection`, ``training_info["check"]``);
    with ``config.check_veto`` a fit that raises that error by more than this fraction is not
    kept: the adapter goes back to its starting tables (``training_info["check"]["kept"]``,
    verdict ``"not kept"``).

    Returns:
        The fitted :class:`Adapter` (camera: the camera of the frames, cropped if the input
        layout needed a crop); ``adapter.training_info`` records the steps done, the final
        losses (mean over the last pass over the windows), the segment, the input layout and the
        configuration; with ``config.refine_intrinsics``, ``training_info["intrinsics"]`` is the
        :class:`~raytun3r_plugin.adaptation.intrinsics.IntrinsicsReport` (as a dict) and the
        adapter's camera the refined one. On Ctrl-C the adapter of the last completed step is
        saved (with a checkpoint) and returned, with ``training_info["interrupted"] = True``.

    Baselines:
        ``tune``: a module whose parameters are fitted *instead of* the adapter's tables (e.g.
        :class:`raytun3r_plugin.baselines.LoraWeights`, already injected into ``model``): same
        objective, windows, optimiser, steps and collapse guard (which keeps and restores the
        module's parameters); the tables stay at zero, so the PE regularisers are constant; no
        checkpoint and no adapter file (the caller saves ``tune``); the loss log and curves are
        still written next to ``out_path``.

    Raises:
        AlreadyAppliedError: the model already carries a raytun3r patch.
        InputError: frames/camera mismatch, a mask of the wrong shape or with nothing inside
            the lens, or no moving window in the segment.
        AdapterError: the checkpoint next to ``out_path`` belongs to another run.
    """
    if depth is not None and poses is not None:
        raise InputError("adapt: give depth (the supervised fit) or poses (the pose oracle)")
    if poses is not None and split_segments(frames) is not None:
        raise InputError("adapt: poses are for one segment; fit several segments without them")
    if config is None:
        recipe = (
            "supervised" if depth is not None else "pose-oracle" if poses is not None else "default"
        )
        config = AdaptConfig.from_recipe(recipe, model=model)
    config = config.resolved_for(model)
    frames, depth, poses, check = split_off_check(frames, depth, poses, config.check_frames)
    start = None if adapter is None else copy.deepcopy(adapter)
    fitted = _fit(
        model,
        camera,
        frames,
        config,
        out_path=out_path,
        adapter=adapter,
        resume=resume,
        progress=progress,
        mask=mask,
        depth=depth,
        poses=poses,
        tune=tune,
    )
    if check is not None and tune is None and not fitted.training_info.get("interrupted"):
        judge_on_check(model, camera, check, fitted, start, config, mask=mask)
        if progress and not fitted.training_info["check"].get("kept", True):
            print(f"adapt: {fitted.training_info['verdict']['summary']}", file=sys.stderr)
        if out_path is not None:
            fitted.save(artifact_paths(out_path)["adapter"])
    return fitted


def _fit(
    model: nn.Module,
    camera: Camera,
    frames: Any,
    config: AdaptConfig,
    *,
    out_path: str | os.PathLike | None,
    adapter: Adapter | None,
    resume: bool,
    progress: bool,
    mask: Any,
    depth: Any,
    poses: Any,
    tune: nn.Module | None,
) -> Adapter:
    """:func:`adapt` on the frames it fits, with its settings resolved."""
    if handle_of(model) is not None:
        raise AlreadyAppliedError(
            "adapt needs an unpatched model; remove the existing raytun3r patch first"
        )
    adapter = (
        Adapter.for_model(model, None, components=config.components)
        if adapter is None
        else copy.deepcopy(adapter)
    )
    problem, intrinsics = _prepared_problem(
        camera, frames, config, adapter.patch_size, mask=mask, depth=depth, poses=poses
    )
    problem.pe_scale = regulariser_scale(model, config)
    adapter.camera = problem.layout.native_camera
    requested = config
    config, gates = _gated(
        model, adapter, problem, config, supervised=depth is not None, posed=poses is not None
    )
    gates["intrinsics"] = intrinsics
    optimizer, paths, start, metadata = _optimiser_and_files(
        adapter, problem, config, out_path=out_path, resume=resume, tune=tune
    )
    # The thresholds are read here, at call time, so patching this module's constants takes effect.
    guard = (
        _CollapseGuard(problem, GUARD_MIN_CORRELATION, GUARD_SPREAD_RANGE)
        if config.guard and problem.windows
        else None
    )
    outcome = run_fit_loop(
        model,
        lambda: patched_as_fitted(model, adapter, problem, config),
        lambda step: adaptation_step(model, adapter, optimizer, problem, config, step),
        steps=config.steps if problem.windows else start,
        start=start,
        seed=config.seed,
        log_path=None if paths is None else paths["log"],
        progress=progress,
        guard=guard,
        # What the guard keeps and restores: the adapter's tables, or what tune mode fits.
        guarded=adapter if tune is None else tune,
        guard_every=config.guard_every,
        checkpoint=None
        if paths is None or tune is not None
        else lambda done: _save_checkpoint(paths["checkpoint"], adapter, optimizer, done, metadata),
        checkpoint_every=config.checkpoint_every,
    )
    completed, history = outcome.completed, outcome.history
    _record_fit(adapter, model, requested, config, problem, outcome, start, gates, guard, tune)
    if progress:
        print(f"adapt: {adapter.training_info['verdict']['summary']}", file=sys.stderr, flush=True)
    if paths is not None:
        if tune is None:
            _save_checkpoint(paths["checkpoint"], adapter, optimizer, completed, metadata)
            adapter.save(paths["adapter"])
        write_loss_artifacts(
            paths, read_loss_log(paths["log"]) if paths["log"].is_file() else history
        )
    return adapter


def _optimiser_and_files(
    adapter: Adapter,
    problem: AdaptationProblem,
    config: AdaptConfig,
    *,
    out_path: str | os.PathLike | None,
    resume: bool,
    tune: nn.Module | None,
) -> tuple[torch.optim.Optimizer, dict[str, Path] | None, int, dict[str, str]]:
    """The fit's optimiser over what it trains (the tables, or tune mode's module), its files,
    the step it starts from (a resumed checkpoint's, else 0) and the metadata every checkpoint
    carries."""
    if tune is not None:
        for table in adapter.parameters():
            table.requires_grad_(False)
    trainable = list(adapter.parameters()) if tune is None else list(tune.parameters())
    optimizer = torch.optim.Adam(trainable, lr=config.step_size())
    paths = artifact_paths(out_path) if out_path is not None else None
    identity = {
        "config": config.identity(),
        "adaptation_set": problem.adaptation.cache_key,
        "backbone": adapter.backbone,
        "pe_fingerprint": adapter.pe_fingerprint,
    }
    start = 0
    if paths is not None and resume and tune is None and paths["checkpoint"].is_file():
        start = _restore_checkpoint(paths["checkpoint"], adapter, optimizer, identity)
    metadata = {
        **identity,
        "config_json": json.dumps(config.to_dict(), sort_keys=True, default=str),
    }
    return optimizer, paths, start, metadata


def _record_fit(
    adapter: Adapter,
    model: nn.Module,
    requested: AdaptConfig,
    config: AdaptConfig,
    problem: AdaptationProblem,
    outcome: LoopOutcome,
    start: int,
    gates: dict[str, Any],
    guard: _CollapseGuard | None,
    tune: nn.Module | None,
) -> None:
    """Write what the fit did into ``adapter.training_info``: the settings (``config``, after
    the gates) and the recipe asked for (``requested``), the loop's ``outcome``, the gates'
    records (``guard``'s added to ``gates``) and the verdict."""
    gates["guard"] = None if guard is None else guard.report()
    adapter.training_info = _training_info(
        config,
        problem,
        outcome.completed,
        outcome.history,
        outcome.interrupted,
        outcome.seconds,
        start,
    )
    adapter.training_info["recipe"] = requested.recipe_record(model)
    order = ("pose_gate", "intrinsics", "guard", "parallax_gate", "teacher")
    adapter.training_info.update({k: gates[k] for k in order if gates[k] is not None})
    adapter.training_info["verdict"] = fit_verdict(
        adapter, outcome.history, problem, guard, gates["parallax_gate"]
    )
    if tune is not None:
        _record_tuned(adapter, tune)


def _gated(
    model: nn.Module,
    adapter: Adapter,
    problem: AdaptationProblem,
    config: AdaptConfig,
    *,
    supervised: bool,
    posed: bool,
) -> tuple[AdaptConfig, dict[str, Any]]:
    """The settings a fit runs with after its gates, and the gates' records (None where a gate
    does not apply): the pose gate (self-supervised fits without true poses), the pinhole-view
    teacher's lens gate (and with it ``lr_without_teacher``) and the parallax gate
    (self-supervised fits)."""
    gates: dict[str, Any] = {"pose_gate": None, "teacher": None, "parallax_gate": None}
    if supervised:
        return config, gates
    if not posed:
        # Measured with the starting tables, before any checkpoint is restored (as the parallax
        # gate below), so a resumed run makes the same choice.
        config, gates["pose_gate"] = gate_pose_term(model, adapter, problem, config)
    gates["teacher"] = _add_teacher(model, problem, config)
    teacher = gates["teacher"] is not None and gates["teacher"]["used"]
    if not teacher and config.lr_without_teacher is not None:
        # Without the teacher's dense targets the matches alone carry the fit, and a step
        # sized for the teacher overfits them (docs/decisions.md, "The step size where the
        # teacher is on").
        config = dataclasses.replace(config, lr=config.lr_without_teacher)
    if config.min_parallax_px > 0:
        gates["parallax_gate"] = _gate_parallax(model, adapter, problem, config, teacher)
    return config, gates


def _prepared_problem(
    camera: Camera,
    frames: Any,
    config: AdaptConfig,
    patch_size: int,
    *,
    mask: Any,
    depth: Any,
    poses: Any,
) -> tuple[Any, dict | None]:
    """The fit's problem (matches, targets, windows), and the intrinsics report when refined."""
    problem = prepare_problem(camera, frames, config, patch_size, mask=mask, depth=depth)
    intrinsics = None
    if config.refine_intrinsics:
        from raytun3r_plugin.adaptation.intrinsics import refine_intrinsics

        # Rough calibration first: the matches and targets are then recomputed with the refined
        # camera, so the rays, targets and the adapter's camera all agree with it.
        camera, report = refine_intrinsics(camera, problem.adaptation)
        intrinsics = report.to_dict()
        if report.refined:
            problem = prepare_problem(camera, frames, config, patch_size, mask=mask, depth=depth)
    if poses is not None:
        # The true relative poses replace the targets of whichever problem is fitted.
        with_pose_targets(problem, poses)
    return problem, intrinsics


def _record_tuned(adapter: Adapter, tune: nn.Module) -> None:
    """A baseline fit (``tune``): what was tuned, and its verdict (the tables stay at zero by
    design, which is not "did nothing")."""
    tuned = {"module": type(tune).__name__, "parameters": sum(p.numel() for p in tune.parameters())}
    adapter.training_info["tuned"] = tuned
    verdict = adapter.training_info["verdict"]
    if verdict["status"] == "did nothing":
        verdict["status"] = "ok"
        verdict["summary"] = (
            f"ok: tuned {tuned['module']} ({tuned['parameters']:,} parameters), loss "
            f"{verdict['first_pass_loss']:.4g} -> {verdict['last_pass_loss']:.4g}"
        )


def _add_teacher(
    model: nn.Module, problem: AdaptationProblem, config: AdaptConfig
) -> dict[str, Any] | None:
    """The lens-gated pinhole-view teacher: on a lens none of its views covers more than
    ``config.teacher_max_coverage`` of, the unpatched model's depth on the views of every window
    becomes ``problem.teacher`` (computed once, before the patch). Returns the record (None when
    the recipe has no teacher term)."""
    if config.weights.teacher <= 0:
        return None
    coverage = teacher_coverage(problem.layout.camera, config.teacher_views, config.teacher_fov_deg)
    used = coverage <= config.teacher_max_coverage
    if used:
        problem.teacher = teacher_targets(
            model, problem, config.teacher_views, config.teacher_fov_deg, config.seed
        )
    return {
        "used": used,
        "coverage": round(coverage, 4),
        "max_coverage": config.teacher_max_coverage,
    }


def _gate_parallax(
    model: nn.Module,
    adapter: Adapter,
    problem: AdaptationProblem,
    config: AdaptConfig,
    teacher: bool,
) -> dict[str, Any]:
    """The parallax gate: drop the windows whose matches cannot tell near from far (measured with
    the starting tables, before any checkpoint is restored, so a resumed run keeps the same
    windows). Returns its record."""
    medians = window_parallax(model, adapter, problem, config)
    # NaN: no evidence. The dense photometric term needs no match to move with depth.
    signal = [not median < config.min_parallax_px for median in medians]
    keep = [config.weights.photo > 0 or teacher or ok for ok in signal]
    parallax = {
        "min_parallax_px": config.min_parallax_px,
        "window_median_px": [round(m, 4) if math.isfinite(m) else None for m in medians],
        "windows_kept": sum(keep),
        "windows_dropped": len(keep) - sum(keep),
    }
    if teacher:
        # The teacher keeps every window; the matches of a window without depth signal still
        # leave the reprojection term, as the gate would have left them out.
        problem.reproject = signal
        parallax["windows_reprojected"] = sum(signal)
    problem.windows = [window for window, k in zip(problem.windows, keep, strict=True) if k]
    return parallax


def _training_info(
    config: AdaptConfig,
    problem: AdaptationProblem,
    steps_done: int,
    history: list[dict[str, Any]],
    interrupted: bool,
    seconds: float,
    start: int,
) -> dict[str, Any]:
    """What an adapter file records about its fitting (metadata ``training``)."""
    tail = history[-len(problem.windows) :]
    final = {
        name: float(np.mean([r[name] for r in tail]))
        for name in ("loss", *TERMS)
        if tail and name in tail[0]
    }
    adaptation, layout = problem.adaptation, problem.layout
    return {
        "method": "raytun3r online adaptation"
        if problem.supervision is None
        else "raytun3r supervised adaptation",
        "supervision": problem.supervision or {"kind": "self-supervised"},
        "steps": steps_done,
        "requested_steps": config.steps,
        "resumed_from": start,
        "interrupted": interrupted,
        "final_losses": final,
        "final_losses_over_steps": len(tail),
        "segment": {
            **problem.segment,
            "windows": [list(w.frames) for w in adaptation.windows],
            "skipped_static": adaptation.skipped_static,
        },
        "input": layout.record(),
        "adaptation_set": adaptation.cache_key,
        "config": config.to_dict(),
        "wall_time_s": round(seconds, 3),
    }
