"""Dense (depth) head: DPT-like, with the uv-grid sinusoid of ``_apply_pos_embed``.

Same stages and hook calls as upstream: per intermediate layer, the patch tokens are
layer-normed, reshaped to the (h, w) patch grid, projected (``projects[i]``), given
``_apply_pos_embed(x, width, height)`` and resized (x4, x2, x1, x0.5); the fused 1/4-scale
feature gets ``_apply_pos_embed`` once more, then ``proj`` / ``proj_conf`` and a pixel shuffle by
patch_size / 4 give depth = exp(.) and confidence = 1 + exp(.) at full resolution.
``create_uv_grid`` and ``position_grid_to_embed`` are imported by name into this module.
Fusion blocks are simplified.
"""

from typing import Tuple

import torch
import torch.nn as nn
import torch.nn.functional as F

from .utils import create_uv_grid, position_grid_to_embed


class _Fusion(nn.Module):
    def __init__(self, features: int, has_residual: bool = True) -> None:
        super().__init__()
        self.has_residual = has_residual
        self.residual = nn.Conv2d(features, features, 3, padding=1) if has_residual else None
        self.out_conv = nn.Conv2d(features, features, 1)

    def forward(self, x, residual=None, size=None):
        if self.has_residual:
            x = x + self.residual(F.relu(residual))
        return self.out_conv(custom_interpolate(F.relu(x), size=size))


class DenseHead(nn.Module):
    def __init__(
        self,
        dim_in: int = 2048,
        patch_size: int = 16,
        features: int = 256,
        out_channels: list[int] = [256, 512, 1024, 1024],
        intermediate_layer_idx: list[int] = [4, 11, 17, 23],
    ) -> None:
        super().__init__()
        if patch_size % 4 != 0:
            raise ValueError(
                f"DenseHead expects patch_size divisible by 4. Got patch_size={patch_size}."
            )
        self.patch_size = patch_size
        self.intermediate_layer_idx = intermediate_layer_idx
        self.final_shuffle_factor = patch_size // 4
        self.norm = nn.LayerNorm(dim_in, eps=1e-5)
        self.projects = nn.ModuleList(nn.Conv2d(dim_in, oc, 1) for oc in out_channels)
        c = out_channels
        self.resize_layers = nn.ModuleList(
            [
                nn.ConvTranspose2d(c[0], c[0], 4, stride=4),
                nn.ConvTranspose2d(c[1], c[1], 2, stride=2),
                nn.Identity(),
                nn.Conv2d(c[3], c[3], 3, stride=2, padding=1),
            ]
        )
        self.scratch = nn.Module()
        for i, channels in enumerate(out_channels, start=1):
            setattr(
                self.scratch,
                f"layer{i}_rn",
                nn.Conv2d(channels, features, 3, padding=1, bias=False),
            )
        self.scratch.refinenet1 = _Fusion(features)
        self.scratch.refinenet2 = _Fusion(features)
        self.scratch.refinenet3 = _Fusion(features)
        self.scratch.refinenet4 = _Fusion(features, has_residual=False)
        self.proj = nn.Conv2d(features, self.final_shuffle_factor**2, 1)
        self.proj_conf = nn.Conv2d(features, self.final_shuffle_factor**2, 1)

    def forward(
        self,
        aggregated_tokens_list: list[torch.Tensor | None],
        images: torch.Tensor,
        patch_token_start: int,
        frames_chunk_size: int | None = 8,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        if patch_token_start is None:
            raise ValueError("patch_token_start is required for DenseHead")
        frames = images.shape[1]
        if frames_chunk_size is None or frames_chunk_size >= frames:
            return self._forward_impl(aggregated_tokens_list, images, patch_token_start)
        chunks = [
            self._forward_impl(
                aggregated_tokens_list,
                images,
                patch_token_start,
                s,
                min(s + frames_chunk_size, frames),
            )
            for s in range(0, frames, frames_chunk_size)
        ]
        return torch.cat([d for d, _ in chunks], dim=1), torch.cat([c for _, c in chunks], dim=1)

    def _forward_impl(
        self,
        aggregated_tokens_list: list[torch.Tensor | None],
        images: torch.Tensor,
        patch_token_start: int,
        frames_start_idx: int | None = None,
        frames_end_idx: int | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        chunked = frames_start_idx is not None and frames_end_idx is not None
        if chunked:
            images = images[:, frames_start_idx:frames_end_idx]
        batch, frames, _, height, width = images.shape
        rows, cols = height // self.patch_size, width // self.patch_size
        features = []
        for i, layer in enumerate(self.intermediate_layer_idx):
            x = aggregated_tokens_list[layer]
            if x is None:
                raise ValueError(f"Aggregator did not cache layer {layer}, which DenseHead needs.")
            x = x[:, :, patch_token_start:]
            if chunked:
                x = x[:, frames_start_idx:frames_end_idx]
            x = self.norm(x.float().reshape(batch * frames, -1, x.shape[-1]))
            x = x.permute(0, 2, 1).reshape(x.shape[0], x.shape[-1], rows, cols)
            x = self._apply_pos_embed(self.projects[i](x), width, height)
            features.append(self.resize_layers[i](x))
        fused = self._apply_pos_embed(self.scratch_forward(features), width, height)
        shuffle = self.final_shuffle_factor
        depth = torch.exp(F.pixel_shuffle(self.proj(fused), shuffle).permute(0, 2, 3, 1))
        conf = 1.0 + torch.exp(F.pixel_shuffle(self.proj_conf(fused), shuffle)[:, 0])
        return depth.view(batch, frames, *depth.shape[1:]), conf.view(
            batch, frames, *conf.shape[1:]
        )

    def _apply_pos_embed(
        self, x: torch.Tensor, width: int, height: int, ratio: float = 0.1
    ) -> torch.Tensor:
        grid = create_uv_grid(
            x.shape[-1], x.shape[-2], aspect_ratio=width / height, dtype=x.dtype, device=x.device
        )
        embed = position_grid_to_embed(grid, x.shape[1]) * ratio
        return x + embed.permute(2, 0, 1)[None].expand(x.shape[0], -1, -1, -1)

    def scratch_forward(self, features: list[torch.Tensor]) -> torch.Tensor:
        s = self.scratch
        l1, l2, l3, l4 = (getattr(s, f"layer{i + 1}_rn")(f) for i, f in enumerate(features))
        out = s.refinenet4(l4, size=l3.shape[2:])
        out = s.refinenet3(out, l3, size=l2.shape[2:])
        out = s.refinenet2(out, l2, size=l1.shape[2:])
        return s.refinenet1(out, l1, size=l1.shape[2:])


def custom_interpolate(
    x: torch.Tensor,
    size: Tuple[int, int] | None = None,
    scale_factor: float | None = None,
    mode: str = "bilinear",
    align_corners: bool = True,
) -> torch.Tensor:
    if size is None:
        if scale_factor is None:
            raise ValueError("custom_interpolate requires either size or scale_factor")
        size = (int(x.shape[-2] * scale_factor), int(x.shape[-1] * scale_factor))
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=size, mode=mode, align_corners=align_corners)
