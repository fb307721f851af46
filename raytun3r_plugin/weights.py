"""Local weight files only: safetensors, or ``.pt``/``.bin`` through ``torch.load(weights_only=True)``.

What users have on disk (docs/backbones.md, "Loading checkpoints"):

* the weight file itself (``model.safetensors``, ``model.pt``, ``pytorch_model.bin``, ...);
* the folder of an official Hugging Face repository (``config.json`` + ``model.safetensors``), or
  the hub cache's snapshot folder, whose entries are symlinks to extension-less blobs;
* a fine-tuned checkpoint: ``{"model": state, "optimizer": ...}`` (VGGT's trainer),
  ``{"model_state_dict": ...}`` or ``{"state_dict": ...}``, with the ``module.`` (DDP) and
  ``_orig_mod.`` (``torch.compile``) prefixes those wrappers add.

:func:`read_checkpoint` turns any of these into one flat ``{key: tensor}`` dict without building
a network, so a wrong path, a wrong size or a wrong family costs a file read, never a build.
"""

from __future__ import annotations

import json
import os
import sys
from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

from raytun3r_plugin.errors import WeightsError

#: File names looked for inside a folder, in this order of preference (safetensors never unpickles).
WEIGHT_FILE_NAMES = ("model.safetensors", "model.pt", "pytorch_model.bin")
#: The Hugging Face config next to the weights (DA3 writes ``{"model_name": ..., ...}`` there).
CONFIG_FILE_NAME = "config.json"
#: Entries of a training checkpoint that hold the network's state dict, tried in this order. Every
#: other entry next to it (``optimizer``, ``scheduler``, ``epoch``, ``scaler``, ...) is ignored.
WRAPPER_KEYS = ("model", "model_state_dict", "state_dict")
#: Key components that wrappers insert: DDP's ``module.`` (leading) and ``torch.compile``'s
#: ``_orig_mod.`` (leading, or in front of a compiled submodule).
WRAPPER_COMPONENTS = ("module", "_orig_mod")
#: Unexpected keys that are known to be harmless and dropped: BatchNorm's step counter, which
#: older torch versions or other frameworks write for modules that no longer track it.
SAFE_LEFTOVER_SUFFIXES = ("num_batches_tracked",)
_MAX_LISTED = 8


class ShapeMismatchError(WeightsError):
    """A weight file's tensors have other shapes than the network's (another size)."""


@dataclass(frozen=True)
class StateSignature:
    """What a state dict's keys and shapes say it is (from a family's ``identify(state)``).

    ``names`` are the model names whose architecture the tensors match (several where two
    releases share one architecture, e.g. ``da3-large`` and ``da3-large-1.1``; empty for a
    custom size); ``detail`` is a human-readable summary such as ``"embed dim 384, 12 blocks"``;
    ``pe_shape`` the absolute PE table's shape, e.g. ``(1, 1370, 384)``.
    """

    family: str
    names: tuple[str, ...]
    detail: str
    pe_shape: tuple[int, ...] | None = None


@dataclass
class Checkpoint:
    """A weight file read into memory: ``state`` is flat, unwrapped and free of wrapper prefixes
    (a family's own prefix such as DA3's ``model.`` is left for the family to strip).

    ``config`` is the parsed ``config.json`` next to the file (``None`` if there is none);
    ``ignored`` the top-level entries dropped when unwrapping (e.g. ``["epoch", "optimizer"]``).
    """

    path: Path
    state: dict[str, torch.Tensor]
    config: dict | None = None
    ignored: list[str] = field(default_factory=list)

    @property
    def source(self) -> str:
        return str(self.path)


def find_weight_file(path: str | os.PathLike) -> Path:
    """The weight file ``path`` names: the file itself, or the preferred file inside a folder.

    A folder (also a hub snapshot folder of symlinks) is searched for :data:`WEIGHT_FILE_NAMES`
    in that order; the returned path keeps the link's own name (blobs have no extension).
    """
    path = Path(path)
    if path.is_dir():
        for name in WEIGHT_FILE_NAMES:
            if (path / name).is_file():  # is_file follows symlinks: a dangling one is skipped
                return path / name
        present = sorted(p.name for p in path.iterdir())[:_MAX_LISTED]
        raise WeightsError(
            f"{path}: folder holds none of the weight files {list(WEIGHT_FILE_NAMES)} "
            f"(found {present})"
        )
    if not path.is_file():
        raise WeightsError(f"{path}: no such weight file")
    return path


