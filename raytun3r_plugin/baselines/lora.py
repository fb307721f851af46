"""LoRA on the backbone's fused ``attn.qkv`` layers: the paper's parameter-efficient baseline.

Each targeted ``nn.Linear`` (in -> out) gets a low-rank update, y = W x + b + (alpha / r) B A x,
with A (r x in) Kaiming-uniform and B (out x r) zero, so a fresh LoRA is the identity (PEFT's
default initialisation). The update is added by a forward hook: the model's own modules,
parameters and state dict are never replaced, and :meth:`LoraHandle.remove` takes the hooks out,
leaving the model bit for bit as it was.

Which layers: the ``attn.qkv`` of every block in the ``ModuleList`` s a backbone declares as
``BackboneSpec.transformer_blocks``. On DA3-Small (12 blocks, 384 -> 1152) r = 8 gives
12 x 8 x (384 + 1152) = 147,456 parameters, the paper's count.

Files: :meth:`LoraWeights.save` writes a folder in PEFT's layout, ``adapter_model.safetensors``
(keys ``base_model.model.<module path>.lora_A.weight`` / ``lora_B.weight``) and
``adapter_config.json``, so PEFT users can load it on the same model; raytun3r's own record
(backbone, camera, what it is) rides in the safetensors metadata, which PEFT ignores.
"""

from __future__ import annotations

import json
import math
import os
import weakref
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from raytun3r_plugin.baselines._handle import BaselineHandle
from raytun3r_plugin.errors import AdapterError, AlreadyAppliedError, UnsupportedUpstreamError

if TYPE_CHECKING:
    from raytun3r_plugin.cameras.base import Camera

__all__ = ["LoraHandle", "LoraWeights", "inject_lora", "lora_targets"]

FORMAT = "raytun3r-lora"
_PEFT_PREFIX = "base_model.model."
# model -> its handle; weak, so a dropped model takes its entry with it, and the model itself
# carries no attribute that deepcopy or state_dict would see.
_ACTIVE: weakref.WeakKeyDictionary[nn.Module, LoraHandle] = weakref.WeakKeyDictionary()


def lora_targets(model: nn.Module) -> list[str]:
    """Dotted paths (from the model passed) of the ``attn.qkv`` linear layers LoRA tunes.

    Raises:
        UnsupportedUpstreamError: the family declares no transformer blocks, or a declared block
            has no ``attn.qkv`` ``nn.Linear``.
    """
    from raytun3r_plugin.registry import resolve_path, spec_for

    spec, root = spec_for(model)
    if not spec.transformer_blocks:
        raise UnsupportedUpstreamError(f"{spec.family}: declares no transformer blocks for LoRA")
    prefix = next((name + "." for name, module in model.named_modules() if module is root), "")
    prefix = "" if prefix == "." else prefix
    paths = []
    for blocks_path in spec.transformer_blocks:
        blocks = resolve_path(root, blocks_path)
        if not isinstance(blocks, nn.ModuleList):
            raise UnsupportedUpstreamError(
                f"{spec.family}: expected a ModuleList of blocks at {blocks_path!r}, found "
                f"{type(blocks).__name__}"
            )
        for index, block in enumerate(blocks):
            qkv = resolve_path(block, "attn.qkv")
            if not isinstance(qkv, nn.Linear):
                raise UnsupportedUpstreamError(
                    f"{spec.family}: expected an nn.Linear at {blocks_path}.{index}.attn.qkv, "
                    f"found {type(qkv).__name__}"
                )
            paths.append(f"{prefix}{blocks_path}.{index}.attn.qkv")
    return paths


