"""One prediction interface for every registered backbone."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from raytun3r_plugin.errors import InputError

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass
class Prediction:
    """Backbone outputs in raytun3r's conventions (docs/conventions.md section 2).

    Attributes:
        depth: (B, S, H, W) depth along the backbone's convention (z-depth for pinhole training;
            read as range along the ray on a fisheye, see docs/conventions.md section 2).
        cam_from_world: (B, S, 4, 4) world-to-camera poses, OpenCV axes; the world is the
            backbone's reference frame.
        confidence: (B, S, H, W) or None when the backbone gives none.
        extras: backbone-specific outputs (e.g. ``intrinsics``, ``local_points``).
    """

    depth: torch.Tensor
    cam_from_world: torch.Tensor
    confidence: torch.Tensor | None = None
    extras: dict = field(default_factory=dict)


def as_batched_images(images: torch.Tensor, patch_size: int | None = 14) -> torch.Tensor:
    """Check and shape images in [0, 1] to (B, S, 3, H, W) float.

    Accepts (S, 3, H, W) or (B, S, 3, H, W). Raises :class:`InputError` naming the problem.
    """
    if not isinstance(images, torch.Tensor):
        raise InputError(f"images must be a torch.Tensor, got {type(images).__name__}")
    if images.ndim == 4:
        images = images[None]
    if images.ndim != 5 or images.shape[2] != 3:
        raise InputError(
            f"images must be (S, 3, H, W) or (B, S, 3, H, W), got shape {tuple(images.shape)}"
        )
    if not images.is_floating_point():
        raise InputError(f"images must be floating point in [0, 1], got dtype {images.dtype}")
    height, width = images.shape[-2:]
    if patch_size and (height % patch_size or width % patch_size):
        raise InputError(
            f"image size {width}x{height} px is not a multiple of the patch size {patch_size}; resize first"
        )
    return images


def imagenet_normalise(images: torch.Tensor) -> torch.Tensor:
    mean = torch.tensor(IMAGENET_MEAN, dtype=images.dtype, device=images.device).view(3, 1, 1)
    std = torch.tensor(IMAGENET_STD, dtype=images.dtype, device=images.device).view(3, 1, 1)
    return (images - mean) / std


def to_homogeneous(poses: torch.Tensor) -> torch.Tensor:
    """(..., 3, 4) rigid transforms -> (..., 4, 4)."""
    if poses.shape[-2:] == (4, 4):
        return poses
    bottom = torch.zeros(*poses.shape[:-2], 1, 4, dtype=poses.dtype, device=poses.device)
    bottom[..., 0, 3] = 1
    return torch.cat((poses, bottom), dim=-2)


def model_device(model: nn.Module) -> torch.device:
    """The device of ``model``'s first parameter or buffer (CPU for a module with neither)."""
    for tensor in model.parameters():
        return tensor.device
    for tensor in model.buffers():
        return tensor.device
    return torch.device("cpu")


def predict(model: nn.Module, images: torch.Tensor, **kwargs) -> Prediction:
    """Run ``model`` (patched or not) on images in [0, 1], (S, 3, H, W) or (B, S, 3, H, W).

    The images may sit on any device: they are moved to the model's (:func:`model_device`), and
    every output tensor is on the model's device. Each backbone's normalisation and pose
    conventions are handled by its registered spec.
    """
    from raytun3r_plugin.registry import spec_for, uncompiled

    spec, root = spec_for(model)
    if uncompiled(model) is root and model is not root:
        root = model  # torch.compile(network): run the compiled module (attributes pass through)
    if isinstance(images, torch.Tensor):
        # Every caller (adapt's windows, eval, infer, Multi-PH's views) builds its inputs on the
        # CPU; one move here lets a model on a GPU take them all.
        device = model_device(root)
        if images.device != device:
            images = images.to(device)
    return spec.predict(root, images, **kwargs)
