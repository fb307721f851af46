"""Calibration tokens: learned tokens inserted before every transformer block (VPT-deep).

The paper's second parameter-efficient baseline. For block i, ``t`` learned tokens
``tokens[i]`` (t, C) join every frame's token sequence right after the special token(s), take
the special token's RoPE position and no absolute PE, go through the frozen block, and are
dropped from its output; block i + 1 gets fresh tokens of its own. Everything downstream of the
blocks therefore sees the same shapes as upstream.

Where they go is declared per family as ``BackboneSpec.prompt_target`` (DA3: the ViT's
``process_attention``, which runs one block on (B, S, N, C) tokens). There is no identity
initialisation: tokens of any value receive attention. They start as VPT does, Xavier-uniform
U(-a, a), a = sqrt(6 / (3 p^2 + C)) for patch size p and width C, from a fixed seed.

On DA3-Small (12 blocks, C = 384) t = 4 gives 12 x 4 x 384 = 18,432 parameters.
"""

from __future__ import annotations

import math
import os
import weakref
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from raytun3r_plugin.baselines._handle import BaselineHandle
from raytun3r_plugin.errors import (
    AdapterError,
    AlreadyAppliedError,
    InputError,
    UnsupportedUpstreamError,
)

if TYPE_CHECKING:
    from raytun3r_plugin.cameras.base import Camera

__all__ = ["CalibrationTokens", "TokenHandle", "inject_calibration_tokens"]

FORMAT = "raytun3r-calibration-tokens"
_ACTIVE: weakref.WeakKeyDictionary[nn.Module, TokenHandle] = weakref.WeakKeyDictionary()


class CalibrationTokens(nn.Module):
    """``tokens`` (blocks, t, C) for one backbone.

    Args:
        blocks, t, width: number of blocks, tokens per block, token width C.
        patch_size: p of the initialisation bound.
        backbone, camera: recorded in the file.
        seed: seed of the initialisation (None: the global generator).
    """

    def __init__(
        self,
        blocks: int,
        t: int = 4,
        width: int = 384,
        *,
        patch_size: int = 14,
        backbone: str = "",
        camera: Camera | None = None,
        seed: int | None = 0,
    ) -> None:
        super().__init__()
        for name, value, high in (("blocks", blocks, 4096), ("t", t, 1024), ("width", width, 8192)):
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= high:
                raise AdapterError(f"{name} must be an integer in [1, {high}], got {value!r}")
        bound = math.sqrt(6.0 / (3 * patch_size**2 + width))
        generator = torch.Generator().manual_seed(seed) if seed is not None else None
        values = torch.empty(blocks, t, width).uniform_(-bound, bound, generator=generator)
        self.tokens = nn.Parameter(values)
        self.patch_size, self.backbone, self.camera = patch_size, backbone, camera

    def num_parameters(self) -> int:
        return self.tokens.numel()

    def save(self, path: str | os.PathLike) -> Path:
        """One ``.safetensors`` file: the ``tokens`` tensor and what it is for, in the metadata."""
        from raytun3r_plugin import __version__
        from raytun3r_plugin._io import atomic_save_safetensors

        metadata = {
            "format": FORMAT,
            "backbone": self.backbone,
            "patch_size": str(self.patch_size),
            "camera": "" if self.camera is None else self.camera.to_json(),
            "raytun3r_version": __version__,
        }
        tokens = self.tokens.detach().to("cpu", torch.float32).contiguous()
        return atomic_save_safetensors(path, {"tokens": tokens}, metadata)

    @classmethod
    def load(cls, path: str | os.PathLike) -> CalibrationTokens:
        from raytun3r_plugin._strict import read_safetensors, strict_int, strict_json

        path = Path(path)
        if not path.is_file():
            raise AdapterError(f"{path}: no such calibration-token file")
        metadata, tensors = read_safetensors(path, 64 * 2**20, AdapterError)
        if metadata.get("format") != FORMAT or set(tensors) != {"tokens"}:
            raise AdapterError(f"{path}: not a {FORMAT} file")
        tokens = tensors["tokens"]
        if (
            tokens.ndim != 3
            or tokens.dtype != torch.float32
            or not bool(torch.isfinite(tokens).all())
        ):
            raise AdapterError(f"{path}: 'tokens' must be a finite float32 (blocks, t, C) tensor")
        patch = strict_int(metadata.get("patch_size"), "patch_size", 1, 64, AdapterError, str(path))
        camera = None
        if metadata.get("camera"):
            from raytun3r_plugin.cameras import from_dict
            from raytun3r_plugin.errors import CameraError

            record = strict_json(metadata["camera"], "camera", AdapterError, str(path))
            try:
                camera = from_dict(record) if isinstance(record, dict) else None
            except CameraError as error:
                raise AdapterError(f"{path}: the recorded camera is not valid ({error})") from None
        result = cls(
            tokens.shape[0],
            tokens.shape[1],
            tokens.shape[2],
            patch_size=patch,
            backbone=metadata.get("backbone", ""),
            camera=camera,
        )
        with torch.no_grad():
            result.tokens.copy_(tokens)
        return result


