"""VGGT-Omega (``facebookresearch/vggt-omega`` at 39a0cb8; not on PyPI, used from a source checkout).

VGGT-Omega replaces VGGT's DINOv2 patch embedding by a DINOv3 ViT-L/16 and has **no absolute
PE table** anywhere: positions enter only through RoPE and the dense head's uv grid. So the
adapter's PE tables have nothing to act on (``BackboneInfo.pos_embed`` is None, the ``pe``
component is inert); the RoPE correction, the tokenisation and the grid apply.

Hook map (docs/backbones.md), all patched per instance on the ``VGGTOmega`` model:

* RoPE: two ``RopePositionEmbedding`` instances, ``aggregator.rope_embed`` (the frame blocks;
  ``Aggregator.forward`` calls it once per forward under ``no_grad``) and
  ``aggregator.patch_embed.rope_embed`` (the DINOv3 blocks, called once per block). Their
  ``forward(*, H, W)`` returns (sin, cos), each (h*w, D_head), from patch-centre coordinates
  normalised to [-1, 1] (``normalize_coords="max"``: one token is 2 / max(h, w)). The
  replacement displaces each patch's coordinates by the adapter's radial RoPE table (token units,
  converted to the normalised units of the instance) and evaluates upstream's formula there with
  the instance's own ``periods`` buffer. Camera, register, class and storage tokens get no RoPE
  upstream (the attention rotates only the last h*w tokens), so they are untouched;
* patch tokenisation: ``aggregator.patch_embed.patch_embed.forward(x)``, the DINOv3
  ``PatchEmbed`` (unflattened (B, h, w, D) output; the shared builder sees it flattened);
* prediction grid: ``dense_head._apply_pos_embed(x, width, height, ratio)`` (``DenseHead``; the
  sinusoid comes from ``vggt_omega.models.heads.dense_head.position_grid_to_embed``).

Not patched: the pinhole intrinsics decoded from the FoV part of ``pose_enc``; the camera and
text-alignment heads (no positional input).
"""

from __future__ import annotations

import math

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
    UpstreamVersion,
    register,
    resolve_path,
)
from raytun3r_plugin.weights import StateSignature, count_blocks, load_into, read_checkpoint

FAMILY = "vggt_omega"
UPSTREAM_MODULE = "vggt_omega"
UPSTREAM_COMMIT = "39a0cb8af88554f15ddcb5354cd52bde588fa014"
UPSTREAM = UpstreamVersion(
    source="facebookresearch/vggt-omega", version=UPSTREAM_COMMIT, module=UPSTREAM_MODULE
)
#: The aggregator's and the DINOv3 ViT's RoPE; both are targets.
ROPE_CLASSES = ("RopePositionEmbedding",)
#: ``RopePositionEmbedding(base=...)``. The angles come from its ``periods`` buffer (computed
#: from ``base`` at init, stored in the checkpoint); ``base`` is checked to exist, as for every
#: RoPE backbone, so a ``min_period``/``max_period`` configuration (``base=None``) is refused.
ROPE_BASE_ATTRIBUTE = "base"
#: Training-time coordinate augmentations of ``RopePositionEmbedding`` (random per call).
_AUGMENTATIONS = ("shift_coords", "jitter_coords", "rescale_coords")

# (embed_dim, aggregator depth) -> name; VGGT-Omega-1B is the only published size, released as
# two checkpoints (the second with the text-alignment head, trained at 256 px).
_KNOWN = {(1024, 24): "vggt-omega-1b-512"}
_KNOWN_TEXT = {(1024, 24): "vggt-omega-1b-256-text"}
_INSTALL_HINT = (
    "VGGT-Omega is not on PyPI: clone the facebookresearch/vggt-omega repository from GitHub and "
    "run 'pip install -e .' in it (or put the checkout on PYTHONPATH)"
)


# ---------------------------------------------------------------------------------------------
# Spec
# ---------------------------------------------------------------------------------------------


def recognise(model: nn.Module) -> nn.Module | None:
    if type(model).__name__ == "VGGTOmega" and type(model).__module__.startswith(UPSTREAM_MODULE):
        return model
    return None