class LoraWeights(nn.Module):
    """The LoRA factors of one model: ``lora_A[path]`` (r, in) and ``lora_B[path]`` (out, r).

    Args:
        shapes: ``{module path: (in_features, out_features)}`` of the targeted layers.
        r, alpha: rank and scaling (the update is multiplied by ``alpha / r``).
        backbone: the backbone name, recorded in the file.
        camera: the camera the weights were fitted on (recorded), or None.
        seed: seed of A's Kaiming-uniform initialisation (None: the global generator).
    """

    def __init__(
        self,
        shapes: dict[str, tuple[int, int]],
        r: int = 8,
        alpha: float = 16.0,
        *,
        backbone: str = "",
        camera: Camera | None = None,
        seed: int | None = 0,
    ) -> None:
        super().__init__()
        if isinstance(r, bool) or not isinstance(r, int) or not 1 <= r <= 1024:
            raise AdapterError(f"LoRA rank r must be an integer in [1, 1024], got {r!r}")
        if not (isinstance(alpha, int | float) and math.isfinite(alpha) and alpha > 0):
            raise AdapterError(f"LoRA alpha must be a positive number, got {alpha!r}")
        self.r, self.alpha = r, float(alpha)
        self.backbone, self.camera = backbone, camera
        self.paths = list(shapes)
        generator = torch.Generator().manual_seed(seed) if seed is not None else None
        self.lora_A = nn.ParameterList()
        self.lora_B = nn.ParameterList()
        for in_features, out_features in shapes.values():
            a = torch.empty(r, in_features)
            # kaiming_uniform_(a=sqrt(5)): bound = 1 / sqrt(in_features), as PEFT initialises A.
            bound = 1.0 / math.sqrt(in_features)
            a.uniform_(-bound, bound, generator=generator)
            self.lora_A.append(nn.Parameter(a))
            self.lora_B.append(nn.Parameter(torch.zeros(out_features, r)))

    @property
    def scaling(self) -> float:
        return self.alpha / self.r

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def delta(self, index: int, x: torch.Tensor) -> torch.Tensor:
        """(alpha / r) B A x for the layer ``index``; x (..., in) -> (..., out)."""
        # The factors stay where they were made (the CPU, like an adapter's tables); moved per
        # call, differentiably, so a model on a GPU can carry them.
        a = self.lora_A[index].to(device=x.device, dtype=x.dtype)
        b = self.lora_B[index].to(device=x.device, dtype=x.dtype)
        return (x @ a.T) @ b.T * self.scaling

    # ------------------------------------------------------------------ files
    def peft_state_dict(self) -> dict[str, torch.Tensor]:
        """PEFT's saved key names: ``base_model.model.<path>.lora_A.weight`` / ``lora_B``."""
        state = {}
        for index, path in enumerate(self.paths):
            state[f"{_PEFT_PREFIX}{path}.lora_A.weight"] = self.lora_A[index].detach().clone()
            state[f"{_PEFT_PREFIX}{path}.lora_B.weight"] = self.lora_B[index].detach().clone()
        return state

    def peft_config(self) -> dict[str, Any]:
        """PEFT's ``adapter_config.json`` for these weights (a LoraConfig, no dropout, no bias)."""
        return {
            "peft_type": "LORA",
            "task_type": None,
            "base_model_name_or_path": None,
            "r": self.r,
            "lora_alpha": self.alpha,
            "lora_dropout": 0.0,
            "bias": "none",
            "fan_in_fan_out": False,
            "init_lora_weights": True,
            "use_rslora": False,
            "use_dora": False,
            "target_modules": sorted(self.paths),
            "inference_mode": True,
        }

    def save(self, folder: str | os.PathLike) -> Path:
        """Write ``folder/adapter_model.safetensors`` and ``folder/adapter_config.json``."""
        from raytun3r_plugin._version import __version__
        from raytun3r_plugin.atomic_files import atomic_save_safetensors, atomic_write_text

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        metadata = {
            "format": "pt",  # what PEFT writes; raytun3r's record follows
            "raytun3r_format": FORMAT,
            "backbone": self.backbone,
            "camera": "" if self.camera is None else self.camera.to_json(),
            "raytun3r_version": __version__,
        }
        atomic_save_safetensors(
            folder / "adapter_model.safetensors", self.peft_state_dict(), metadata
        )
        atomic_write_text(
            folder / "adapter_config.json", json.dumps(self.peft_config(), indent=2, sort_keys=True)
        )
        return folder

    @classmethod
    def load(cls, folder: str | os.PathLike) -> LoraWeights:
        """Read a folder written by :meth:`save` (or by PEFT for LoRA on the same layers)."""
        from raytun3r_plugin._strict import read_safetensors, strict_json

        folder = Path(folder)
        config_path = folder / "adapter_config.json"
        if not config_path.is_file():
            raise AdapterError(f"{folder}: no adapter_config.json")
        config = strict_json(
            config_path.read_text(), "adapter_config.json", AdapterError, str(folder)
        )
        if not isinstance(config, dict) or config.get("peft_type") != "LORA":
            raise AdapterError(f"{config_path}: not a LoRA config (peft_type must be 'LORA')")
        r, alpha = config.get("r"), config.get("lora_alpha")
        metadata, tensors = read_safetensors(
            folder / "adapter_model.safetensors", 256 * 2**20, AdapterError
        )
        shapes: dict[str, tuple[int, int]] = {}
        for key in sorted(tensors):
            if not (key.startswith(_PEFT_PREFIX) and key.endswith(".lora_A.weight")):
                continue
            path = key[len(_PEFT_PREFIX) : -len(".lora_A.weight")]
            b_key = f"{_PEFT_PREFIX}{path}.lora_B.weight"
            a = tensors[key]
            if b_key not in tensors or a.ndim != 2 or tensors[b_key].ndim != 2:
                raise AdapterError(f"{folder}: {path}: lora_A and lora_B must both be matrices")
            if a.shape[0] != r or tensors[b_key].shape[1] != r:
                raise AdapterError(f"{folder}: {path}: factors are not of rank r = {r}")
            shapes[path] = (a.shape[1], tensors[b_key].shape[0])
        if not shapes or 2 * len(shapes) != len(tensors):
            raise AdapterError(
                f"{folder}: expected lora_A/lora_B pairs only, got {len(tensors)} tensors"
            )
        camera = None
        if metadata.get("camera"):
            from raytun3r_plugin.cameras import from_dict
            from raytun3r_plugin.errors import CameraError

            record = strict_json(metadata["camera"], "camera", AdapterError, str(folder))
            try:
                camera = from_dict(record) if isinstance(record, dict) else None
            except CameraError as error:
                raise AdapterError(
                    f"{folder}: the recorded camera is not valid ({error})"
                ) from None
        weights = cls(shapes, r, alpha, backbone=metadata.get("backbone", ""), camera=camera)
        with torch.no_grad():
            for index, path in enumerate(weights.paths):
                for name, table in (("lora_A", weights.lora_A), ("lora_B", weights.lora_B)):
                    value = tensors[f"{_PEFT_PREFIX}{path}.{name}.weight"]
                    if not bool(torch.isfinite(value).all()):
                        raise AdapterError(f"{folder}: {path}.{name} has non-finite values")
                    table[index].copy_(value)
        return weights


