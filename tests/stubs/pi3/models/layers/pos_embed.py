"""RoPE2D and PositionGetter of the Pi3 decoder (stub implementations).

As upstream, the module first tries the compiled CUDA RoPE of a top-level ``models.curope``
package; only when that import fails is the PyTorch ``RoPE2D`` below defined. The PyTorch
version looks cos/sin up in integer position tables (``F.embedding``), so positions must be
integer (Long) tensors.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

try:
    from models.curope import cuRoPE2D

    RoPE2D = cuRoPE2D
except ImportError:
    print("Warning (raytun3r Pi3 stub): no compiled cuRoPE2D found, using the PyTorch RoPE2D")

    class RoPE2D(torch.nn.Module):
        def __init__(self, freq=100.0, F0=1.0):
            super().__init__()
            self.base = freq
            self.F0 = F0
            self.cache = {}

        def get_cos_sin(self, D, seq_len, device, dtype):
            key = (D, seq_len, device, dtype)
            if key not in self.cache:
                inv_freq = 1.0 / (self.base ** (torch.arange(0, D, 2).float().to(device) / D))
                table_pos = torch.arange(seq_len, device=device, dtype=inv_freq.dtype)
                angles = (table_pos[:, None] * inv_freq[None, :]).to(dtype)
                angles = torch.cat((angles, angles), dim=-1)  # (seq_len, D)
                self.cache[key] = (angles.cos(), angles.sin())
            return self.cache[key]

        @staticmethod
        def rotate_half(x):
            half = x.shape[-1] // 2
            return torch.cat((-x[..., half:], x[..., :half]), dim=-1)

        def apply_rope1d(self, tokens, pos1d, cos, sin):
            assert pos1d.ndim == 2
            cos = F.embedding(pos1d, cos)[:, None, :, :]
            sin = F.embedding(pos1d, sin)[:, None, :, :]
            return tokens * cos + self.rotate_half(tokens) * sin

        def forward(self, tokens, positions):
            """tokens (B, heads, N, dim); positions (B, N, 2) integer (y, x)."""
            assert tokens.size(3) % 2 == 0, "number of dimensions should be a multiple of two"
            D = tokens.size(3) // 2
            assert positions.ndim == 3 and positions.shape[-1] == 2
            cos, sin = self.get_cos_sin(D, int(positions.max()) + 1, tokens.device, tokens.dtype)
            y, x = tokens.chunk(2, dim=-1)
            y = self.apply_rope1d(y, positions[:, :, 0], cos, sin)
            x = self.apply_rope1d(x, positions[:, :, 1], cos, sin)
            return torch.cat((y, x), dim=-1)


class PositionGetter:
    """(y, x) grid positions of the patches, cached per (h, w)."""

    def __init__(self):
        self.cache_positions = {}

    def __call__(self, b, h, w, device):
        if (h, w) not in self.cache_positions:
            self.cache_positions[h, w] = torch.cartesian_prod(torch.arange(h, device=device), torch.arange(w, device=device))
        return self.cache_positions[h, w].view(1, h * w, 2).expand(b, -1, 2).clone()
