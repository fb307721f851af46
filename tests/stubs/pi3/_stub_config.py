"""Stub-only sizing of the Pi3 / Pi3X stub (no upstream equivalent).

Upstream ``Pi3(pos_type, decoder_size)`` and ``Pi3X(ckpt, use_multimodal)`` fix every size
inside ``__init__`` (ViT-L/14 encoder, 1024-wide 36-block decoder, 5-block 1024-wide head
decoders, ...). The stub reads those numbers from ``SIZES`` at construction time, so ``Pi3()``
and ``Pi3X()`` build tiny models. The encoder keeps the upstream ``img_size=518`` (37 x 37
positional table). Change the sizes temporarily with ``stub_sizes(**changes)``.
"""

from __future__ import annotations

import contextlib
import dataclasses

import torch


@dataclasses.dataclass(frozen=True)
class StubSizes:
    embed_dim: int = 32  # encoder and decoder width; upstream 1024 (ViT-L, decoder 'large')
    encoder_depth: int = 2  # upstream 24
    encoder_num_heads: int = 2  # upstream 16
    decoder_depth: int = 4  # upstream 36 (must be even: frame/global alternate)
    decoder_num_heads: int = 2  # upstream 16
    head_embed_dim: int = 32  # TransformerDecoder width of the heads; upstream 1024
    head_num_heads: int = 2  # upstream 16
    head_depth: int = 1  # upstream 5
    camera_dim: int = 16  # camera decoder output / CameraHead width; upstream 512
    # Pi3X only
    metric_embed_dim: int = 16  # upstream 512
    metric_num_heads: int = 2  # upstream 8
    metric_depth: int = 1  # upstream 5
    pose_inject_layers: tuple[int, ...] = (1,)  # decoder layers followed by a PoseInjectBlock; upstream (1, 9, 17, 25, 33)
    conv_upsample: tuple[int, ...] = (16, 16, 8)  # ConvHead dim_upsample; upstream (256, 128, 64)
    conv_num_res_blocks: int = 1  # upstream 2
    conv_last_channels: int = 8  # upstream 32
    seed: int | None = 0  # Pi3() / Pi3X() initialise from this seed (None: global RNG)


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
