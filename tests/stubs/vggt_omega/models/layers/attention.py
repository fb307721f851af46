from typing import Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def rope_rotate_half(x: Tensor) -> Tensor:
    first, second = x.chunk(2, dim=-1)
    return torch.cat([-second, first], dim=-1)


def rope_apply(x: Tensor, sin: Tensor, cos: Tensor) -> Tensor:
    return (x * cos) + (rope_rotate_half(x) * sin)


class LinearKMaskedBias(nn.Linear):
    """qkv projection whose key bias is masked out by the persistent buffer ``bias_mask``."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        assert self.out_features % 3 == 0
        if self.bias is not None:
            # Upstream starts from NaN and relies on the ViT init or the checkpoint; the stub
            # writes the final mask (1 for q and v, 0 for k) at once.
            mask = torch.ones_like(self.bias)
            third = self.out_features // 3
            mask[third : 2 * third] = 0
            self.register_buffer("bias_mask", mask)

    def forward(self, input: Tensor) -> Tensor:
        bias = self.bias * self.bias_mask.to(self.bias.dtype) if self.bias is not None else None
        return F.linear(input, self.weight, bias)


class SelfAttention(nn.Module):
    """Multi-head attention; RoPE (sin, cos) of shape (hw, D) rotates the last hw tokens of q, k."""

    def __init__(
        self,
        dim: int,
        num_heads: int = 8,
        qkv_bias: bool = False,
        proj_bias: bool = True,
        attn_drop: float = 0.0,
        proj_drop: float = 0.0,
        mask_k_bias: bool = False,
        use_qk_norm: bool = False,
        device=None,
    ) -> None:
        super().__init__()
        self.num_heads = num_heads
        head_dim = dim // num_heads
        self.scale = head_dim**-0.5
        self.use_qk_norm = use_qk_norm
        self.q_norm = nn.LayerNorm(head_dim, eps=1e-5) if use_qk_norm else None
        self.k_norm = nn.LayerNorm(head_dim, eps=1e-5) if use_qk_norm else None
        linear = LinearKMaskedBias if mask_k_bias else nn.Linear
        self.qkv = linear(dim, dim * 3, bias=qkv_bias, device=device)
        self.attn_drop = nn.Dropout(attn_drop)
        self.proj = nn.Linear(dim, dim, bias=proj_bias, device=device)
        self.proj_drop = nn.Dropout(proj_drop)

    def apply_rope(
        self, q: Tensor, k: Tensor, rope: Tensor | Tuple[Tensor, Tensor]
    ) -> Tuple[Tensor, Tensor]:
        sin, cos = rope
        prefix = q.shape[-2] - sin.shape[-2]
        assert prefix >= 0

        def rotate(t):
            rotated = rope_apply(t[:, :, prefix:].to(sin.dtype), sin, cos).to(t.dtype)
            return torch.cat((t[:, :, :prefix], rotated), dim=-2)

        return rotate(q), rotate(k)

    def forward(self, x: Tensor, attn_bias=None, rope: Tensor = None) -> Tensor:
        return self.proj_drop(self.proj(self.compute_attention(self.qkv(x), attn_bias, rope)))

    def compute_attention(self, qkv: Tensor, attn_bias=None, rope=None) -> Tensor:
        assert attn_bias is None
        batch, tokens, _ = qkv.shape
        channels = self.qkv.in_features
        qkv = qkv.reshape(batch, tokens, 3, self.num_heads, channels // self.num_heads)
        q, k, v = (t.transpose(1, 2) for t in qkv.unbind(2))
        if self.use_qk_norm:
            q, k = self.q_norm(q), self.k_norm(k)
        if rope is not None:
            q, k = self.apply_rope(q, k, rope)
        x = F.scaled_dot_product_attention(q, k, v)
        return x.transpose(1, 2).reshape(batch, tokens, channels)
