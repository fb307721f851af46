"""The backbone table of the contract tests: one row per registered backbone family.

``tests/test_backbone_contract.py`` and ``tests/test_lifecycle.py`` run every contract on every
row (PEFT's ``TEST_CASES x PeftCommonTester``), and fail when a registered family has no row. To
add a backbone, add one :class:`BackboneCase` to :data:`CASES` with a builder of a tiny model
that exercises every hook of its spec (docs/adding_a_backbone.md).

VGGT and Pi3 / Pi3X come from the stub packages in ``tests/stubs`` (their documented tiny
recipes), or, when the real upstream packages are importable, from small networks assembled
from the upstream classes (:func:`tiny_real`) exactly as the real ``__init__`` wires them.
"""

from __future__ import annotations

import copy
import importlib
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import torch
from torch import nn

#: Input size (H, W) of the VGGT / Pi3 cases: 3 x 4 patches of 14 px.
H, W = 42, 56
#: Input size (H, W) of the VGGT-Omega case: 3 x 4 patches of 16 px.
OMEGA_SIZE = (48, 64)


@dataclass(frozen=True)
class BackboneCase:
    """One row of the contract matrix.

    Attributes:
        family: the registered ``BackboneSpec.family``.
        package: the upstream top-level package; the row is skipped when it is not importable.
        build: ``build(seed) -> nn.Module``: a fresh, small model in eval mode, deterministic in
            ``seed`` and leaving the global RNG alone. It must carry every owner of every
            target of the spec (optional ones included), so that every hook is exercised.
        size: the (H, W) of the test images, a multiple of the patch size.
        inert: components with nothing to act on in this backbone (they must change nothing).
    """

    family: str
    package: str
    build: Callable[[int], nn.Module]
    size: tuple[int, int]
    inert: frozenset[str] = frozenset()

    def images(self, views: int = 2, seed: int = 1) -> torch.Tensor:
        """(1, views, 3, H, W) images in [0, 1]."""
        return torch.rand(1, views, 3, *self.size, generator=torch.Generator().manual_seed(seed))


# ---------------------------------------------------------------------------------------------
# Builders
# ---------------------------------------------------------------------------------------------


def _build_da3(seed: int) -> nn.Module:
    from raytun3r_plugin.patches.da3_networks import build_tiny_network

    return build_tiny_network(seed=seed)


_PACKAGE = {"vggt": "vggt", "pi3": "pi3", "pi3x": "pi3", "vggt_omega": "vggt_omega"}


def is_stub(kind: str) -> bool:
    """True when ``kind``'s upstream package is the stub of ``tests/stubs``."""
    return bool(getattr(importlib.import_module(_PACKAGE[kind]), "__raytun3r_stub__", False))


def _seeded(seed):
    generator_state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    return generator_state


def tiny_real(kind: str, seed: int = 0) -> nn.Module:
    """A small network made of the real upstream classes, wired as upstream's ``__init__`` does."""
    state = _seeded(seed)
    try:
        return {
            "vggt": _tiny_real_vggt,
            "pi3": _tiny_real_pi3,
            "pi3x": _tiny_real_pi3x,
            "vggt_omega": _tiny_real_vggt_omega,
        }[kind]().eval()
    finally:
        torch.random.set_rng_state(state)


def _tiny_real_vggt():
    from vggt.heads.camera_head import CameraHead
    from vggt.heads.dpt_head import DPTHead
    from vggt.models.aggregator import Aggregator
    from vggt.models.vggt import VGGT

    model = VGGT.__new__(VGGT)
    nn.Module.__init__(model)
    model.aggregator = Aggregator(
        img_size=70,
        patch_size=14,
        embed_dim=384,
        depth=2,
        num_heads=6,
        patch_embed="dinov2_vits14_reg",
    )
    model.camera_head = CameraHead(dim_in=768, trunk_depth=1, num_heads=6)
    dpt = dict(
        dim_in=768, features=32, out_channels=[16, 32, 64, 64], intermediate_layer_idx=[0, 1, 0, 1]
    )
    model.point_head = DPTHead(output_dim=4, activation="inv_log", conf_activation="expp1", **dpt)
    model.depth_head = DPTHead(output_dim=2, activation="exp", conf_activation="expp1", **dpt)
    model.track_head = None
    return model


