"""Head decoders of Pi3 (stub implementations)."""

from __future__ import annotations

from functools import partial

import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint

from ..dinov2.layers import Mlp
from .attention import FlashAttentionRope, FlashCrossAttentionRope
from .block import BlockRope, CrossOnlyBlockRope


class TransformerDecoder(nn.Module):
    """Linear projection, ``depth`` RoPE self-attention blocks (frame level), linear output."""

    def __init__(
        self,
        in_dim,
        out_dim,
        dec_embed_dim=512,
        depth=5,
        dec_num_heads=8,
        mlp_ratio=4,
        rope=None,
        need_project=True,
        use_checkpoint=False,
    ):
        super().__init__()
        self.projects = nn.Linear(in_dim, dec_embed_dim) if need_project else nn.Identity()
        self.use_checkpoint = use_checkpoint
        self.blocks = nn.ModuleList(
            BlockRope(
                dim=dec_embed_dim,
                num_heads=dec_num_heads,
                mlp_ratio=mlp_ratio,
                qkv_bias=True,
                proj_bias=True,
                ffn_bias=True,
                drop_path=0.0,
                norm_layer=partial(nn.LayerNorm, eps=1e-6),
                act_layer=nn.GELU,
                ffn_layer=Mlp,
                init_values=None,
                qk_norm=False,
                attn_class=FlashAttentionRope,
                rope=rope,
            )
            for _ in range(depth)
        )
        self.linear_out = nn.Linear(dec_embed_dim, out_dim)

    def forward(self, hidden, xpos=None):
        hidden = self.projects(hidden)
        for blk in self.blocks:
            if self.use_checkpoint and self.training:
                hidden = checkpoint(blk, hidden, xpos=xpos, use_reentrant=False)
            else:
                hidden = blk(hidden, xpos=xpos)
        return self.linear_out(hidden)


class LinearPts3d(nn.Module):
    """Each patch token -> patch_size^2 x output_dim values, pixel-shuffled to (B, H, W, output_dim)."""

    def __init__(self, patch_size, dec_embed_dim, output_dim=3):
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Linear(dec_embed_dim, output_dim * patch_size**2)

    def forward(self, decout, img_shape):
        H, W = img_shape
        tokens = decout[-1]
        B, _, _ = tokens.shape
        feat = self.proj(tokens).transpose(-1, -2)
        feat = feat.reshape(B, -1, H // self.patch_size, W // self.patch_size)
        return F.pixel_shuffle(feat, self.patch_size).permute(0, 2, 3, 1)


class ContextOnlyTransformerDecoder(nn.Module):
    """Query tokens cross-attend to a context (RoPE with xpos for queries, ypos for context)."""

    def __init__(
        self,
        in_dim,
        out_dim,
        dec_embed_dim=512,
        depth=5,
        dec_num_heads=8,
        mlp_ratio=4,
        rope=None,
        prenorm=False,
        use_checkpoint=True,
    ):
        super().__init__()
        self.pre_norm = nn.LayerNorm(in_dim) if prenorm else None
        self.projects_x = nn.Linear(in_dim, dec_embed_dim)
        self.projects_y = nn.Linear(in_dim, dec_embed_dim)
        self.use_checkpoint = use_checkpoint
        self.blocks = nn.ModuleList(
            CrossOnlyBlockRope(
                dim=dec_embed_dim,
                num_heads=dec_num_heads,
                mlp_ratio=mlp_ratio,
                qkv_bias=True,
                proj_bias=True,
                ffn_bias=True,
                norm_layer=partial(nn.LayerNorm, eps=1e-6),
                act_layer=nn.GELU,
                ffn_layer=Mlp,
                init_values=None,
                qk_norm=False,
                cross_attn_class=FlashCrossAttentionRope,
                rope=rope,
            )
            for _ in range(depth)
        )
        self.linear_out = nn.Linear(dec_embed_dim, out_dim)

    def forward(self, hidden, context, xpos=None, ypos=None):
        if self.pre_norm is not None:
            hidden, context = self.pre_norm(hidden), self.pre_norm(context)
        hidden = self.projects_x(hidden)
        context = self.projects_y(context)
        for blk in self.blocks:
            if self.use_checkpoint and self.training:
                hidden = checkpoint(blk, hidden, context, xpos=xpos, ypos=ypos, use_reentrant=False)
            else:
                hidden = blk(hidden, context, xpos=xpos, ypos=ypos)
        return self.linear_out(hidden)
