"""Text-alignment read-out (only built with ``enable_alignment=True``); not hooked by raytun3r."""

import torch
import torch.nn as nn
import torch.nn.functional as F

from vggt_omega import _stub_config
from vggt_omega.models.layers import SelfAttentionBlock


class TextAlignmentHead(nn.Module):
    def __init__(self, dim_in: int = 2048) -> None:
        super().__init__()
        self.token_norm = nn.LayerNorm(dim_in, eps=1e-5)
        self.language_token = nn.Parameter(torch.randn(1, 1, dim_in) * 0.02)
        self.readout_blocks = nn.ModuleList(
            [SelfAttentionBlock(dim=dim_in, num_heads=_stub_config.SIZES.head_num_heads)]
        )
        self.language_token_norm = nn.LayerNorm(dim_in, eps=1e-5)
        self.embedding_projector = nn.Linear(dim_in, dim_in)

    def forward(
        self,
        aggregated_tokens_list: list[torch.Tensor | None],
        patch_token_start: int,
    ) -> dict[str, torch.Tensor]:
        tokens = aggregated_tokens_list[-1].float()
        batch, frames = tokens.shape[:2]
        special = self.token_norm(tokens[:, :, :patch_token_start]).reshape(
            batch, -1, tokens.shape[-1]
        )
        readout = torch.cat([self.language_token.expand(batch, -1, -1), special], dim=1)
        for block in self.readout_blocks:
            readout = block(readout, None)
        language = self.language_token_norm(readout[:, 0])
        return {
            "text_alignment_embedding": F.normalize(self.embedding_projector(language), dim=-1),
            "text_alignment_token": language,
        }
