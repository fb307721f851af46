"""Learned flow networks as matchers, from *local* weight files (never downloading):
:class:`TorchFlowMatcher`, registered as ``"torch_flow"`` in
:mod:`raytun3r_plugin.adaptation.matchers`."""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from raytun3r_plugin.adaptation.matches import (
    Matches,
    check_pair,
    erode_mask,
    matches_from_flows,
)
from raytun3r_plugin.errors import InputError, WeightsError

__all__ = ["TorchFlowMatcher"]


# --------------------------------------------------------------------------------------------
# Learned flow networks from local weight files
# --------------------------------------------------------------------------------------------


def _load_state_dict(path: Path) -> dict[str, torch.Tensor]:
    """Read a state dict from a local ``.safetensors`` or torch file; never downloads."""
    if not path.is_file():
        raise WeightsError(f"weight file not found: {path}")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state: Any = load_file(str(path), device="cpu")
        else:
            state = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupt file, pickled objects refused by weights_only, ...
        raise WeightsError(f"cannot read weights from {path}: {exc}") from exc
    # Common checkpoint wrappers: {"state_dict": {...}} / {"model": {...}}.
    for key in ("state_dict", "model"):
        if isinstance(state, Mapping) and isinstance(state.get(key), Mapping):
            state = state[key]
    if not isinstance(state, Mapping) or not all(
        isinstance(v, torch.Tensor) for v in state.values()
    ):
        raise WeightsError(f"{path} does not hold a state dict of tensors")
    return dict(state)


