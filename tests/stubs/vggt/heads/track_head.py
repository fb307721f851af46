"""Placeholder track head (stub). Built when ``enable_track=True``; tracking is not implemented."""

from __future__ import annotations

from torch import nn

from vggt import _stub_config

from .dpt_head import DPTHead


class TrackHead(nn.Module):
    def __init__(
        self,
        dim_in,
        patch_size=14,
        features=128,
        iters=4,
        predict_conf=True,
        stride=2,
        corr_levels=7,
        corr_radius=4,
        hidden_size=384,
    ):
        super().__init__()
        sizes = _stub_config.SIZES
        self.patch_size = patch_size
        self.iters = iters
        self.feature_extractor = DPTHead(
            dim_in=dim_in,
            patch_size=patch_size,
            features=features,
            out_channels=list(sizes.dpt_out_channels),
            intermediate_layer_idx=list(sizes.dpt_intermediate_layer_idx),
            feature_only=True,
            down_ratio=2,
            pos_embed=False,
        )

    def forward(self, aggregated_tokens_list, images, patch_start_idx, query_points=None, iters=None):
        raise NotImplementedError("the raytun3r VGGT stub does not implement point tracking")