def _tiny_real_vggt_omega():
    """Upstream ``VGGTOmega.__init__`` with a small aggregator and heads (its DINOv3 ViT keeps
    upstream's fixed 24 blocks / 16 heads, at width 64)."""
    from vggt_omega.models.aggregator import Aggregator
    from vggt_omega.models.heads import CameraHead, DenseHead
    from vggt_omega.models.layers import LayerScale
    from vggt_omega.models.layers.utils import named_apply
    from vggt_omega.models.layers.vision_transformer import init_weights_vit
    from vggt_omega.models.vggt_omega import VGGTOmega

    model = VGGTOmega.__new__(VGGTOmega)
    nn.Module.__init__(model)
    model.aggregator = Aggregator(
        patch_size=16,
        embed_dim=64,
        depth=2,
        num_heads=4,
        num_register_tokens=2,
        register_attention_block_indices=[1],
        cached_layer_indices=(0, 1),
    )
    model.camera_head = CameraHead(dim_in=128)
    model.dense_head = DenseHead(
        dim_in=128,
        patch_size=16,
        features=16,
        out_channels=[8, 8, 16, 16],
        intermediate_layer_idx=[0, 1, 0, 1],
    )
    model.text_alignment_head = None
    # Upstream leaves the aggregator's and heads' key-bias masks at NaN until a checkpoint is
    # loaded; the ViT initialiser writes them (and small random weights) everywhere.
    named_apply(init_weights_vit, model)
    for module in model.modules():  # LayerScale starts at 1e-5: positions would hardly matter
        if isinstance(module, LayerScale):
            nn.init.constant_(module.gamma, 1.0)
    return model


