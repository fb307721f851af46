"""Normalised image-plane grid and its sinusoidal embedding (used by the DPT heads)."""

from __future__ import annotations

import torch


def position_grid_to_embed(pos_grid: torch.Tensor, embed_dim: int, omega_0: float = 100) -> torch.Tensor:
    """(H, W, 2) grid -> (H, W, embed_dim): first half of the channels from u, second from v."""
    height, width, two = pos_grid.shape
    assert two == 2
    flat = pos_grid.reshape(-1, 2)
    emb_u = make_sincos_pos_embed(embed_dim // 2, flat[:, 0], omega_0=omega_0)
    emb_v = make_sincos_pos_embed(embed_dim // 2, flat[:, 1], omega_0=omega_0)
    return torch.cat([emb_u, emb_v], dim=-1).view(height, width, embed_dim)


def make_sincos_pos_embed(embed_dim: int, pos: torch.Tensor, omega_0: float = 100) -> torch.Tensor:
    """1-D embedding [sin(p * w_k), cos(p * w_k)], w_k = omega_0^(-k / (embed_dim/2)); float32 out."""
    assert embed_dim % 2 == 0
    work_dtype = torch.float32 if pos.device.type == "mps" else torch.float64
    k = torch.arange(embed_dim // 2, dtype=work_dtype, device=pos.device)
    omega = 1.0 / omega_0 ** (k / (embed_dim / 2.0))
    angles = pos.reshape(-1)[:, None] * omega[None, :]
    return torch.cat([angles.sin(), angles.cos()], dim=1).float()


def create_uv_grid(
    width: int, height: int, aspect_ratio: float = None, dtype: torch.dtype = None, device: torch.device = None
) -> torch.Tensor:
    """Cell-centre grid of an image plane whose half-diagonal is 1; returns (height, width, 2) as (u, v)."""
    if aspect_ratio is None:
        aspect_ratio = float(width) / float(height)
    diag = (aspect_ratio**2 + 1.0) ** 0.5
    span_u = aspect_ratio / diag
    span_v = 1.0 / diag
    u_end = span_u * (width - 1) / width
    v_end = span_v * (height - 1) / height
    u = torch.linspace(-u_end, u_end, steps=width, dtype=dtype, device=device)
    v = torch.linspace(-v_end, v_end, steps=height, dtype=dtype, device=device)
    uu, vv = torch.meshgrid(u, v, indexing="xy")
    return torch.stack((uu, vv), dim=-1)
