"""Attention layers of the Pi3 decoder and heads (stub implementations).

RoPE is applied to q and k after the q/k norm with positions ``xpos`` (self-attention) or
``qpos``/``kpos`` (cross-attention). xformers and SDPA-kernel selection are not mirrored.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

XFORMERS_AVAILABLE = False


def _heads(x: Tensor, num_heads: int) -> Tensor:
    B, N, C = x.shape
    return x.view(B, N, num_heads, C // num_heads).transpose(1, 2)  # (B, heads, N, d)


def _merge(x: Tensor) -> Tensor:
    B, h, N, d = x.shape
    return x.transpose(1, 2).reshape(B, N, h * d)


class Attention(nn.Module):
    def __init__(
        self,
        dim: int,
        num_heads: int = 8,
        qkv_bias: bool = False,
        proj_bias: bool = True,
        attn_drop: float = 0.0,
        proj_drop: float = 0.0,
    ) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.scale = (dim // num_heads) ** -0.5
        self.qkv = nn.Linear(dim, 3 * dim, bias=qkv_bias)
        self.attn_drop = nn.Dropout(attn_drop)
        self.proj = nn.Linear(dim, dim, bias=proj_bias)
        self.proj_drop = nn.Dropout(proj_drop)

    def forward(self, x: Tensor, attn_bias=None) -> Tensor:
        q, k, v = (_heads(t, self.num_heads) for t in self.qkv(x).chunk(3, dim=-1))
        weights = self.attn_drop((q * self.scale @ k.transpose(-2, -1)).softmax(dim=-1))
        return self.proj_drop(self.proj(_merge(weights @ v)))


class MemEffAttention(Attention):
    def forward(self, x: Tensor, attn_bias=None) -> Tensor:
        if attn_bias is not None:
            raise AssertionError("xFormers is required for using nested tensors")
        return super().forward(x)


class FlashAttention(Attention):
    """Encoder attention (SDPA)."""

    def forward(self, x: Tensor, attn_bias=None) -> Tensor:
        q, k, v = (_heads(t, self.num_heads) for t in self.qkv(x).chunk(3, dim=-1))
        return self.proj_drop(self.proj(_merge(F.scaled_dot_product_attention(q, k, v))))


class AttentionRope(nn.Module):
    def __init__(
        self,
        dim: int,
        num_heads: int = 8,
        qkv_bias: bool = False,
        proj_bias: bool = True,
        attn_drop: float = 0.0,
        proj_drop: float = 0.0,
        qk_norm: bool = False,
        norm_layer: nn.Module = nn.LayerNorm,
        rope=None,
    ) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.scale = self.head_dim**-0.5
        self.qkv = nn.Linear(dim, 3 * dim, bias=qkv_bias)
        self.attn_drop = nn.Dropout(attn_drop)
        self.proj = nn.Linear(dim, dim, bias=proj_bias)
        self.proj_drop = nn.Dropout(proj_drop)
        self.q_norm = norm_layer(self.head_dim) if qk_norm else nn.Identity()
        self.k_norm = norm_layer(self.head_dim) if qk_norm else nn.Identity()
        self.rope = rope

    def _qkv(self, x: Tensor, xpos):
        q, k, v = (_heads(t, self.num_heads) for t in self.qkv(x).chunk(3, dim=-1))
        q, k = self.q_norm(q).to(v.dtype), self.k_norm(k).to(v.dtype)
        if self.rope is not None:
            q = self.rope(q, xpos)
            k = self.rope(k, xpos)
        return q, k, v

    def forward(self, x: Tensor, attn_bias=None, xpos=None) -> Tensor:
        q, k, v = self._qkv(x, xpos)
        weights = self.attn_drop((q * self.scale @ k.transpose(-2, -1)).softmax(dim=-1))
        return self.proj_drop(self.proj(_merge(weights @ v)))


class MemEffAttentionRope(AttentionRope):
    def forward(self, x: Tensor, attn_bias=None, xpos=None) -> Tensor:
        if attn_bias is not None:
            raise AssertionError("xFormers is required for using nested tensors")
        return super().forward(x, xpos=xpos)


class FlashAttentionRope(AttentionRope):
    """Decoder self-attention: q/k norm, RoPE on q and k with ``xpos``, SDPA."""

    def forward(self, x: Tensor, attn_bias=None, xpos=None) -> Tensor:
        q, k, v = self._qkv(x, xpos)
        return self.proj_drop(self.proj(_merge(F.scaled_dot_product_attention(q, k, v))))


class CrossAttentionRope(nn.Module):
    def __init__(
        self,
        dim: int,
        num_heads: int = 8,
        qkv_bias: bool = False,
        proj_bias: bool = True,
        attn_drop: float = 0.0,
        proj_drop: float = 0.0,
        qk_norm: bool = False,
        norm_layer: nn.Module = nn.LayerNorm,
        rope=None,
    ) -> None:
        super().__init__()
        self.num_heads = num_heads
        head_dim = dim // num_heads
        self.scale = head_dim**-0.5
        self.q_proj = nn.Linear(dim, dim, bias=qkv_bias)
        self.k_proj = nn.Linear(dim, dim, bias=qkv_bias)
        self.v_proj = nn.Linear(dim, dim, bias=qkv_bias)
        self.q_norm = norm_layer(head_dim) if qk_norm else nn.Identity()
        self.k_norm = norm_layer(head_dim) if qk_norm else nn.Identity()
        self.attn_drop = nn.Dropout(attn_drop)
        self.proj = nn.Linear(dim, dim, bias=proj_bias)
        self.proj_drop = nn.Dropout(proj_drop)
        self.rope = rope

    def _qkv(self, query, key, value, qpos, kpos):
        q = _heads(self.q_proj(query), self.num_heads)
        k = _heads(self.k_proj(key), self.num_heads)
        v = _heads(self.v_proj(value), self.num_heads)
        q, k = self.q_norm(q).to(v.dtype), self.k_norm(k).to(v.dtype)
        if self.rope is not None:
            q = self.rope(q, qpos)
            k = self.rope(k, kpos)
        return q, k, v

    def forward(self, query: Tensor, key: Tensor, value: Tensor, attn_bias=None, qpos=None, kpos=None) -> Tensor:
        q, k, v = self._qkv(query, key, value, qpos, kpos)
        scores = q * self.scale @ k.transpose(-2, -1)
        if attn_bias is not None:
            scores = scores + attn_bias
        weights = self.attn_drop(scores.softmax(dim=-1))
        return self.proj_drop(self.proj(_merge(weights @ v)))


class FlashCrossAttentionRope(CrossAttentionRope):
    def forward(self, query: Tensor, key: Tensor, value: Tensor, attn_bias=None, qpos=None, kpos=None) -> Tensor:
        q, k, v = self._qkv(query, key, value, qpos, kpos)
        p = self.attn_drop.p if self.training else 0.0
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_bias, dropout_p=p)
        return self.proj_drop(self.proj(_merge(out)))


class PRopeFlashAttention(AttentionRope):
    """Pose-injection attention of Pi3X.

    Stub: instead of upstream's projective RoPE (``pi3.models.layers.prope``), each view's
    camera-from-world matrix (top 3 x 4) is embedded by a linear layer and added to that view's
    tokens before q/k/v. Tokens are laid out (B, N * hw, C), views in order.
    """

    def __init__(self, dim: int, *args, **kwargs) -> None:
        super().__init__(dim, *args, **kwargs)
        self.pose_proj = nn.Linear(12, dim)

    def forward(self, x: Tensor, extrinsics, H, W, patch_h, patch_w, K=None, attn_mask=None) -> Tensor:
        B, L, C = x.shape
        n_views = extrinsics.shape[1]
        pose = self.pose_proj(extrinsics[..., :3, :].reshape(B, n_views, 12).to(x.dtype))
        x = (x.view(B, n_views, L // n_views, C) + pose[:, :, None]).view(B, L, C)
        q, k, v = (_heads(t, self.num_heads) for t in self.qkv(x).chunk(3, dim=-1))
        q, k = self.q_norm(q).to(v.dtype), self.k_norm(k).to(v.dtype)
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask)
        return self.proj_drop(self.proj(_merge(out)))


__all__ = [
    "Attention",
    "MemEffAttention",
    "FlashAttention",
    "AttentionRope",
    "MemEffAttentionRope",
    "FlashAttentionRope",
    "CrossAttentionRope",
    "FlashCrossAttentionRope",
    "PRopeFlashAttention",
]
