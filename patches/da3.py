"""Depth Anything 3 (PyPI ``depth-anything-3`` 0.1.1 = GitHub main at 2c21ea8).

Hook map (docs/backbones.md), all patched per instance on the ``DepthAnything3Net``:

* PE: ``backbone.pretrained.interpolate_pos_encoding(x, w, h)`` (``w`` is the image height);
* RoPE: ``backbone.pretrained._prepare_rope(B, S, H, W, device)`` gives the frame blocks the
  (y+1, x+1) grid and the global blocks (1, 1) everywhere; only the former carries image position,
  so only it is displaced. The shared ``RotaryPositionEmbedding2D.forward`` is replaced by the
  continuous-angle version;
* patch tokenisation: ``backbone.pretrained.patch_embed.forward(x)``;
* prediction grid: ``head._add_pos_embed(x, W, H, ratio)`` (DualDPT; also DPT / GSDPT).

The nested model (``NestedDepthAnything3Net``: an any-view ``da3`` and a metric ``da3_metric``
network) is a second spec, ``da3nested``, whose two branches are each patched as a DA3 net; the
adapter goes to the ``da3`` branch only (docs/backbones.md, "The nested model").
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import torch

# The family's weight-file hooks, which raytun3r_plugin/weights.py looks up on this module, and
# its builders: they live in da3_networks (building a network, not patching it).
from raytun3r_plugin.patches.da3_networks import FAMILY, KNOWN_CONFIGS, _builders
from raytun3r_plugin.patches.da3_networks import SIZE_NAMES as SIZE_NAMES
from raytun3r_plugin.patches.da3_networks import build_network as build_network
from raytun3r_plugin.patches.da3_networks import (
    build_tiny_nested_network as build_tiny_nested_network,
)
from raytun3r_plugin.patches.da3_networks import build_tiny_network as build_tiny_network
from raytun3r_plugin.patches.da3_networks import canonical_name as canonical_name
from raytun3r_plugin.patches.da3_networks import config_name as config_name
from raytun3r_plugin.patches.da3_networks import identify as identify
from raytun3r_plugin.patches.da3_networks import load_weights as load_weights
from raytun3r_plugin.patches.da3_networks import require_modules as require_modules
from torch import nn

from raytun3r_plugin import hooks
from raytun3r_plugin.errors import (
    InputError,
    UnsupportedUpstreamError,
)
from raytun3r_plugin.prediction import (
    Prediction,
    as_batched_images,
    imagenet_normalise,
    to_homogeneous,
)
from raytun3r_plugin.registry import (
    BackboneInfo,
    BackboneSpec,
    PatchTarget,
    PromptTarget,
    UpstreamVersion,
    register,
)

UPSTREAM_MODULE = "depth_anything_3"
UPSTREAM = UpstreamVersion(
    source="depth-anything-3",
    version="0.1.1",
    module=UPSTREAM_MODULE,
    note="GitHub ByteDance-Seed/Depth-Anything-3 2c21ea8",
)
#: RoPE classes of the ViT (one instance, shared by every block from ``rope_start``).
ROPE_CLASSES = ("RotaryPositionEmbedding2D",)
#: ``RotaryPositionEmbedding2D.__init__(frequency)`` stores the base as ``base_frequency``.
ROPE_BASE_ATTRIBUTE = "base_frequency"
NESTED_FAMILY = "da3nested"
#: Upstream's assertion when the nested model's metric alignment has no scene to align on
#: (``NestedDepthAnything3Net.forward``); :func:`predict_nested` turns it into an InputError.
NESTED_SKY_ASSERTION = "Insufficient non-sky pixels for alignment"
#: The nested model's patch roots: (attribute, family); the first is the main (adapter) branch.
NESTED_BRANCHES = (("da3", FAMILY), ("da3_metric", FAMILY))


def recognise(model: nn.Module) -> nn.Module | None:
    def is_net(module) -> bool:
        return type(module).__name__ == "DepthAnything3Net" and type(module).__module__.startswith(
            UPSTREAM_MODULE
        )

    if is_net(model):
        return model
    inner = getattr(model, "model", None)  # the depth_anything_3.api.DepthAnything3 wrapper
    if type(model).__module__.startswith(UPSTREAM_MODULE) and inner is not None and is_net(inner):
        return inner
    return None


def recognise_nested(model: nn.Module) -> nn.Module | None:
    """The ``NestedDepthAnything3Net``, bare or inside the ``DepthAnything3`` API wrapper."""

    def is_nested(module) -> bool:
        return type(module).__name__ == "NestedDepthAnything3Net" and type(
            module
        ).__module__.startswith(UPSTREAM_MODULE)

    if is_nested(model):
        return model
    inner = getattr(model, "model", None)
    if (
        type(model).__module__.startswith(UPSTREAM_MODULE)
        and inner is not None
        and is_nested(inner)
    ):
        return inner
    return None


def describe_nested(root: nn.Module) -> BackboneInfo:
    """The nested model as the adapter sees it: exactly its main (``da3``) network.

    So an adapter fitted on ``model.da3`` (whose forward is differentiable; upstream's nested
    forward scales the depth in place) is an adapter of the nested model, and the other way round.
    """
    return describe(root.da3)


def describe(root: nn.Module) -> BackboneInfo:
    vit = getattr(getattr(root, "backbone", None), "pretrained", None)
    if vit is None or not isinstance(getattr(vit, "pos_embed", None), torch.Tensor):
        found = f"{type(vit).__module__}.{type(vit).__qualname__}" if vit is not None else "nothing"
        raise UnsupportedUpstreamError(
            f"da3: expected a DinoVisionTransformer with an absolute PE table at 'backbone.pretrained', found {found} "
            f"(the da3 patch was checked against {UPSTREAM})"
        )
    has_rope = getattr(vit, "rope", None) is not None
    key = (vit.embed_dim, len(vit.blocks), has_rope)
    name = (
        getattr(root, "raytun3r_name", None)
        or KNOWN_CONFIGS.get(key)
        or f"da3-custom-e{vit.embed_dim}-d{len(vit.blocks)}"
    )
    return BackboneInfo(
        name=name,
        embed_dim=vit.embed_dim,
        patch_size=vit.patch_size,
        has_rope=has_rope,
        pos_embed=vit.pos_embed,
        has_grid=bool(getattr(root.head, "pos_embed", False)),
    )


def _prepare_rope(owner, state):
    """Displace the frame-attention positions; the global blocks' constant (1, 1) stays."""
    patch_start = owner.patch_start_idx

    def prepare_rope(original, B, S, H, W, device):
        pos, pos_nodiff = original(B, S, H, W, device)
        if pos is None or not state.uses("rope"):
            return pos, pos_nodiff
        return hooks.displaced_rope_positions(pos, patch_start, state, H, W), pos_nodiff

    return prepare_rope


