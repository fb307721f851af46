"""DINOv3-style axial RoPE: sin/cos of patch-centre coordinates normalised to [-1, 1].

Numerics follow upstream (raytun3r's hook re-evaluates them at displaced coordinates): centre
coordinates ``arange(0.5, n) / norm`` with norm max(H, W) / min(H, W) / per axis, mapped by
``2 c - 1``; angles ``2 pi c / periods`` for y then x ((HW, 2, D/4) flattened to (HW, D/2)),
tiled twice to (HW, D); ``periods = base ** (2 k / (D/2))``, a persistent buffer.
"""

import math
from typing import Literal

import torch
from torch import Tensor, nn


class RopePositionEmbedding(nn.Module):
    def __init__(
        self,
        embed_dim: int,
        *,
        num_heads: int,
        base: float | None = 100.0,
        min_period: float | None = None,
        max_period: float | None = None,
        normalize_coords: Literal["min", "max", "separate"] = "separate",
        shift_coords: float | None = None,
        jitter_coords: float | None = None,
        rescale_coords: float | None = None,
        dtype: torch.dtype | None = None,
        device: torch.device | None = None,
    ):
        super().__init__()
        assert embed_dim % (4 * num_heads) == 0
        if (base is None) == (min_period is None or max_period is None):
            raise ValueError("Either `base` or `min_period`+`max_period` must be provided.")
        self.base = base
        self.min_period = min_period
        self.max_period = max_period
        self.D_head = embed_dim // num_heads
        self.normalize_coords = normalize_coords
        # Training-time augmentations; the stub keeps the attributes but never applies them.
        self.shift_coords = shift_coords
        self.jitter_coords = jitter_coords
        self.rescale_coords = rescale_coords
        self.dtype = dtype
        self.register_buffer(
            "periods", torch.empty(self.D_head // 4, device=device, dtype=dtype), persistent=True
        )
        self._init_weights()

    def forward(self, *, H: int, W: int) -> tuple[Tensor, Tensor]:
        options = {"device": self.periods.device, "dtype": self.dtype}
        if self.normalize_coords == "max":
            scale_h = scale_w = max(H, W)
        elif self.normalize_coords == "min":
            scale_h = scale_w = min(H, W)
        elif self.normalize_coords == "separate":
            scale_h, scale_w = H, W
        else:
            raise ValueError(f"Unknown normalize_coords: {self.normalize_coords}")
        rows = torch.arange(0.5, H, **options) / scale_h
        cols = torch.arange(0.5, W, **options) / scale_w
        coords = torch.stack(torch.meshgrid(rows, cols, indexing="ij"), dim=-1).flatten(0, 1)
        coords = 2.0 * coords - 1.0
        angles = (2 * math.pi * coords[:, :, None] / self.periods[None, None, :]).flatten(1, 2)
        angles = angles.tile(2)
        return (torch.sin(angles), torch.cos(angles))

    def _init_weights(self):
        options = {"device": self.periods.device, "dtype": self.dtype}
        quarter = self.D_head // 4
        if self.base is not None:
            exponent = 2 * torch.arange(quarter, **options) / (self.D_head // 2)
            periods = self.base**exponent
        else:
            ratio = self.max_period / self.min_period
            periods = ratio ** torch.linspace(0, 1, quarter, **options) / ratio * self.max_period
        self.periods.data = periods
