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

The loop around the step is :func:`adapt`'s (:mod:`~raytun3r_plugin.adaptation.loop`), so a rig
fit has the collapse guard, checkpoints and resuming, Ctrl-C and the supervised mode
(``depth=``) as a single-camera fit does. Not here: pairs across cameras unless
``cross_camera=True``, and the pinhole-view teacher; ``training_info["rig"]["left_out"]`` says
so. The joint step and the cross-camera terms are in :mod:`~raytun3r_plugin.adaptation.rig_step`.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from raytun3r_plugin.adaptation.checkpoint import (
    _restore_checkpoint,
    _save_checkpoint,
    read_loss_log,
    write_loss_artifacts,
)
from raytun3r_plugin.adaptation.config import TERMS, AdaptConfig
from raytun3r_plugin.adaptation.guard import (
    GUARD_MIN_CORRELATION,
    GUARD_SPREAD_RANGE,
    _CollapseGuard,
)
from raytun3r_plugin.adaptation.loop import LoopOutcome, run_fit_loop
from raytun3r_plugin.adaptation.parallax import window_parallax
from raytun3r_plugin.adaptation.problem import AdaptationProblem, _Pair, prepare_problem
from raytun3r_plugin.adaptation.rig_step import cross_pairs, rig_step, rig_views
from raytun3r_plugin.adaptation.step import regulariser_scale
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.errors import AlreadyAppliedError, InputError
from raytun3r_plugin.patching import apply, handle_of

if TYPE_CHECKING:
    from raytun3r_plugin.datasets.rig import Rig

__all__ = ["adapt_rig", "rig_artifact_paths"]

#: What a rig fit leaves out, recorded in every adapter's ``training_info["rig"]``.
NOT_IN_A_RIG_FIT = ("cross-camera pairs", "pinhole-view teacher")


