"""Pi3X model (stub): Pi3 plus optional depth / ray (intrinsics) / pose conditioning, a ConvHead
with uv channels, ray and metric-scale outputs. Same constructor, attributes, method
signatures and outputs as upstream; see docs/stubs.md for the simplifications.
"""

from __future__ import annotations

from copy import deepcopy
from functools import partial

import torch
import torch.nn.functional as F
from torch import nn

from .. import _stub_config
from ..utils.geometry import get_pixel, homogenize_points, se3_inverse
from .dinov2.layers import Mlp, PatchEmbed
from .layers.block import PoseInjectBlock
from .layers.camera_head import CameraHead
from .layers.conv_head import ConvHead
from .layers.pos_embed import PositionGetter, RoPE2D
from .layers.transformer_head import ContextOnlyTransformerDecoder, TransformerDecoder
from .pi3 import _build_decoder, _build_encoder


class Pi3X(nn.Module):
    def __init__(self, ckpt=None, use_multimodal=True):
        super().__init__()
        with _stub_config.seeded_init():
            self._build(_stub_config.SIZES, use_multimodal)

    def _build(self, sizes, use_multimodal):
        self.use_multimodal = use_multimodal
        self.encoder = _build_encoder(sizes)
        self.patch_size = 14

        self.rope = RoPE2D(freq=100)
        self.position_getter = PositionGetter()
        self.decoder = _build_decoder(sizes, self.rope)
        self.dec_embed_dim = dim = sizes.embed_dim
        self.pose_inject_layers = tuple(sizes.pose_inject_layers)  # stub attribute (upstream: literal list)

        num_register_tokens = 5
        self.patch_start_idx = num_register_tokens
        self.register_token = nn.Parameter(torch.randn(1, 1, num_register_tokens, dim))
        nn.init.normal_(self.register_token, std=1e-6)

        if use_multimodal:
            self.depth_encoder = deepcopy(self.encoder)
            del self.depth_encoder.patch_embed
            self.depth_encoder.patch_embed = PatchEmbed(img_size=224, patch_size=14, in_chans=2, embed_dim=dim)
            self.depth_emb = nn.Parameter(torch.zeros(1, 1, dim))
            self.ray_embed = PatchEmbed(img_size=224, patch_size=14, in_chans=2, embed_dim=dim)
            # stub: small random init (upstream zero-initialises ray_embed) so that the
            # intrinsics/ray condition changes the outputs of a model without a checkpoint
            nn.init.normal_(self.ray_embed.proj.weight, std=0.02)
            nn.init.zeros_(self.ray_embed.proj.bias)
            self.pose_inject_blk = nn.ModuleList(
                PoseInjectBlock(
                    dim=dim,
                    num_heads=sizes.decoder_num_heads,
                    mlp_ratio=4,
                    qkv_bias=True,
                    proj_bias=True,
                    ffn_bias=True,
                    drop_path=0.0,
                    norm_layer=partial(nn.LayerNorm, eps=1e-6),
                    act_layer=nn.GELU,
                    ffn_layer=Mlp,
                    init_values=0.01,
                    qk_norm=True,
                )
                for _ in self.pose_inject_layers
            )

        head = dict(dec_embed_dim=sizes.head_embed_dim, dec_num_heads=sizes.head_num_heads, depth=sizes.head_depth)
        conv = dict(
            num_features=4,
            dim_in=dim,
            projects=nn.Identity(),
            dim_proj=sizes.head_embed_dim,
            dim_upsample=list(sizes.conv_upsample),
            dim_times_res_block_hidden=2,
            num_res_blocks=sizes.conv_num_res_blocks,
            res_block_norm="group_norm",
            last_res_blocks=0,
            last_conv_channels=sizes.conv_last_channels,
            last_conv_size=1,
            using_uv=True,
        )
        self.point_decoder = TransformerDecoder(in_dim=2 * dim, out_dim=sizes.head_embed_dim, rope=self.rope, **head)
        self.point_head = ConvHead(dim_out=[2, 1], **conv)
        self.camera_decoder = TransformerDecoder(in_dim=2 * dim, out_dim=sizes.camera_dim, rope=self.rope, **head)
        self.camera_head = CameraHead(dim=sizes.camera_dim)

        self.metric_token = nn.Parameter(torch.randn(1, 1, 2 * dim))
        self.metric_decoder = ContextOnlyTransformerDecoder(
            in_dim=2 * dim,
            out_dim=sizes.metric_embed_dim,
            dec_embed_dim=sizes.metric_embed_dim,
            depth=sizes.metric_depth,
            dec_num_heads=sizes.metric_num_heads,
            rope=self.rope,
        )
        self.metric_head = nn.Linear(sizes.metric_embed_dim, 1)
        nn.init.normal_(self.metric_token, std=1e-6)

        # as upstream Pi3X: built separately (not a deepcopy), sharing self.rope
        self.conf_decoder = TransformerDecoder(in_dim=2 * dim, out_dim=sizes.head_embed_dim, rope=self.rope, **head)
        self.conf_head = ConvHead(dim_out=[1], **conv)

        self.register_buffer("image_mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
        self.register_buffer("image_std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))

    def disable_multimodal(self, free_cuda_cache: bool = True):
        """Drop the conditioning branches (depth encoder, ray embedding, pose injection)."""
        self.use_multimodal = False
        for attr in ("depth_encoder", "depth_emb", "ray_embed", "pose_inject_blk"):
            if hasattr(self, attr):
                delattr(self, attr)
        if free_cuda_cache and torch.cuda.is_available():
            torch.cuda.empty_cache()

    def forward(
        self,
        imgs,
        depths=None,
        intrinsics=None,
        rays=None,
        poses=None,
        with_prior=True,
        mask_add_depth=None,
        mask_add_ray=None,
        mask_add_pose=None,
    ):
        """imgs (B, N, 3, H, W) in [0, 1]; depths (B, N, H, W); intrinsics (B, N, 3, 3) pixels;
        rays (B, N, H, W, 3); poses (B, N, 4, 4) camera-to-world (OpenCV); masks (B, N) bool."""
        imgs = (imgs - self.image_mean) / self.image_std
        B, N, _, H, W = imgs.shape
        patch_h, patch_w = H // 14, W // 14
        hidden, poses_, _use_depth_mask, use_pose_mask, _norm = self.encode(
            imgs,
            with_prior=with_prior,
            depths=depths,
            intrinsics=intrinsics,
            poses=poses,
            rays=rays,
            mask_add_depth=mask_add_depth,
            mask_add_ray=mask_add_ray,
            mask_add_pose=mask_add_pose,
        )
        hidden = hidden.reshape(B, N, -1, self.dec_embed_dim)
        hidden, pos = self.decode(hidden, N, H, W, poses_, use_pose_mask)
        return self.forward_head(hidden, pos, B, N, H, W, patch_h, patch_w)

    def encode(
        self,
        imgs,
        with_prior=True,
        depths=None,
        rays=None,
        intrinsics=None,
        poses=None,
        mask_add_depth=None,
        mask_add_ray=None,
        mask_add_pose=None,
    ):
        B, N, C, H, W = imgs.shape
        device = imgs.device
        hidden = self.encoder(imgs.reshape(B * N, C, H, W), is_training=True)["x_norm_patchtokens"]
        if not self.use_multimodal:
            return hidden, None, None, None, None

        p_depth = p_ray = p_pose = 1.0 if with_prior is True else 0.0
        if depths is None:
            p_depth = 0.0
            depths = torch.zeros((B, N, H, W), device=device)
        if rays is not None:
            rays = rays[..., :2] / (rays[..., 2:3] + 1e-6)  # (x/z, y/z)
        elif intrinsics is None:
            p_ray = 0.0
            rays = torch.zeros((B, N, H, W, 2), device=device)
        else:
            pix = torch.from_numpy(get_pixel(H, W).T.reshape(H, W, 3)).to(device).float()
            rays = torch.einsum("bnij,hwj->bnhwi", torch.inverse(intrinsics), pix)[..., :2]
        if poses is None:
            p_pose = 0.0
            poses = torch.eye(4, device=device)[None, None].repeat(B, N, 1, 1)

        # stub: deterministic masks (upstream draws rand(B, N) <= p, the same for p in {0, 1}
        # up to a measure-zero event)
        if mask_add_depth is None:
            mask_add_depth = torch.full((B, N), p_depth > 0, device=device)
        if mask_add_ray is None:
            mask_add_ray = torch.full((B, N), p_ray > 0, device=device)
        if mask_add_pose is None:
            mask_add_pose = torch.full((B, N), p_pose > 0, device=device)
        mask_add_pose = mask_add_pose.clone()
        mask_add_pose[mask_add_pose.sum(dim=1) == 1] = False  # a single posed view constrains nothing

        normalized_depths, dep_median = self.normalize_depth(depths, method="mean")
        depths_masks = (normalized_depths > 0).float().reshape(B * N, 1, H, W)
        poses_ = torch.einsum("bij,bnjk->bnik", se3_inverse(poses[:, 0]), poses)
        poses_[..., :3, 3] /= dep_median.view(B, 1, 1)

        use_depth_batch = mask_add_depth.sum(dim=1) > 0
        if (~use_depth_batch).any() and N > 1:
            # batches without depth: normalise by the mean camera distance instead
            pose_scale = poses_[..., 1:, :3, 3].norm(dim=-1)
            is_static = pose_scale.max(dim=1)[0] < 2e-2
            pose_scale = pose_scale.mean(dim=1)
            moving = ~use_depth_batch & ~is_static
            poses_[moving, ..., :3, 3] /= pose_scale.view(B, 1, 1)[moving] + 1e-8
            normalized_depths[moving] /= pose_scale.view(B, 1, 1, 1)[moving] + 1e-8
            dep_median[moving] *= pose_scale[moving]
        normalized_depths = normalized_depths.reshape(B * N, 1, H, W)

        if mask_add_depth.sum() > 0:
            depth_in = torch.cat([normalized_depths, depths_masks], dim=1)
            depth_emb = self.depth_encoder(depth_in, is_training=True)["x_norm_patchtokens"] + self.depth_emb
        else:
            depth_emb = torch.zeros_like(hidden)
        if mask_add_ray.sum() > 0:
            ray_emb = self.ray_embed(rays.reshape(B * N, H, W, 2).permute(0, 3, 1, 2))
        else:
            ray_emb = torch.zeros_like(hidden)

        hidden = hidden + ray_emb * mask_add_ray.reshape(B * N, 1, 1)
        hidden = hidden + depth_emb * mask_add_depth.reshape(B * N, 1, 1)
        return hidden, poses_, mask_add_depth, mask_add_pose, dep_median

    def _chunked_conv_head(self, head, feat, patch_h, patch_w, chunk_size=64):
        if feat.shape[0] <= chunk_size:
            return head(feat, patch_h=patch_h, patch_w=patch_w)
        parts = [head(feat[i : i + chunk_size], patch_h=patch_h, patch_w=patch_w) for i in range(0, feat.shape[0], chunk_size)]
        return [torch.cat([p[j] for p in parts], dim=0) for j in range(len(parts[0]))]

    def forward_head(self, hidden, pos, B, N, H, W, patch_h, patch_w):
        hw = patch_h * patch_w + self.patch_start_idx
        ret_point = self.point_decoder(hidden, xpos=pos)
        ret_camera = self.camera_decoder(hidden, xpos=pos)
        pos_hw = pos.reshape(B, N * hw, -1)
        # the metric token takes the first token's position (0, 0); keys use all positions
        ret_metric = self.metric_decoder(
            self.metric_token.repeat(B, 1, 1), hidden.reshape(B, N * hw, -1), xpos=pos_hw[:, 0:1], ypos=pos_hw
        )
        ret_conf = self.conf_decoder(hidden, xpos=pos)

        with torch.amp.autocast(device_type="cuda", enabled=False):
            start = self.patch_start_idx
            xy, z = self._chunked_conv_head(self.point_head, ret_point[:, start:].float(), patch_h, patch_w)
            xy = xy.permute(0, 2, 3, 1).reshape(B, N, H, W, -1)
            z = z.permute(0, 2, 3, 1).reshape(B, N, H, W, -1)
            z = torch.exp(z.clamp(max=15.0))
            local_points = torch.cat([xy * z, z], dim=-1)
            rays = F.normalize(torch.cat([xy, torch.ones_like(z)], dim=-1), dim=-1)
            camera_poses = self.camera_head(ret_camera[:, start:].float(), patch_h, patch_w).reshape(B, N, 4, 4)
            metric = self.metric_head(ret_metric.float()).reshape(B).exp()
            conf = self._chunked_conv_head(self.conf_head, ret_conf[:, start:].float(), patch_h, patch_w)[0]
            conf = conf.permute(0, 2, 3, 1).reshape(B, N, H, W, -1)
            scale = metric.view(B, 1, 1, 1, 1)
            points = torch.einsum("bnij,bnhwj->bnhwi", camera_poses, homogenize_points(local_points))[..., :3] * scale
            camera_poses[..., :3, 3] = camera_poses[..., :3, 3] * metric.view(B, 1, 1)
            local_points = local_points * scale

        return dict(
            points=points,
            local_points=local_points,
            rays=rays,
            conf=conf,
            camera_poses=camera_poses,
            metric=metric,
        )

    def decode(self, hidden, N, H, W, poses, use_pose_mask):
        if hidden.dim() == 4:
            B, N, hw, _ = hidden.shape
        else:
            BN, hw, _ = hidden.shape
            B = BN // N
        dim = self.dec_embed_dim
        hidden = hidden.reshape(B * N, hw, -1)
        register_token = self.register_token.repeat(B, N, 1, 1).reshape(B * N, *self.register_token.shape[-2:])
        hidden = torch.cat([register_token, hidden], dim=1)
        hw = hidden.shape[1]

        pos = self.position_getter(B * N, H // self.patch_size, W // self.patch_size, hidden.device)
        if self.patch_start_idx > 0:
            special = torch.zeros(B * N, self.patch_start_idx, 2).to(hidden.device).to(pos.dtype)
            pos = torch.cat([special, pos + 1], dim=1)

        pose_inject_mask = None
        if self.use_multimodal and use_pose_mask.sum() != B * N:
            views = use_pose_mask[:, :, None] & use_pose_mask[:, None, :]  # (B, N, N)
            n_patch = hw - self.patch_start_idx
            tokens = views.repeat_interleave(n_patch, dim=1).repeat_interleave(n_patch, dim=2)
            pose_inject_mask = tokens[:, None]

        inject_idx = 0
        temp_features = None
        for i, blk in enumerate(self.decoder):
            if i % 2 == 0:
                pos = pos.reshape(B * N, hw, -1)
                hidden = hidden.reshape(B * N, hw, -1)
            else:
                pos = pos.reshape(B, N * hw, -1)
                hidden = hidden.reshape(B, N * hw, -1)
            hidden = blk(hidden, xpos=pos)

            if self.use_multimodal and i in self.pose_inject_layers and use_pose_mask.sum() > 0:
                hidden = hidden.reshape(B, N, -1, dim)
                patches = hidden[..., self.patch_start_idx :, :].reshape(B, N * (hw - self.patch_start_idx), -1)
                feat = self.pose_inject_blk[inject_idx](
                    patches, poses, H, W, H // 14, W // 14, attn_mask=pose_inject_mask
                ).reshape(B, N, -1, dim)
                hidden = torch.cat(
                    [hidden[..., : self.patch_start_idx, :], hidden[..., self.patch_start_idx :, :] + feat * use_pose_mask.view(B, N, 1, 1)],
                    dim=2,
                ).reshape(B, N * hw, -1)
                inject_idx += 1
            if i == len(self.decoder) - 2:
                temp_features = hidden.clone().reshape(B * N, hw, -1)

        out = torch.cat((temp_features, hidden.reshape(B * N, hw, -1)), dim=-1)
        return out, pos.reshape(B * N, hw, -1)

    def normalize_depth(self, depths: torch.Tensor, method: str = "median") -> tuple[torch.Tensor, torch.Tensor]:
        """Divide each batch element's depths by the median or mean of its positive values."""
        if not isinstance(depths, torch.Tensor):
            depths = torch.tensor(depths, dtype=torch.float32)
        if method not in ("median", "mean"):
            raise ValueError(f"Invalid normalization method: '{method}'. Choose 'median' or 'mean'.")
        B = depths.shape[0]
        valid = torch.where(depths > 0, depths, torch.full_like(depths, float("nan"))).reshape(B, -1)
        factors = torch.nanmedian(valid, dim=1).values if method == "median" else torch.nanmean(valid, dim=1)
        factors = torch.nan_to_num(factors, nan=1.0)
        return depths / (factors.view(B, 1, 1, 1) + 1e-8), factors.reshape(-1)
