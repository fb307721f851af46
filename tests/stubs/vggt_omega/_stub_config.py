"""Stub-only sizing of the VGGT-Omega stub (no upstream equivalent).

Upstream ``VGGTOmega.__init__`` exposes only ``patch_size`` and ``embed_dim``; the depths, head
counts, token counts and head widths are fixed inside the code (24 + 24 aggregator blocks, 16
heads, 16 register tokens, a 24-block DINOv3 ViT-L/16, dense head features 256 ...). The stub
reads those numbers from ``SIZES`` when a model is constructed; ``stub_sizes(**changes)``
changes them temporarily.
"""

from __future__ import annotations

import contextlib
import dataclasses

import torch


@dataclasses.dataclass(frozen=True)
class StubSizes:
    aggregator_depth: int = 2  # upstream Aggregator depth=24
    aggregator_num_heads: int = 2  # upstream 16
    num_register_tokens: int = 2  # upstream 16
    register_attention_block_indices: tuple[int, ...] = (1,)  # upstream [2, 6, 9, 14, 20]
    cached_layer_indices: tuple[int, ...] = (0, 1)  # upstream (4, 11, 17, 23)
    dino_depth: int = 1  # upstream ViT-L/16: 24 blocks
    dino_num_heads: int = 2  # upstream 16
    dino_storage_tokens: int = 4  # upstream n_storage_tokens=4
    camera_trunk_depth: int = 1  # upstream CameraHead: 4 blocks
    head_num_heads: int = 2  # upstream CameraHead / TextAlignmentHead: 16
    dense_features: int = 8  # upstream DenseHead features=256
    dense_out_channels: tuple[int, ...] = (8, 8, 16, 16)  # upstream [256, 512, 1024, 1024]
    dense_intermediate_layer_idx: tuple[int, ...] = (0, 1, 0, 1)  # upstream [4, 11, 17, 23]
    # Upstream LayerScale starts at 1e-5 (its trained values are far larger); a fresh stub
    # with that init would hardly depend on attention, hence on positions.
    layerscale: float = 1.0
    seed: int | None = 0  # VGGTOmega() initialises from this seed (None: global RNG)


SIZES = StubSizes()


@contextlib.contextmanager
def stub_sizes(**changes):
    """Temporarily replace fields of ``SIZES`` (read when a model is constructed)."""
    global SIZES
    previous = SIZES
    SIZES = dataclasses.replace(previous, **changes)
    try:
        yield SIZES
    finally:
        SIZES = previous


@contextlib.contextmanager
def seeded_init():
    """Deterministic parameter initialisation that leaves the global RNG alone."""
    if SIZES.seed is None:
        yield
        return
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(SIZES.seed)
        yield