def rig_artifact_paths(out_dir: str | os.PathLike, names: list[str]) -> dict[str, Path]:
    """Files a rig fit writes into ``out_dir``: one adapter per camera, one log, one checkpoint
    and the loss curves."""
    folder = Path(out_dir)
    paths = {f"adapter:{name}": folder / f"{name}.safetensors" for name in names}
    paths.update(
        {
            "log": folder / "rig.log.jsonl",
            "checkpoint": folder / "rig.ckpt.safetensors",
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
    resume: bool = True,
    progress: bool = True,
    cross_camera: bool = False,
    depth: Mapping[str, Any] | None = None,
) -> dict[str, Adapter]:
    """Fit one adapter per camera of ``rig``, all cameras' views in each forward.

    The loop is :func:`adapt`'s (:func:`~raytun3r_plugin.adaptation.loop.run_fit_loop`): the
    collapse guard watches the depth of one joint forward (window 0 of every camera) and
    restores every camera's last healthy tables; checkpoints hold every camera's tables and
    the Adam moments, and a rerun with the same ``out_dir`` resumes; Ctrl-C keeps the last
    completed step.

    Args:
        model: a supported backbone, not patched; its weights are never changed.
        rig: a :class:`~raytun3r_plugin.datasets.rig.Rig` (time-aligned sequences, one image
            size); its :attr:`~raytun3r_plugin.datasets.rig.Rig.names` order is the view order.
        config: :class:`AdaptConfig` for every camera (None: the ``rig`` recipe, which is the
            ``default`` one without the teacher term, or ``supervised`` with ``depth``; an
            ``input_size`` of None is the backbone's own); ``window_size`` frames of each
            camera per step, so ``window_size x V`` views per forward.
        adapters: start from these (copied), by camera name; default zero adapters.
        out_dir: write ``<camera>.safetensors`` per camera, ``rig.log.jsonl`` (one JSON object
            per step), ``rig.ckpt.safetensors`` (the checkpoint) and the loss curves
            (``rig.losses.csv``, ``.png``).
        resume: continue from the checkpoint in ``out_dir`` when there is one.
        progress: a tqdm bar on a terminal, else a line to stderr every 5 s.
        cross_camera: add a reprojection term between the cameras at each instant (matches
            between camera i and camera j at one instant, the rig's known rotation and
            translation direction, the translation scale chosen for the pixel residual as for
            temporal pairs; :func:`~raytun3r_plugin.adaptation.rig_step.cross_pairs`). Every
            step then takes the reference camera's window and, for the other cameras, their
            window of the same frames; the temporal terms still need the gate's windows, the
            cross terms do not.
        depth: the **supervised rig fit**: camera name -> (N, H, W) ground-truth depth of its
            frames (as :func:`adapt`'s ``depth``; every camera needs one). Each camera's views
            are scored with the scale-invariant log depth loss; no gate, no cross terms.

    Returns:
        ``{camera name: Adapter}``, each with its camera and ``training_info`` (the single-camera
        fields for its segment, plus ``"rig"``: the cameras, views per forward, and what a rig
        fit leaves out, :data:`NOT_IN_A_RIG_FIT`).

    Raises:
        AlreadyAppliedError: the model carries a raytun3r patch.
        InputError: a camera without a usable window, cameras whose input layouts differ, a
            teacher weight without depth, ``depth`` missing a camera or with ``cross_camera``.
        AdapterError: the checkpoint in ``out_dir`` belongs to another run.
    """
    supervised = depth is not None
    _check_rig_request(rig, config, depth, cross_camera)
    config = _rig_config(model, config, supervised)
    fit = _prepare_rig(model, rig, config, adapters, depth, cross_camera)
    names, fitted, problems = fit.names, fit.fitted, fit.problems
    tables = nn.ModuleList([fitted[name] for name in names])
    optimizer = torch.optim.Adam(list(tables.parameters()), lr=config.step_size())
    paths = rig_artifact_paths(out_dir, names) if out_dir is not None else None
    identity = {
        "config": config.identity(),
        "adaptation_set": json.dumps([problems[n].adaptation.cache_key for n in names]),
        "backbone": fitted[names[0]].backbone,
        "pe_fingerprint": fitted[names[0]].pe_fingerprint,
        "rig_cameras": json.dumps(names),
        "cross_camera": str(bool(fit.cross)),
    }
    start = 0
    if paths is not None and resume and paths["checkpoint"].is_file():
        start = _restore_checkpoint(paths["checkpoint"], tables, optimizer, identity)
    metadata = {
        **identity,
        "config_json": json.dumps(config.to_dict(), sort_keys=True, default=str),
    }
    guard = _rig_guard(fit, config)
    outcome = run_fit_loop(
        model,
        lambda: apply(
            model,
            [problems[name].layout.native_camera for name in names],
            [fitted[name] for name in names],
            components=config.components,
            strict=False,
            mask=[problems[name].mask for name in names],
        ),
        lambda step: rig_step(
            model,
            fitted,
            problems,
            names,
            optimizer,
            config,
            step,
            fit.frames_per_view,
            fit.scored,
            fit.cross if cross_camera else None,
        ),
        steps=config.steps if fit.has_signal else start,
        start=start,
        seed=config.seed,
        log_path=None if paths is None else paths["log"],
        progress=progress,
        label="adapt_rig",
        guard=guard,
        guarded=tables,
        guard_every=config.guard_every,
        checkpoint=None
        if paths is None
        else lambda done: _save_checkpoint(paths["checkpoint"], tables, optimizer, done, metadata),
        checkpoint_every=config.checkpoint_every,
    )
    history = outcome.history
    if paths is not None and paths["log"].is_file():
        history = read_loss_log(paths["log"])  # with the steps a resumed run restored
    _record_fits(fit, model, config, outcome, history, start, guard, cross_camera)
    if paths is not None:
        _save_checkpoint(paths["checkpoint"], tables, optimizer, outcome.completed, metadata)
        for name in names:
            fitted[name].save(paths[f"adapter:{name}"])
        _write_rig_losses(paths, names, history)
    return fitted


@dataclasses.dataclass
class _PreparedRig:
    """What a rig fit prepares before its first step, per camera by name."""

    names: list[str]
    fitted: dict[str, Adapter]  # the tables being fitted
    problems: dict[str, AdaptationProblem]
    frames_per_view: int  # frames of each camera per forward
    scored: dict[str, list[int]]  # the windows the parallax gate keeps
    gates: dict[str, dict[str, Any] | None]  # the gate's record
    cross: dict[int, list[tuple[int, int, _Pair]]]  # cross-camera pairs by instant

    @property
    def has_signal(self) -> bool:
        """Any camera with a window to score, or any cross-camera match."""
        return any(self.scored.values()) or any(
            pair.uv_i.shape[0] for pairs in self.cross.values() for *_, pair in pairs
        )


def _rig_config(model: nn.Module, config: AdaptConfig | None, supervised: bool) -> AdaptConfig:
    """The fit's config (the ``rig`` or ``supervised`` recipe when None), resolved for the model
    (its size, its family's step); refuses a patched model and the settings a rig fit does not
    have yet."""
    recipe = "supervised" if supervised else "rig"
    config = (
        AdaptConfig.from_recipe(recipe, model=model) if config is None else config
    ).resolved_for(model)
    if handle_of(model) is not None:
        raise AlreadyAppliedError(
            "adapt_rig needs an unpatched model; remove the existing raytun3r patch first"
        )
    if config.weights.teacher > 0 and not supervised:
        raise InputError(
            "adapt_rig has no pinhole-view teacher term yet: use the 'rig' recipe "
            "(AdaptConfig.from_recipe('rig')), set weights.teacher to 0, or fit each camera "
            "with adapt() for the teacher"
        )
    if config.pose_gate is not None:
        raise InputError(
            "adapt_rig has no pose gate (AdaptConfig.pose_gate) yet: leave it None, or fit "
            "each camera with adapt()"
        )
    return config


def _prepare_rig(
    model: nn.Module,
    rig: Rig,
    config: AdaptConfig,
    adapters: Mapping[str, Adapter] | None,
    depth: Mapping[str, Any] | None,
    cross_camera: bool,
) -> _PreparedRig:
    """Each camera's starting tables, problem and parallax gate, and the cross-camera pairs."""
    names = rig.names
    fitted = _starting_adapters(model, names, adapters, config)
    problems = _rig_problems(model, rig, names, fitted, config, depth)
    frames_per_view = min(len(p.windows[0][0].frames) for p in problems.values())
    scored, gates = _parallax_gates(model, names, fitted, problems, config, depth is not None)
    cross: dict[int, list[tuple[int, int, _Pair]]] = {}
    if cross_camera and len(names) > 1:
        frames = sorted({f for window, _ in problems[names[0]].windows for f in window.frames})
        cross = cross_pairs(rig, problems, names, frames, config)
    return _PreparedRig(names, fitted, problems, frames_per_view, scored, gates, cross)


def _rig_guard(fit: _PreparedRig, config: AdaptConfig) -> _CollapseGuard | None:
    """The collapse guard on one joint forward (window 0 of every camera); None when off or
    when nothing is fitted."""
    if not (config.guard and fit.has_signal):
        return None
    batches = {name: fit.problems[name].batch(0)[: fit.frames_per_view] for name in fit.names}
    valid = [fit.problems[name].valid for name in fit.names] * fit.frames_per_view
    return _CollapseGuard(
        None,
        GUARD_MIN_CORRELATION,
        GUARD_SPREAD_RANGE,
        images=rig_views(batches, fit.names),
        valid=torch.stack(valid),
    )


def _record_fits(
    fit: _PreparedRig,
    model: nn.Module,
    config: AdaptConfig,
    outcome: LoopOutcome,
    history: list[dict],
    start: int,
    guard: _CollapseGuard | None,
    cross_camera: bool,
) -> None:
    """Write each camera's ``training_info`` (its segment, the rig, the recipe, the gate, the
    guard and the verdict) onto its adapter."""
    names = fit.names
    for index, name in enumerate(names):
        info = _training_info(
            config,
            fit.problems[name],
            history,
            name,
            index,
            names,
            fit.frames_per_view,
            outcome.seconds,
        )
        info.update(steps=outcome.completed, resumed_from=start, interrupted=outcome.interrupted)
        info["recipe"] = config.recipe_record(model)
        if fit.gates[name] is not None:
            info["parallax_gate"] = fit.gates[name]
        if guard is not None:
            info["guard"] = guard.report()
        if cross_camera:
            info["rig"]["cross_camera"] = _cross_record(fit.cross, index, history)
            info["rig"]["left_out"] = [
                x for x in info["rig"]["left_out"] if x != "cross-camera pairs"
            ]
        info["verdict"] = _verdict(
            info, bool(fit.scored[name]) or bool(history and cross_camera), history, guard
        )
        fit.fitted[name].training_info = info


def _check_rig_request(
    rig: Rig, config: AdaptConfig | None, depth: Mapping[str, Any] | None, cross_camera: bool
) -> None:
    """Refuse a supervised request that cannot be honoured, before anything is prepared."""
    if depth is None:
        return
    missing = [name for name in rig.names if name not in depth]
    if missing:
        raise InputError(f"adapt_rig: depth has no entry for camera(s) {missing}")
    if cross_camera:
        raise InputError("adapt_rig: the supervised fit (depth=...) takes no cross-camera terms")


def _starting_adapters(
    model: nn.Module,
    names: list[str],
    adapters: Mapping[str, Adapter] | None,
    config: AdaptConfig,
) -> dict[str, Adapter]:
    """Each camera's starting adapter: a copy of the given one, else a zero adapter."""
    start = {} if adapters is None else dict(adapters)
    return {
        name: (
            Adapter.for_model(model, None, components=config.components)
            if name not in start
            else copy.deepcopy(start[name])
        )
        for name in names
    }


def _rig_problems(
    model: nn.Module,
    rig: Rig,
    names: list[str],
    fitted: dict[str, Adapter],
    config: AdaptConfig,
    depth: Mapping[str, Any] | None,
) -> dict[str, AdaptationProblem]:
    """Each camera's segment prepared as :func:`adapt` prepares one; one input size for all."""
    patch = fitted[names[0]].patch_size
    problems: dict[str, AdaptationProblem] = {}
    for name in names:
        seq = rig.sequences[name]
        problem = prepare_problem(
            seq.camera,
            seq,
            _for_camera(config, rig, name),
            patch,
            mask=_static_mask(seq),
            depth=None if depth is None else depth[name],
        )
        problem.pe_scale = regulariser_scale(model, config)
        problems[name] = problem
        fitted[name].camera = problem.layout.native_camera
    sizes = {name: (p.layout.height, p.layout.width) for name, p in problems.items()}
    if len(set(sizes.values())) != 1:
        raise InputError(
            f"the rig's cameras give different network inputs {sizes}: a rig forward needs one"
        )
    return problems


def _parallax_gates(
    model: nn.Module,
    names: list[str],
    fitted: dict[str, Adapter],
    problems: dict[str, AdaptationProblem],
    config: AdaptConfig,
    supervised: bool,
) -> tuple[dict[str, list[int]], dict[str, dict[str, Any] | None]]:
    """Per camera, measured with the starting tables: (windows to score, the gate's record).

    The supervised fit scores every window (depth needs no parallax), as :func:`adapt` does.
    """
    scored: dict[str, list[int]] = {}
    gates: dict[str, dict[str, Any] | None] = {}
    for name in names:
        problem = problems[name]
        everything = list(range(len(problem.windows)))
        if config.min_parallax_px <= 0 or supervised:
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
    return scored, gates


def _cross_record(
    cross: dict[int, list[tuple[int, int, _Pair]]], index: int, history: list[dict[str, Any]]
) -> dict[str, Any]:
    """``training_info["rig"]["cross_camera"]`` of camera ``index``."""
    counts = [p[2].uv_i.shape[0] for pairs in cross.values() for p in pairs if p[0] == index]
    return {
        "pairs": len(counts),
        "median_matches": float(np.median(counts)) if counts else 0.0,
        "aligned_steps": sum(1 for r in history if r.get("aligned", False)),
    }


def _write_rig_losses(
    paths: dict[str, Path], names: list[str], history: list[dict[str, Any]]
) -> None:
    """The rig's per-camera loss columns as CSV and a loss-curve picture."""
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


def _verdict(
    info: dict[str, Any],
    has_signal: bool,
    history: list[dict[str, Any]],
    guard: _CollapseGuard | None = None,
) -> dict[str, Any]:
    """What the fit of one camera came to, as a sentence (``status`` and ``summary``).

    A camera with no temporal window of its own (cross-camera terms only) is judged by the
    cross-camera loss of the first and last pass. A tripped guard is the whole rig's verdict:
    it watches one joint forward and restores every camera's tables.
    """
    if not has_signal:
        return {
            "status": "no signal",
            "summary": "no signal: every window of this camera was dropped by the parallax "
            "gate (its matches carry no depth signal); the tables stay as they started",
        }
    if guard is not None and guard.tripped is not None:
        tripped = guard.tripped
        return {
            "status": "collapsed",
            "summary": f"COLLAPSED at step {tripped['step']} (log-depth correlation "
            f"{tripped['correlation']:.2f}, spread x{tripped['spread']:.2f} over the rig's "
            f"joint forward); every camera's tables of step {tripped['restored_step']} restored",
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
        "method": "raytun3r rig adaptation"
        if problem.supervision is None
        else "raytun3r supervised rig adaptation",
        "supervision": problem.supervision or {"kind": "self-supervised"},
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