def _pi3_trunk(model, module):
    """Encoder, RoPE, decoder and register tokens as in ``Pi3.__init__`` / ``Pi3X.__init__``."""
    from pi3.models.dinov2.hub.backbones import dinov2_vits14_reg
    from pi3.models.dinov2.layers import Mlp
    from pi3.models.layers.attention import FlashAttentionRope
    from pi3.models.layers.block import BlockRope
    from pi3.models.layers.pos_embed import PositionGetter

    model.encoder = dinov2_vits14_reg(pretrained=False)
    del model.encoder.mask_token
    model.patch_size = 14
    dim = model.encoder.embed_dim
    model.rope = module.RoPE2D(
        freq=100.0
    )  # the name the upstream module imported (cuRoPE2D or RoPE2D)
    model.position_getter = PositionGetter()
    norm = partial(nn.LayerNorm, eps=1e-6)
    model.decoder = nn.ModuleList(
        BlockRope(
            dim=dim,
            num_heads=6,
            mlp_ratio=4,
            qkv_bias=True,
            proj_bias=True,
            ffn_bias=True,
            drop_path=0.0,
            norm_layer=norm,
            act_layer=nn.GELU,
            ffn_layer=Mlp,
            init_values=0.01,
            qk_norm=True,
            attn_class=FlashAttentionRope,
            rope=model.rope,
        )
        for _ in range(2)
    )
    model.dec_embed_dim = dim
    model.patch_start_idx = 5
    model.register_token = nn.Parameter(torch.randn(1, 1, 5, dim) * 1e-6)
    model.register_buffer("image_mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
    model.register_buffer("image_std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))
    return dim


def _tiny_real_pi3():
    import pi3.models.pi3 as module
    from pi3.models.layers.camera_head import CameraHead
    from pi3.models.layers.transformer_head import LinearPts3d, TransformerDecoder

    model = module.Pi3.__new__(module.Pi3)
    nn.Module.__init__(model)
    model.pos_type = "rope100"
    dim = _pi3_trunk(model, module)
    head = dict(in_dim=2 * dim, dec_embed_dim=64, dec_num_heads=4, depth=1, rope=model.rope)
    model.point_decoder = TransformerDecoder(out_dim=64, **head)
    model.point_head = LinearPts3d(patch_size=14, dec_embed_dim=64, output_dim=3)
    model.conf_decoder = copy.deepcopy(model.point_decoder)
    model.conf_head = LinearPts3d(patch_size=14, dec_embed_dim=64, output_dim=1)
    model.camera_decoder = TransformerDecoder(out_dim=32, use_checkpoint=False, **head)
    model.camera_head = CameraHead(dim=32)
    return model


def _tiny_real_pi3x():
    import pi3.models.pi3x as module
    from pi3.models.dinov2.layers import PatchEmbed
    from pi3.models.layers.camera_head import CameraHead
    from pi3.models.layers.conv_head import ConvHead
    from pi3.models.layers.transformer_head import ContextOnlyTransformerDecoder, TransformerDecoder

    model = module.Pi3X.__new__(module.Pi3X)
    nn.Module.__init__(model)
    model.use_multimodal = True
    dim = _pi3_trunk(model, module)
    model.depth_encoder = copy.deepcopy(model.encoder)
    del model.depth_encoder.patch_embed
    model.depth_encoder.patch_embed = PatchEmbed(
        img_size=224, patch_size=14, in_chans=2, embed_dim=dim
    )
    model.depth_emb = nn.Parameter(torch.zeros(1, 1, dim))
    model.ray_embed = PatchEmbed(img_size=224, patch_size=14, in_chans=2, embed_dim=dim)
    nn.init.normal_(
        model.ray_embed.proj.weight, std=0.02
    )  # upstream zero-initialises; nonzero so it matters
    model.pose_inject_blk = (
        nn.ModuleList()
    )  # pose conditioning is not exercised on the tiny real model
    head = dict(in_dim=2 * dim, dec_embed_dim=64, dec_num_heads=4, depth=1, rope=model.rope)
    conv = dict(
        num_features=4,
        dim_in=dim,
        projects=nn.Identity(),
        dim_proj=64,
        dim_upsample=[32, 32, 16],
        dim_times_res_block_hidden=2,
        num_res_blocks=1,
        res_block_norm="group_norm",
        last_res_blocks=0,
        last_conv_channels=8,
        last_conv_size=1,
        using_uv=True,
    )
    model.point_decoder = TransformerDecoder(out_dim=64, **head)
    model.point_head = ConvHead(dim_out=[2, 1], **conv)
    model.camera_decoder = TransformerDecoder(out_dim=32, **head)
    model.camera_head = CameraHead(dim=32)
    model.metric_token = nn.Parameter(torch.randn(1, 1, 2 * dim) * 1e-6)
    model.metric_decoder = ContextOnlyTransformerDecoder(
        in_dim=2 * dim, out_dim=32, dec_embed_dim=32, depth=1, dec_num_heads=2, rope=model.rope
    )
    model.metric_head = nn.Linear(32, 1)
    model.conf_decoder = TransformerDecoder(out_dim=64, **head)  # shares model.rope, as upstream
    model.conf_head = ConvHead(dim_out=[1], **conv)
    return model


def build(kind: str, seed: int = 0) -> nn.Module:
    """A fresh VGGT / Pi3 / Pi3X / VGGT-Omega: the stub's documented tiny recipe, or a tiny real network."""
    if not is_stub(kind):
        return tiny_real(kind, seed)
    stub_config = importlib.import_module(f"{_PACKAGE[kind]}._stub_config")
    with stub_config.stub_sizes(seed=seed):
        if kind == "vggt":
            from vggt.models.vggt import VGGT

            return VGGT(img_size=70, patch_size=14, embed_dim=64, enable_track=False).eval()
        if kind == "vggt_omega":
            from vggt_omega.models.vggt_omega import VGGTOmega

            return VGGTOmega(embed_dim=64).eval()
        if kind == "pi3":
            from pi3.models.pi3 import Pi3

            return Pi3().eval()
        from pi3.models.pi3x import Pi3X

        return Pi3X().eval()


# ---------------------------------------------------------------------------------------------
# The table
# ---------------------------------------------------------------------------------------------

CASES: tuple[BackboneCase, ...] = (
    BackboneCase("da3", "depth_anything_3", _build_da3, (70, 84)),
    BackboneCase("vggt", "vggt", partial(build, "vggt"), (H, W)),
    BackboneCase(
        "pi3", "pi3", partial(build, "pi3"), (H, W), inert=frozenset({"grid"})
    ),  # LinearPts3d heads: no grid
    BackboneCase("pi3x", "pi3", partial(build, "pi3x"), (H, W)),
    BackboneCase(
        "vggt_omega",
        "vggt_omega",
        partial(build, "vggt_omega"),
        OMEGA_SIZE,
        inert=frozenset({"pe"}),  # RoPE only: no absolute PE table
    ),
)
CASE = {case.family: case for case in CASES}

_PRISTINE: dict[tuple[str, int], nn.Module] = {}


def make(family: str, seed: int = 0) -> nn.Module:
    """A private copy of a cached pristine model of ``family`` (real tiny builds take seconds)."""
    if (family, seed) not in _PRISTINE:
        _PRISTINE[family, seed] = CASE[family].build(seed)
    return copy.deepcopy(_PRISTINE[family, seed])
