"""2-D rotary position embedding (axial, rotate-half), looked up from integer position tables.

Head channels are split in two halves: the first half rotates with the y position, the second
with the x position. cos/sin tables are built for integer positions 0..max and indexed with
``F.embedding``, so positions must be integer (Long) tensors.
"""

from __future__ import annotations

from typing import Dict, Tuple

import torch
import torch.nn.functional as F
from torch import nn


class PositionGetter:
    """(y, x) grid positions of the patches, cached per (height, width)."""

    def __init__(self):
        self.position_cache: Dict[Tuple[int, int], torch.Tensor] = {}

    def __call__(self, batch_size: int, height: int, width: int, device: torch.device) -> torch.Tensor:
        key = (height, width)
        if key not in self.position_cache:
            rows = torch.arange(height, device=device)
            cols = torch.arange(width, device=device)
            self.position_cache[key] = torch.cartesian_prod(rows, cols)  # (h*w, 2), row-major
        grid = self.position_cache[key]
        return grid.view(1, height * width, 2).expand(batch_size, -1, -1).clone()


class RotaryPositionEmbedding2D(nn.Module):
    def __init__(self, frequency: float = 100.0, scaling_factor: float = 1.0):
        super().__init__()
        self.base_frequency = frequency
        self.scaling_factor = scaling_factor  # stored, unused (as upstream)
        self.frequency_cache: Dict[Tuple, Tuple[torch.Tensor, torch.Tensor]] = {}

    def _compute_frequency_components(
        self, dim: int, seq_len: int, device: torch.device, dtype: torch.dtype
    ) -> Tuple[torch.Tensor, torch.Tensor]:
        key = (dim, seq_len, device, dtype)
        cached = self.frequency_cache.get(key)
        if cached is None:
            inv_freq = 1.0 / (self.base_frequency ** (torch.arange(0, dim, 2, device=device).float() / dim))
            table_pos = torch.arange(seq_len, device=device, dtype=inv_freq.dtype)
            angles = (table_pos[:, None] * inv_freq[None, :]).to(dtype)
            angles = torch.cat((angles, angles), dim=-1)  # (seq_len, dim)
            cached = (angles.cos().to(dtype), angles.sin().to(dtype))
            self.frequency_cache[key] = cached
        return cached

    @staticmethod
    def _rotate_features(x: torch.Tensor) -> torch.Tensor:
        half = x.shape[-1] // 2
        return torch.cat((-x[..., half:], x[..., :half]), dim=-1)

    def _apply_1d_rope(
        self, tokens: torch.Tensor, positions: torch.Tensor, cos_comp: torch.Tensor, sin_comp: torch.Tensor
    ) -> torch.Tensor:
        # integer table lookup: (B, N) positions -> (B, 1, N, dim)
        cos = F.embedding(positions, cos_comp).unsqueeze(1)
        sin = F.embedding(positions, sin_comp).unsqueeze(1)
        return tokens * cos + self._rotate_features(tokens) * sin

    def forward(self, tokens: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        """tokens (B, heads, N, D), positions (B, N, 2) integer (y, x)."""
        assert tokens.size(-1) % 2 == 0, "Feature dimension must be even"
        assert positions.ndim == 3 and positions.shape[-1] == 2, "Positions must have shape (batch_size, n_tokens, 2)"
        half_dim = tokens.size(-1) // 2
        table_len = int(positions.max()) + 1
        cos_comp, sin_comp = self._compute_frequency_components(half_dim, table_len, tokens.device, tokens.dtype)
        y_part, x_part = tokens.chunk(2, dim=-1)
        y_part = self._apply_1d_rope(y_part, positions[..., 0], cos_comp, sin_comp)
        x_part = self._apply_1d_rope(x_part, positions[..., 1], cos_comp, sin_comp)
        return torch.cat((y_part, x_part), dim=-1)