def read_config(weight_file: Path) -> dict | None:
    """The ``config.json`` next to ``weight_file`` as a dict, or ``None`` if there is none."""
    config_path = weight_file.parent / CONFIG_FILE_NAME
    if not config_path.is_file():
        return None
    try:
        config = json.loads(config_path.read_text())
    except (OSError, ValueError) as error:
        raise WeightsError(f"{config_path}: not a readable JSON file ({error})") from error
    if not isinstance(config, dict):
        raise WeightsError(f"{config_path}: expected a JSON object, found {type(config).__name__}")
    return config


def _is_safetensors(path: Path) -> bool:
    if path.suffix == ".safetensors":
        return True
    if path.suffix in (".pt", ".pth", ".bin", ".ckpt"):
        return False
    with open(path, "rb") as handle:  # an extension-less blob: safetensors' JSON header at byte 8
        head = handle.read(9)
    return len(head) == 9 and head[8:9] == b"{"


def unwrap_state(obj: object, source: str) -> tuple[dict[str, torch.Tensor], list[str]]:
    """The flat state dict inside a loaded checkpoint, and the top-level entries ignored.

    A dict whose values are all tensors is the state itself; otherwise the first of
    :data:`WRAPPER_KEYS` holding a dict is taken (once more for ``{"model": {"state_dict": ..}}``).
    """
    ignored: list[str] = []
    for _ in range(3):
        if isinstance(obj, dict) and obj and all(isinstance(v, torch.Tensor) for v in obj.values()):
            return dict(obj), ignored
        if not isinstance(obj, dict):
            break
        inner = next((key for key in WRAPPER_KEYS if isinstance(obj.get(key), dict)), None)
        if inner is None:
            break
        ignored += sorted(str(key) for key in obj if key != inner)
        obj = obj[inner]
    kind = type(obj).__name__
    if isinstance(obj, dict):
        bad = [str(k) for k, v in obj.items() if not isinstance(v, torch.Tensor)][:_MAX_LISTED]
        kind = f"dict with non-tensor entries {bad}" if obj else "empty dict"
    raise WeightsError(
        f"{source}: expected a dict of tensors, or a checkpoint with one under {list(WRAPPER_KEYS)}; "
        f"found a {kind}"
    )


