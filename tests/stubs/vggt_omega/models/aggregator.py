"""Alternating frame / inter-frame attention over ``[camera, registers, patches]`` tokens.

As upstream: ImageNet normalisation with non-persistent buffers; DINOv3 patch tokens
(``x_norm_patchtokens``); ``camera_token`` (1, 2, 1, C) and ``register_token`` (1, 2, R, C),
slot 0 for the first frame; ``patch_token_start = 1 + R``. The frame RoPE (sin, cos) is
computed once per forward from ``rope_embed(H=h, W=w)`` under ``no_grad`` and cast to float32;
inter-frame blocks get no RoPE ("global" over all tokens, or "register": camera and register
tokens only). Outputs: ``cat(frame, inter-frame)`` (B, S, P, 2C) at the cached layers, else None.
"""

import torch
import torch.nn as nn

from vggt_omega import _stub_config
from vggt_omega.models.layers import Mlp, RopePositionEmbedding, SelfAttentionBlock
from vggt_omega.models.layers.vision_transformer import DinoVisionTransformer

_RESNET_MEAN = [0.485, 0.456, 0.406]
_RESNET_STD = [0.229, 0.224, 0.225]


def _block(embed_dim, num_heads, mlp_ratio):
    return SelfAttentionBlock(
        dim=embed_dim,
        num_heads=num_heads,
        ffn_ratio=mlp_ratio,
        qkv_bias=True,
        proj_bias=True,
        ffn_bias=True,
        ffn_layer=Mlp,
        init_values=1e-5,
        use_qk_norm=True,
        mask_k_bias=True,
    )


