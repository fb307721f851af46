"""Stub-only sizing of the VGGT stub (no upstream equivalent).

Upstream ``VGGT.__init__`` exposes only ``img_size``, ``patch_size`` and ``embed_dim``; the
depths, head counts and DPT widths are fixed inside the code (24 aggregator blocks, 16 heads, a
24-block ViT-L, DPT features 256 ...). The stub reads those hard-wired numbers from ``SIZES``
at construction time, so ``VGGT(img_size=70, patch_size=14, embed_dim=64, enable_track=False)``
builds a model of a few hundred thousand parameters. Change the sizes temporarily with
``stub_sizes(**changes)``.
"""

from __future__ import annotations

import contextlib
import dataclasses

import torch


@dataclasses.dataclass(frozen=True)
class StubSizes:
    aggregator_depth: int = 4  # upstream Aggregator depth=24
    aggregator_num_heads: int = 4  # upstream 16
    dino_depth: int = 2  # upstream ViT-L/14: 24 blocks
    dino_num_heads: int = 4  # upstream 16
    camera_trunk_depth: int = 1  # upstream CameraHead trunk_depth=4
    camera_num_heads: int = 4  # upstream 16
    dpt_features: int = 16  # upstream 256
    dpt_out_channels: tuple[int, ...] = (8, 16, 32, 32)  # upstream (256, 512, 1024, 1024)
    dpt_intermediate_layer_idx: tuple[int, ...] = (0, 1, 2, 3)  # upstream (4, 11, 17, 23)
    track_features: int = 16  # upstream TrackHead features=128
    seed: int | None = 0  # VGGT() initialises from this seed (None: global RNG)


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
    """Make parameter initialisation deterministic without touching the global RNG."""
    if SIZES.seed is None:
        yield
        return
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(SIZES.seed)
        yield
