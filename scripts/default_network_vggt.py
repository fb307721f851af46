"""The VGGT architecture in the built-in networks' training (``train_default_network.py
--arch vggt``, issue 37): its sizes, its build, and its forward pass split for the losses.

VGGT's conventions, which the shared losses are mapped onto (``default_network_losses``):

* images go in as (B, S, 3, H, W) in [0, 1]: the aggregator normalises them itself (no
  ``imagenet_normalise`` as for DA3);
* ``pose_enc`` (absT_quaR_FoV, the same 9 numbers as DA3's) encodes each view's
  camera-from-world with the world = the first view, where DA3's encodes world-from-camera; the
  pose targets are inverted accordingly (``targets(batch, arch="vggt")``);
* depth is z-depth, as DA3's: the depth head's first channel (``exp`` activation), with
  ``depth_conf`` (``1 + exp``) as its confidence. There is no ray head: the ray loss is dropped.

The network is the stub package's ``VGGT`` (``tests/stubs/vggt``, upstream's module paths and
classes), sized with its ``stub_sizes``; ``raytun3r_plugin.apps.trained_networks`` builds it
and loads an exported file.
"""

from __future__ import annotations

import torch

#: The trained network: width 128 (as the DA3 built-ins), a 2-block DINO patch embedding and 4
#: frame + 4 global aggregator blocks (upstream: 24 + 24 + a 24-block ViT-L), the DPT widths of
#: the DA3 built-ins. A 37 x 37 PE table (518 px, as VGGT-1B), interpolated to the input size.
VGGT_KWARGS = dict(
    img_size=518,
    patch_size=14,
    embed_dim=128,
    sizes=dict(
        aggregator_depth=4,
        aggregator_num_heads=4,
        dino_depth=2,
        dino_num_heads=4,
        camera_trunk_depth=1,
        camera_num_heads=4,
        dpt_features=32,
        dpt_out_channels=[16, 32, 64, 64],
        dpt_intermediate_layer_idx=[0, 1, 2, 3],
        seed=0,
    ),
)
#: Smoke tests only: the same network, narrower and shallower.
VGGT_TINY_KWARGS = {
    **VGGT_KWARGS,
    "embed_dim": 32,
    "sizes": {
        **VGGT_KWARGS["sizes"],
        "aggregator_depth": 2,
        "aggregator_num_heads": 2,
        "dino_depth": 1,
        "dino_num_heads": 2,
        "camera_num_heads": 2,
        "dpt_features": 8,
        "dpt_out_channels": [8, 8, 16, 16],
        "dpt_intermediate_layer_idx": [0, 0, 1, 1],
    },
}


def require_vggt() -> None:
    """Exit with a message naming ``PYTHONPATH=tests/stubs`` when ``vggt`` is not importable."""
    try:
        import vggt.models.vggt  # noqa: F401
        from vggt import _stub_config  # noqa: F401
    except ImportError as error:
        raise SystemExit(
            f"--arch vggt needs the vggt stub package ({error}): run with "
            "PYTHONPATH=tests/stubs (e.g. PYTHONPATH=$PWD:$PWD/tests/stubs python "
            "scripts/train_default_network.py --arch vggt ...)"
        ) from None


def build_vggt(tiny: bool, seed: int) -> tuple[torch.nn.Module, dict]:
    """(the small VGGT in train mode, its build kwargs as recorded in the export sidecar)."""
    from raytun3r_plugin.apps.trained_networks import build_small_vggt

    require_vggt()
    kwargs = {**(VGGT_TINY_KWARGS if tiny else VGGT_KWARGS)}
    kwargs["sizes"] = {**kwargs["sizes"], "seed": seed}
    return build_small_vggt(kwargs).train(), kwargs


def is_vggt(model) -> bool:
    """True for a VGGT (an ``aggregator`` where DA3 has a ``backbone``)."""
    return hasattr(model, "aggregator") and not hasattr(model, "backbone")


def pe_table(model) -> torch.nn.Parameter:
    """The absolute PE table (1, 1 + n * n, C) of either architecture's DINOv2 ViT (row 0: class)."""
    if is_vggt(model):
        return model.aggregator.patch_embed.pos_embed
    return model.backbone.pretrained.pos_embed


def forward_train_vggt(
    model, images: torch.Tensor, pose_only: bool = False
) -> tuple[dict | None, torch.Tensor, list]:
    """VGGT's own forward, split as ``forward_train`` is for DA3.

    images (B, S, 3, H, W) in [0, 1]. Returns ``{"depth": (B, S, H, W), "depth_conf": (B, S, H,
    W)}`` (None with ``pose_only``), the camera head's last ``pose_enc`` (B, S, 9) and the
    aggregator's per-block tokens.
    """
    aggregator = model.aggregator
    was = aggregator.training
    # Upstream checkpoints every aggregator block while training (GPU memory); at this size on
    # a CPU that only recomputes the forward, so the blocks run as in eval (no dropout anywhere).
    aggregator.training = False
    try:
        tokens, patch_start = aggregator(images)
    finally:
        aggregator.training = was
    pose_enc = model.camera_head(tokens)[-1]
    if pose_only:
        return None, pose_enc, tokens
    depth, conf = model.depth_head(tokens, images=images, patch_start_idx=patch_start)
    return {"depth": depth[..., 0], "depth_conf": conf}, pose_enc, tokens


def cam_from_world(model, pose_enc: torch.Tensor, hw: tuple[int, int]) -> torch.Tensor:
    """(B, S, 4, 4) float64 cam_from_world (world = first view) from either network's pose_enc."""
    if is_vggt(model):
        from vggt.utils.pose_enc import pose_encoding_to_extri_intri

        extrinsics, _ = pose_encoding_to_extri_intri(pose_enc, hw)
        invert = False
    else:
        from depth_anything_3.model.utils.transform import pose_encoding_to_extri_intri

        extrinsics, _ = pose_encoding_to_extri_intri(pose_enc, hw)
        invert = True  # DA3 encodes world_from_cam
    extrinsics = extrinsics.double()
    bottom = extrinsics.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(*extrinsics.shape[:-2], 1, 4)
    full = torch.cat([extrinsics, bottom], dim=-2)
    return torch.linalg.inv(full) if invert else full
