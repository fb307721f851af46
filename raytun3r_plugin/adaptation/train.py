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
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import sys
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from raytun3r_plugin._io import atomic_save_safetensors
from raytun3r_plugin.adaptation.losses import (
    LossWeights,
    backproject,
    fit_translation_scale,
    pe_correction_grid,
    pe_energy,
    pe_l2,
    pe_tv,
    pixel_optimal_scale,
    pose_loss,
    relative_pose,
    reprojection_loss,
    sample_bilinear,
    silog_loss,
    smoothness_loss,
    to_input_pixels,
    total_loss,
)
from raytun3r_plugin.adaptation.matchers import get_matcher
from raytun3r_plugin.adaptation.windows import AdaptationSet, Window, prepare_adaptation_set
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.errors import AdapterError, AlreadyAppliedError, InputError
from raytun3r_plugin.geometry import GeometryCache
from raytun3r_plugin.patching import apply, handle_of
from raytun3r_plugin.prediction import predict
from raytun3r_plugin.preprocess import InputLayout, input_layout
from raytun3r_plugin.registry import spec_for

__all__ = [
    "AdaptConfig",
    "AdaptationProblem",
    "InputLayout",
    "adapt",
    "adaptation_step",
    "artifact_paths",
    "depth_health",
    "fit_verdict",
    "input_layout",
    "load_checkpoint",
    "objective_value",
    "prepare_problem",
    "read_loss_log",
    "scene_mask",
    "window_of_step",
    "window_terms",
    "write_loss_artifacts",
]

CHECKPOINT_FORMAT = "raytun3r-adapt-checkpoint"
CHECKPOINT_VERSION = "1"
POSE_SOURCES = ("model", "targets")
SCALES = ("pixel", "least_squares")
PE_REGULARISERS = ("relative", "absolute")
TERMS = ("reproj", "smooth", "l2", "tv", "pose", "depth")

#: Default loss weights of the self-supervised fit. The paper's (reproj 1, smooth 10, L2 2, TV
#: 20, pose 1) were set in absolute PE units; here L2 and TV count relative to the backbone's own
#: PE energy (``pe_regulariser="relative"``), and at the paper's weights even that prices the
#: correction that ground-truth depth finds (0.7-1.1 rms on a PE of std 0.5) at about 110
#: against data terms of about 2, so the tables stay at zero. These weights were chosen on the
#: three development sequences of docs/adaptation.md ("Choosing the defaults"), never on the
#: benchmark's held-out seeds.
SELF_SUPERVISED_WEIGHTS = {"reproj": 1.0, "smooth": 1.0, "l2": 0.02, "tv": 0.2, "pose": 1.0, "depth": 0.0}
#: Loss weights of the supervised fit (:func:`adapt` with ``depth=``): the scale-invariant depth
#: term alone, no regulariser (the ground truth decides the correction).
SUPERVISED_WEIGHTS = {"reproj": 0.0, "smooth": 0.0, "l2": 0.0, "tv": 0.0, "pose": 0.0, "depth": 1.0}

# Configuration fields that may change between an interrupted run and its resumption.
_RESUMABLE_CHANGES = {"steps", "checkpoint_every", "cache_dir"}


