"""uv grid and its sinusoidal embedding for the dense head (numerics as upstream)."""

import torch


def position_grid_to_embed(
    pos_grid: torch.Tensor, embed_dim: int, omega_0: float = 100
) -> torch.Tensor:
    """(H, W, 2) grid -> (H, W, embed_dim): x embedding then y embedding, each embed_dim/2."""
    rows, cols, two = pos_grid.shape
    assert two == 2
    flat = pos_grid.reshape(-1, 2)
    parts = [make_sincos_pos_embed(embed_dim // 2, flat[:, i], omega_0=omega_0) for i in (0, 1)]
    return torch.cat(parts, dim=-1).view(rows, cols, embed_dim)


def make_sincos_pos_embed(embed_dim: int, pos: torch.Tensor, omega_0: float = 100) -> torch.Tensor:
    """(M,) positions -> (M, embed_dim) [sin | cos], float64 frequencies (float32 on MPS)."""
    assert embed_dim % 2 == 0
    dtype = torch.float32 if pos.device.type == "mps" else torch.double
    omega = torch.arange(embed_dim // 2, dtype=dtype, device=pos.device) / (embed_dim / 2.0)
    omega = 1.0 / omega_0**omega
    angles = torch.einsum("m,d->md", pos.reshape(-1), omega)
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=1).float()


def create_uv_grid(
    width: int,
    height: int,
    aspect_ratio: float = None,
    dtype: torch.dtype = None,
    device: torch.device = None,
) -> torch.Tensor:
    """(height, width, 2) grid of (u, v) cell centres on the plane normalised by its diagonal."""
    if aspect_ratio is None:
        aspect_ratio = float(width) / float(height)
    diagonal = (aspect_ratio**2 + 1.0) ** 0.5
    span_x, span_y = aspect_ratio / diagonal, 1.0 / diagonal
    xs = torch.linspace(
        -span_x * (width - 1) / width,
        span_x * (width - 1) / width,
        steps=width,
        dtype=dtype,
        device=device,
    )
    ys = torch.linspace(
        -span_y * (height - 1) / height,
        span_y * (height - 1) / height,
        steps=height,
        dtype=dtype,
        device=device,
    )
    u, v = torch.meshgrid(xs, ys, indexing="xy")
    return torch.stack((u, v), dim=-1)
