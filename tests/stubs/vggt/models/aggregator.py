"""Alternating frame/global attention over the DINO patch tokens (stub implementation)."""

from __future__ import annotations

import logging
from typing import List, Tuple

import torch
from torch import nn
from torch.utils.checkpoint import checkpoint

from vggt import _stub_config
from vggt.layers import PatchEmbed
from vggt.layers.block import Block
from vggt.layers.rope import PositionGetter, RotaryPositionEmbedding2D
from vggt.layers.vision_transformer import vit_base, vit_giant2, vit_large, vit_small

logger = logging.getLogger(__name__)

_RESNET_MEAN = [0.485, 0.456, 0.406]
_RESNET_STD = [0.229, 0.224, 0.225]


class Aggregator(nn.Module):
    def __init__(
        self,
        img_size=518,
        patch_size=14,
        embed_dim=1024,
        depth=24,
        num_heads=16,
        mlp_ratio=4.0,
        num_register_tokens=4,
        block_fn=Block,
        qkv_bias=True,
        proj_bias=True,
        ffn_bias=True,
        patch_embed="dinov2_vitl14_reg",
        aa_order=["frame", "global"],  # noqa: B006 (upstream default)
        aa_block_size=1,
        qk_norm=True,
        rope_freq=100,
        init_values=0.01,
    ):
        super().__init__()
        self.__build_patch_embed__(patch_embed, img_size, patch_size, num_register_tokens, embed_dim=embed_dim)

        self.rope = RotaryPositionEmbedding2D(frequency=rope_freq) if rope_freq > 0 else None
        self.position_getter = PositionGetter() if self.rope is not None else None

        def make_blocks():
            return nn.ModuleList(
                block_fn(
                    dim=embed_dim,
                    num_heads=num_heads,
                    mlp_ratio=mlp_ratio,
                    qkv_bias=qkv_bias,
                    proj_bias=proj_bias,
                    ffn_bias=ffn_bias,
                    init_values=init_values,
                    qk_norm=qk_norm,
                    rope=self.rope,
                )
                for _ in range(depth)
            )

        self.frame_blocks = make_blocks()
        self.global_blocks = make_blocks()
        self.depth = depth
        self.aa_order = aa_order
        self.patch_size = patch_size
        self.aa_block_size = aa_block_size
        if depth % aa_block_size != 0:
            raise ValueError(f"depth ({depth}) must be divisible by aa_block_size ({aa_block_size})")
        self.aa_block_num = depth // aa_block_size

        # index 0: first frame (reference), index 1: every other frame
        self.camera_token = nn.Parameter(torch.randn(1, 2, 1, embed_dim))
        self.register_token = nn.Parameter(torch.randn(1, 2, num_register_tokens, embed_dim))
        self.patch_start_idx = 1 + num_register_tokens
        nn.init.normal_(self.camera_token, std=1e-6)
        nn.init.normal_(self.register_token, std=1e-6)

        self.register_buffer("_resnet_mean", torch.tensor(_RESNET_MEAN).view(1, 1, 3, 1, 1), persistent=False)
        self.register_buffer("_resnet_std", torch.tensor(_RESNET_STD).view(1, 1, 3, 1, 1), persistent=False)
        self.use_reentrant = False

    def __build_patch_embed__(
        self,
        patch_embed,
        img_size,
        patch_size,
        num_register_tokens,
        interpolate_antialias=True,
        interpolate_offset=0.0,
        block_chunks=0,
        init_values=1.0,
        embed_dim=1024,
    ):
        if "conv" in patch_embed:
            self.patch_embed = PatchEmbed(img_size=img_size, patch_size=patch_size, in_chans=3, embed_dim=embed_dim)
            return
        builders = {
            "dinov2_vitl14_reg": vit_large,
            "dinov2_vitb14_reg": vit_base,
            "dinov2_vits14_reg": vit_small,
            "dinov2_vitg2_reg": vit_giant2,
        }
        sizes = _stub_config.SIZES
        self.patch_embed = builders[patch_embed](
            img_size=img_size,
            patch_size=patch_size,
            num_register_tokens=num_register_tokens,
            interpolate_antialias=interpolate_antialias,
            interpolate_offset=interpolate_offset,
            block_chunks=block_chunks,
            init_values=init_values,
            # stub: the ViT width follows embed_dim, its depth/heads come from the stub sizes
            embed_dim=embed_dim,
            depth=sizes.dino_depth,
            num_heads=sizes.dino_num_heads,
        )
        if hasattr(self.patch_embed, "mask_token"):
            self.patch_embed.mask_token.requires_grad_(False)

    def forward(self, images: torch.Tensor) -> Tuple[List[torch.Tensor], int]:
        """images (B, S, 3, H, W) in [0, 1] -> (list of (B, S, P, 2C) per block, patch_start_idx)."""
        B, S, C_in, H, W = images.shape
        if C_in != 3:
            raise ValueError(f"Expected 3 input channels, got {C_in}")
        images = (images - self._resnet_mean) / self._resnet_std
        images = images.view(B * S, C_in, H, W)
        patch_tokens = self.patch_embed(images)
        if isinstance(patch_tokens, dict):
            patch_tokens = patch_tokens["x_norm_patchtokens"]

        camera_token = slice_expand_and_flatten(self.camera_token, B, S)
        register_token = slice_expand_and_flatten(self.register_token, B, S)
        tokens = torch.cat([camera_token, register_token, patch_tokens], dim=1)

        pos = None
        if self.rope is not None:
            pos = self.position_getter(B * S, H // self.patch_size, W // self.patch_size, device=images.device)
        if self.patch_start_idx > 0:
            # patches at (y + 1, x + 1); camera and register tokens at (0, 0)
            pos = pos + 1
            special = torch.zeros(B * S, self.patch_start_idx, 2).to(images.device).to(pos.dtype)
            pos = torch.cat([special, pos], dim=1)

        _, P, C = tokens.shape
        frame_idx = global_idx = 0
        output_list = []
        for _ in range(self.aa_block_num):
            frame_inter = global_inter = []
            for attn_type in self.aa_order:
                if attn_type == "frame":
                    tokens, frame_idx, frame_inter = self._process_frame_attention(
                        tokens, B, S, P, C, frame_idx, pos=pos
                    )
                elif attn_type == "global":
                    tokens, global_idx, global_inter = self._process_global_attention(
                        tokens, B, S, P, C, global_idx, pos=pos
                    )
                else:
                    raise ValueError(f"Unknown attention type: {attn_type}")
            for f_tok, g_tok in zip(frame_inter, global_inter):
                output_list.append(torch.cat([f_tok, g_tok], dim=-1))
        return output_list, self.patch_start_idx

    def _run(self, block, tokens, pos):
        if self.training:
            return checkpoint(block, tokens, pos, use_reentrant=self.use_reentrant)
        return block(tokens, pos=pos)

    def _process_frame_attention(self, tokens, B, S, P, C, frame_idx, pos=None):
        """Attention within each frame: tokens (B*S, P, C), positions (B*S, P, 2)."""
        tokens = tokens.reshape(B * S, P, C)
        if pos is not None:
            pos = pos.reshape(B * S, P, 2)
        intermediates = []
        for _ in range(self.aa_block_size):
            tokens = self._run(self.frame_blocks[frame_idx], tokens, pos)
            frame_idx += 1
            intermediates.append(tokens.view(B, S, P, C))
        return tokens, frame_idx, intermediates

    def _process_global_attention(self, tokens, B, S, P, C, global_idx, pos=None):
        """Attention across all frames: tokens (B, S*P, C), positions (B, S*P, 2)."""
        tokens = tokens.reshape(B, S * P, C)
        if pos is not None:
            pos = pos.reshape(B, S * P, 2)
        intermediates = []
        for _ in range(self.aa_block_size):
            tokens = self._run(self.global_blocks[global_idx], tokens, pos)
            global_idx += 1
            intermediates.append(tokens.view(B, S, P, C))
        return tokens, global_idx, intermediates


def slice_expand_and_flatten(token_tensor, B, S):
    """(1, 2, X, C) -> (B*S, X, C): slot 0 for the first frame, slot 1 for the others."""
    first = token_tensor[:, :1].expand(B, 1, *token_tensor.shape[2:])
    rest = token_tensor[:, 1:].expand(B, S - 1, *token_tensor.shape[2:])
    return torch.cat([first, rest], dim=1).reshape(B * S, *token_tensor.shape[2:])
