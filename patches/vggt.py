"""VGGT (``facebookresearch/vggt`` at 44b3afb; not on PyPI, used from a source checkout).

Hook map (docs/backbones.md), all patched per instance on the ``VGGT`` model:

* PE: ``aggregator.patch_embed.interpolate_pos_encoding(x, w, h)`` of the DINOv2 ViT-L/14-reg
  that VGGT uses as its patch embedding (``w`` is the image height; row 0 of the table is the
  class slot; the 4 register tokens are inserted after the PE is added, so they get none);
* RoPE: one ``RotaryPositionEmbedding2D`` instance, ``aggregator.rope``, serves all frame and
  global blocks. ``Aggregator.forward`` assembles the positions inline (the position getter's
  (y, x) grid, +1, then 5 special tokens at (0, 0)) and hands them to ``rope.forward(tokens,
  positions)``. The replacement of ``rope.forward`` identifies every patch token by its own
  upstream integer position (y + 1, x + 1), displaces it by the adapter's radial RoPE table, and
  evaluates cos/sin at the resulting float position; special tokens, at (0, 0), are untouched.
  This covers frame blocks ((B*S, P, 2) positions) and global blocks ((B, S*P, 2)) alike, with
  no change to ``Aggregator.forward`` or to the position getter (see :func:`grid_position_rope`);
* patch tokenisation: ``aggregator.patch_embed.patch_embed.forward(x)`` (inside the ViT, so the
  border-token replacement happens after patch embedding and before the PE is added);
* prediction grid: ``depth_head._apply_pos_embed(x, W, H, ratio)`` and
  ``point_head._apply_pos_embed(...)`` (``DPTHead``; same contract as DA3's ``_add_pos_embed``,
  the sinusoid comes from ``vggt.heads.dpt_head.position_grid_to_embed``).

Not patched: the track head's own sin-cos embedding of query points (a fifth, track-only
positional hook) and the pinhole intrinsics decoded from the FoV part of ``pose_enc``.
"""

from __future__ import annotations

import torch
from torch import nn

from raytun3r_plugin import hooks
from raytun3r_plugin.errors import (
    InputError,
    MissingDependencyError,
    UnsupportedUpstreamError,
    WeightsError,
)
from raytun3r_plugin.prediction import Prediction, as_batched_images, to_homogeneous
from raytun3r_plugin.registry import (
    BackboneInfo,
    BackboneSpec,
    PatchTarget,
    PromptTarget,
    UpstreamVersion,
    register,
)
from raytun3r_plugin.weights import StateSignature, count_blocks, load_into, read_checkpoint

FAMILY = "vggt"
UPSTREAM_MODULE = "vggt"
UPSTREAM_COMMIT = "44b3afbd1869d8bde4894dd8ea1e293112dd5eba"
UPSTREAM = UpstreamVersion(
    source="facebookresearch/vggt", version=UPSTREAM_COMMIT, module=UPSTREAM_MODULE
)
#: One ``RotaryPositionEmbedding2D`` serves every frame and global block.
ROPE_CLASSES = ("RotaryPositionEmbedding2D",)
#: ``RotaryPositionEmbedding2D.__init__(frequency)`` stores the base as ``base_frequency``.
ROPE_BASE_ATTRIBUTE = "base_frequency"

# (embed_dim, aggregator depth) -> name; VGGT-1B is the only published configuration.
_KNOWN = {(1024, 24): "vggt-1b"}
_INSTALL_HINT = (
    "VGGT is not on PyPI: clone the facebookresearch/vggt repository from GitHub and run "
    "'pip install -e .' in it (or put the checkout on PYTHONPATH; it also needs huggingface_hub)"
)
# ---------------------------------------------------------------------------------------------
# Spec
# ---------------------------------------------------------------------------------------------


def recognise(model: nn.Module) -> nn.Module | None:
    if type(model).__name__ == "VGGT" and type(model).__module__.startswith(UPSTREAM_MODULE):
        return model
    return None