#: ``depth_anything_3.model.dinov2.vision_transformer``: from this many views on, upstream moves
#: a reference view to the front of the tokens (not of the RoPE positions); read at call time.
REFERENCE_THRESHOLD = "THRESH_FOR_REF_SELECTION"


def _reference_view(owner, state):
    """Keep a rig's per-view RoPE positions with their views through DA3's view reordering.

    From ``THRESH_FOR_REF_SELECTION`` views on, ``_get_intermediate_layers_not_chunked`` picks a
    reference view (``ref_view_strategy``, default ``"saddle_balanced"``) and moves its tokens
    to the front, but leaves the frame blocks' RoPE positions in input order: harmless when
    every view has the same positions, wrong for a rig whose cameras displace them differently.
    Only then (a rig, RoPE tables whose displacements differ between views) the reference is
    the first view (``"first"``), which keeps tokens and positions together; docs/rigs.md.
    """
    module = sys.modules.get(type(owner).__module__)

    def run(original, x, n=1, export_feat_layers=[], **kwargs):  # noqa: B006 (upstream's default)
        threshold = getattr(module, REFERENCE_THRESHOLD, 3)
        if (
            state.rig
            and state.uses("rope")
            and x.ndim == 5
            and x.shape[1] >= threshold
            and kwargs.get("cam_token") is None
            and kwargs.get("ref_view_strategy", "saddle_balanced") != "first"
        ):
            displacement = state.rope_displacement_views(
                x.shape[-2], x.shape[-1], x.device, torch.float32
            )
            if not bool((displacement == displacement[:1]).all()):
                kwargs["ref_view_strategy"] = "first"
        return original(x, n, export_feat_layers, **kwargs)

    return run


TARGETS = (
    PatchTarget(
        name="pe_interpolation",
        hook="pe",
        owners=("backbone.pretrained",),
        attribute="interpolate_pos_encoding",
        signature=("x", "w", "h"),
        owner_classes=("DinoVisionTransformer",),
        build=hooks.pe_interpolation,
    ),
    PatchTarget(
        name="rope_positions",
        hook="rope",
        owners=("backbone.pretrained",),
        attribute="_prepare_rope",
        signature=("B", "S", "H", "W", "device"),
        owner_classes=("DinoVisionTransformer",),
        build=_prepare_rope,
    ),
    PatchTarget(
        name="rope_reference_view",
        hook="rope",
        owners=("backbone.pretrained",),
        attribute="_get_intermediate_layers_not_chunked",
        signature=("x", "n", "export_feat_layers", "kwargs"),
        owner_classes=("DinoVisionTransformer",),
        build=_reference_view,
    ),
    PatchTarget(
        name="rope_angles",
        hook="rope",
        owners=("backbone.pretrained.rope",),
        attribute="forward",
        signature=("tokens", "positions"),
        owner_classes=("RotaryPositionEmbedding2D",),
        build=hooks.continuous_rope,
        optional=True,  # mono / metric models have no RoPE
    ),
    PatchTarget(
        name="patch_embedding",
        hook="patch_embed",
        owners=("backbone.pretrained.patch_embed",),
        attribute="forward",
        signature=("x",),
        owner_classes=("PatchEmbed",),
        build=hooks.patch_embedding,
    ),
    PatchTarget(
        name="prediction_grid",
        hook="grid",
        owners=("head",),
        attribute="_add_pos_embed",
        signature=("x", "W", "H", "ratio"),
        owner_classes=("DualDPT", "DPT"),
        build=hooks.uv_grid_embedding,
    ),
)


