"""Camera head of Pi3 (stub): patch features -> camera-to-world 4x4 (SVD-orthogonalised rotation)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class ResConvBlock(nn.Module):
    """Three linear layers with ReLU and a residual connection."""

    def __init__(self, in_channels, out_channels):
        super().__init__()
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.head_skip = nn.Identity() if in_channels == out_channels else nn.Linear(in_channels, out_channels)
        self.res_conv1 = nn.Linear(in_channels, out_channels)
        self.res_conv2 = nn.Linear(out_channels, out_channels)
        self.res_conv3 = nn.Linear(out_channels, out_channels)

    def forward(self, res):
        x = F.relu(self.res_conv3(F.relu(self.res_conv2(F.relu(self.res_conv1(res))))))
        return self.head_skip(res) + x


class CameraHead(nn.Module):
    def __init__(self, dim=512):
        super().__init__()
        self.res_conv = nn.ModuleList(ResConvBlock(dim, dim) for _ in range(2))
        self.avgpool = nn.AdaptiveAvgPool2d(1)
        self.more_mlps = nn.Sequential(nn.Linear(dim, dim), nn.ReLU(), nn.Linear(dim, dim), nn.ReLU())
        self.fc_t = nn.Linear(dim, 3)
        self.fc_rot = nn.Linear(dim, 9)

    def forward(self, feat, patch_h, patch_w):
        """feat (B*N, hw, C) patch features -> (B*N, 4, 4) camera-to-world."""
        BN = feat.shape[0]
        for block in self.res_conv:
            feat = block(feat)
        feat = feat.permute(0, 2, 1).reshape(BN, -1, patch_h, patch_w)
        feat = self.more_mlps(self.avgpool(feat).flatten(1))
        return self.convert_pose_to_4x4(BN, self.fc_rot(feat.float()), self.fc_t(feat.float()), feat.device)

    def convert_pose_to_4x4(self, B, out_r, out_t, device):
        out_r = self.svd_orthogonalize(out_r)
        pose = torch.zeros((B, 4, 4), device=device)
        pose[:, :3, :3] = out_r
        pose[:, :3, 3] = out_t
        pose[:, 3, 3] = 1.0
        return pose

    def svd_orthogonalize(self, m):
        """Nearest rotation (det +1) to each 3x3 matrix, rows normalised first (upstream's code
        path: torch.svd of the transpose, the last right-singular vector flipped by the det)."""
        if m.dim() < 3:
            m = m.reshape((-1, 3, 3))
        m_transpose = torch.transpose(F.normalize(m, p=2, dim=-1), dim0=-1, dim1=-2)
        u, s, v = torch.svd(m_transpose)
        det = torch.det(torch.matmul(v, u.transpose(-2, -1)))
        return torch.matmul(torch.cat([v[:, :, :-1], v[:, :, -1:] * det.view(-1, 1, 1)], dim=2), u.transpose(-2, -1))
