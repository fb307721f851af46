"""Camera head: camera + register tokens of the last layer, mixed across frames, -> 9-D pose."""

import torch
import torch.nn as nn
import torch.nn.functional as F

from vggt_omega import _stub_config
from vggt_omega.models.layers import SelfAttentionBlock


class CameraHead(nn.Module):
    def __init__(self, dim_in: int = 2048) -> None:
        super().__init__()
        sizes = _stub_config.SIZES
        self.token_norm = nn.LayerNorm(dim_in, eps=1e-5)
        self.trunk = nn.ModuleList(
            SelfAttentionBlock(
                dim=dim_in,
                num_heads=sizes.head_num_heads,
                qkv_bias=True,
                init_values=1e-5,
                mask_k_bias=True,
            )
            for _ in range(sizes.camera_trunk_depth)
        )
        self.trunk_norm = nn.LayerNorm(dim_in, eps=1e-5)
        self.camera_branch = nn.Sequential(
            nn.Linear(dim_in, dim_in // 2), nn.GELU(), nn.Linear(dim_in // 2, 9)
        )
        with torch.no_grad():  # stub: start near identity rotation (w = 1) and fov ~1 rad
            self.camera_branch[2].weight.mul_(0.1)
            self.camera_branch[2].bias.copy_(torch.tensor([0, 0, 0, 0, 0, 0, 1, 1, 1.0]))

    def forward(
        self,
        aggregated_tokens_list: list[torch.Tensor | None],
        patch_token_start: int,
    ) -> torch.Tensor:
        tokens = aggregated_tokens_list[-1]
        if tokens is None:
            raise ValueError("Aggregator did not cache the final layer, which CameraHead needs.")
        batch, frames, num_tokens, _ = tokens.shape
        if patch_token_start is None or patch_token_start > num_tokens:
            raise ValueError(f"bad patch_token_start {patch_token_start} for {num_tokens} tokens")
        special = self.token_norm(tokens[:, :, :patch_token_start].float())
        special = special.reshape(batch, frames * patch_token_start, -1)
        for block in self.trunk:
            special = block(special, None)
        camera = self.trunk_norm(special.reshape(batch, frames, patch_token_start, -1)[:, :, 0])
        raw = self.camera_branch(camera)
        return torch.cat([raw[..., :7], F.relu(raw[..., 7:]) + 0.01], dim=-1)
