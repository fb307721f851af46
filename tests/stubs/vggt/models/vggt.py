"""VGGT model (stub). Same constructor, forward signature and output dict as upstream."""

from __future__ import annotations

import torch
from torch import nn

from vggt import _stub_config
from vggt.heads.camera_head import CameraHead
from vggt.heads.dpt_head import DPTHead
from vggt.heads.track_head import TrackHead
from vggt.models.aggregator import Aggregator


class VGGT(nn.Module):
    def __init__(
        self,
        img_size=518,
        patch_size=14,
        embed_dim=1024,
        enable_camera=True,
        enable_point=True,
        enable_depth=True,
        enable_track=True,
    ):
        super().__init__()
        sizes = _stub_config.SIZES
        if max(sizes.dpt_intermediate_layer_idx) >= sizes.aggregator_depth:
            raise ValueError("stub sizes: dpt_intermediate_layer_idx must index the aggregator blocks")
        dpt = dict(
            features=sizes.dpt_features,
            out_channels=list(sizes.dpt_out_channels),
            intermediate_layer_idx=list(sizes.dpt_intermediate_layer_idx),
        )
        with _stub_config.seeded_init():
            self.aggregator = Aggregator(
                img_size=img_size,
                patch_size=patch_size,
                embed_dim=embed_dim,
                depth=sizes.aggregator_depth,
                num_heads=sizes.aggregator_num_heads,
            )
            self.camera_head = (
                CameraHead(
                    dim_in=2 * embed_dim, trunk_depth=sizes.camera_trunk_depth, num_heads=sizes.camera_num_heads
                )
                if enable_camera
                else None
            )
            self.point_head = (
                DPTHead(dim_in=2 * embed_dim, output_dim=4, activation="inv_log", conf_activation="expp1", **dpt)
                if enable_point
                else None
            )
            self.depth_head = (
                DPTHead(dim_in=2 * embed_dim, output_dim=2, activation="exp", conf_activation="expp1", **dpt)
                if enable_depth
                else None
            )
            self.track_head = (
                TrackHead(dim_in=2 * embed_dim, patch_size=patch_size, features=sizes.track_features)
                if enable_track
                else None
            )

    def forward(self, images: torch.Tensor, query_points: torch.Tensor = None):
        """images (S, 3, H, W) or (B, S, 3, H, W) in [0, 1]."""
        if images.dim() == 4:
            images = images.unsqueeze(0)
        if query_points is not None and query_points.dim() == 2:
            query_points = query_points.unsqueeze(0)

        aggregated_tokens_list, patch_start_idx = self.aggregator(images)
        predictions = {}
        with torch.amp.autocast(device_type="cuda", enabled=False):
            if self.camera_head is not None:
                pose_enc_list = self.camera_head(aggregated_tokens_list)
                predictions["pose_enc"] = pose_enc_list[-1]
                predictions["pose_enc_list"] = pose_enc_list
            if self.depth_head is not None:
                depth, depth_conf = self.depth_head(aggregated_tokens_list, images=images, patch_start_idx=patch_start_idx)
                predictions["depth"] = depth
                predictions["depth_conf"] = depth_conf
            if self.point_head is not None:
                pts3d, pts3d_conf = self.point_head(
                    aggregated_tokens_list, images=images, patch_start_idx=patch_start_idx
                )
                predictions["world_points"] = pts3d
                predictions["world_points_conf"] = pts3d_conf
        if self.track_head is not None and query_points is not None:
            track_list, vis, conf = self.track_head(
                aggregated_tokens_list, images=images, patch_start_idx=patch_start_idx, query_points=query_points
            )
            predictions["track"] = track_list[-1]
            predictions["vis"] = vis
            predictions["conf"] = conf
        if not self.training:
            predictions["images"] = images
        return predictions
