"""Pi3X convolutional point/conf head (stub implementation).

``ConvHead.forward`` concatenates 2 raw uv channels from ``normalized_view_plane_uv`` (looked
up in this module's globals at call time) before each upsample stage and once after the
bilinear resize to full resolution. Like upstream, every layer runs under
``torch.utils.checkpoint`` (also in eval mode).
"""

from __future__ import annotations

from typing import List, Literal

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint


def normalized_view_plane_uv(
    width: int, height: int, aspect_ratio: float = None, dtype: torch.dtype = None, device: torch.device = None
) -> torch.Tensor:
    """Cell-centre uv grid of an image plane with half-diagonal 1; (height, width, 2) as (u, v)."""
    if aspect_ratio is None:
        aspect_ratio = width / height
    span_u = aspect_ratio / (1 + aspect_ratio**2) ** 0.5
    span_v = 1 / (1 + aspect_ratio**2) ** 0.5
    u_end = span_u * (width - 1) / width
    v_end = span_v * (height - 1) / height
    u = torch.linspace(-u_end, u_end, width, dtype=dtype, device=device)
    v = torch.linspace(-v_end, v_end, height, dtype=dtype, device=device)
    uu, vv = torch.meshgrid(u, v, indexing="xy")
    return torch.stack([uu, vv], dim=-1)


class ResidualConvBlock(nn.Module):
    def __init__(
        self,
        in_channels: int,
        out_channels: int = None,
        hidden_channels: int = None,
        padding_mode: str = "replicate",
        activation: Literal["relu", "leaky_relu", "silu", "elu"] = "relu",
        norm: Literal["group_norm", "layer_norm"] = "group_norm",
    ):
        super().__init__()
        out_channels = out_channels or in_channels
        hidden_channels = hidden_channels or in_channels
        acts = {"relu": nn.ReLU, "leaky_relu": nn.LeakyReLU, "silu": nn.SiLU, "elu": nn.ELU}
        if activation not in acts:
            raise ValueError(f"Unsupported activation function: {activation}")
        groups = max(1, hidden_channels // 32) if norm == "group_norm" else 1
        self.layers = nn.Sequential(
            nn.GroupNorm(1, in_channels),
            acts[activation](),
            nn.Conv2d(in_channels, hidden_channels, 3, padding=1, padding_mode=padding_mode),
            nn.GroupNorm(groups, hidden_channels),
            acts[activation](),
            nn.Conv2d(hidden_channels, out_channels, 3, padding=1, padding_mode=padding_mode),
        )
        self.skip_connection = (
            nn.Conv2d(in_channels, out_channels, kernel_size=1) if in_channels != out_channels else nn.Identity()
        )

    def forward(self, x):
        return self.layers(x) + self.skip_connection(x)


class ConvHead(nn.Module):
    def __init__(
        self,
        num_features: int,
        dim_in: int,
        dim_out: List[int],
        dim_proj: int = 512,
        dim_upsample: List[int] = [256, 128, 128],  # noqa: B006 (upstream default)
        dim_times_res_block_hidden: int = 1,
        num_res_blocks: int = 1,
        res_block_norm: Literal["group_norm", "layer_norm"] = "group_norm",
        last_res_blocks: int = 0,
        last_conv_channels: int = 32,
        last_conv_size: int = 1,
        projects: nn.Module = None,
        using_uv: bool = True,
    ):
        super().__init__()
        self.using_uv = using_uv
        self.projects = projects
        extra = 2 if using_uv else 0
        ins = [dim_proj] + list(dim_upsample[:-1])
        self.upsample_blocks = nn.ModuleList(
            nn.Sequential(
                self._make_upsampler(c_in + extra, c_out),
                *(
                    ResidualConvBlock(c_out, c_out, dim_times_res_block_hidden * c_out, norm=res_block_norm)
                    for _ in range(num_res_blocks)
                ),
            )
            for c_in, c_out in zip(ins, dim_upsample)
        )
        self.output_block = nn.ModuleList(
            self._make_output_block(
                dim_upsample[-1] + extra,
                d,
                dim_times_res_block_hidden,
                last_res_blocks,
                last_conv_channels,
                last_conv_size,
                res_block_norm,
            )
            for d in dim_out
        )

    def _make_upsampler(self, in_channels: int, out_channels: int):
        return nn.Sequential(
            nn.ConvTranspose2d(in_channels, out_channels, kernel_size=2, stride=2),
            nn.Conv2d(out_channels, out_channels, 3, padding=1, padding_mode="replicate"),
        )

    def _make_output_block(
        self, dim_in, dim_out, dim_times_res_block_hidden, last_res_blocks, last_conv_channels, last_conv_size, res_block_norm
    ):
        return nn.Sequential(
            nn.Conv2d(dim_in, last_conv_channels, 3, padding=1, padding_mode="replicate"),
            *(
                ResidualConvBlock(
                    last_conv_channels, last_conv_channels, dim_times_res_block_hidden * last_conv_channels, norm=res_block_norm
                )
                for _ in range(last_res_blocks)
            ),
            nn.ReLU(inplace=True),
            nn.Conv2d(last_conv_channels, dim_out, last_conv_size, padding=last_conv_size // 2, padding_mode="replicate"),
        )

    def _with_uv(self, x, img_w, img_h):
        if not self.using_uv:
            return x
        uv = normalized_view_plane_uv(
            width=x.shape[-1], height=x.shape[-2], aspect_ratio=img_w / img_h, dtype=x.dtype, device=x.device
        )
        return torch.cat([x, uv.permute(2, 0, 1).unsqueeze(0).expand(x.shape[0], -1, -1, -1)], dim=1)

    def forward(self, hidden_states: torch.Tensor, image: torch.Tensor = None, patch_h: int = None, patch_w: int = None):
        """hidden_states (B, patch_h * patch_w, C) -> list of (B, d, H, W), one per ``dim_out`` entry."""
        if image is not None:
            img_h, img_w = image.shape[-2:]
            patch_h, patch_w = img_h // 14, img_w // 14
        else:
            assert patch_h is not None and patch_w is not None
            img_h, img_w = patch_h * 14, patch_w * 14
        if self.projects is not None:
            x = self.projects(hidden_states).permute(0, 2, 1).unflatten(2, (patch_h, patch_w)).contiguous()
        else:
            x = hidden_states
        for block in self.upsample_blocks:  # patch grid -> x2 -> x4 -> x8
            x = self._with_uv(x, img_w, img_h)
            for layer in block:
                x = checkpoint(layer, x, use_reentrant=False)
        x = F.interpolate(x, (img_h, img_w), mode="bilinear", align_corners=False)
        x = self._with_uv(x, img_w, img_h)
        return [checkpoint(block, x, use_reentrant=False) for block in self.output_block]
