"""Camera head (stub): iterative refinement of the 9-D pose encoding from the camera tokens.

Simplified relative to upstream (no adaLN modulation); same constructor, same forward
signature, same output (a list of ``num_iterations`` tensors (B, S, 9): T, quaternion xyzw,
fov_h, fov_w, FoV through ``fl_act``).
"""

from __future__ import annotations

import torch
from torch import nn

from vggt.heads.head_act import activate_pose
from vggt.layers import Mlp
from vggt.layers.block import Block


class CameraHead(nn.Module):
    def __init__(
        self,
        dim_in: int = 2048,
        trunk_depth: int = 4,
        pose_encoding_type: str = "absT_quaR_FoV",
        num_heads: int = 16,
        mlp_ratio: int = 4,
        init_values: float = 0.01,
        trans_act: str = "linear",
        quat_act: str = "linear",
        fl_act: str = "relu",
    ):
        super().__init__()
        if pose_encoding_type != "absT_quaR_FoV":
            raise ValueError(f"Unsupported camera encoding type: {pose_encoding_type}")
        self.target_dim = 9
        self.trans_act, self.quat_act, self.fl_act = trans_act, quat_act, fl_act
        self.trunk_depth = trunk_depth
        self.trunk = nn.Sequential(
            *[Block(dim=dim_in, num_heads=num_heads, mlp_ratio=mlp_ratio, init_values=init_values) for _ in range(trunk_depth)]
        )
        self.token_norm = nn.LayerNorm(dim_in)
        self.trunk_norm = nn.LayerNorm(dim_in)
        self.empty_pose_tokens = nn.Parameter(torch.zeros(1, 1, self.target_dim))
        self.embed_pose = nn.Linear(self.target_dim, dim_in)
        self.pose_branch = Mlp(in_features=dim_in, hidden_features=dim_in // 2, out_features=self.target_dim, drop=0)
        # stub: the refinement starts from identity rotation and fov_h = fov_w = 1 rad (~57 deg)
        # (upstream starts from zeros), and the updates start small, so decoded K is finite
        with torch.no_grad():
            self.empty_pose_tokens[..., 6:] = 1.0
            self.pose_branch.fc2.weight.mul_(0.1)
            self.pose_branch.fc2.bias.zero_()

    def forward(self, aggregated_tokens_list: list, num_iterations: int = 4) -> list:
        tokens = aggregated_tokens_list[-1]
        pose_tokens = self.token_norm(tokens[:, :, 0])  # camera token of every frame
        return self.trunk_fn(pose_tokens, num_iterations)

    def trunk_fn(self, pose_tokens: torch.Tensor, num_iterations: int) -> list:
        B, S, _ = pose_tokens.shape
        current = self.empty_pose_tokens.expand(B, S, -1)
        results = []
        for _ in range(num_iterations):
            current = current.detach()
            feat = self.trunk(pose_tokens + self.embed_pose(current))
            current = current + self.pose_branch(self.trunk_norm(feat))
            results.append(activate_pose(current, trans_act=self.trans_act, quat_act=self.quat_act, fl_act=self.fl_act))
        return results