class Aggregator(nn.Module):
    def __init__(
        self,
        patch_size: int = 16,
        embed_dim: int = 1024,
        depth: int = 24,
        num_heads: int = 16,
        mlp_ratio: float = 4.0,
        num_register_tokens: int = 16,
        register_attention_block_indices: list[int] = [2, 6, 9, 14, 20],
        cached_layer_indices: tuple[int, ...] = (4, 11, 17, 23),
    ) -> None:
        super().__init__()
        self.patch_embed = _build_patch_embed(patch_size=patch_size, embed_dim=embed_dim)
        self.rope_embed = RopePositionEmbedding(
            embed_dim=embed_dim,
            num_heads=num_heads,
            base=100,
            normalize_coords="max",
            dtype=torch.float32,
        )
        self.frame_blocks = nn.ModuleList(
            _block(embed_dim, num_heads, mlp_ratio) for _ in range(depth)
        )
        self.inter_frame_blocks = nn.ModuleList(
            _block(embed_dim, num_heads, mlp_ratio) for _ in range(depth)
        )
        self.depth = depth
        self.patch_size = patch_size
        self.cached_layer_indices = set(cached_layer_indices)
        self.camera_token = nn.Parameter(torch.randn(1, 2, 1, embed_dim))
        self.register_token = nn.Parameter(torch.randn(1, 2, num_register_tokens, embed_dim))
        self.patch_token_start = 1 + num_register_tokens
        self.inter_frame_attention_types = ["global"] * depth
        for index in register_attention_block_indices:
            if not 0 <= index < depth:
                raise ValueError(
                    f"register_attention_block_indices contains invalid block index {index}"
                )
            self.inter_frame_attention_types[index] = "register"
        for name, value in (("_resnet_mean", _RESNET_MEAN), ("_resnet_std", _RESNET_STD)):
            self.register_buffer(name, torch.tensor(value).view(1, 1, 3, 1, 1), persistent=False)

    def forward(
        self,
        images: torch.Tensor,
    ) -> tuple[list[torch.Tensor | None], int]:
        batch, frames, channels, height, width = images.shape
        if channels != 3:
            raise ValueError(f"Expected 3 input channels, got {channels}")
        images = ((images - self._resnet_mean) / self._resnet_std).view(
            batch * frames, channels, height, width
        )
        patch_tokens = self.patch_embed(images)
        if isinstance(patch_tokens, dict):
            patch_tokens = patch_tokens["x_norm_patchtokens"]
        tokens = torch.cat(
            [
                slice_expand_and_flatten(self.camera_token, batch, frames),
                slice_expand_and_flatten(self.register_token, batch, frames),
                patch_tokens,
            ],
            dim=1,
        )
        _, num_tokens, embed_dim = tokens.shape
        with torch.no_grad():
            sin, cos = self.rope_embed(H=height // self.patch_size, W=width // self.patch_size)
            frame_rope = (
                sin.to(device=patch_tokens.device, dtype=torch.float32),
                cos.to(device=patch_tokens.device, dtype=torch.float32),
            )
        outputs = []
        for index in range(self.depth):
            tokens, frame_tokens = self._run_frame_block(
                tokens, batch, frames, num_tokens, embed_dim, index, frame_rope
            )
            tokens = self._run_inter_frame_attention_block(
                tokens,
                batch,
                frames,
                num_tokens,
                embed_dim,
                index,
                self.inter_frame_attention_types[index],
            )
            cached = index in self.cached_layer_indices
            outputs.append(torch.cat([frame_tokens, tokens], dim=-1) if cached else None)
        return outputs, self.patch_token_start

    def _run_frame_block(
        self,
        tokens: torch.Tensor,
        batch_size: int,
        num_frames: int,
        num_tokens: int,
        embed_dim: int,
        block_idx: int,
        rope_sincos: tuple[torch.Tensor, torch.Tensor],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        tokens = tokens.reshape(batch_size * num_frames, num_tokens, embed_dim)
        tokens = self.frame_blocks[block_idx](tokens, rope_sincos)
        return tokens, tokens.view(batch_size, num_frames, num_tokens, embed_dim)

    def _run_inter_frame_attention_block(
        self,
        tokens: torch.Tensor,
        batch_size: int,
        num_frames: int,
        num_tokens: int,
        embed_dim: int,
        block_idx: int,
        attention_type: str,
    ) -> torch.Tensor:
        tokens = tokens.reshape(batch_size, num_frames, num_tokens, embed_dim)
        block = self.inter_frame_blocks[block_idx]
        if attention_type == "global":
            tokens = block(tokens.reshape(batch_size, num_frames * num_tokens, embed_dim), None)
            return tokens.view(batch_size, num_frames, num_tokens, embed_dim)
        if attention_type != "register":
            raise ValueError(f"Unknown inter-frame attention type: {attention_type}")
        start = self.patch_token_start
        special = tokens[:, :, :start].reshape(batch_size, num_frames * start, embed_dim)
        special = block(special, None).view(batch_size, num_frames, start, embed_dim)
        return torch.cat([special, tokens[:, :, start:]], dim=2)


def _build_patch_embed(patch_size: int, embed_dim: int) -> DinoVisionTransformer:
    sizes = _stub_config.SIZES
    model = DinoVisionTransformer(
        img_size=224,
        patch_size=patch_size,
        in_chans=3,
        pos_embed_rope_base=100,
        pos_embed_rope_normalize_coords="max",
        pos_embed_rope_dtype="fp32",
        embed_dim=embed_dim,
        depth=sizes.dino_depth,
        num_heads=sizes.dino_num_heads,
        ffn_ratio=4,
        qkv_bias=True,
        drop_path_rate=0.0,
        layerscale_init=1.0e-5,
        norm_layer="layernormbf16",
        ffn_layer="mlp",
        ffn_bias=True,
        proj_bias=True,
        n_storage_tokens=sizes.dino_storage_tokens,
        mask_k_bias=True,
    )
    model.init_weights()
    return model


def slice_expand_and_flatten(
    token_tensor: torch.Tensor, batch_size: int, num_frames: int
) -> torch.Tensor:
    first = token_tensor[:, 0:1].expand(batch_size, 1, *token_tensor.shape[2:])
    others = token_tensor[:, 1:].expand(batch_size, num_frames - 1, *token_tensor.shape[2:])
    tokens = torch.cat([first, others], dim=1)
    return tokens.reshape(batch_size * num_frames, *tokens.shape[2:])
