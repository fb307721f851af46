"""DINOv2-style ViT used by VGGT as its "patch embed" (stub implementation)."""

from __future__ import annotations

import math
from functools import partial
from typing import Callable, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.init import trunc_normal_
from torch.utils.checkpoint import checkpoint

from . import MemEffAttention, Mlp, PatchEmbed, SwiGLUFFNFused
from . import NestedTensorBlock as Block


def named_apply(fn: Callable, module: nn.Module, name="", depth_first=True, include_root=False) -> nn.Module:
    if not depth_first and include_root:
        fn(module=module, name=name)
    for child_name, child in module.named_children():
        full = f"{name}.{child_name}" if name else child_name
        named_apply(fn=fn, module=child, name=full, depth_first=depth_first, include_root=True)
    if depth_first and include_root:
        fn(module=module, name=name)
    return module


class BlockChunk(nn.ModuleList):
    def forward(self, x):
        for blk in self:
            x = blk(x)
        return x


class DinoVisionTransformer(nn.Module):
    def __init__(
        self,
        img_size=224,
        patch_size=16,
        in_chans=3,
        embed_dim=768,
        depth=12,
        num_heads=12,
        mlp_ratio=4.0,
        qkv_bias=True,
        ffn_bias=True,
        proj_bias=True,
        drop_path_rate=0.0,
        drop_path_uniform=False,
        init_values=None,
        embed_layer=PatchEmbed,
        act_layer=nn.GELU,
        block_fn=Block,
        ffn_layer="mlp",
        block_chunks=1,
        num_register_tokens=0,
        interpolate_antialias=False,
        interpolate_offset=0.1,
        qk_norm=False,
    ):
        super().__init__()
        norm_layer = partial(nn.LayerNorm, eps=1e-6)
        self.num_features = self.embed_dim = embed_dim
        self.num_tokens = 1
        self.n_blocks = depth
        self.num_heads = num_heads
        self.patch_size = patch_size
        self.num_register_tokens = num_register_tokens
        self.interpolate_antialias = interpolate_antialias
        self.interpolate_offset = interpolate_offset
        self.use_reentrant = False

        self.patch_embed = embed_layer(img_size=img_size, patch_size=patch_size, in_chans=in_chans, embed_dim=embed_dim)
        n_patches = self.patch_embed.num_patches
        self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + n_patches, embed_dim))
        assert num_register_tokens >= 0
        self.register_tokens = (
            nn.Parameter(torch.zeros(1, num_register_tokens, embed_dim)) if num_register_tokens else None
        )

        if drop_path_uniform:
            rates = [drop_path_rate] * depth
        else:
            rates = torch.linspace(0, drop_path_rate, depth).tolist()
        if ffn_layer == "mlp":
            ffn = Mlp
        elif ffn_layer in ("swiglu", "swiglufused"):
            ffn = SwiGLUFFNFused
        elif ffn_layer == "identity":
            def ffn(*args, **kwargs):
                return nn.Identity()
        else:
            raise NotImplementedError(ffn_layer)

        blocks = [
            block_fn(
                dim=embed_dim,
                num_heads=num_heads,
                mlp_ratio=mlp_ratio,
                qkv_bias=qkv_bias,
                proj_bias=proj_bias,
                ffn_bias=ffn_bias,
                drop_path=rates[i],
                norm_layer=norm_layer,
                act_layer=act_layer,
                ffn_layer=ffn,
                init_values=init_values,
                qk_norm=qk_norm,
            )
            for i in range(depth)
        ]
        if block_chunks > 0:
            self.chunked_blocks = True
            size = depth // block_chunks
            self.blocks = nn.ModuleList(
                [BlockChunk([nn.Identity()] * i + blocks[i : i + size]) for i in range(0, depth, size)]
            )
        else:
            self.chunked_blocks = False
            self.blocks = nn.ModuleList(blocks)
        self.norm = norm_layer(embed_dim)
        self.head = nn.Identity()
        self.mask_token = nn.Parameter(torch.zeros(1, embed_dim))
        self.init_weights()

    def init_weights(self):
        trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)
        if self.register_tokens is not None:
            nn.init.normal_(self.register_tokens, std=1e-6)
        named_apply(init_weights_vit_timm, self)

    def interpolate_pos_encoding(self, x, w, h):
        """Absolute PE for the token tensor ``x`` (cls + patches).

        As upstream, ``w`` receives the image height and ``h`` the image width; the square
        table is resized to (w // p, h // p) with bicubic interpolation.
        """
        in_dtype = x.dtype
        n_patch = x.shape[1] - 1
        n_table = self.pos_embed.shape[1] - 1
        if n_patch == n_table and w == h:
            return self.pos_embed
        table = self.pos_embed.float()
        side = int(math.sqrt(n_table))
        assert side * side == n_table
        rows, cols = w // self.patch_size, h // self.patch_size
        grid = table[:, 1:].reshape(1, side, side, -1).permute(0, 3, 1, 2)
        if self.interpolate_offset:
            scale = ((rows + self.interpolate_offset) / side, (cols + self.interpolate_offset) / side)
            grid = F.interpolate(grid, scale_factor=scale, mode="bicubic", antialias=self.interpolate_antialias)
        else:
            grid = F.interpolate(grid, size=(rows, cols), mode="bicubic", antialias=self.interpolate_antialias)
        assert tuple(grid.shape[-2:]) == (rows, cols)
        patch_pe = grid.permute(0, 2, 3, 1).reshape(1, rows * cols, -1)
        return torch.cat((table[:, :1], patch_pe), dim=1).to(in_dtype)

    def prepare_tokens_with_masks(self, x, masks=None):
        _, _, w, h = x.shape  # w = height, h = width (upstream naming)
        tokens = self.patch_embed(x)
        if masks is not None:
            tokens = torch.where(masks.unsqueeze(-1), self.mask_token.to(tokens.dtype).unsqueeze(0), tokens)
        tokens = torch.cat((self.cls_token.expand(tokens.shape[0], -1, -1), tokens), dim=1)
        tokens = tokens + self.interpolate_pos_encoding(tokens, w, h)
        if self.register_tokens is not None:
            regs = self.register_tokens.expand(tokens.shape[0], -1, -1)
            tokens = torch.cat((tokens[:, :1], regs, tokens[:, 1:]), dim=1)
        return tokens

    def _run_blocks(self, x):
        for blk in self.blocks:
            if self.training:
                x = checkpoint(blk, x, use_reentrant=self.use_reentrant)
            else:
                x = blk(x)
        return x

    def _feature_dict(self, x, masks):
        x_norm = self.norm(x)
        r = self.num_register_tokens
        return {
            "x_norm_clstoken": x_norm[:, 0],
            "x_norm_regtokens": x_norm[:, 1 : r + 1],
            "x_norm_patchtokens": x_norm[:, r + 1 :],
            "x_prenorm": x,
            "masks": masks,
        }

    def forward_features_list(self, x_list, masks_list):
        return [self.forward_features(x, m) for x, m in zip(x_list, masks_list)]

    def forward_features(self, x, masks=None):
        if isinstance(x, list):
            return self.forward_features_list(x, masks)
        x = self._run_blocks(self.prepare_tokens_with_masks(x, masks))
        return self._feature_dict(x, masks)

    def get_intermediate_layers(
        self,
        x: torch.Tensor,
        n: Union[int, Sequence] = 1,
        reshape: bool = False,
        return_class_token: bool = False,
        norm=True,
    ) -> Tuple[Union[torch.Tensor, Tuple[torch.Tensor]]]:
        tokens = self.prepare_tokens_with_masks(x)
        flat = [b for chunk in self.blocks for b in chunk] if self.chunked_blocks else list(self.blocks)
        flat = [b for b in flat if not isinstance(b, nn.Identity)]
        wanted = range(len(flat) - n, len(flat)) if isinstance(n, int) else n
        outputs = []
        for i, blk in enumerate(flat):
            tokens = blk(tokens)
            if i in wanted:
                outputs.append(tokens)
        if norm:
            outputs = [self.norm(o) for o in outputs]
        cls_tokens = [o[:, 0] for o in outputs]
        outputs = [o[:, 1 + self.num_register_tokens :] for o in outputs]
        if reshape:
            b, _, hh, ww = x.shape
            outputs = [
                o.reshape(b, hh // self.patch_size, ww // self.patch_size, -1).permute(0, 3, 1, 2).contiguous()
                for o in outputs
            ]
        if return_class_token:
            return tuple(zip(outputs, cls_tokens))
        return tuple(outputs)

    def forward(self, *args, is_training=True, **kwargs):
        ret = self.forward_features(*args, **kwargs)
        if is_training:
            return ret
        return self.head(ret["x_norm_clstoken"])


def init_weights_vit_timm(module: nn.Module, name: str = ""):
    if isinstance(module, nn.Linear):
        trunc_normal_(module.weight, std=0.02)
        if module.bias is not None:
            nn.init.zeros_(module.bias)


def _vit(patch_size, num_register_tokens, embed_dim, depth, num_heads, kwargs):
    # Stub: embed_dim / depth / num_heads may be overridden through kwargs (upstream fixes them).
    kwargs.setdefault("embed_dim", embed_dim)
    kwargs.setdefault("depth", depth)
    kwargs.setdefault("num_heads", num_heads)
    kwargs.setdefault("mlp_ratio", 4)
    kwargs.setdefault("block_fn", partial(Block, attn_class=MemEffAttention))
    return DinoVisionTransformer(patch_size=patch_size, num_register_tokens=num_register_tokens, **kwargs)


def vit_small(patch_size=16, num_register_tokens=0, **kwargs):
    return _vit(patch_size, num_register_tokens, 384, 12, 6, kwargs)


def vit_base(patch_size=16, num_register_tokens=0, **kwargs):
    return _vit(patch_size, num_register_tokens, 768, 12, 12, kwargs)


def vit_large(patch_size=16, num_register_tokens=0, **kwargs):
    return _vit(patch_size, num_register_tokens, 1024, 24, 16, kwargs)


def vit_giant2(patch_size=16, num_register_tokens=0, **kwargs):
    return _vit(patch_size, num_register_tokens, 1536, 40, 24, kwargs)