@dataclass
class AdaptConfig:
    """Settings of :func:`adapt`. Defaults: docs/conventions.md section 7 and docs/adaptation.md.

    Attributes:
        steps: optimisation steps, one 3-frame window each (300 = 10 passes over 30 windows).
        lr: Adam learning rate.
        clip: gradient-norm clipping threshold (None = no clipping).
        weights: loss weights (reproj 1, smooth 10, L2 2, TV 20, pose 1).
        input_size: long side of the network input in pixels (rounded to the patch size);
            504 as in the paper, smaller for CPU runs.
        n_windows: number of 3-frame windows spread over the segment.
        window_size: frames per window.
        stride: frame step inside a window.
        min_motion_px: windows whose mean correspondence displacement is below this (native
            pixels) are static and skipped.
        matcher: name of a registered matcher (``"dis"``, ``"sift"``, ...).
        matcher_options: keyword arguments of the matcher factory.
        max_matches: matches per ordered pair used in one step (a seeded random subset, drawn
            again every step); 0 = all.
        seed: seeds the window order, the match subsets and the MAGSAC++ estimation.
        checkpoint_every: write a checkpoint every this many steps (0 = only at the end and
            on interruption); needs ``out_path``.
        cache_dir: folder of the adaptation-set cache (matches + targets); None = no cache.
        sequence_id: identity of the frames for the cache key (None hashes the image bytes).
        pose_source: ``"model"`` uses the network's predicted relative poses (the paper);
            ``"targets"`` takes them from the MAGSAC++ targets instead, for backbones whose pose
            head is unusable: the unit translation is scaled per pair in closed form to agree
            with the predicted depth, only pairs with a usable target contribute to the
            reprojection term, and the pose term is dropped (it would compare the targets with
            themselves).
        depth_convention: ``"range"`` (depth = distance along the unit ray, the fisheye
            default) or ``"z"`` (z-depth; FOV below 180 degrees only).
        components: corrections switched on during adaptation (None = all).
        scale: with ``pose_source="targets"``, how the unit target translation is scaled to the
            predicted depth: ``"pixel"`` (default, :func:`~raytun3r_plugin.adaptation.losses.pixel_optimal_scale`:
            the scale that minimises the robust pixel residual, held fixed for the gradient) or
            ``"least_squares"`` (the 3-D least-squares scale, dominated by far points).
        robust_px: scale ``c`` of the log-L1 reprojection penalty ``c log(1 + e / c)`` in input
            pixels; None = the paper's plain L1.
        pe_regulariser: ``"relative"`` (default): L2 and TV of the PE correction divided by the
            backbone's PE energy ``mean_k ||P_A[k]||^2`` (:func:`~raytun3r_plugin.adaptation.losses.pe_energy`),
            so the weights need no retuning per backbone; ``"absolute"``: in PE units, as the paper.
        guard: stop a fit whose depth collapses and roll the tables back to the last healthy
            check (:func:`depth_health`), every ``guard_every`` steps.
        guard_every: steps between two collapse checks.
    """

    steps: int = 300
    lr: float = 3e-3
    clip: float | None = 1.0
    weights: LossWeights = field(default_factory=lambda: LossWeights(**SELF_SUPERVISED_WEIGHTS))
    input_size: int = 504
    n_windows: int = 30
    window_size: int = 3
    stride: int = 1
    min_motion_px: float = 2.0
    matcher: str = "dis"
    matcher_options: dict = field(default_factory=dict)
    max_matches: int = 4096
    seed: int = 0
    checkpoint_every: int = 50
    cache_dir: str | None = None
    sequence_id: str | None = None
    pose_source: str = "model"
    depth_convention: str = "range"
    components: list[str] | None = None
    scale: str = "pixel"
    robust_px: float | None = 1.0
    pe_regulariser: str = "relative"
    guard: bool = True
    guard_every: int = 25

    def __post_init__(self) -> None:
        if isinstance(self.weights, Mapping):
            self.weights = LossWeights(**self.weights)
        if self.cache_dir is not None:
            self.cache_dir = str(self.cache_dir)
        checks = (
            ("steps", self.steps >= 0),
            ("lr", self.lr > 0),
            ("clip", self.clip is None or self.clip > 0),
            ("input_size", self.input_size >= 1),
            ("n_windows", self.n_windows >= 1),
            ("window_size", self.window_size >= 2),
            ("stride", self.stride >= 1),
            ("max_matches", self.max_matches >= 0),
            ("checkpoint_every", self.checkpoint_every >= 0),
            ("pose_source", self.pose_source in POSE_SOURCES),
            ("depth_convention", self.depth_convention in ("range", "z")),
            ("scale", self.scale in SCALES),
            ("robust_px", self.robust_px is None or self.robust_px > 0),
            ("pe_regulariser", self.pe_regulariser in PE_REGULARISERS),
            ("guard_every", self.guard_every >= 1),
        )
        for name, ok in checks:
            if not ok:
                raise InputError(f"AdaptConfig.{name} = {getattr(self, name)!r} is not allowed")

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (``AdaptConfig(**d)`` rebuilds it)."""
        return asdict(self)

    @classmethod
    def supervised(cls, **changes: Any) -> AdaptConfig:
        """Settings of the supervised fit (:func:`adapt` with ``depth=``): the scale-invariant
        log depth loss alone, Adam lr 3e-2, no regularisers, no collapse guard (the ground truth
        cannot collapse); ``changes`` override any field."""
        defaults = {"lr": 3e-2, "weights": LossWeights(**SUPERVISED_WEIGHTS), "guard": False}
        return cls(**{**defaults, **changes})

    def identity(self) -> str:
        """Hash of the settings that must not change when a checkpoint is resumed."""
        kept = {k: v for k, v in self.to_dict().items() if k not in _RESUMABLE_CHANGES}
        return hashlib.sha256(json.dumps(kept, sort_keys=True, default=str).encode()).hexdigest()[:16]


def scene_mask(mask: Any, camera: Any) -> np.ndarray:
    """A user mask of the native frames, checked and combined with the camera's valid region.

    Args:
        mask: (H, W) array-like, True (non-zero) where a pixel sees the scene; False marks what
            never should be matched or supervised (the vehicle's body, a lens mount).
        camera: camera of the native frames (``width == W``, ``height == H``).

    Returns:
        (H, W) bool: ``mask & camera.valid_mask()``.

    Raises:
        InputError: wrong shape, or no pixel left inside the lens.
    """
    array = np.asarray(mask.detach().cpu() if isinstance(mask, torch.Tensor) else mask)
    expected = (int(camera.height), int(camera.width))
    if array.shape != expected:
        raise InputError(f"mask must be (H, W) = {expected} like the frames, got shape {array.shape}")
    combined = (array != 0) & camera.valid_mask().cpu().numpy().astype(bool)
    if not combined.any():
        raise InputError("mask leaves no pixel inside the camera's valid region")
    return combined


# --------------------------------------------------------------------------------------------
# Frames and pairs
# --------------------------------------------------------------------------------------------


def _frames_array(frames: Any) -> tuple[np.ndarray, dict[str, Any]]:
    """Accept (N, H, W, 3) float32 arrays/tensors or a ``datasets.Sequence``; return the array
    and a description of the segment."""
    info: dict[str, Any] = {}
    if hasattr(frames, "images") and hasattr(frames, "camera"):
        info["name"] = str(getattr(frames, "name", ""))
        images = frames.images
        if images is None:
            images = np.stack([frames.image(i) for i in range(len(frames))])
        frames = images
    if isinstance(frames, torch.Tensor):
        frames = frames.detach().cpu().numpy()
    array = np.asarray(frames)
    if array.ndim != 4 or array.shape[-1] != 3:
        raise InputError(f"frames must be (N, H, W, 3) RGB in [0, 1], got shape {array.shape}")
    array = array.astype(np.float32, copy=False)
    info.update(n_frames=int(array.shape[0]), width=int(array.shape[2]), height=int(array.shape[1]))
    return array, info


@dataclass
class _Pair:
    """One ordered pair of a window, in network-input pixels, filtered to usable matches."""

    a: int
    b: int
    uv_i: torch.Tensor  # (M, 2) input pixels in frame a
    uv_j: torch.Tensor  # (M, 2) input pixels in frame b
    confidence: torch.Tensor  # (M,)
    rays_i: torch.Tensor  # (M, 3) unit rays of uv_i
    rays_j: torch.Tensor  # (M, 3) unit rays of uv_j
    rotation: torch.Tensor | None  # (3, 3) float64 target R (cam_b_from_cam_a), None if unusable
    direction: torch.Tensor | None  # (3,) float64 unit target translation


def _inside(uv: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    height, width = valid.shape
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= height - 0.5)
    col = torch.round(uv[:, 0]).clamp(0, width - 1).long()
    row = torch.round(uv[:, 1]).clamp(0, height - 1).long()
    return inside & valid[row, col]


def _prepare_pairs(window: Window, layout: InputLayout, valid: torch.Tensor) -> list[_Pair]:
    camera = layout.camera
    pairs = []
    for (a, b), matches in window.pairs.items():
        uv_i = to_input_pixels(torch.from_numpy(matches.uv_i).float(), layout.native_size, (layout.width, layout.height), layout.offset)
        uv_j = to_input_pixels(torch.from_numpy(matches.uv_j).float(), layout.native_size, (layout.width, layout.height), layout.offset)
        with torch.no_grad():
            rays_i, ok_i = camera.unproject(uv_i)
            rays_j, ok_j = camera.unproject(uv_j)
        keep = ok_i & ok_j & _inside(uv_i, valid) & _inside(uv_j, valid)
        target = window.targets.get((a, b))
        usable = target is not None and target.ok
        pairs.append(
            _Pair(
                a, b, uv_i[keep], uv_j[keep], torch.from_numpy(matches.confidence).float()[keep],
                rays_i[keep].float(), rays_j[keep].float(),
                torch.from_numpy(target.R).double() if usable else None,
                torch.from_numpy(target.t).double() if usable else None,
            )
        )
    return pairs


# --------------------------------------------------------------------------------------------
# Files: log, checkpoint
# --------------------------------------------------------------------------------------------


def artifact_paths(out_path: str | os.PathLike) -> dict[str, Path]:
    """``{"adapter", "log", "checkpoint", "csv", "curve"}`` paths for an adapter file ``out_path``."""
    out = Path(out_path)
    stem = out.name[: -len(".safetensors")] if out.name.endswith(".safetensors") else out.name
    return {
        "adapter": out,
        "log": out.with_name(f"{stem}.log.jsonl"),
        "checkpoint": out.with_name(f"{stem}.ckpt.safetensors"),
        "csv": out.with_name(f"{stem}.losses.csv"),
        "curve": out.with_name(f"{stem}.losses.png"),
    }


def write_loss_artifacts(paths: Mapping[str, Path], records: list[dict[str, Any]]) -> None:
    """The per-step losses as CSV (``paths["csv"]``) and as a loss-curve picture (``paths["curve"]``).

    Columns: ``step``, ``loss``, every term the run had, ``grad_norm``, ``skipped``, ``time_s``.
    The picture shows the total and the raw value of each term over the steps (log scale).
    """
    import csv

    import cv2

    from raytun3r_plugin.plots import line_chart

    terms = [name for name in TERMS if records and name in records[0]]
    columns = ["step", "loss", *terms, "grad_norm", "skipped", "time_s"]
    with open(paths["csv"], "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        for record in records:
            writer.writerow([record.get(name, "") for name in columns])
    series = {name: [float(r[name]) for r in records] for name in ("loss", *terms) if any(float(r[name]) > 0 for r in records)}
    title = f"adaptation losses ({len(records)} steps)"
    cv2.imwrite(str(paths["curve"]), line_chart(series, title))


def read_loss_log(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The per-step records of a loss log (``*.log.jsonl``), or of the log next to an adapter."""
    path = Path(path)
    if not path.name.endswith(".jsonl"):
        path = artifact_paths(path)["log"]
    with open(path, encoding="utf-8") as handle:
        return [json.loads(line) for line in handle if line.strip()]


def _save_checkpoint(path: Path, adapter: Adapter, optimizer: torch.optim.Optimizer, step: int, identity: dict[str, str]) -> None:
    names = [name for name, _ in adapter.named_parameters()]
    tensors = {f"adapter.{name}": value for name, value in adapter.tensors().items()}
    state = optimizer.state_dict()["state"]
    for index, name in enumerate(names):
        for key, value in state.get(index, {}).items():
            tensors[f"adam.{name}.{key}"] = torch.as_tensor(value).detach().to("cpu", torch.float32).reshape(-1).clone()
    metadata = {"format": CHECKPOINT_FORMAT, "format_version": CHECKPOINT_VERSION, "step": str(step), **identity}
    atomic_save_safetensors(path, tensors, metadata)


def load_checkpoint(path: str | os.PathLike) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors and metadata of an adaptation checkpoint (safetensors; nothing is unpickled)."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as handle:
        metadata = dict(handle.metadata() or {})
        tensors = {name: handle.get_tensor(name) for name in handle.keys()}  # noqa: SIM118
    if metadata.get("format") != CHECKPOINT_FORMAT:
        raise AdapterError(f"{path}: not a raytun3r adaptation checkpoint (format {metadata.get('format')!r})")
    return tensors, metadata


def _restore_checkpoint(path: Path, adapter: Adapter, optimizer: torch.optim.Optimizer, identity: dict[str, str]) -> int:
    tensors, metadata = load_checkpoint(path)
    for key, expected in identity.items():
        if metadata.get(key) != expected:
            raise AdapterError(
                f"{path}: checkpoint was written for another run ({key} {metadata.get(key)!r}, this run {expected!r}); "
                "pass resume=False to start over"
            )
    with torch.no_grad():
        for name, parameter in adapter.named_parameters():
            stored = tensors.get(f"adapter.{name}")
            if stored is None or stored.shape != parameter.shape:
                raise AdapterError(f"{path}: checkpoint has no table {name!r} of shape {tuple(parameter.shape)}")
            parameter.copy_(stored)
    state: dict[int, dict[str, torch.Tensor]] = {}
    for index, (name, parameter) in enumerate(adapter.named_parameters()):
        entry = {}
        for key in ("step", "exp_avg", "exp_avg_sq"):
            stored = tensors.get(f"adam.{name}.{key}")
            if stored is not None:
                entry[key] = stored.reshape(()) if key == "step" else stored.reshape(parameter.shape).clone()
        if entry:
            state[index] = entry
    optimizer.load_state_dict({"state": state, "param_groups": optimizer.state_dict()["param_groups"]})
    return int(metadata["step"])


def _rewrite_log(path: Path, keep_before: int) -> None:
    """Drop records of steps >= ``keep_before`` (they are redone after a resume)."""
    if not path.is_file():
        return
    kept = [line for line in path.read_text(encoding="utf-8").splitlines() if line.strip() and json.loads(line)["step"] < keep_before]
    path.write_text("".join(line + "\n" for line in kept), encoding="utf-8")


# --------------------------------------------------------------------------------------------
# Collapse guard and the verdict of a fit
# --------------------------------------------------------------------------------------------

#: A fit is collapsing when the log-depth of the guard window correlates less than this with the
#: zero adapter's (structure lost) ...
GUARD_MIN_CORRELATION = 0.5
#: ... or when its spread (std of log depth) leaves this range of the zero adapter's.
GUARD_SPREAD_RANGE = (0.5, 2.0)


def depth_health(reference: torch.Tensor, current: torch.Tensor) -> tuple[float, float]:
    """(Pearson correlation, spread ratio) of two log-depth samples over the same pixels.

    The spread ratio is ``std(current) / std(reference)``. Together they catch the failure seen
    when the regularisers are off: an outdoor fit whose depth lost its structure (held-out
    AbsRel 0.22 -> 1.05) while its data terms still fell.
    """
    a = reference - reference.mean()
    b = current - current.mean()
    correlation = float((a * b).sum() / (a.norm() * b.norm()).clamp_min(1e-12))
    spread = float(b.std() / a.std().clamp_min(1e-12))
    return correlation, spread


class _CollapseGuard:
    """Every ``guard_every`` steps: predict window 0, compare its log-depth with the zero
    adapter's (:func:`depth_health`), keep a copy of the tables while healthy and restore the
    last healthy copy when not."""

    def __init__(self, problem: AdaptationProblem, config: AdaptConfig) -> None:
        self.images = problem.batch(0)
        self.valid = problem.valid
        self.reference: torch.Tensor | None = None
        self.snapshot: dict[str, torch.Tensor] | None = None
        self.healthy_step = 0
        self.tripped: dict[str, Any] | None = None
        self.checks: list[dict[str, float]] = []
        self.usable: torch.Tensor | None = None

    def _depth(self, model: nn.Module) -> torch.Tensor:
        with torch.no_grad():
            return predict(model, self.images[None]).depth[0].float()

    def check(self, model: nn.Module, adapter: Adapter, step: int) -> bool:
        """True when healthy (the tables are kept); False after restoring the last healthy ones."""
        depth = self._depth(model)
        if self.reference is None:
            self.usable = self.valid[None].expand_as(depth) & torch.isfinite(depth) & (depth > 0)
            self.reference = torch.log(depth[self.usable])
            self.snapshot = {name: p.detach().clone() for name, p in adapter.named_parameters()}
            self.healthy_step = step
            return True
        current = torch.log(depth[self.usable].clamp_min(1e-12))
        correlation, spread = depth_health(self.reference, current) if torch.isfinite(current).all() else (float("nan"), float("nan"))
        self.checks.append({"step": step, "correlation": round(correlation, 4), "spread": round(spread, 4)})
        low, high = GUARD_SPREAD_RANGE
        if correlation >= GUARD_MIN_CORRELATION and low <= spread <= high:
            self.snapshot = {name: p.detach().clone() for name, p in adapter.named_parameters()}
            self.healthy_step = step
            return True
        with torch.no_grad():
            for name, parameter in adapter.named_parameters():
                parameter.copy_(self.snapshot[name])
        self.tripped = {"step": step, "correlation": correlation, "spread": spread, "restored_step": self.healthy_step}
        return False

    def report(self) -> dict[str, Any]:
        return {"tripped": self.tripped, "checks": self.checks[-12:], "min_correlation": GUARD_MIN_CORRELATION, "spread_range": list(GUARD_SPREAD_RANGE)}


def fit_verdict(adapter: Adapter, history: list[dict[str, Any]], problem: AdaptationProblem, guard: _CollapseGuard | None) -> dict[str, Any]:
    """What a finished fit did, in one word and one sentence.

    ``status``: ``"collapsed"`` (the guard stopped it and restored earlier tables),
    ``"diverged"`` (non-finite losses, more than 10 % skipped steps, or a last pass with a loss
    above twice the first pass's), ``"did nothing"`` (the PE correction stayed below 1 % of the
    backbone's PE rms and the RoPE table below 0.01 token) or ``"ok"``.
    """
    correction = pe_correction_grid(adapter, problem.geometry).detach()
    relative = math.sqrt(float(pe_l2(correction)) / problem.pe_scale) if problem.pe_scale > 0 else float("nan")
    rope = float(adapter.rope["radial"].detach().abs().max()) if adapter.rope else 0.0
    window = max(1, len(problem.windows))
    first = [r["loss"] for r in history[:window]]
    last = [r["loss"] for r in history[-window:]]
    skipped = sum(bool(r["skipped"]) for r in history)
    finite = all(math.isfinite(v) for v in last)
    first_mean = float(np.mean(first)) if first else float("nan")
    last_mean = float(np.mean(last)) if last else float("nan")
    size = f"PE correction {100 * relative:.1f} % of the PE rms, RoPE shift up to {rope:.3f} token"
    if guard is not None and guard.tripped is not None:
        status = "collapsed"
        summary = (
            f"COLLAPSED at step {guard.tripped['step']} (log-depth correlation {guard.tripped['correlation']:.2f}, "
            f"spread x{guard.tripped['spread']:.2f}); tables of step {guard.tripped['restored_step']} restored; {size}"
        )
    elif history and (not finite or skipped > 0.1 * len(history) or last_mean > 2 * first_mean):
        status = "diverged"
        summary = f"DIVERGED: loss {first_mean:.4g} -> {last_mean:.4g}, {skipped} of {len(history)} steps skipped; {size}"
    elif relative < 0.01 and rope < 0.01:
        status = "did nothing"
        summary = f"DID NOTHING: the tables stayed at zero ({size}); loss {first_mean:.4g} -> {last_mean:.4g}"
    else:
        status = "ok"
        summary = f"ok: loss {first_mean:.4g} -> {last_mean:.4g} over {len(history)} steps; {size}"
    return {"status": status, "summary": summary, "pe_correction_relative_rms": relative, "rope_max_token": rope,
            "first_pass_loss": first_mean, "last_pass_loss": last_mean, "skipped_steps": skipped}


# --------------------------------------------------------------------------------------------
# Model state: frozen backbone, eval mode
# --------------------------------------------------------------------------------------------


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


class _Progress:
    """tqdm when available, otherwise a line to stderr every ~5% of the run."""

    def __init__(self, total: int, initial: int, enabled: bool) -> None:
        self.enabled = enabled
        self.total = total
        self.bar = None
        if enabled:
            try:
                from tqdm.auto import tqdm

                self.bar = tqdm(total=total, initial=initial, desc="adapt", unit="step", dynamic_ncols=True)
            except ImportError:
                self.bar = None
        self.every = max(1, total // 20)

    def update(self, step: int, loss: float) -> None:
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix(loss=f"{loss:.4g}", refresh=False)
        elif (step + 1) % self.every == 0 or step + 1 == self.total:
            print(f"adapt: step {step + 1}/{self.total} loss {loss:.4g}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# --------------------------------------------------------------------------------------------
# One step
# --------------------------------------------------------------------------------------------


def _subset(pair: _Pair, max_matches: int, generator: torch.Generator) -> tuple[torch.Tensor, ...]:
    count = pair.uv_i.shape[0]
    if max_matches and count > max_matches:
        index = torch.randperm(count, generator=generator)[:max_matches]
        return pair.uv_i[index], pair.uv_j[index], pair.confidence[index], pair.rays_i[index], pair.rays_j[index]
    return pair.uv_i, pair.uv_j, pair.confidence, pair.rays_i, pair.rays_j


def _targets_pose(
    pair: _Pair, depth_i: torch.Tensor, uv_i: torch.Tensor, uv_j: torch.Tensor, confidence: torch.Tensor,
    rays_i: torch.Tensor, rays_j: torch.Tensor, camera: Any, config: AdaptConfig,
) -> torch.Tensor:
    """``cam_j_from_cam_i`` from the MAGSAC++ target, translation scaled to the predicted depth
    (``config.scale``: pixel-optimal and detached, or the differentiable least-squares scale)."""
    depth = sample_bilinear(depth_i, uv_i)
    usable = torch.isfinite(depth) & (depth > 0)
    points = backproject(torch.where(usable, depth, torch.ones_like(depth)), rays_i, config.depth_convention)
    rotation = pair.rotation.to(depth_i.dtype)
    direction = pair.direction.to(depth_i.dtype)
    scale = fit_translation_scale(points[usable], rays_j[usable], rotation, direction, confidence[usable])
    if config.scale == "pixel":
        scale = pixel_optimal_scale(
            points[usable], uv_j[usable], rotation, direction, camera, confidence[usable],
            robust_px=config.robust_px or 1.0, initial=scale.detach(),
        )
    pose = torch.eye(4, dtype=depth_i.dtype)
    return torch.cat((torch.cat((rotation, (scale * direction)[:, None]), dim=1), pose[3:]), dim=0)


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

    Returns:
        (terms, counts): 0-d tensors per term name (pose absent in ``targets`` mode) and the
        numbers of reprojection matches / pose targets that entered them.
    """
    prediction = predict(model, images[None])
    depth, poses = prediction.depth[0], prediction.cam_from_world[0]
    correction = pe_correction_grid(adapter, geometry)
    regularisers = {"l2": pe_l2(correction) / pe_scale, "tv": pe_tv(correction) / pe_scale}
    if depth_targets is not None:
        losses = [silog_loss(sample_bilinear(depth[k], uv), target) for k, (uv, target) in enumerate(depth_targets) if uv.shape[0]]
        n_depth = sum(int(uv.shape[0]) for uv, _ in depth_targets)
        term = torch.stack(losses).mean() if losses else depth.sum() * 0.0
        return {"depth": term, **regularisers}, {"n_matches": 0, "n_pose": 0, "n_depth": n_depth}
    reproj, pose_terms, n_matches = [], [], 0
    for pair in pairs:
        if config.pose_source == "model":
            relative = relative_pose(poses, pair.a, pair.b)
            if pair.rotation is not None:
                pose_terms.append(pose_loss(relative, pair.rotation, pair.direction))
        if pair.uv_i.shape[0] == 0 or (config.pose_source == "targets" and pair.rotation is None):
            continue
        uv_i, uv_j, confidence, rays_i, rays_j = _subset(pair, config.max_matches, generator)
        if config.pose_source == "targets":
            relative = _targets_pose(pair, depth[pair.a], uv_i, uv_j, confidence, rays_i, rays_j, layout.camera, config)
        loss, count = reprojection_loss(
            depth[pair.a], relative, uv_i, uv_j, confidence, layout.camera, valid, config.depth_convention,
            rays_i=(rays_i, torch.ones_like(confidence, dtype=torch.bool)), robust_px=config.robust_px,
        )
        if count:
            reproj.append(loss)
            n_matches += count
    zero = depth.sum() * 0.0
    terms = {
        "reproj": torch.stack(reproj).mean() if reproj else zero,
        "smooth": smoothness_loss(depth, images.to(depth.dtype), valid),
        **regularisers,
    }
    if config.pose_source == "model":
        terms["pose"] = torch.stack(pose_terms).mean() if pose_terms else zero
    return terms, {"n_matches": n_matches, "n_pose": len(pose_terms)}


# --------------------------------------------------------------------------------------------
# Prepared problem and one optimisation step
# --------------------------------------------------------------------------------------------


@dataclass
class AdaptationProblem:
    """Everything a step needs, prepared once: input layout, windows with their pairs in
    network-input pixels, resized frames, valid region and token geometry.

    Attributes:
        layout: :class:`InputLayout` of the frames.
        adaptation: the :class:`~raytun3r_plugin.adaptation.windows.AdaptationSet`.
        windows: ``[(window, pairs)]`` with the pairs filtered to usable matches.
        inputs: ``{frame index: (3, h, w) network input in [0, 1]}`` for every used frame.
        valid: (h, w) bool valid region at the input size.
        geometry: :class:`raytun3r_plugin.geometry.SizeGeometry` at the input size.
        segment: description of the frames (name, count, size).
        mask: the user mask of the (cropped) native frames, (H, W) bool, or None; the model is
            patched with it during adaptation.
        pe_scale: divisor of the PE regularisers (set by :func:`adapt` from the backbone).
        depth_targets: supervised mode: ``{frame: (uv (K, 2) input pixels, depth (K,))}``.
        supervision: description of the ground truth (kind, coverage), or None.
    """

    layout: InputLayout
    adaptation: AdaptationSet
    windows: list[tuple[Window, list[_Pair]]]
    inputs: dict[int, torch.Tensor]
    valid: torch.Tensor
    geometry: Any
    segment: dict[str, Any]
    mask: torch.Tensor | None = None
    pe_scale: float = 1.0
    depth_targets: dict[int, tuple[torch.Tensor, torch.Tensor]] | None = None
    supervision: dict[str, Any] | None = None

    def batch(self, index: int) -> torch.Tensor:
        """(S, 3, h, w) network input of window ``index``."""
        return torch.stack([self.inputs[frame] for frame in self.windows[index][0].frames])

    def window_depth(self, index: int) -> list[tuple[torch.Tensor, torch.Tensor]] | None:
        """Supervised mode: the depth samples of window ``index``'s frames, in window order."""
        if self.depth_targets is None:
            return None
        return [self.depth_targets[frame] for frame in self.windows[index][0].frames]


#: Most ground-truth depth samples kept per frame (a seeded subset; 112 px frames have fewer).
MAX_DEPTH_SAMPLES = 8192


def _depth_targets(
    depth: Any, frames: list[int], layout: InputLayout, native_valid: np.ndarray | None, shape: tuple[int, ...], seed: int,
) -> tuple[dict[int, tuple[torch.Tensor, torch.Tensor]], dict[str, Any]]:
    """Ground-truth depth of the native frames -> per-frame samples at network-input pixels.

    ``depth`` is (N, H, W) like the frames (a dense map, or a sparse one such as projected LiDAR
    points: 0, negative or NaN = unknown). Each known pixel centre becomes a sample at the
    input-pixel position of that centre (``to_input_pixels``, so a crop is honoured), where the
    prediction is read bilinearly; no resampling of the ground truth blurs depth edges.
    """
    array = np.asarray(depth.detach().cpu() if isinstance(depth, torch.Tensor) else depth, dtype=np.float64)
    if array.shape != tuple(shape):
        raise InputError(f"depth must be (N, H, W) = {tuple(shape)} like the frames, got shape {array.shape}")
    width, height = layout.native_size
    x0, y0 = layout.offset
    lens = layout.native_camera.valid_mask().cpu().numpy().astype(bool)
    region = lens if native_valid is None else lens & native_valid[y0 : y0 + height, x0 : x0 + width]
    generator = np.random.default_rng(seed)
    targets, known = {}, []
    for frame in frames:
        values = array[frame, y0 : y0 + height, x0 : x0 + width]
        ok = np.isfinite(values) & (values > 0) & region
        rows, cols = np.nonzero(ok)
        known.append(ok.sum() / max(1, lens.sum()))
        if rows.size > MAX_DEPTH_SAMPLES:
            keep = np.sort(generator.choice(rows.size, MAX_DEPTH_SAMPLES, replace=False))
            rows, cols = rows[keep], cols[keep]
        uv = torch.from_numpy(np.stack([cols + x0, rows + y0], axis=1).astype(np.float32))
        uv = to_input_pixels(uv, layout.native_size, (layout.width, layout.height), layout.offset)
        targets[frame] = (uv, torch.from_numpy(values[rows, cols].astype(np.float32)))
    coverage = float(np.mean(known)) if known else 0.0
    if coverage == 0.0:
        raise InputError("depth has no positive, finite value inside the lens on the adaptation frames")
    return targets, {"kind": "depth", "coverage": round(coverage, 4), "dense": coverage > 0.5, "frames": len(frames)}


def prepare_problem(camera: Any, frames: Any, config: AdaptConfig, patch: int = 14, mask: Any = None, depth: Any = None) -> AdaptationProblem:
    """Match, estimate targets (or load them from the cache) and lay the segment out for training.

    ``mask`` (optional, (H, W) like the frames, True where the scene is seen) keeps matches,
    reprojection and smoothness off the pixels it excludes (:func:`scene_mask`). ``depth``
    (optional, (N, H, W) like the frames) switches to the supervised fit (:func:`adapt`).
    """
    images, segment = _frames_array(frames)
    if (segment["width"], segment["height"]) != (int(camera.width), int(camera.height)):
        raise InputError(f"frames are {segment['width']}x{segment['height']} px but the camera is {camera.width}x{camera.height}")
    native_valid = None if mask is None else scene_mask(mask, camera)
    segment["sequence_id"] = config.sequence_id
    layout = input_layout(camera, config.input_size, patch)
    adaptation = prepare_adaptation_set(
        images, camera, get_matcher(config.matcher, **config.matcher_options), n_windows=config.n_windows,
        stride=config.stride, cache_dir=config.cache_dir, sequence_id=config.sequence_id,
        min_motion_px=config.min_motion_px, window_size=config.window_size, seed=config.seed, valid=native_valid,
    )
    if len(adaptation) == 0:
        raise InputError(
            f"no usable adaptation window: all {adaptation.skipped_static} candidate windows are static "
            f"(mean correspondence displacement below {config.min_motion_px} px)"
        )
    valid = layout.camera.valid_mask().bool()
    native_mask = None
    if native_valid is not None:
        native_mask = layout.native_mask(native_valid)
        valid = valid & layout.mask(native_valid)
        segment["mask"] = {"valid_fraction": round(float(native_valid.mean()), 4), "sha256": hashlib.sha256(np.packbits(native_valid).tobytes()).hexdigest()}
    used = sorted({frame for window in adaptation.windows for frame in window.frames})
    inputs = dict(zip(used, layout.frames(images[used]), strict=True))
    windows = [(window, _prepare_pairs(window, layout, valid)) for window in adaptation.windows]
    geometry = GeometryCache(layout.native_camera, patch).at(layout.height, layout.width)
    problem = AdaptationProblem(layout, adaptation, windows, inputs, valid, geometry, segment, native_mask)
    if depth is not None:
        problem.depth_targets, problem.supervision = _depth_targets(depth, used, layout, native_valid, tuple(images.shape[:3]), config.seed)
    return problem


def window_of_step(step: int, n_windows: int, seed: int) -> int:
    """Window index of a step: a seeded permutation of the windows per pass (epoch)."""
    epoch, position = divmod(step, n_windows)
    generator = torch.Generator().manual_seed(int(seed) * 1_000_003 + epoch)
    return int(torch.randperm(n_windows, generator=generator)[position])


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
    window, pairs = problem.windows[index]
    generator = torch.Generator().manual_seed(int(config.seed) * 7_919 + step)
    terms, counts = window_terms(
        model, adapter, problem.batch(index), pairs, problem.layout, problem.valid, problem.geometry, config, generator,
        pe_scale=problem.pe_scale, depth_targets=problem.window_depth(index),
    )
    loss = total_loss(terms, config.weights)
    parameters = [p for group in optimizer.param_groups for p in group["params"]]
    optimizer.zero_grad(set_to_none=True)
    grad_norm = float("nan")
    if bool(torch.isfinite(loss)):
        loss.backward()
        grads = [p.grad for p in parameters if p.grad is not None]
        if config.clip is not None:
            grad_norm = float(torch.nn.utils.clip_grad_norm_(parameters, config.clip))
        elif grads:
            grad_norm = float(torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads])))
        if math.isfinite(grad_norm):
            optimizer.step()
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