def strip_wrapper_prefixes(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Drop DDP's leading ``module.`` and every ``_orig_mod.`` component from the keys."""

    def clean(key: str) -> str:
        parts = key.split(".")
        while len(parts) > 1 and parts[0] in WRAPPER_COMPONENTS:
            parts = parts[1:]
        return ".".join(part for part in parts if part != "_orig_mod") or key

    cleaned = {clean(key): value for key, value in state.items()}
    if len(cleaned) != len(state):
        raise WeightsError("two keys become one once module./_orig_mod. are removed")
    return cleaned


def read_checkpoint(path: str | os.PathLike | Checkpoint) -> Checkpoint:
    """Read a weight file or folder (see the module docstring) into a :class:`Checkpoint`."""
    if isinstance(path, Checkpoint):
        return path
    weight_file = find_weight_file(path)
    config = read_config(weight_file)
    if _is_safetensors(weight_file):
        from safetensors import SafetensorError
        from safetensors.torch import load_file

        try:
            raw: object = load_file(str(weight_file))
        except (SafetensorError, OSError, ValueError, RuntimeError) as error:
            raise WeightsError(
                f"{weight_file}: not a readable safetensors file ({error})"
            ) from error
    else:
        try:
            raw = torch.load(str(weight_file), map_location="cpu", weights_only=True)
        except Exception as error:  # torch raises many types for a corrupt or unsafe pickle
            raise WeightsError(
                f"{weight_file}: cannot be read with torch.load(weights_only=True) ({error})"
            ) from error
    state, ignored = unwrap_state(raw, str(weight_file))
    try:
        state = strip_wrapper_prefixes(state)
    except WeightsError as error:
        raise WeightsError(f"{weight_file}: {error}") from None
    return Checkpoint(path=weight_file, state=state, config=config, ignored=ignored)


def read_state_dict(path: str | os.PathLike | Checkpoint) -> dict[str, torch.Tensor]:
    """Tensors of a local weight file or folder, unwrapped, never unpickling objects."""
    return read_checkpoint(path).state


def count_blocks(state: dict[str, torch.Tensor], prefix: str) -> int:
    """How many numbered blocks a state dict holds under ``prefix`` (e.g. ``"encoder.blocks."``:
    the distinct first key parts after it), for telling model sizes apart from the keys alone."""
    return len({key[len(prefix) :].split(".")[0] for key in state if key.startswith(prefix)})


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


def _listed(keys: list[str]) -> str:
    return f"{keys[:_MAX_LISTED]}{' ...' if len(keys) > _MAX_LISTED else ''}"


def load_into(model: nn.Module, state: dict[str, torch.Tensor], source: str) -> nn.Module:
    """Load ``state`` strictly, tolerating only missing keys that alias a loaded tensor.

    Unexpected keys ending in :data:`SAFE_LEFTOVER_SUFFIXES` are dropped; every other mismatch
    (missing, unexpected, or a shape) is a :class:`WeightsError` listing the keys.
    """
    expected = model.state_dict()
    state = {
        key: value
        for key, value in state.items()
        if key in expected or not key.endswith(SAFE_LEFTOVER_SUFFIXES)
    }
    shapes = [
        f"{key} {tuple(value.shape)} (network {tuple(expected[key].shape)})"
        for key, value in state.items()
        if key in expected and value.shape != expected[key].shape
    ]
    if shapes:
        raise ShapeMismatchError(
            f"{source}: {len(shapes)} tensor(s) have another shape than the network's: "
            f"{_listed(shapes)}"
        )
    aliases = alias_keys(model)
    missing, unexpected = model.load_state_dict(state, strict=False)
    not_aliases = [key for key in missing if aliases.get(key) not in state]
    if not_aliases or unexpected:
        parts = []
        if not_aliases:
            parts.append(f"missing keys {_listed(not_aliases)}")
        if unexpected:
            parts.append(f"unexpected keys {_listed(list(unexpected))}")
        raise WeightsError(f"{source}: does not match the network ({'; '.join(parts)})")
    return model


# ---------------------------------------------------------------------------------------------
# What a checkpoint is, and load_backbone
# ---------------------------------------------------------------------------------------------


def _family_modules() -> list:
    """The patch modules of the registered families (each may define the optional hooks
    ``identify(state)``, ``config_name(config)``, ``canonical_name(name)``)."""
    from raytun3r_plugin.registry import specs

    modules = []
    for spec in specs().values():
        module = sys.modules.get(getattr(spec.recognise, "__module__", ""))
        if module is not None and module not in modules:
            modules.append(module)
    return modules


def _hook(name: str) -> list[Callable]:
    return [getattr(m, name) for m in _family_modules() if callable(getattr(m, name, None))]


def identify_state(state: dict[str, torch.Tensor]) -> StateSignature | None:
    """Which backbone a state dict's keys and shapes belong to, or ``None`` if no family knows it."""
    for identify in _hook("identify"):
        signature = identify(state)
        if signature is not None:
            return signature
    return None


def config_name(config: dict | None) -> str | None:
    """The model name a ``config.json`` declares (e.g. DA3's ``model_name``), if any."""
    if config is None:
        return None
    for read in _hook("config_name"):
        name = read(config)
        if name is not None:
            return name
    return None


def canonical_name(name: str) -> str:
    """The architecture a model name builds (``da3-large-1.1`` -> ``da3-large``)."""
    for canonical in _hook("canonical_name"):
        name = canonical(name)
    return name


def _builders() -> dict[str, Callable[..., nn.Module]]:
    from raytun3r_plugin.registry import specs

    return {name: b for spec in specs().values() for name, b in spec.builders.items()}


def _family_of(name: str) -> str | None:
    from raytun3r_plugin.registry import specs

    return next((spec.family for spec in specs().values() if name in spec.builders), None)


def _infer_name(checkpoint: Checkpoint, signature: StateSignature | None) -> str:
    declared = config_name(checkpoint.config)
    if declared is not None:
        return declared
    if signature is not None and len({canonical_name(n) for n in signature.names}) == 1:
        return signature.names[0]
    what = (
        f"a {signature.family} checkpoint ({signature.detail}) that fits "
        f"{list(signature.names) or 'no official size'}"
        if signature is not None
        else "no known backbone layout"
    )
    raise WeightsError(
        f"{checkpoint.path}: cannot tell which backbone to build: the file is {what} and no "
        f"{CONFIG_FILE_NAME} names it; pass the name (available: {available_backbones()})"
    )


def check_name(name: str, checkpoint: Checkpoint, signature: StateSignature | None) -> None:
    """Refuse ``name`` when the folder's ``config.json`` or the tensors' shapes say otherwise."""
    declared = config_name(checkpoint.config)
    if declared is not None and canonical_name(declared) != canonical_name(name):
        raise WeightsError(
            f"{checkpoint.path}: asked for {name!r}, but {checkpoint.path.parent / CONFIG_FILE_NAME} "
            f"says model_name {declared!r}"
        )
    if signature is None:
        return
    family = _family_of(name)
    if family != signature.family:
        # Refused only where the asked-for family can say what its own files look like; a
        # family without ``identify`` is left to the strict load.
        own = getattr(_module_of(family), "identify", None)
        mine = own(checkpoint.state) if callable(own) else None
        if not callable(own):
            return
        if mine is not None and mine.family == family:
            signature = mine
    if family != signature.family:
        raise WeightsError(
            f"{checkpoint.path}: asked for {name!r} ({family}), but the tensors are a "
            f"{signature.family} checkpoint ({signature.detail}); likely "
            f"{list(signature.names) or 'a custom size'}"
        )
    sizes = {canonical_name(n) for n in getattr(_module_of(family), "SIZE_NAMES", ())}
    if canonical_name(name) in sizes and canonical_name(name) not in {
        canonical_name(n) for n in signature.names
    }:
        likely = " or ".join(signature.names) if signature.names else "a custom size"
        raise WeightsError(
            f"{checkpoint.path}: asked for {name!r}, but the tensors are {likely} "
            f"({signature.detail})"
        )


def _module_of(family: str | None):
    from raytun3r_plugin.registry import specs

    for spec in specs().values():
        if spec.family == family:
            return sys.modules.get(getattr(spec.recognise, "__module__", ""))
    return None


def load_backbone(name: str | None, path: str | os.PathLike | None = None) -> nn.Module:
    """Build backbone ``name`` and load local weights from ``path``; returns it in eval mode.

    ``name`` is any model name a registered backbone offers (``available_backbones()``), or
    ``None`` to take it from the folder's ``config.json`` or, failing that, from the tensors.
    ``path`` is a weight file or a folder holding one (see the module docstring). The file is
    read, and its name and shapes checked, before anything is built. Built-in networks that ship
    with raytun3r need no path. Raises :class:`WeightsError` naming the file and the problem.
    """
    builders = _builders()
    if name is not None and name not in builders:
        raise WeightsError(f"unknown backbone {name!r}; available: {available_backbones()}")
    if path is None:
        if name is None:
            raise WeightsError("load_backbone needs a backbone name, a weight path, or both")
        return builders[name](None).eval()
    if name is not None:  # a missing package fails before a (large) file is read
        require = getattr(_module_of(_family_of(name)), "require_modules", None)
        if callable(require):
            require(name)
    checkpoint = read_checkpoint(path)
    signature = identify_state(checkpoint.state)
    if name is None:
        name = _infer_name(checkpoint, signature)
        if name not in builders:
            raise WeightsError(
                f"{checkpoint.path}: is {name!r}, which raytun3r cannot build; available: "
                f"{available_backbones()}"
            )
    check_name(name, checkpoint, signature)
    builder = builders[name]
    # Builders of the official families take the read checkpoint (no second read of a 5 GB file);
    # others (e.g. the shipped network) take the weight file's path.
    argument = checkpoint if getattr(builder, "takes_checkpoint", False) else checkpoint.path
    try:
        return builder(argument).eval()
    except ShapeMismatchError as error:
        if signature is None:
            raise
        raise ShapeMismatchError(
            f"{error}; the file is a {signature.family} of {signature.detail}, not the {name} "
            "architecture"
        ) from None


def describe_checkpoint(path: str | os.PathLike) -> dict:
    """What a checkpoint is, without building anything (``raytun3r weights``).

    Returns ``{"file", "family", "name", "candidates", "detail", "tensors", "parameters",
    "dtypes", "pe_shape", "config_model_name", "ignored_entries", "load"}``; ``load`` is the
    Python call that loads it (``None`` when no registered backbone builds it).
    """
    checkpoint = read_checkpoint(path)
    signature = identify_state(checkpoint.state)
    declared = config_name(checkpoint.config)
    try:
        name: str | None = _infer_name(checkpoint, signature)
    except WeightsError:
        name = None
    dtypes = Counter(str(t.dtype).removeprefix("torch.") for t in checkpoint.state.values())
    builds = name is not None and name in _builders()
    load = f"raytun3r_plugin.load_backbone({name!r}, {str(path)!r})" if builds else None
    return {
        "file": str(checkpoint.path),
        "family": signature.family if signature else None,
        "name": name,
        "candidates": list(signature.names) if signature else [],
        "detail": signature.detail if signature else None,
        "tensors": len(checkpoint.state),
        "parameters": int(sum(t.numel() for t in checkpoint.state.values())),
        "dtypes": dict(sorted(dtypes.items())),
        "pe_shape": list(signature.pe_shape) if signature and signature.pe_shape else None,
        "config_model_name": declared,
        "ignored_entries": checkpoint.ignored,
        "load": load,
    }


def available_backbones() -> list[str]:
    from raytun3r_plugin.registry import specs

    return sorted(name for spec in specs().values() for name in spec.builders)