class LoraHandle(BaselineHandle):
    """What :func:`inject_lora` returns: ``remove()``, a context manager, and ``disabled()``."""

    def __init__(self, model: nn.Module, weights: LoraWeights) -> None:
        # Weak: the registry maps model -> handle, and a strong reference back would keep every
        # model alive for ever.
        self._model = weakref.ref(model)
        self.weights = weights
        self._hooks: list[Any] = []
        self._enabled = True

    @property
    def active(self) -> bool:
        return bool(self._hooks)

    def remove(self) -> None:
        """Take every hook out (in reverse order); idempotent."""
        while self._hooks:
            self._hooks.pop().remove()
        model = self._model()
        if model is not None and _ACTIVE.get(model) is self:
            del _ACTIVE[model]


def inject_lora(
    model: nn.Module, weights: LoraWeights | None = None, *, r: int = 8, alpha: float = 16.0
) -> LoraHandle:
    """Add LoRA to ``model``'s ``attn.qkv`` layers (:func:`lora_targets`); returns the handle.

    Args:
        model: a registered backbone (not carrying a LoRA already).
        weights: factors to use (from :meth:`LoraWeights.load`, or a previous fit); default: a
            fresh identity LoRA of rank ``r`` and scaling ``alpha / r``.

    Validates everything (targets, shapes) before the first hook is added.
    """
    from raytun3r_plugin.registry import spec_for

    if model in _ACTIVE:
        raise AlreadyAppliedError("this model carries a LoRA already; remove it first")
    paths = lora_targets(model)
    layers = dict(model.named_modules())
    shapes = {path: (layers[path].in_features, layers[path].out_features) for path in paths}
    if weights is None:
        spec, root = spec_for(model)
        weights = LoraWeights(shapes, r, alpha, backbone=spec.describe(root).name)
    elif dict(zip(weights.paths, _shapes_of(weights), strict=True)) != shapes:
        raise AdapterError(
            "the LoRA weights were made for other layers or sizes than this model's attn.qkv"
        )
    handle = LoraHandle(model, weights)
    try:
        for index, path in enumerate(weights.paths):
            layer = layers[path]
            hooked = weakref.ref(layer)

            def add_delta(module, inputs, output, index=index, hooked=hooked):
                # A deepcopy of the model copies this hook too; it only acts on the layer it
                # was registered on, so a copy runs without the LoRA.
                if not handle._enabled or module is not hooked():
                    return output
                return output + weights.delta(index, inputs[0])

            handle._hooks.append(layer.register_forward_hook(add_delta))
        _ACTIVE[model] = handle
    except BaseException:
        handle.remove()
        raise
    return handle


def _shapes_of(weights: LoraWeights) -> list[tuple[int, int]]:
    return [(a.shape[1], b.shape[0]) for a, b in zip(weights.lora_A, weights.lora_B, strict=True)]
