"""What each :class:`~raytun3r_plugin.adaptation.config.AdaptConfig` setting may be: the named
choices of the enumerated fields and the check every config passes when it is built.

Kept apart from the config so that the settings' vocabulary and their bounds sit in one table
(``AdaptConfig`` re-exports the vocabulary under its own module's names).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from raytun3r_plugin.errors import InputError
from raytun3r_plugin.pinhole_views import VIEW_NAMES as TEACHER_VIEWS

__all__ = [
    "MODEL_REPROJECTION_SOURCES",
    "PE_REGULARISERS",
    "POSE_SOURCES",
    "POSE_TERM_SOURCES",
    "POSE_WINDOWS",
    "SCALES",
    "TARGET_REPROJECTION_SOURCES",
    "TEACHER_VIEWS",
    "TERMS",
    "check_settings",
    "parse_check_frames",
]

POSE_SOURCES = ("model", "targets", "hybrid", "both")
#: What each pose source does: reproject through the network's own relative pose, reproject
#: through the MAGSAC++ targets (scaled per pair), and keep the pose term on the network's pose.
MODEL_REPROJECTION_SOURCES = ("model", "both")
TARGET_REPROJECTION_SOURCES = ("targets", "hybrid", "both")
POSE_TERM_SOURCES = ("model", "hybrid", "both")
#: Which windows the pose term scores: every window, or only those whose matches the parallax
#: gate leaves out of the reprojection term (``AdaptConfig.pose_windows``).
POSE_WINDOWS = ("all", "unreprojected")
SCALES = ("pixel", "least_squares", "photometric")
PE_REGULARISERS = ("relative", "absolute")
TERMS = ("reproj", "smooth", "l2", "tv", "pose", "depth", "photo", "teacher")


def check_settings(config: Mapping[str, Any]) -> str | int:
    """Refuse a value no fit can run with; return the ``check_frames`` setting parsed (``"auto"``
    or a count: a command line gives ``"5"``).

    Args:
        config: an ``AdaptConfig``'s fields by name (``vars(config)``); read, not changed.

    Raises:
        InputError: the first setting out of bounds, named with what it expects; or a loss
            weight that is negative or not finite.
    """
    try:
        check_frames = parse_check_frames(config["check_frames"])  # "5" from a command line
        check_frames_ok = True
    except InputError:
        check_frames, check_frames_ok = config["check_frames"], False
    checks = _within_bounds(config, check_frames, check_frames_ok)
    expected = _expected(config)
    for name, ok in checks:
        if not ok:
            hint = f" ({expected[name]})" if name in expected else ""
            raise InputError(f"AdaptConfig.{name} = {config[name]!r} is not allowed{hint}")
    for term, weight in config["weights"].as_dict().items():
        # A negative weight would reward the term it weighs; NaN would poison every step.
        if not (isinstance(weight, (int, float)) and math.isfinite(weight) and weight >= 0):
            raise InputError(
                f"AdaptConfig.weights.{term} = {weight!r} is not allowed "
                "(expected a finite number >= 0)"
            )
    return check_frames


def _within_bounds(
    config: Mapping[str, Any], check_frames: str | int, check_frames_ok: bool
) -> tuple[tuple[str, bool], ...]:
    """Each bounded setting's name and whether ``config``'s value is inside its bounds."""
    return (
        ("steps", config["steps"] >= 0),
        ("lr", config["lr"] is None or _step_size_ok(config["lr"])),
        (
            "lr_without_teacher",
            config["lr_without_teacher"] is None or _step_size_ok(config["lr_without_teacher"]),
        ),
        ("clip", config["clip"] is None or config["clip"] > 0),
        ("input_size", config["input_size"] is None or config["input_size"] >= 1),
        ("n_windows", config["n_windows"] >= 1),
        ("window_size", config["window_size"] >= 2),
        ("stride", config["stride"] >= 1),
        ("max_matches", config["max_matches"] >= 0),
        ("checkpoint_every", config["checkpoint_every"] >= 0),
        ("pose_source", config["pose_source"] in POSE_SOURCES),
        ("depth_convention", config["depth_convention"] in ("range", "z")),
        ("scale", config["scale"] in SCALES),
        ("robust_px", config["robust_px"] is None or config["robust_px"] > 0),
        ("pe_regulariser", config["pe_regulariser"] in PE_REGULARISERS),
        ("guard_every", config["guard_every"] >= 1),
        ("min_parallax_px", config["min_parallax_px"] >= 0),
        ("pose_gate", config["pose_gate"] is None or config["pose_gate"] >= 0),
        (
            "pose_windows",
            config["pose_windows"] == "all"
            or (config["pose_windows"] in POSE_WINDOWS and config["pose_source"] == "hybrid"),
        ),
        ("check_frames", check_frames_ok),
        (
            "check_veto",
            config["check_veto"] is None
            or (
                isinstance(config["check_veto"], (int, float))
                and 0 <= config["check_veto"] < 1
                and check_frames != 0
            ),
        ),
        ("refine_intrinsics", isinstance(config["refine_intrinsics"], bool)),
        ("recipe", isinstance(config["recipe"], str)),
        ("photo_sigma", math.isfinite(config["photo_sigma"]) and config["photo_sigma"] >= 0),
        ("photo_pixels", config["photo_pixels"] >= 1),
        (
            "teacher_views",
            len(config["teacher_views"]) >= 1
            and len(set(config["teacher_views"])) == len(config["teacher_views"])
            and set(config["teacher_views"]) <= set(TEACHER_VIEWS),
        ),
        ("teacher_view_weights", _view_weights_ok(config)),
        (
            "teacher_fov_deg",
            isinstance(config["teacher_fov_deg"], (int, float))
            and math.isfinite(config["teacher_fov_deg"])
            and 0 < config["teacher_fov_deg"] < 180,
        ),
        (
            "teacher_max_coverage",
            isinstance(config["teacher_max_coverage"], (int, float))
            and 0 <= config["teacher_max_coverage"] <= 1,
        ),
    )


def _expected(config: Mapping[str, Any]) -> dict[str, str]:
    """What the settings whose bounds are not obvious from their name expect."""
    return {
        "check_frames": "expected 'auto', 0, or a count of at least 3",
        "pose_windows": (
            f"expected one of {POSE_WINDOWS}; 'unreprojected' only with pose_source='hybrid'"
        ),
        "check_veto": "expected None, or a fraction in [0, 1) with check_frames set",
        "lr": "expected None (the recipe's step for the backbone), or a step size > 0",
        "lr_without_teacher": "expected None, or a step size > 0",
        "teacher_view_weights": (
            f"expected None or {{view: weight >= 0}} naming exactly the teacher views "
            f"{config['teacher_views']!r}, at least one weight > 0"
        ),
    }


def _step_size_ok(value: Any) -> bool:
    return (
        isinstance(value, (int, float))
        and not isinstance(value, bool)
        and math.isfinite(value)
        and value > 0
    )


def _view_weights_ok(config: Mapping[str, Any]) -> bool:
    weights = config["teacher_view_weights"]
    if weights is None:
        return True
    if not isinstance(weights, dict) or set(weights) != set(config["teacher_views"]):
        return False
    values = list(weights.values())
    return all(
        isinstance(w, (int, float)) and not isinstance(w, bool) and math.isfinite(w) and w >= 0
        for w in values
    ) and any(w > 0 for w in values)


def parse_check_frames(asked: Any) -> str | int:
    """``"auto"``, or the count of check frames ``asked`` names (``5`` or ``"5"``): 0, or at least
    3 (a scored window has 3 frames).

    Raises:
        InputError: anything else.
    """
    if asked == "auto":
        return "auto"
    if isinstance(asked, bool) or not isinstance(asked, (int, str)):
        raise InputError(f"--check-frames must be 'auto' or an integer, got {asked!r}")
    try:
        count = int(asked)
    except ValueError:
        raise InputError(f"--check-frames must be 'auto' or an integer, got {asked!r}") from None
    if count != 0 and count < 3:
        raise InputError(f"--check-frames {count}: 0, or at least 3 frames (one window)")
    return count