def _aggregator(root: nn.Module) -> nn.Module:
    aggregator = getattr(root, "aggregator", None)
    vit = getattr(aggregator, "patch_embed", None)
    if vit is None or not isinstance(getattr(aggregator, "patch_size", None), int):
        found = f"{type(vit).__module__}.{type(vit).__qualname__}" if vit is not None else "nothing"
        raise UnsupportedUpstreamError(
            f"vggt_omega: expected an Aggregator with a DINOv3 ViT at 'aggregator.patch_embed' and an "
            f"integer 'aggregator.patch_size', found {found} (checked against {UPSTREAM})"
        )
    return aggregator


def describe(root: nn.Module) -> BackboneInfo:
    aggregator = _aggregator(root)
    embed_dim = int(aggregator.patch_embed.embed_dim)
    depth = len(aggregator.frame_blocks)
    text = getattr(root, "text_alignment_head", None) is not None
    known = (_KNOWN_TEXT if text else _KNOWN).get((embed_dim, depth))
    name = (
        getattr(root, "raytun3r_name", None) or known or f"vggt_omega-custom-e{embed_dim}-d{depth}"
    )
    return BackboneInfo(
        name=name,
        embed_dim=embed_dim,
        patch_size=int(aggregator.patch_size),
        has_rope=getattr(aggregator, "rope_embed", None) is not None,
        pos_embed=None,  # RoPE only: there is no absolute PE table to correct
        has_grid=getattr(root, "dense_head", None) is not None,
    )


def _normalised_rope(owner, state):
    """Wrap ``RopePositionEmbedding.forward(*, H, W)``: displaced, normalised patch coordinates.

    Upstream: centre coordinates ``(i + 0.5) / n`` (n = max(H, W), min(H, W), or H and W per
    axis for ``normalize_coords`` "max", "min", "separate"), ``c -> 2 c - 1``, angles
    ``2 pi c / periods`` for y then x, tiled twice; returns (sin, cos), each (H*W, D_head).
    Here the adapter's displacement (H*W, 2), (y, x) in token units, is added to the
    coordinates first, times 2 / n (one token in normalised units); a zero displacement leaves
    the upstream values bit-identical. The ``periods``, ``dtype`` and ``normalize_coords`` are
    the instance's own, read at call time.

    ``Aggregator.forward`` computes its RoPE under ``torch.no_grad()``; while the adapter's RoPE
    table requires gradients (fitting), the evaluation runs under ``enable_grad`` so the frame
    blocks contribute to its gradient too.
    """
    patch = state.info.patch_size

    def forward(original, *, H, W):
        if not state.uses("rope"):
            return original(H=H, W=W)
        rope = hooks.owner_of(original)  # looked up per call: the behaviour keeps no owner
        periods, dtype, mode = rope.periods, rope.dtype, rope.normalize_coords
        if mode == "max":
            scale_h = scale_w = max(H, W)
        elif mode == "min":
            scale_h = scale_w = min(H, W)
        elif mode == "separate":
            scale_h, scale_w = H, W
        else:
            return original(H=H, W=W)  # upstream raises its own error for an unknown mode
        table = state.adapter.rope["radial"]
        grad = table.requires_grad and not torch.is_inference_mode_enabled()
        with torch.set_grad_enabled(grad or torch.is_grad_enabled()):
            options = {"device": periods.device, "dtype": dtype}
            rows = torch.arange(0.5, H, **options) / scale_h
            cols = torch.arange(0.5, W, **options) / scale_w
            coords = torch.stack(torch.meshgrid(rows, cols, indexing="ij"), dim=-1).flatten(0, 1)
            coords = 2.0 * coords - 1.0
            geometry = state.geometry(H * patch, W * patch)
            displacement = state.rope_displacement(geometry, periods.device, torch.float32)
            unit = torch.tensor([2.0 / scale_h, 2.0 / scale_w], device=periods.device)
            coords = coords + (displacement * unit).to(coords.dtype)
            angles = (2 * math.pi * coords[:, :, None] / periods[None, None, :]).flatten(1, 2)
            angles = angles.tile(2)
            return (torch.sin(angles), torch.cos(angles))

    return forward