def objective_value(model: nn.Module, adapter: Adapter, problem: AdaptationProblem, config: AdaptConfig, seed: int = 0) -> dict[str, float]:
    """The objective of ``config`` for ``adapter``, averaged over every window of ``problem``.

    Runs the model patched with ``adapter`` (the model must be unpatched; it is again
    afterwards), without gradients. Match subsets come from a generator seeded by ``seed`` and
    the window index, so two adapters are scored on the same samples. Used to check that the
    objective ranks a better adapter lower (``tests``, ``docs/adaptation.md``).

    Returns:
        ``{"loss": total, <term>: mean value, ...}``.
    """
    if handle_of(model) is not None:
        raise AlreadyAppliedError("objective_value needs an unpatched model")
    sums: dict[str, float] = {}
    with _frozen(model), torch.no_grad(), apply(model, problem.layout.native_camera, adapter, components=config.components, strict=False, mask=problem.mask):
        for index, (_, pairs) in enumerate(problem.windows):
            generator = torch.Generator().manual_seed(int(seed) * 7_919 + index)
            terms, _ = window_terms(
                model, adapter, problem.batch(index), pairs, problem.layout, problem.valid, problem.geometry, config, generator,
                pe_scale=problem.pe_scale, depth_targets=problem.window_depth(index),
            )
            terms = {**terms, "loss": total_loss(terms, config.weights)}
            for name, value in terms.items():
                sums[name] = sums.get(name, 0.0) + float(value) / len(problem.windows)
    return sums


