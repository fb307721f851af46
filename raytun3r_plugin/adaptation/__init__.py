"""Online adaptation: correspondences, relative-pose targets and adaptation windows."""

from __future__ import annotations

from raytun3r_plugin.adaptation.matchers import (
    MATCHERS,
    DISFlowMatcher,
    Matcher,
    Matches,
    SIFTMatcher,
    TorchFlowMatcher,
    get_matcher,
    register_matcher,
)
from raytun3r_plugin.adaptation.pose_targets import PoseTarget, estimate_relative_pose
from raytun3r_plugin.adaptation.windows import (
    AdaptationSet,
    Window,
    build_windows,
    prepare_adaptation_set,
)

__all__ = [
    "MATCHERS",
    "AdaptationSet",
    "DISFlowMatcher",
    "Matcher",
    "Matches",
    "PoseTarget",
    "SIFTMatcher",
    "TorchFlowMatcher",
    "Window",
    "build_windows",
    "estimate_relative_pose",
    "get_matcher",
    "prepare_adaptation_set",
    "register_matcher",
]

# Losses and training (issue 6).
from raytun3r_plugin.adaptation.checkpoint import read_loss_log  # noqa: E402
from raytun3r_plugin.adaptation.config import AdaptConfig  # noqa: E402
from raytun3r_plugin.adaptation.losses import LossWeights  # noqa: E402
from raytun3r_plugin.adaptation.problem import AdaptationProblem, prepare_problem, scene_mask  # noqa: E402
from raytun3r_plugin.adaptation.step import adaptation_step  # noqa: E402
from raytun3r_plugin.adaptation.train import adapt  # noqa: E402
from raytun3r_plugin.preprocess import InputLayout, input_layout  # noqa: E402

__all__ += [
    "AdaptConfig",
    "AdaptationProblem",
    "InputLayout",
    "LossWeights",
    "adapt",
    "adaptation_step",
    "input_layout",
    "prepare_problem",
    "read_loss_log",
    "scene_mask",
]

# Rough calibration (issue 18).
from raytun3r_plugin.adaptation.intrinsics import (  # noqa: E402
    IntrinsicsReport,
    refine_intrinsics,
)

__all__ += ["IntrinsicsReport", "refine_intrinsics"]

# Multi-camera rigs (issue 18).
from raytun3r_plugin.adaptation.rig import adapt_rig  # noqa: E402

__all__ += ["adapt_rig"]
