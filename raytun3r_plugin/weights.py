"""Local weight files only: safetensors, or ``.pt`` through ``torch.load(weights_only=True)``."""

from __future__ import annotations

import os
from collections import defaultdict
from pathlib import Path

import torch
from torch import nn

from raytun3r_plugin.errors import WeightsError


def read_state_dict(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """Read tensors from a local ``.safetensors`` or ``.pt``/``.pth``/``.bin`` file, never unpickling objects."""
    path = Path(path)
    if not path.is_file():
        raise WeightsError(f"{path}: no such weight file")
    if path.suffix == ".safetensors":
        from safetensors import SafetensorError
        from safetensors.torch import load_file

        try:
            return load_file(str(path))
        except (SafetensorError, OSError, ValueError, RuntimeError) as error:
            raise WeightsError(f"{path}: not a readable safetensors file ({error})") from error
    try:
        state = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a corrupt or unsafe pickle
        raise WeightsError(
            f"{path}: cannot be read with torch.load(weights_only=True) ({error})"
        ) from error
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise WeightsError(f"{path}: expected a dict of tensors")
    return state


def strip_prefix(state: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """Remove ``prefix`` from keys that have it (checkpoints of wrapper classes add one)."""
    if not any(key.startswith(prefix) for key in state):
        return state
    return {
        key[len(prefix) :] if key.startswith(prefix) else key: value for key, value in state.items()
    }


def alias_keys(model: nn.Module) -> dict[str, str]:
    """``{alias: canonical}`` for state-dict entries that share storage with an earlier entry.

    safetensors stores a shared tensor once, so a file misses exactly these keys (DA3's DualDPT
    shares one LayerNorm between its auxiliary output convs).
    """
    groups: dict[tuple, list[str]] = defaultdict(list)
    for key, tensor in model.state_dict(keep_vars=True).items():
        groups[
            (tensor.data_ptr(), tuple(tensor.shape), tuple(tensor.stride()), tensor.dtype)
        ].append(key)
    return {alias: keys[0] for keys in groups.values() for alias in keys[1:]}


def load_into(model: nn.Module, state: dict[str, torch.Tensor], source: str) -> nn.Module:
    """Load ``state`` strictly, tolerating only missing keys that alias a loaded tensor."""
    aliases = alias_keys(model)
    missing, unexpected = model.load_state_dict(state, strict=False)
    not_aliases = [key for key in missing if aliases.get(key) not in state]
    if not_aliases or unexpected:
        parts = []
        if not_aliases:
            parts.append(f"missing keys {not_aliases[:8]}{' ...' if len(not_aliases) > 8 else ''}")
        if unexpected:
            parts.append(f"unexpected keys {unexpected[:8]}{' ...' if len(unexpected) > 8 else ''}")
        raise WeightsError(f"{source}: does not match the network ({'; '.join(parts)})")
    return model


def load_backbone(name: str, path: str | os.PathLike | None = None) -> nn.Module:
    """Build backbone ``name`` and load local weights from ``path``; returns it in eval mode.

    ``name`` is any model name a registered backbone offers (``available_backbones()``).
    Built-in networks that ship with raytun3r need no path.
    """
    from raytun3r_plugin.registry import specs

    for spec in specs().values():
        if name in spec.builders:
            model = spec.builders[name](path)
            return model.eval()
    raise WeightsError(f"unknown backbone {name!r}; available: {available_backbones()}")


def available_backbones() -> list[str]:
    from raytun3r_plugin.registry import specs

    return sorted(name for spec in specs().values() for name in spec.builders)