# --------------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------------


def adapt(
    model: nn.Module,
    camera: Any,
    frames: Any,
    config: AdaptConfig | None = None,
    *,
    out_path: str | os.PathLike | None = None,
    adapter: Adapter | None = None,
    resume: bool = True,
    progress: bool = True,
    mask: Any = None,
    depth: Any = None,
) -> Adapter:
    """Fit an adapter for ``model`` on a fisheye segment, without ground truth (or with it).

    Args:
        model: a supported backbone (not already patched); its weights are never changed.
        camera: camera of the native frames.
        frames: (N, H, W, 3) float32 RGB in [0, 1] (numpy or torch), or a
            ``raytun3r_plugin.datasets.Sequence``.
        config: :class:`AdaptConfig` (defaults if None).
        out_path: adapter file to write (``.safetensors``); the loss log and the checkpoint go
            next to it (:func:`artifact_paths`). None keeps everything in memory (no log file,
            no checkpoint).
        adapter: start from this adapter (copied) instead of a zero one.
        resume: continue from the checkpoint next to ``out_path`` when there is one.
        progress: show a progress bar (tqdm, or a line to stderr every 5% without it).
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
            records the kind and the coverage (fraction of lens pixels with a value).

    Returns:
        The fitted :class:`Adapter` (camera: the camera of the frames, cropped if the input
        layout needed a crop); ``adapter.training_info`` records the steps done, the final
        losses (mean over the last pass over the windows), the segment, the input layout and the
        configuration. On Ctrl-C the adapter of the last completed step is saved (with a
        checkpoint) and returned, with ``training_info["interrupted"] = True``.

    Raises:
        AlreadyAppliedError: the model already carries a raytun3r patch.
        InputError: frames/camera mismatch, a mask of the wrong shape or with nothing inside
            the lens, or no moving window in the segment.
        AdapterError: the checkpoint next to ``out_path`` belongs to another run.
    """
    if config is None:
        config = AdaptConfig() if depth is None else AdaptConfig.supervised()
    if handle_of(model) is not None:
        raise AlreadyAppliedError("adapt needs an unpatched model; remove the existing raytun3r patch first")
    adapter = Adapter.for_model(model, None, components=config.components) if adapter is None else copy.deepcopy(adapter)
    problem = prepare_problem(camera, frames, config, adapter.patch_size, mask=mask, depth=depth)
    if config.pe_regulariser == "relative":
        spec, root = spec_for(model)
        problem.pe_scale = pe_energy(spec.describe(root).pos_embed)
    adapter.camera = problem.layout.native_camera
    optimizer = torch.optim.Adam(list(adapter.parameters()), lr=config.lr)

    paths = artifact_paths(out_path) if out_path is not None else None
    identity = {
        "config": config.identity(),
        "adaptation_set": problem.adaptation.cache_key,
        "backbone": adapter.backbone,
        "pe_fingerprint": adapter.pe_fingerprint,
    }
    start = 0
    if paths is not None and resume and paths["checkpoint"].is_file():
        start = _restore_checkpoint(paths["checkpoint"], adapter, optimizer, identity)
    if paths is not None:
        paths["log"].parent.mkdir(parents=True, exist_ok=True)
        if start == 0:
            paths["log"].write_text("", encoding="utf-8")
        else:
            _rewrite_log(paths["log"], start)
    metadata = {**identity, "config_json": json.dumps(config.to_dict(), sort_keys=True, default=str)}

    history: list[dict[str, Any]] = []
    guard = _CollapseGuard(problem, config) if config.guard else None
    completed, interrupted, began = start, False, time.perf_counter()
    bar = _Progress(config.steps, start, progress)
    log = open(paths["log"], "a", encoding="utf-8") if paths is not None else None  # noqa: SIM115
    try:
        with _frozen(model), torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed)
            handle = apply(model, problem.layout.native_camera, adapter, components=config.components, strict=False, mask=problem.mask)
            try:
                if guard is not None:
                    guard.check(model, adapter, start)
                for step in range(start, config.steps):
                    record = adaptation_step(model, adapter, optimizer, problem, config, step)
                    completed = step + 1
                    history.append(record)
                    if log is not None:
                        log.write(json.dumps(record) + "\n")
                        log.flush()
                    bar.update(step, record["loss"])
                    if guard is not None and (completed % config.guard_every == 0 or completed == config.steps) and not guard.check(model, adapter, completed):
                        break
                    if paths is not None and config.checkpoint_every and completed % config.checkpoint_every == 0 and completed < config.steps:
                        _save_checkpoint(paths["checkpoint"], adapter, optimizer, completed, metadata)
            except KeyboardInterrupt:
                interrupted = True
            finally:
                handle.remove()
    finally:
        bar.close()
        if log is not None:
            log.close()

    adapter.training_info = _training_info(config, problem, completed, history, interrupted, time.perf_counter() - began, start)
    if guard is not None:
        adapter.training_info["guard"] = guard.report()
    adapter.training_info["verdict"] = fit_verdict(adapter, history, problem, guard)
    if progress:
        print(f"adapt: {adapter.training_info['verdict']['summary']}", file=sys.stderr, flush=True)
    if paths is not None:
        _save_checkpoint(paths["checkpoint"], adapter, optimizer, completed, metadata)
        adapter.save(paths["adapter"])
        write_loss_artifacts(paths, read_loss_log(paths["log"]) if paths["log"].is_file() else history)
    return adapter


def _training_info(
    config: AdaptConfig, problem: AdaptationProblem, steps_done: int, history: list[dict[str, Any]],
    interrupted: bool, seconds: float, start: int,
) -> dict[str, Any]:
    """What an adapter file records about its fitting (metadata ``training``)."""
    tail = history[-len(problem.windows) :]
    final = {name: float(np.mean([r[name] for r in tail])) for name in ("loss", *TERMS) if tail and name in tail[0]}
    adaptation, layout = problem.adaptation, problem.layout
    return {
        "method": "raytun3r online adaptation" if problem.supervision is None else "raytun3r supervised adaptation",
        "supervision": problem.supervision or {"kind": "self-supervised"},
        "steps": steps_done,
        "requested_steps": config.steps,
        "resumed_from": start,
        "interrupted": interrupted,
        "final_losses": final,
        "final_losses_over_steps": len(tail),
        "segment": {**problem.segment, "windows": [list(w.frames) for w in adaptation.windows], "skipped_static": adaptation.skipped_static},
        "input": layout.record(),
        "adaptation_set": adaptation.cache_key,
        "config": config.to_dict(),
        "wall_time_s": round(seconds, 3),
    }