def predict(root: nn.Module, images: torch.Tensor, **kwargs) -> Prediction:
    """Run a DA3 network on images in [0, 1]; DA3 itself wants ImageNet-normalised input."""
    images = as_batched_images(images, root.backbone.pretrained.patch_size)
    return _prediction(root(imagenet_normalise(images), **kwargs))


def predict_nested(root: nn.Module, images: torch.Tensor, **kwargs) -> Prediction:
    """Run the nested model on images in [0, 1]: the ``da3`` depth and pose in metres.

    Upstream's own forward does the metric alignment (the ``da3_metric`` depth scaled by the
    predicted focal length / 300, a least-squares scale of the ``da3`` depth and translation
    onto it, sky set to far); ``extras["metric_scale"]`` is that scale (a 0-d tensor).
    """
    images = as_batched_images(images, root.da3.backbone.pretrained.patch_size)
    try:
        output = root(imagenet_normalise(images), **kwargs)
    except AssertionError as error:
        if NESTED_SKY_ASSERTION not in str(error):
            raise
        raise InputError(
            "the nested DA3 model's metric alignment found (almost) only sky in these images "
            f"(upstream needs more than 10 non-sky pixels: {error}); give views that see the scene"
        ) from error
    prediction = _prediction(output)
    if "scale_factor" in output:
        prediction.extras["metric_scale"] = torch.tensor(float(output["scale_factor"]))
    return prediction


def _prediction(output) -> Prediction:
    extras = {key: output[key] for key in ("intrinsics",) if key in output}
    if "extrinsics" not in output:
        raise InputError("this DA3 network has no camera decoder: it predicts no pose")
    return Prediction(
        depth=output["depth"],
        cam_from_world=to_homogeneous(output["extrinsics"]),
        confidence=output.get("depth_conf"),
        extras=extras,
    )


@contextmanager
def quiet_info() -> Iterator[None]:
    """DA3 prints an INFO line on every forward with 3+ views (hundreds per adaptation run):
    show its warnings only, unless the user chose a level with ``DA3_LOG_LEVEL``; restored on
    exit."""
    try:
        from depth_anything_3.utils.logger import logger
    except ImportError:
        logger = None
    if logger is None or "DA3_LOG_LEVEL" in os.environ:
        yield
        return
    level, logger.level = logger.level, min(logger.level, 1)  # 1 = WARN in DA3's scale
    try:
        yield
    finally:
        logger.level = level


#: The settings the DA3 family's fits change from a recipe's (``BackboneSpec.recipe_changes``):
#: under the ``default`` recipe, Adam's step is 1e-2 where the pinhole-view teacher is on (the
#: lenses it covers, about 160 degrees and wider) and the recipe's 3e-3 where it is off. Measured
#: on both DA3-architecture built-in networks (docs/decisions.md, "The step size where the teacher
#: is on" and its next round): on held-out seeds the wide-lens AbsRel gap closed rose from 0.592
#: to 0.663 (v3, 30 sequences) and from 0.440 to 0.530 (v2, 20), and on 20 further seeds from
#: 0.507 to 0.569 (v3, rotation within 0.1 degrees of the recipe's in every wide-lens cell) and
#: from 0.266 to 0.339 (v2), no sequence more than 2 % worse than without an adapter.
#: Narrow-lens fits are the recipe's, step for step. Not the VGGT family's: on the small
#: VGGT-architecture network a step of 1e-2 made outdoor depth worse.
RECIPE_CHANGES = {"default": {"lr": 1e-2, "lr_without_teacher": 3e-3}}

#: The nested model: both networks patched by one ``apply`` as DA3 nets (``branches``). A
#: composite of the da3 family: its builders are da3's (``load_backbone("da3nested-giant-large",
#: path)``), and it offers no LoRA / calibration-token baseline (those tune one network).
NESTED_SPEC = BackboneSpec(
    family=NESTED_FAMILY,
    upstream=UPSTREAM,
    recognise=recognise_nested,
    describe=describe_nested,
    targets=(),
    predict=predict_nested,
    branches=NESTED_BRANCHES,
    recipe_changes=RECIPE_CHANGES,
)

SPEC = register(
    BackboneSpec(
        family=FAMILY,
        upstream=UPSTREAM,
        recognise=recognise,
        describe=describe,
        targets=TARGETS,
        predict=predict,
        builders=_builders(),
        rope_classes=ROPE_CLASSES,
        rope_base_attribute=ROPE_BASE_ATTRIBUTE,
        transformer_blocks=("backbone.pretrained.blocks",),
        prompt_target=PromptTarget(
            owner="backbone.pretrained",
            attribute="process_attention",
            signature=("x", "block", "attn_type", "pos", "attn_mask"),
            blocks="backbone.pretrained.blocks",
            insert_at=1,  # after the cls/camera slot
        ),
        quiet=quiet_info,
        composites=(NESTED_SPEC,),
        recipe_changes=RECIPE_CHANGES,
    )
)