class TokenHandle(BaselineHandle):
    """What :func:`inject_calibration_tokens` returns: ``remove()``, context manager,
    ``disabled()``."""

    def __init__(self, owner: nn.Module, attribute: str, model: nn.Module, tokens) -> None:
        self._owner, self._attribute = weakref.ref(owner), attribute
        self._model = weakref.ref(model)
        self.tokens = tokens
        self._enabled = True
        self._installed = False

    @property
    def active(self) -> bool:
        return self._installed

    def remove(self) -> None:
        """Take the wrapper out (the class's method shows through again); idempotent."""
        owner = self._owner()
        if self._installed and owner is not None:
            owner.__dict__.pop(self._attribute, None)
        self._installed = False
        model = self._model()
        if model is not None and _ACTIVE.get(model) is self:
            del _ACTIVE[model]


def inject_calibration_tokens(
    model: nn.Module, tokens: CalibrationTokens | None = None, *, t: int = 4
) -> TokenHandle:
    """Insert calibration tokens before every block of ``model`` (``BackboneSpec.prompt_target``).

    Args:
        model: a registered backbone that declares a prompt target.
        tokens: tokens to use (loaded, or from a fit); default: fresh ones, ``t`` per block.

    Raises:
        UnsupportedUpstreamError: no prompt target, or upstream does not match it.
        AdapterError: ``tokens`` do not fit this model's blocks or width.
    """
    import inspect

    from raytun3r_plugin.registry import resolve_path, spec_for

    spec, root = spec_for(model)
    target = spec.prompt_target
    if target is None:
        raise UnsupportedUpstreamError(f"{spec.family}: declares no place for calibration tokens")
    if model in _ACTIVE:
        raise AlreadyAppliedError(
            "this model carries calibration tokens already; remove them first"
        )
    owner = resolve_path(root, target.owner)
    blocks = resolve_path(root, target.blocks)
    method = getattr(type(owner), target.attribute, None) if owner is not None else None
    if method is None or not isinstance(blocks, nn.ModuleList):
        raise UnsupportedUpstreamError(
            f"{spec.family}: expected {target.owner}.{target.attribute} and a ModuleList at "
            f"{target.blocks}, found {type(owner).__name__} / {type(blocks).__name__}"
        )
    signature = inspect.signature(method)  # once: run_block binds every call against it
    found = tuple(signature.parameters)[1:]
    if found != target.signature:
        raise UnsupportedUpstreamError(
            f"{spec.family}: {target.attribute} expected parameters {target.signature}, found {found}"
        )
    info = spec.describe(root)
    if tokens is None:
        tokens = CalibrationTokens(
            len(blocks), t, info.embed_dim, patch_size=info.patch_size, backbone=info.name
        )
    elif tuple(tokens.tokens.shape[::2]) != (len(blocks), info.embed_dim):
        raise AdapterError(
            f"calibration tokens of shape {tuple(tokens.tokens.shape)} do not fit {len(blocks)} "
            f"blocks of width {info.embed_dim}"
        )
    index_of = {id(block): i for i, block in enumerate(blocks)}
    handle = TokenHandle(owner, target.attribute, model, tokens)
    at = target.insert_at
    owner_ref = weakref.ref(owner)

    def run_block(*args: Any, **kwargs: Any) -> Any:
        live = owner_ref()
        bound = signature.bind(live, *args, **kwargs)
        bound.apply_defaults()
        call = dict(bound.arguments)
        call.pop(next(iter(call)))  # self
        x, block = call["x"], call["block"]
        i = index_of.get(id(block))
        if not handle._enabled or i is None:
            return method(live, *args, **kwargs)
        if call.get("attn_mask") is not None:
            raise InputError("calibration tokens do not support an attention mask")
        b, s, _, c = x.shape
        count = tokens.tokens.shape[1]
        extra = tokens.tokens[i].to(x.dtype).expand(b, s, count, c)
        call["x"] = torch.cat([x[:, :, :at], extra, x[:, :, at:]], dim=2)
        pos = call.get("pos")
        if pos is not None:
            same = pos[:, :, :1].expand(b, s, count, pos.shape[-1])
            call["pos"] = torch.cat([pos[:, :, :at], same, pos[:, :, at:]], dim=2)
        out = method(live, **call)
        return torch.cat([out[:, :, :at], out[:, :, at + count :]], dim=2)

    _ACTIVE[model] = handle
    try:
        owner.__dict__[target.attribute] = run_block
        handle._installed = True
    except BaseException:
        handle.remove()
        raise
    return handle