def _vit(root: nn.Module) -> nn.Module:
    vit = getattr(getattr(root, "aggregator", None), "patch_embed", None)
    if vit is None or not isinstance(getattr(vit, "pos_embed", None), torch.Tensor):
        found = f"{type(vit).__module__}.{type(vit).__qualname__}" if vit is not None else "nothing"
        raise UnsupportedUpstreamError(
            f"vggt: expected a DINOv2 ViT with an absolute PE table at 'aggregator.patch_embed', found {found} "
            f"(the 'conv' patch embedding variant is not supported; the vggt patch was checked against {UPSTREAM})"
        )
    return vit


def describe(root: nn.Module) -> BackboneInfo:
    vit = _vit(root)
    aggregator = root.aggregator
    depth = len(aggregator.frame_blocks)
    heads = [getattr(root, name, None) for name in ("depth_head", "point_head")]
    name = (
        getattr(root, "raytun3r_name", None)
        or _KNOWN.get((vit.embed_dim, depth))
        or f"vggt-custom-e{vit.embed_dim}-d{depth}"
    )
    return BackboneInfo(
        name=name,
        embed_dim=vit.embed_dim,
        patch_size=vit.patch_size,
        has_rope=getattr(aggregator, "rope", None) is not None,
        pos_embed=vit.pos_embed,
        has_grid=any(bool(getattr(head, "pos_embed", False)) for head in heads if head is not None),
    )


ROPE_OWNERS = ("aggregator.rope",)

TARGETS = (
    PatchTarget(
        name="pe_interpolation",
        hook="pe",
        owners=("aggregator.patch_embed",),
        attribute="interpolate_pos_encoding",
        signature=("x", "w", "h"),
        owner_classes=("DinoVisionTransformer",),
        build=hooks.pe_interpolation,
    ),
    PatchTarget(
        name="rope",
        hook="rope",
        owners=ROPE_OWNERS,
        attribute="forward",
        signature=("tokens", "positions"),
        owner_classes=("RotaryPositionEmbedding2D",),
        build=hooks.grid_position_rope,
        optional=True,  # Aggregator(rope_freq=0) has no RoPE
    ),
    PatchTarget(
        name="patch_embedding",
        hook="patch_embed",
        owners=("aggregator.patch_embed.patch_embed",),
        attribute="forward",
        signature=("x",),
        owner_classes=("PatchEmbed",),
        build=hooks.patch_embedding,
    ),
    PatchTarget(
        name="prediction_grid",
        hook="grid",
        owners=("depth_head", "point_head"),
        attribute="_apply_pos_embed",
        signature=("x", "W", "H", "ratio"),
        owner_classes=("DPTHead",),
        build=hooks.uv_grid_embedding,
        optional=True,  # VGGT(enable_depth=False / enable_point=False)
    ),
)


def check(root: nn.Module) -> None:
    _vit(root)


def _pose_decoder():
    try:
        from vggt.utils.pose_enc import pose_encoding_to_extri_intri
    except ImportError as error:
        raise MissingDependencyError(
            f"vggt.utils.pose_enc is not importable ({error}); {_INSTALL_HINT}"
        ) from error
    return pose_encoding_to_extri_intri


def predict(root: nn.Module, images: torch.Tensor, **kwargs) -> Prediction:
    """Run VGGT on images in [0, 1] (it normalises them itself).

    ``pose_enc`` is decoded with upstream's ``pose_encoding_to_extri_intri`` into cam_from_world
    (B, S, 4, 4) (OpenCV axes, world = first camera); depth (B, S, H, W) is VGGT's depth channel
    and the confidence its ``depth_conf``. ``extras`` holds upstream's pinhole ``intrinsics``
    (principal point at (W/2, H/2) as upstream writes it), ``world_points`` and
    ``world_points_conf`` when the point head is enabled.
    """
    images = as_batched_images(images, root.aggregator.patch_size)
    output = root(images, **kwargs)
    if "pose_enc" not in output:
        raise InputError("this VGGT has no camera head (enable_camera=False): it predicts no pose")
    if "depth" not in output:
        raise InputError("this VGGT has no depth head (enable_depth=False): it predicts no depth")
    extrinsics, intrinsics = _pose_decoder()(output["pose_enc"], images.shape[-2:])
    extras = {"intrinsics": intrinsics}
    for key in ("world_points", "world_points_conf"):
        if key in output:
            extras[key] = output[key]
    return Prediction(
        depth=output["depth"][..., 0],
        cam_from_world=to_homogeneous(extrinsics),
        confidence=output.get("depth_conf"),
        extras=extras,
    )


