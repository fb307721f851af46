"""Pi3 model (stub). Same constructor, attributes, ``decode``/``forward`` and outputs as upstream."""

from __future__ import annotations

from copy import deepcopy
from functools import partial

import torch
from torch import nn

from .. import _stub_config
from ..utils.geometry import homogenize_points
from .dinov2.hub.backbones import dinov2_vitl14, dinov2_vitl14_reg  # noqa: F401 (upstream imports both)
from .dinov2.layers import Mlp
from .layers.attention import FlashAttentionRope
from .layers.block import BlockRope
from .layers.camera_head import CameraHead
from .layers.pos_embed import PositionGetter, RoPE2D
from .layers.transformer_head import LinearPts3d, TransformerDecoder


def _build_encoder(sizes):
    encoder = dinov2_vitl14_reg(
        pretrained=False, embed_dim=sizes.embed_dim, depth=sizes.encoder_depth, num_heads=sizes.encoder_num_heads
    )
    del encoder.mask_token
    return encoder


def _build_decoder(sizes, rope):
    return nn.ModuleList(
        BlockRope(
            dim=sizes.embed_dim,
            num_heads=sizes.decoder_num_heads,
            mlp_ratio=4,
            qkv_bias=True,
            proj_bias=True,
            ffn_bias=True,
            drop_path=0.0,
            norm_layer=partial(nn.LayerNorm, eps=1e-6),
            act_layer=nn.GELU,
            ffn_layer=Mlp,
            init_values=0.01,
            qk_norm=True,
            attn_class=FlashAttentionRope,
            rope=rope,
        )
        for _ in range(sizes.decoder_depth)
    )


class Pi3(nn.Module):
    def __init__(self, pos_type="rope100", decoder_size="large"):
        super().__init__()
        sizes = _stub_config.SIZES
        if decoder_size not in ("small", "base", "large"):
            raise NotImplementedError(decoder_size)
        with _stub_config.seeded_init():
            self._build(sizes, pos_type)

    def _build(self, sizes, pos_type):
        self.encoder = _build_encoder(sizes)
        self.patch_size = 14

        self.pos_type = pos_type if pos_type is not None else "none"
        self.rope = None
        if not self.pos_type.startswith("rope"):
            raise NotImplementedError(self.pos_type)
        if RoPE2D is None:
            raise ImportError("Cannot find cuRoPE2D")
        self.rope = RoPE2D(freq=float(self.pos_type[len("rope") :]))
        self.position_getter = PositionGetter()

        self.decoder = _build_decoder(sizes, self.rope)
        self.dec_embed_dim = sizes.embed_dim

        num_register_tokens = 5
        self.patch_start_idx = num_register_tokens
        self.register_token = nn.Parameter(torch.randn(1, 1, num_register_tokens, self.dec_embed_dim))
        nn.init.normal_(self.register_token, std=1e-6)

        head = dict(dec_embed_dim=sizes.head_embed_dim, dec_num_heads=sizes.head_num_heads, depth=sizes.head_depth)
        self.point_decoder = TransformerDecoder(
            in_dim=2 * self.dec_embed_dim, out_dim=sizes.head_embed_dim, rope=self.rope, **head
        )
        self.point_head = LinearPts3d(patch_size=14, dec_embed_dim=sizes.head_embed_dim, output_dim=3)
        # a deepcopy: the conf decoder owns a second RoPE2D instance (with its own cache)
        self.conf_decoder = deepcopy(self.point_decoder)
        self.conf_head = LinearPts3d(patch_size=14, dec_embed_dim=sizes.head_embed_dim, output_dim=1)
        self.camera_decoder = TransformerDecoder(
            in_dim=2 * self.dec_embed_dim, out_dim=sizes.camera_dim, rope=self.rope, use_checkpoint=False, **head
        )
        self.camera_head = CameraHead(dim=sizes.camera_dim)

        self.register_buffer("image_mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
        self.register_buffer("image_std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))

    def decode(self, hidden, N, H, W):
        """hidden (B*N, hw, C) encoder patch tokens -> ((B*N, 5 + hw, 2C), positions (B*N, 5 + hw, 2))."""
        BN, hw, _ = hidden.shape
        B = BN // N
        hidden = hidden.reshape(B * N, hw, -1)
        register_token = self.register_token.repeat(B, N, 1, 1).reshape(B * N, *self.register_token.shape[-2:])
        hidden = torch.cat([register_token, hidden], dim=1)
        hw = hidden.shape[1]

        if self.pos_type.startswith("rope"):
            pos = self.position_getter(B * N, H // self.patch_size, W // self.patch_size, hidden.device)
        if self.patch_start_idx > 0:
            # patches at (y + 1, x + 1); the 5 register tokens at (0, 0)
            pos = pos + 1
            special = torch.zeros(B * N, self.patch_start_idx, 2).to(hidden.device).to(pos.dtype)
            pos = torch.cat([special, pos], dim=1)

        final_output = []
        for i, blk in enumerate(self.decoder):
            if i % 2 == 0:  # frame attention
                pos = pos.reshape(B * N, hw, -1)
                hidden = hidden.reshape(B * N, hw, -1)
            else:  # global attention over all views
                pos = pos.reshape(B, N * hw, -1)
                hidden = hidden.reshape(B, N * hw, -1)
            hidden = blk(hidden, xpos=pos)
            if i + 1 in (len(self.decoder) - 1, len(self.decoder)):
                final_output.append(hidden.reshape(B * N, hw, -1))
        return torch.cat([final_output[0], final_output[1]], dim=-1), pos.reshape(B * N, hw, -1)

    def forward(self, imgs):
        """imgs (B, N, 3, H, W) in [0, 1]."""
        imgs = (imgs - self.image_mean) / self.image_std
        B, N, C, H, W = imgs.shape
        patch_h, patch_w = H // 14, W // 14
        hidden = self.encoder(imgs.reshape(B * N, C, H, W), is_training=True)
        if isinstance(hidden, dict):
            hidden = hidden["x_norm_patchtokens"]
        hidden, pos = self.decode(hidden, N, H, W)

        point_hidden = self.point_decoder(hidden, xpos=pos)
        conf_hidden = self.conf_decoder(hidden, xpos=pos)
        camera_hidden = self.camera_decoder(hidden, xpos=pos)

        with torch.amp.autocast(device_type="cuda", enabled=False):
            start = self.patch_start_idx
            ret = self.point_head([point_hidden.float()[:, start:]], (H, W)).reshape(B, N, H, W, -1)
            xy, z = ret.split([2, 1], dim=-1)
            z = torch.exp(z)
            local_points = torch.cat([xy * z, z], dim=-1)
            conf = self.conf_head([conf_hidden.float()[:, start:]], (H, W)).reshape(B, N, H, W, -1)
            camera_poses = self.camera_head(camera_hidden.float()[:, start:], patch_h, patch_w).reshape(B, N, 4, 4)
            points = torch.einsum("bnij,bnhwj->bnhwi", camera_poses, homogenize_points(local_points))[..., :3]

        return dict(points=points, local_points=local_points, conf=conf, camera_poses=camera_poses)
