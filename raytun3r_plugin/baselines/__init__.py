"""Baselines the paper compares raytun3r with, on the same frozen backbones.

- :mod:`raytun3r_plugin.baselines.lora`: LoRA on the fused ``attn.qkv`` of the backbone's own
  transformer blocks (declared per family as ``BackboneSpec.transformer_blocks``), reversible
  like :func:`raytun3r_plugin.apply` and saved in PEFT's layout.
- :mod:`raytun3r_plugin.baselines.calibration_tokens`: learned tokens inserted before every
  block (VPT-deep), where a family declares ``BackboneSpec.prompt_target`` (DA3, VGGT, Pi3,
  Pi3X).
- :mod:`raytun3r_plugin.baselines.multi_ph`: Multi-PH, five virtual pinhole views (Center-PH's
  plus four tilted ones) through the unpatched model, depth and pose fused back to the fisheye.

The first two are fitted with ``adapt(..., tune=weights)``: the objective, windows, optimiser
and steps of raytun3r's own fit, with the adapter's tables held at zero.
"""

from raytun3r_plugin.baselines.calibration_tokens import (
    CalibrationTokens,
    TokenHandle,
    inject_calibration_tokens,
)
from raytun3r_plugin.baselines.lora import LoraHandle, LoraWeights, inject_lora, lora_targets
from raytun3r_plugin.baselines.multi_ph import (
    MultiPHPrediction,
    PinholeView,
    chain_relative_poses,
    choose_tilt,
    chordal_mean,
    fuse_depth,
    fuse_relative_poses,
    multi_pinhole_views,
    predict_multi_ph,
    resample_to_view,
    view_coverage,
    view_depth_to_fisheye,
    view_lookup,
    view_rotation,
    virtual_pinhole,
)

__all__ = [
    "CalibrationTokens",
    "LoraHandle",
    "LoraWeights",
    "MultiPHPrediction",
    "PinholeView",
    "TokenHandle",
    "chain_relative_poses",
    "choose_tilt",
    "chordal_mean",
    "fuse_depth",
    "fuse_relative_poses",
    "inject_calibration_tokens",
    "inject_lora",
    "lora_targets",
    "multi_pinhole_views",
    "predict_multi_ph",
    "resample_to_view",
    "view_coverage",
    "view_depth_to_fisheye",
    "view_lookup",
    "view_rotation",
    "virtual_pinhole",
]
