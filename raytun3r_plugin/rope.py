"""Axial 2-D rotary position encoding evaluated at continuous positions.

The three upstream backbones look their cos/sin tables up with integer positions
(``F.embedding``), so a fractional RoPE position needs the rotary function itself replaced. The
functions here compute the angles directly from the positions with the same operation order as
the upstream tables (float32 product of position and inverse frequency, then cast, duplicated,
rotate-half pairing), so integer positions give bit-identical results.
"""

from __future__ import annotations

import torch


def inverse_frequencies(half_dim: int, base: float, device) -> torch.Tensor:
    """Inverse frequencies base^(-2k/half_dim), k < half_dim/2, float32 (half_dim/2,)."""
    exponents = torch.arange(0, half_dim, 2, device=device).float() / half_dim
    return 1.0 / (base**exponents)


def rotate_half(x: torch.Tensor) -> torch.Tensor:
    """(x1, x2) -> (-x2, x1) on the last dimension split in halves."""
    half = x.shape[-1] // 2
    return torch.cat((-x[..., half:], x[..., :half]), dim=-1)


def apply_rope_1d(
    tokens: torch.Tensor, positions: torch.Tensor, inv_freq: torch.Tensor
) -> torch.Tensor:
    """Rotate ``tokens`` (B, heads, N, d) by angles ``positions`` (B, N) x ``inv_freq`` (d/2,)."""
    angles = (positions.to(inv_freq.dtype)[..., None] * inv_freq).to(tokens.dtype)
    angles = torch.cat((angles, angles), dim=-1)[:, None]
    return tokens * angles.cos() + rotate_half(tokens) * angles.sin()


def apply_rope_2d(tokens: torch.Tensor, positions: torch.Tensor, base: float) -> torch.Tensor:
    """Axial RoPE: first half of the head channels driven by y, second half by x.

    tokens: (B, heads, N, D); positions: (B, N, 2) in (y, x) order, any real dtype.
    """
    half_dim = tokens.shape[-1] // 2
    inv_freq = inverse_frequencies(half_dim, base, tokens.device)
    vertical, horizontal = tokens.chunk(2, dim=-1)
    return torch.cat(
        (
            apply_rope_1d(vertical, positions[..., 0], inv_freq),
            apply_rope_1d(horizontal, positions[..., 1], inv_freq),
        ),
        dim=-1,
    )


def displaced_positions(
    positions: torch.Tensor, patch_start: int, displacement: torch.Tensor
) -> torch.Tensor:
    """Add a per-patch displacement (hw, 2) to the patch rows of ``positions`` (..., patch_start + hw, 2).

    Special tokens (the first ``patch_start`` rows) keep their positions. Returns float positions.
    """
    positions = positions.to(displacement.dtype)
    special, patches = positions[..., :patch_start, :], positions[..., patch_start:, :]
    return torch.cat((special, patches + displacement), dim=-2)
