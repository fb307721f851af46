"""VGGTOmega: aggregator, camera head, dense (depth) head, optional text-alignment head."""

import warnings

import torch
import torch.nn as nn

from vggt_omega import _stub_config
from vggt_omega.models.aggregator import Aggregator
from vggt_omega.models.heads import CameraHead, DenseHead, TextAlignmentHead
from vggt_omega.models.layers import LayerScale


class VGGTOmega(nn.Module):
    def __init__(
        self,
        patch_size: int = 16,
        embed_dim: int = 1024,
        enable_camera: bool = True,
        enable_depth: bool = True,
        enable_alignment: bool = False,
    ) -> None:
        super().__init__()
        sizes = _stub_config.SIZES
        with _stub_config.seeded_init():
            self.aggregator = Aggregator(
                patch_size=patch_size,
                embed_dim=embed_dim,
                depth=sizes.aggregator_depth,
                num_heads=sizes.aggregator_num_heads,
                num_register_tokens=sizes.num_register_tokens,
                register_attention_block_indices=list(sizes.register_attention_block_indices),
                cached_layer_indices=sizes.cached_layer_indices,
            )
            _warn_if_rope_not_max(self.aggregator)
            dim = 2 * embed_dim
            self.camera_head = CameraHead(dim_in=dim) if enable_camera else None
            self.dense_head = (
                DenseHead(
                    dim_in=dim,
                    patch_size=patch_size,
                    features=sizes.dense_features,
                    out_channels=list(sizes.dense_out_channels),
                    intermediate_layer_idx=list(sizes.dense_intermediate_layer_idx),
                )
                if enable_depth
                else None
            )
            self.text_alignment_head = TextAlignmentHead(dim_in=dim) if enable_alignment else None
            for module in self.modules():  # stub: see _stub_config.StubSizes.layerscale
                if isinstance(module, LayerScale):
                    nn.init.constant_(module.gamma, sizes.layerscale)

    def forward(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        if images.ndim == 4:
            images = images.unsqueeze(0)
        # Upstream autocasts the aggregator to bf16/fp16 on CUDA; the stub runs in float32.
        tokens_list, start = self.aggregator(images)
        final = tokens_list[-1]
        if final is None:
            raise ValueError("Aggregator did not cache the final layer, which VGGTOmega needs.")
        predictions = {"camera_and_register_tokens": final[:, :, :start].contiguous()}
        if self.camera_head is not None:
            predictions["pose_enc"] = self.camera_head(tokens_list, patch_token_start=start)
        if self.dense_head is not None:
            depth, depth_conf = self.dense_head(tokens_list, images=images, patch_token_start=start)
            predictions["depth"] = depth
            predictions["depth_conf"] = depth_conf
        if self.text_alignment_head is not None:
            predictions.update(self.text_alignment_head(tokens_list, patch_token_start=start))
        if not self.training:
            predictions["images"] = images
        return predictions


def _warn_if_rope_not_max(aggregator: nn.Module) -> None:
    for name, module in (
        ("aggregator.patch_embed", aggregator.patch_embed),
        ("aggregator", aggregator),
    ):
        mode = getattr(getattr(module, "rope_embed", None), "normalize_coords", None)
        if mode != "max":
            warnings.warn(
                f"{name} RoPE normalize_coords is {mode!r}; the released checkpoint used 'max'.",
                stacklevel=2,
            )