def _state_dict_digest(module: torch.nn.Module) -> str:
    """sha256 over names, shapes, dtypes and bytes of a module's parameters and buffers."""
    h = hashlib.sha256()
    for name, tensor in sorted(module.state_dict().items()):
        t = tensor.detach().cpu().contiguous()
        h.update(name.encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(str(t.dtype).encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


class TorchFlowMatcher:
    """Any dense flow network (``torch.nn.Module``) used as a matcher; weights from a local file.

    The user constructs the network (e.g. ``torchvision.models.optical_flow.raft_small(
    weights=None)`` or a UFM/RoMa wrapper that outputs flow); this class loads a *local* weight
    file into it -- ``.safetensors`` via ``safetensors.torch.load_file``, anything else via
    ``torch.load(path, weights_only=True)`` (no pickled code is executed) -- and never downloads.

    Network contract: ``network(image_i, image_j)`` with ``(B, 3, H, W)`` float32 images
    (``input_range="unit"``: ``[0, 1]``; ``"symmetric"``: ``[-1, 1]``, what RAFT expects) returns
    the flow ``i -> j`` in pixels as ``(B, 2, H, W)``, or a list/tuple of such refinements (the
    last is used), or a dict with key ``"flow"``. Images are edge-padded to a multiple of
    ``pad_multiple`` (RAFT: 8). Forward and backward flow run as one batch of 2; matches then
    follow exactly the :class:`DISFlowMatcher` rules (grid, valid mask, forward-backward check,
    confidence).

    Args:
        network: the flow network (moved to ``device`` and put in eval mode).
        weights_path: local ``.safetensors`` / ``.pt`` / ``.pth`` file, or ``None`` to use the
            network's current weights. Checkpoints wrapped as ``{"state_dict": ...}`` or
            ``{"model": ...}`` are unwrapped.
        name: matcher name (enters the cache key).
        strict: passed to ``load_state_dict``.
        stride, fb_threshold_px, border_px: as in :class:`DISFlowMatcher`.
        input_range: ``"unit"`` or ``"symmetric"``.
        pad_multiple: pad H and W up to a multiple of this (1 = no padding).
        device: torch device for inference.

    The cache key includes a sha256 of the loaded state dict, so new weights invalidate cached
    matches.
    """

    def __init__(
        self,
        network: torch.nn.Module,
        weights_path: str | Path | None = None,
        *,
        name: str = "torch_flow",
        strict: bool = True,
        stride: int = 4,
        fb_threshold_px: float = 1.0,
        border_px: int = 4,
        input_range: str = "unit",
        pad_multiple: int = 8,
        device: str | torch.device = "cpu",
    ) -> None:
        if not isinstance(network, torch.nn.Module):
            raise InputError(f"network must be a torch.nn.Module, got {type(network).__name__}")
        if input_range not in ("unit", "symmetric"):
            raise InputError(f"input_range must be 'unit' or 'symmetric', got {input_range!r}")
        if int(stride) < 1 or int(pad_multiple) < 1 or int(border_px) < 0:
            raise InputError("stride and pad_multiple must be >= 1, border_px >= 0")
        if not fb_threshold_px > 0:
            raise InputError(f"fb_threshold_px must be > 0, got {fb_threshold_px}")
        self.name = str(name)
        self.device = torch.device(device)
        self.weights_path = None if weights_path is None else Path(weights_path)
        if self.weights_path is not None:
            state = _load_state_dict(self.weights_path)
            try:
                network.load_state_dict(state, strict=strict)
            except RuntimeError as exc:
                raise WeightsError(
                    f"weights in {self.weights_path} do not fit {type(network).__name__}: {exc}"
                ) from exc
        self.network = network.to(self.device).eval()
        self.stride = int(stride)
        self.fb_threshold_px = float(fb_threshold_px)
        self.border_px = int(border_px)
        self.input_range = input_range
        self.pad_multiple = int(pad_multiple)
        self._digest = _state_dict_digest(self.network)

    def settings(self) -> dict:
        return {
            "name": self.name,
            "network": type(self.network).__name__,
            "weights_sha256": self._digest,
            "stride": self.stride,
            "fb_threshold_px": self.fb_threshold_px,
            "border_px": self.border_px,
            "input_range": self.input_range,
            "pad_multiple": self.pad_multiple,
        }

    @staticmethod
    def _flow_output(out: Any) -> torch.Tensor:
        if isinstance(out, Mapping):
            out = out["flow"]
        if isinstance(out, (list, tuple)):
            out = out[-1]
        if not isinstance(out, torch.Tensor):
            raise InputError(f"flow network returned {type(out).__name__}, expected a tensor")
        return out

    def flows(self, image_i: np.ndarray, image_j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward and backward flow, each ``(H, W, 2)`` float32 pixels."""
        h, w = image_i.shape[:2]
        a = torch.from_numpy(np.ascontiguousarray(image_i, dtype=np.float32)).permute(2, 0, 1)
        b = torch.from_numpy(np.ascontiguousarray(image_j, dtype=np.float32)).permute(2, 0, 1)
        first = torch.stack([a, b]).to(self.device)
        second = torch.stack([b, a]).to(self.device)
        if self.input_range == "symmetric":
            first, second = first * 2.0 - 1.0, second * 2.0 - 1.0
        ph = (-h) % self.pad_multiple
        pw = (-w) % self.pad_multiple
        if ph or pw:
            first = torch.nn.functional.pad(first, (0, pw, 0, ph), mode="replicate")
            second = torch.nn.functional.pad(second, (0, pw, 0, ph), mode="replicate")
        with torch.inference_mode():
            flow = self._flow_output(self.network(first, second))
        if flow.ndim != 4 or flow.shape[0] != 2 or flow.shape[1] != 2:
            raise InputError(f"flow network must return (B, 2, H, W), got {tuple(flow.shape)}")
        flow = flow[:, :, :h, :w].float().permute(0, 2, 3, 1).cpu().numpy()
        return np.ascontiguousarray(flow[0]), np.ascontiguousarray(flow[1])

    def match(
        self, image_i: np.ndarray, image_j: np.ndarray, valid: np.ndarray | None = None
    ) -> Matches:
        image_i, image_j, mask = check_pair(image_i, image_j, valid)
        flow_fw, flow_bw = self.flows(image_i, image_j)
        return matches_from_flows(
            flow_fw, flow_bw, erode_mask(mask, self.border_px), self.stride, self.fb_threshold_px
        )

    def __repr__(self) -> str:
        return f"TorchFlowMatcher(name={self.name!r}, network={type(self.network).__name__})"