def _unflattened_patch_embedding(owner, state):
    """:func:`hooks.patch_embedding` for a ``PatchEmbed`` that returns (B, h, w, D) tokens.

    The shared behaviour sees the tokens flattened to (B, h*w, D) and the result is given back
    in the shape upstream returned (DINOv3 builds ``PatchEmbed(flatten_embedding=False)``).
    """
    shared = hooks.patch_embedding(owner, state)

    def forward(original, x):
        shapes = []

        def flattened(images):
            tokens = original(images)
            shapes.append(tokens.shape)
            return tokens.flatten(1, 2) if tokens.ndim == 4 else tokens

        tokens = shared(flattened, x)
        return tokens.reshape(shapes[-1]) if len(shapes[-1]) == 4 else tokens

    return forward


ROPE_OWNERS = ("aggregator.rope_embed", "aggregator.patch_embed.rope_embed")

TARGETS = (
    PatchTarget(
        name="rope",
        hook="rope",
        owners=ROPE_OWNERS,
        attribute="forward",
        signature=("H", "W"),
        owner_classes=("RopePositionEmbedding",),
        build=_normalised_rope,
        per_view=False,  # one (sin, cos) table for every frame upstream
    ),
    PatchTarget(
        name="patch_embedding",
        hook="patch_embed",
        owners=("aggregator.patch_embed.patch_embed",),
        attribute="forward",
        signature=("x",),
        owner_classes=("PatchEmbed",),
        build=_unflattened_patch_embedding,
    ),
    PatchTarget(
        name="prediction_grid",
        hook="grid",
        owners=("dense_head",),
        attribute="_apply_pos_embed",
        signature=("x", "width", "height", "ratio"),
        owner_classes=("DenseHead",),
        build=hooks.uv_grid_embedding,
        optional=True,  # VGGTOmega(enable_depth=False)
    ),
)


def check(root: nn.Module) -> None:
    """Refuse what the targets cannot express: an absolute PE table, random RoPE coordinates."""
    aggregator = _aggregator(root)
    if isinstance(getattr(aggregator.patch_embed, "pos_embed", None), torch.Tensor):
        raise UnsupportedUpstreamError(
            "vggt_omega: expected no absolute PE table at 'aggregator.patch_embed.pos_embed', found a "
            f"tensor; this patch only corrects RoPE (checked against {UPSTREAM})"
        )
    for path in ROPE_OWNERS:
        rope = resolve_path(root, path)
        augmented = [name for name in _AUGMENTATIONS if getattr(rope, name, None) is not None]
        if augmented:
            raise UnsupportedUpstreamError(
                f"vggt_omega: expected no RoPE coordinate augmentation at '{path}', found "
                f"{', '.join(f'{n}={getattr(rope, n)!r}' for n in augmented)} (checked against {UPSTREAM})"
            )


def _pose_decoder():
    try:
        from vggt_omega.utils.pose_enc import encoding_to_camera
    except ImportError as error:
        raise MissingDependencyError(
            f"vggt_omega.utils.pose_enc is not importable ({error}); {_INSTALL_HINT}"
        ) from error
    return encoding_to_camera


def predict(root: nn.Module, images: torch.Tensor, **kwargs) -> Prediction:
    """Run VGGT-Omega on images in [0, 1] (it normalises them itself).

    ``pose_enc`` (B, S, 9) is decoded with upstream's ``encoding_to_camera`` into cam_from_world
    (B, S, 4, 4) (OpenCV axes, world = first camera); depth (B, S, H, W) is the dense head's
    depth channel and the confidence its ``depth_conf``. ``extras`` holds upstream's pinhole
    ``intrinsics`` (principal point at (W/2, H/2)) and ``camera_and_register_tokens``, plus
    ``text_alignment_embedding`` with the text-aligned checkpoint.
    """
    images = as_batched_images(images, root.aggregator.patch_size)
    output = root(images, **kwargs)
    if "pose_enc" not in output:
        raise InputError(
            "this VGGT-Omega has no camera head (enable_camera=False): it predicts no pose"
        )
    if "depth" not in output:
        raise InputError(
            "this VGGT-Omega has no dense head (enable_depth=False): it predicts no depth"
        )
    extrinsics, intrinsics = _pose_decoder()(output["pose_enc"], images.shape[-2:])
    extras = {"intrinsics": intrinsics}
    for key in ("camera_and_register_tokens", "text_alignment_embedding"):
        if key in output:
            extras[key] = output[key]
    return Prediction(
        depth=output["depth"][..., 0],
        cam_from_world=to_homogeneous(extrinsics),
        confidence=output.get("depth_conf"),
        extras=extras,
    )


