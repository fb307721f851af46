"""A check a user can read after a fit: reprojection error on frames the fit did not see.

``AdaptConfig.check_frames`` keeps the trailing frames of the last segment out of the fit
(:func:`split_off_check`); :func:`judge_on_check` scores them after it and, with
``AdaptConfig.check_veto``, puts the starting tables back when the fit raises that error by more
than the veto (docs/decisions.md, "A held-out check that decides whether a fit is kept").

``raytun3r adapt`` keeps the last frames of the segment out of the fit (``--check-frames``) and
scores them with the zero adapter and with the fitted one: matched pixels (the fit's own
matcher), back-projected with the predicted depth, moved by the relative pose estimated from the
matches (MAGSAC++, its unit translation scaled per pair to the predicted depth) and projected
through the camera; the mean L1 distance to their matches, in pixels of the network input. It
needs no ground truth, so it is what a user can check on their own footage; lower means the
predicted depth agrees better with how the scene moves between frames (docs/recipes.md).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from raytun3r_plugin.adaptation.config import AdaptConfig
from raytun3r_plugin.adaptation.losses import LossWeights
from raytun3r_plugin.adaptation.problem import prepare_problem, split_segments
from raytun3r_plugin.adaptation.settings_check import parse_check_frames
from raytun3r_plugin.adaptation.step import objective_value
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.errors import InputError

if TYPE_CHECKING:
    from torch import nn

    from raytun3r_plugin.cameras.base import Camera

__all__ = [
    "MIN_SEGMENT_FOR_CHECK",
    "check_frame_count",
    "held_out_reprojection",
    "judge_on_check",
    "split_off_check",
]

#: A segment shorter than this keeps every frame for the fit: ``--check-frames auto`` is then 0.
MIN_SEGMENT_FOR_CHECK = 15


def check_frame_count(frames: int, asked: str | int = "auto") -> int:
    """How many trailing frames of a ``frames``-frame segment to keep out of the fit.

    ``"auto"``: a fifth of the segment (at least 3) when it has at least
    :data:`MIN_SEGMENT_FOR_CHECK` frames, else 0. An integer is taken as given, but must leave
    at least 3 frames to fit on and be 0 or at least 3 (a window of 3 frames is scored).
    """
    count = parse_check_frames(asked)
    if isinstance(count, str):  # "auto"
        return max(3, frames // 5) if frames >= MIN_SEGMENT_FOR_CHECK else 0
    if frames - count < 3:
        raise InputError(
            f"--check-frames {count} leaves {frames - count} of {frames} frames to fit on; "
            "at least 3 are needed"
        )
    return count


def held_out_reprojection(
    model: nn.Module,
    camera: Camera,
    frames: Any,
    adapter: Adapter,
    config: AdaptConfig,
    *,
    mask: Any = None,
    reference: Adapter | None = None,
) -> dict[str, Any]:
    """Mean match reprojection error on ``frames`` with the zero adapter (or ``reference``, the
    tables a fit started from) and with ``adapter``.

    Args:
        model: the (unpatched) backbone the adapter was fitted for.
        camera: camera of the native frames.
        frames: (N >= 3, H, W, 3) float RGB in [0, 1]: frames the fit did not see.
        adapter: the fitted adapter.
        config: the fit's settings (input size, matcher, components; its loss weights are not
            used: the score is the plain L1 reprojection through the MAGSAC++ poses).
        mask: the fit's scene mask, if any.

    Returns:
        ``{"frames": N, "windows": W, "zero_adapter_px": e0, "adapted_px": e1,
        "change": e1 / e0 - 1}``; the errors are None (and ``"reason"`` says why) when the
        frames hold no moving window with a usable pose.
    """
    count = len(frames)
    scoring = dataclasses.replace(
        config,
        pose_source="targets",
        scale="pixel",
        robust_px=None,
        weights=LossWeights(reproj=1.0, smooth=0.0, l2=0.0, tv=0.0, pose=0.0, depth=0.0),
        n_windows=max(1, count - 2),
        min_parallax_px=0.0,
        cache_dir=None,
        sequence_id=None,
        refine_intrinsics=False,
    )
    record: dict[str, Any] = {"frames": count, "windows": 0}
    try:
        problem = prepare_problem(camera, frames, scoring, adapter.patch_size, mask=mask)
    except InputError as error:
        return {**record, "zero_adapter_px": None, "adapted_px": None, "reason": str(error)}
    record["windows"] = len(problem.windows)
    if reference is None:
        reference = Adapter.for_model(model, adapter.camera, components=adapter.components)
    before = objective_value(model, reference, problem, scoring)
    after = objective_value(model, adapter, problem, scoring)
    if "reproj" not in before:
        return {**record, "zero_adapter_px": None, "adapted_px": None, "reason": "no scored pair"}
    e0, e1 = float(before["reproj"]), float(after["reproj"])
    return {
        **record,
        "zero_adapter_px": round(e0, 4),
        "adapted_px": round(e1, 4),
        "change": round(e1 / e0 - 1.0, 4) if e0 > 0 else None,
    }


def split_off_check(
    frames: Any, depth: Any, poses: Any, asked: str | int
) -> tuple[Any, Any, Any, Any]:
    """Keep the trailing frames of the last segment out of a fit.

    Args:
        frames: what :func:`~raytun3r_plugin.adaptation.train.adapt` takes: one segment ((N, H,
            W, 3) array or tensor, or a ``datasets.Sequence``) or a list of segments.
        depth: None, one (N, H, W) depth, or one per segment; cut like its segment.
        poses: None or (N, 4, 4) poses of one segment; cut like it.
        asked: ``AdaptConfig.check_frames`` (``"auto"`` or a count; 0: no check).

    Returns:
        ``(frames, depth, poses, check)`` to fit and to check, ``check`` an (n, H, W, 3) array
        or tensor, or None (and the inputs unchanged) when no frame is kept out.
    """
    if asked in (0, "0"):
        return frames, depth, poses, None
    parts = split_segments(frames, depth)
    segments, depths = (list(parts[0]), list(parts[1])) if parts else ([frames], [depth])
    images = getattr(segments[-1], "images", segments[-1])
    if isinstance(images, (list, tuple)):
        images = np.stack([np.asarray(image) for image in images])
    count = check_frame_count(len(images), asked)
    if not count:
        return frames, depth, poses, None
    keep = len(images) - count
    segments[-1], check = images[:keep], images[keep:]
    if depths[-1] is not None:
        depths[-1] = depths[-1][:keep]
    if poses is not None:
        poses = poses[:keep]
    if parts:
        return segments, (depths if depth is not None else None), poses, check
    return segments[0], depths[0], poses, check


def judge_on_check(
    model: nn.Module,
    camera: Camera,
    check: Any,
    adapter: Adapter,
    start: Adapter | None,
    config: AdaptConfig,
    *,
    mask: Any = None,
) -> None:
    """Score the held-out ``check`` frames with the starting tables (``start``; None: zero) and
    the fitted ones, record it in ``adapter.training_info["check"]`` and, with
    ``config.check_veto``, put the starting tables back when the fit raised the error by more than
    that fraction (``"kept"`` says which; the verdict becomes ``"not kept"``). A check that cannot
    be scored (no moving window among the frames) keeps the fit: it saw no harm. Outdoors the
    check barely moves whatever the fit does (far matches reproject alike at any depth), so it
    can veto a fit but not vouch for one (docs/decisions.md)."""
    if start is None:
        start = Adapter.for_model(model, adapter.camera, components=adapter.components)
    result = held_out_reprojection(
        model, camera, check, adapter, config, mask=mask, reference=start
    )
    info = adapter.training_info
    info["check"] = result
    if config.check_veto is None:
        return
    change = result.get("change")
    kept = change is None or change <= config.check_veto
    result["kept"], result["check_veto"] = kept, config.check_veto
    if change is None or kept:
        return
    with torch.no_grad():
        for table, original in zip(adapter.parameters(), start.parameters(), strict=True):
            table.copy_(original)
    info["verdict"] = {
        **info["verdict"],
        "status": "not kept",
        "fit_status": info["verdict"]["status"],
        "summary": (
            f"NOT KEPT: on the {result['frames']} held-out frames the fit raised the reprojection "
            f"error by {100 * change:+.1f} % (more than the {100 * config.check_veto:g} % it may), "
            "so the adapter keeps its starting tables; the fit said: " + info["verdict"]["summary"]
        ),
    }