def build_network() -> nn.Module:
    """A randomly initialised ``VGGT()`` (VGGT-1B) from the user's installed upstream package."""
    try:
        from vggt.models.vggt import VGGT
    except ImportError as error:
        raise MissingDependencyError(
            f"VGGT is not importable ({error}); {_INSTALL_HINT}"
        ) from error
    return VGGT()


def load_weights(model: nn.Module, path) -> nn.Module:
    """Load a VGGT checkpoint strictly: a file, a folder holding one, or a read ``Checkpoint``.

    Official files (``model.safetensors`` / ``model.pt``) have unprefixed keys; a training
    checkpoint (``{"model": ..., "optimizer": ...}``, ``module.`` / ``_orig_mod.``) is unwrapped.
    """
    checkpoint = read_checkpoint(path)
    return load_into(model, checkpoint.state, checkpoint.source)


#: The official size (upstream ``VGGT()`` fixes everything but the embed dim).
SIZE_NAMES = ("vggt-1b",)
_PE_KEY = "aggregator.patch_embed.pos_embed"


def identify(state: dict[str, torch.Tensor]) -> StateSignature | None:
    """A VGGT state dict (its aggregator's DINOv2 PE table and frame/global blocks), else ``None``.

    VGGT has one official size, so the name is always ``vggt-1b``; a file of another size fails
    the strict load, which lists the tensors whose shapes differ.
    """
    pe = state.get(_PE_KEY)
    if pe is None or "aggregator.camera_token" not in state:
        return None
    depth = count_blocks(state, "aggregator.frame_blocks.")
    detail = f"embed dim {int(pe.shape[-1])}, {depth} aggregator blocks"
    return StateSignature(FAMILY, SIZE_NAMES, detail, tuple(pe.shape))


def _build_vggt_1b(path=None) -> nn.Module:
    if path is None:
        raise WeightsError(
            "vggt-1b needs a local weight file (.safetensors or .pt); raytun3r never downloads"
        )
    checkpoint = read_checkpoint(path)  # before the (slow, 5 GB) build: a bad path fails at once
    model = load_weights(build_network(), checkpoint)
    model.raytun3r_name = "vggt-1b"
    return model


_build_vggt_1b.takes_checkpoint = True  # load_backbone passes the Checkpoint it has read


#: Calibration tokens: one token set per aggregator block (24 frame, then 24 global blocks at
#: full size), inserted after the camera token and the 4 register tokens (``patch_start_idx``).
#: The two runners take B, S, P; each runs ``aa_block_size`` blocks, which must be 1 (upstream's
#: value) for one token set per block. The DINO patch-embedding ViT is not covered.
PROMPT_TARGET = PromptTarget(
    owner="aggregator",
    attribute="_process_frame_attention",
    signature=("tokens", "B", "S", "P", "C", "frame_idx", "pos"),
    blocks="aggregator.frame_blocks",
    insert_at=5,
    select="frame_idx",
    tokens_argument="tokens",
    sizes=("B", "S", "P"),
    requires=(("aggregator.aa_block_size", 1),),
    more=(
        PromptTarget(
            owner="aggregator",
            attribute="_process_global_attention",
            signature=("tokens", "B", "S", "P", "C", "global_idx", "pos"),
            blocks="aggregator.global_blocks",
            insert_at=5,
            select="global_idx",
            tokens_argument="tokens",
            sizes=("B", "S", "P"),
        ),
    ),
)

SPEC = register(
    BackboneSpec(
        family=FAMILY,
        upstream=UPSTREAM,
        recognise=recognise,
        describe=describe,
        targets=TARGETS,
        predict=predict,
        builders={"vggt-1b": _build_vggt_1b},
        rope_classes=ROPE_CLASSES,
        rope_base_attribute=ROPE_BASE_ATTRIBUTE,
        transformer_blocks=(
            "aggregator.patch_embed.blocks",
            "aggregator.frame_blocks",
            "aggregator.global_blocks",
        ),
        prompt_target=PROMPT_TARGET,
        check=check,
        # vggt.utils.load_fn.load_and_preprocess_images makes the width 518.
        input_size=518,
    )
)