def build_network(enable_alignment: bool = False) -> nn.Module:
    """A randomly initialised ``VGGTOmega()`` (1B) from the user's installed upstream package."""
    try:
        from vggt_omega.models.vggt_omega import VGGTOmega
    except ImportError as error:
        raise MissingDependencyError(
            f"VGGT-Omega is not importable ({error}); {_INSTALL_HINT}"
        ) from error
    return VGGTOmega(enable_alignment=enable_alignment)


def identify(state: dict[str, torch.Tensor]) -> StateSignature | None:
    """A VGGT-Omega state dict (two RoPE ``periods`` buffers, no PE table), else ``None``.

    The text-aligned checkpoint is told from the other by its ``text_alignment_head.`` keys.
    """
    periods = state.get("aggregator.rope_embed.periods")
    if (
        periods is None
        or "aggregator.patch_embed.rope_embed.periods" not in state
        or "aggregator.patch_embed.pos_embed" in state
    ):
        return None
    embed = state.get("aggregator.camera_token")
    embed_dim = int(embed.shape[-1]) if embed is not None else 0
    depth = count_blocks(state, "aggregator.frame_blocks.")
    text = any(key.startswith("text_alignment_head.") for key in state)
    known = (_KNOWN_TEXT if text else _KNOWN).get((embed_dim, depth))
    detail = f"embed dim {embed_dim}, {depth} aggregator blocks, no PE table"
    if text:
        detail += ", with the text-alignment head"
    return StateSignature(FAMILY, (known,) if known else (), detail, None)


def _builder(name: str, enable_alignment: bool):
    def build(path=None) -> nn.Module:
        if path is None:
            raise WeightsError(
                f"{name} needs a local weight file (.pt or .safetensors, e.g. the official "
                f"{name.replace('-', '_')}.pt); raytun3r never downloads"
            )
        checkpoint = read_checkpoint(path)  # before the slow build: a bad path fails at once
        model = load_into(build_network(enable_alignment), checkpoint.state, checkpoint.source)
        model.raytun3r_name = name
        return model

    build.takes_checkpoint = True  # load_backbone passes the Checkpoint it has read
    return build


#: The two released checkpoints (``vggt_omega_1b_512.pt``; ``vggt_omega_1b_256_text.pt`` needs
#: ``enable_alignment=True``); both are state dicts with unprefixed keys, loaded strictly.
BUILDERS = {
    "vggt-omega-1b-512": _builder("vggt-omega-1b-512", False),
    "vggt-omega-1b-256-text": _builder("vggt-omega-1b-256-text", True),
}

SPEC = register(
    BackboneSpec(
        family=FAMILY,
        upstream=UPSTREAM,
        recognise=recognise,
        describe=describe,
        targets=TARGETS,
        predict=predict,
        builders=BUILDERS,
        rope_classes=ROPE_CLASSES,
        rope_base_attribute=ROPE_BASE_ATTRIBUTE,
        check=check,
        input_size=512,  # the released checkpoint is vggt_omega_1b_512 (16-px patches)
        # The DINOv3 ViT, the frame and the inter-frame blocks; not the camera head's trunk.
        transformer_blocks=(
            "aggregator.patch_embed.blocks",
            "aggregator.frame_blocks",
            "aggregator.inter_frame_blocks",
        ),
    )
)
