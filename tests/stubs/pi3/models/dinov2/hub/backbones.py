"""DINOv2 constructors (stub). ``pretrained=True`` is refused: the stub never downloads."""

from __future__ import annotations

from enum import Enum
from typing import Union


class Weights(Enum):
    LVD142M = "LVD142M"


def _make_dinov2_model(
    *,
    arch_name: str = "vit_large",
    img_size: int = 518,
    patch_size: int = 14,
    init_values: float = 1.0,
    ffn_layer: str = "mlp",
    block_chunks: int = 0,
    num_register_tokens: int = 0,
    interpolate_antialias: bool = False,
    interpolate_offset: float = 0.1,
    pretrained: bool = True,
    weights: Union[Weights, str] = Weights.LVD142M,
    **kwargs,
):
    from ..models import vision_transformer as vits

    if pretrained:
        raise RuntimeError("the raytun3r Pi3 stub cannot load pretrained DINOv2 weights; use pretrained=False")
    vit_kwargs = dict(
        img_size=img_size,
        patch_size=patch_size,
        init_values=init_values,
        ffn_layer=ffn_layer,
        block_chunks=block_chunks,
        num_register_tokens=num_register_tokens,
        interpolate_antialias=interpolate_antialias,
        interpolate_offset=interpolate_offset,
    )
    vit_kwargs.update(kwargs)
    return getattr(vits, arch_name)(**vit_kwargs)


def _plain(arch, pretrained, weights, kwargs):
    return _make_dinov2_model(arch_name=arch, pretrained=pretrained, weights=weights, **kwargs)


def _reg(arch, pretrained, weights, kwargs):
    # the *_reg constructors: 4 registers, size-based bicubic interpolation with antialias
    return _make_dinov2_model(
        arch_name=arch,
        pretrained=pretrained,
        weights=weights,
        num_register_tokens=4,
        interpolate_antialias=True,
        interpolate_offset=0.0,
        **kwargs,
    )


def dinov2_vits14(*, pretrained: bool = True, weights: Union[Weights, str] = Weights.LVD142M, **kwargs):
    return _plain("vit_small", pretrained, weights, kwargs)


def dinov2_vitb14(*, pretrained: bool = True, weights: Union[Weights, str] = Weights.LVD142M, **kwargs):
    return _plain("vit_base", pretrained, weights, kwargs)


def dinov2_vitl14(*, pretrained: bool = True, weights: Union[Weights, str] = Weights.LVD142M, **kwargs):
    return _plain("vit_large", pretrained, weights, kwargs)


def dinov2_vitg14(*, pretrained: bool = True, weights: Union[Weights, str] = Weights.LVD142M, **kwargs):
    kwargs.setdefault("ffn_layer", "swiglufused")
    return _plain("vit_giant2", pretrained, weights, kwargs)


def dinov2_vits14_reg(*, pretrained: bool = True, weights: Union[Weights, str] = Weights.LVD142M, **kwargs):
    return _reg("vit_small", pretrained, weights, kwargs)


def dinov2_vitb14_reg(*, pretrained: bool = True, weights: Union[Weights, str] = Weights.LVD142M, **kwargs):
    return _reg("vit_base", pretrained, weights, kwargs)


def dinov2_vitl14_reg(*, pretrained: bool = True, weights: Union[Weights, str] = Weights.LVD142M, **kwargs):
    return _reg("vit_large", pretrained, weights, kwargs)


def dinov2_vitg14_reg(*, pretrained: bool = True, weights: Union[Weights, str] = Weights.LVD142M, **kwargs):
    kwargs.setdefault("ffn_layer", "swiglufused")
    return _reg("vit_giant2", pretrained, weights, kwargs)
