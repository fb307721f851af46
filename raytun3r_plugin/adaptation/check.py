"""A check a user can read after a fit: reprojection error on frames the fit did not see.

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

from raytun3r_plugin.adaptation.config import AdaptConfig
from raytun3r_plugin.adaptation.losses import LossWeights
from raytun3r_plugin.adaptation.problem import prepare_problem
from raytun3r_plugin.adaptation.step import objective_value
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.errors import InputError

if TYPE_CHECKING:
    from torch import nn

    from raytun3r_plugin.cameras.base import Camera

__all__ = ["MIN_SEGMENT_FOR_CHECK", "check_frame_count", "held_out_reprojection"]

#: A segment shorter than this keeps every frame for the fit: ``--check-frames auto`` is then 0.
MIN_SEGMENT_FOR_CHECK = 15


def check_frame_count(frames: int, asked: str | int = "auto") -> int:
    """How many trailing frames of a ``frames``-frame segment to keep out of the fit.

    ``"auto"``: a fifth of the segment (at least 3) when it has at least
    :data:`MIN_SEGMENT_FOR_CHECK` frames, else 0. An integer is taken as given, but must leave
    at least 3 frames to fit on and be 0 or at least 3 (a window of 3 frames is scored).
    """
    if asked == "auto":
        return max(3, frames // 5) if frames >= MIN_SEGMENT_FOR_CHECK else 0
    try:
        count = int(asked)
    except (TypeError, ValueError):
        raise InputError(f"--check-frames must be 'auto' or an integer, got {asked!r}") from None
    if count != 0 and count < 3:
        raise InputError(f"--check-frames {count}: 0, or at least 3 frames (one window)")
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
) -> dict[str, Any]:
    """Mean match reprojection error on ``frames`` with the zero adapter and with ``adapter``.

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
    zero = Adapter.for_model(model, adapter.camera, components=adapter.components)
    before = objective_value(model, zero, problem, scoring)
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
