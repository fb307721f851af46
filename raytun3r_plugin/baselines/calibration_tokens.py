"""Calibration tokens: learned tokens inserted before every transformer block (VPT-deep).

The paper's second parameter-efficient baseline. For block i, ``t`` learned tokens
``tokens[i]`` (t, C) join every frame's token sequence right after the special tokens, take
the special tokens' RoPE position and no absolute PE, go through the frozen block, and are
dropped from its output; block i + 1 gets fresh tokens of its own. Everything downstream of the
blocks therefore sees the same shapes as upstream.

Where they go is declared per family as ``BackboneSpec.prompt_target``: the upstream method(s)
that run one block (the *runners*), the block lists, the insertion index and the token layout
(:class:`~raytun3r_plugin.registry.PromptTarget`). Blocks are numbered runner by runner, in
declaration order; the saved file records the block lists. There is no identity
initialisation: tokens of any value receive attention. They start as VPT does, Xavier-uniform
U(-a, a), a = sqrt(6 / (3 p^2 + C)) for patch size p and width C, from a fixed seed.

Parameters, t = 4: DA3-Small (12 blocks, C = 384) 12 x 4 x 384 = 18,432; VGGT-1B (aggregator,
24 frame + 24 global blocks, C = 1024) 196,608; Pi3 / Pi3X (36 decoder blocks, C = 1024) 147,456.
"""

from __future__ import annotations

import copy
import inspect
import json
import math
import os
import threading
import weakref
from collections.abc import Callable
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
    from raytun3r_plugin.registry import PromptTarget

__all__ = ["CalibrationTokens", "TokenHandle", "inject_calibration_tokens"]

FORMAT = "raytun3r-calibration-tokens"
_ACTIVE: weakref.WeakKeyDictionary[nn.Module, TokenHandle] = weakref.WeakKeyDictionary()


class CalibrationTokens(nn.Module):
    """``tokens`` (blocks, t, C) for one backbone.

    Args:
        blocks, t, width: number of blocks, tokens per block, token width C.
        patch_size: p of the initialisation bound.
        backbone, camera: recorded in the file.
        block_lists: the (dotted path, length) of each block list the tokens cover, in token
            order (recorded in the file; empty: not known). Their lengths sum to ``blocks``.
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
        block_lists: tuple[tuple[str, int], ...] = (),
        seed: int | None = 0,
    ) -> None:
        super().__init__()
        for name, value, high in (("blocks", blocks, 4096), ("t", t, 1024), ("width", width, 8192)):
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= high:
                raise AdapterError(f"{name} must be an integer in [1, {high}], got {value!r}")
        block_lists = tuple((str(path), int(length)) for path, length in block_lists)
        if block_lists and sum(length for _, length in block_lists) != blocks:
            raise AdapterError(f"block lists {block_lists} do not add up to {blocks} blocks")
        bound = math.sqrt(6.0 / (3 * patch_size**2 + width))
        generator = torch.Generator().manual_seed(seed) if seed is not None else None
        values = torch.empty(blocks, t, width).uniform_(-bound, bound, generator=generator)
        self.tokens = nn.Parameter(values)
        self.patch_size, self.backbone, self.camera = patch_size, backbone, camera
        self.block_lists = block_lists

    def num_parameters(self) -> int:
        return self.tokens.numel()

    def save(self, path: str | os.PathLike) -> Path:
        """One ``.safetensors`` file: the ``tokens`` tensor and what it is for, in the metadata."""
        from raytun3r_plugin._version import __version__
        from raytun3r_plugin.atomic_files import atomic_save_safetensors

        metadata = {
            "format": FORMAT,
            "backbone": self.backbone,
            "patch_size": str(self.patch_size),
            "blocks": json.dumps([list(entry) for entry in self.block_lists]),
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
        block_lists = _read_block_lists(metadata.get("blocks"), tokens.shape[0], str(path))
        result = cls(
            tokens.shape[0],
            tokens.shape[1],
            tokens.shape[2],
            patch_size=patch,
            backbone=metadata.get("backbone", ""),
            camera=camera,
            block_lists=block_lists,
        )
        with torch.no_grad():
            result.tokens.copy_(tokens)
        return result


def _read_block_lists(text: Any, blocks: int, where: str) -> tuple[tuple[str, int], ...]:
    """The ``blocks`` metadata: a JSON list of [dotted path, length] adding up to ``blocks``."""
    from raytun3r_plugin._strict import strict_json

    if not text:  # files written before the field existed
        return ()
    record = strict_json(text, "blocks", AdapterError, where)
    if not isinstance(record, list) or not all(
        isinstance(entry, list)
        and len(entry) == 2
        and isinstance(entry[0], str)
        and isinstance(entry[1], int)
        and not isinstance(entry[1], bool)
        and entry[1] >= 1
        for entry in record
    ):
        raise AdapterError(f"{where}: 'blocks' must be a list of [path, length] pairs")
    result = tuple((path, length) for path, length in record)
    if sum(length for _, length in result) != blocks:
        raise AdapterError(f"{where}: 'blocks' {result} do not add up to the {blocks} token sets")
    return result


_MISSING = object()


class _Runner:
    """The instance attribute that stands in for one upstream method while tokens are in.

    ``call(live_owner, inner, args, kwargs)`` does the work; ``inner`` runs what the attribute
    shadows (the class's method, or an instance attribute the owner had before). A deep copy of
    the model gets that instead of the runner, bound to the copy, so copies run without tokens.
    """

    def __init__(self, owner: nn.Module, attribute: str, call: Callable[..., Any]) -> None:
        self._owner = weakref.ref(owner)
        self._attribute = attribute
        self._call = call
        self._previous = owner.__dict__.get(attribute, _MISSING)

    def inner(self, owner: Any) -> Callable[..., Any]:
        if self._previous is not _MISSING:
            return self._previous
        return getattr(type(owner), self._attribute).__get__(owner, type(owner))

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        owner = self._owner()
        return self._call(owner, self.inner(owner), args, kwargs)

    def install(self) -> None:
        owner = self._owner()
        if owner is not None:
            owner.__dict__[self._attribute] = self

    def uninstall(self) -> None:
        owner = self._owner()
        if owner is None or owner.__dict__.get(self._attribute) is not self:
            return  # gone, or replaced by someone else since: leave theirs alone
        if self._previous is _MISSING:
            del owner.__dict__[self._attribute]
        else:
            owner.__dict__[self._attribute] = self._previous

    def __deepcopy__(self, memo: dict) -> Any:
        # The owner is being copied (this runner sits in its __dict__): memo holds its twin.
        twin = copy.deepcopy(self._owner(), memo)
        if self._previous is not _MISSING:
            return copy.deepcopy(self._previous, memo)
        return getattr(type(twin), self._attribute).__get__(twin, type(twin))


class TokenHandle(BaselineHandle):
    """What :func:`inject_calibration_tokens` returns: ``remove()``, context manager,
    ``disabled()``. ``tokens`` is the :class:`CalibrationTokens` in use."""

    def __init__(self, model: nn.Module, tokens: CalibrationTokens) -> None:
        self._model = weakref.ref(model)
        self.tokens = tokens
        self._enabled = True
        self._runners: list[_Runner] = []

    @property
    def active(self) -> bool:
        return bool(self._runners)

    def remove(self) -> None:
        """Take the wrappers out (the upstream methods show through again); idempotent."""
        for runner in reversed(self._runners):
            runner.uninstall()
        self._runners = []
        model = self._model()
        if model is not None and _ACTIVE.get(model) is self:
            del _ACTIVE[model]


def _resolve(root: nn.Module, path: str) -> Any:
    from raytun3r_plugin.registry import resolve_path

    return root if path == "" else resolve_path(root, path)


def _signature(
    family: str, owner: Any, runner: PromptTarget | None, attribute: str
) -> inspect.Signature:
    """The upstream method's signature, refused unless it is the declared one."""
    method = getattr(type(owner), attribute, None)
    if method is None:
        raise UnsupportedUpstreamError(
            f"{family}: expected a method {attribute} on {type(owner).__name__}"
        )
    signature = inspect.signature(method)
    found = tuple(signature.parameters)[1:]
    if runner is not None and found != runner.signature:
        raise UnsupportedUpstreamError(
            f"{family}: {attribute} expected parameters {runner.signature}, found {found}"
        )
    return signature


class _Plan:
    """One runner of a prompt target, resolved and checked against the model."""

    def __init__(self, family: str, root: nn.Module, runner: PromptTarget) -> None:
        self.runner = runner
        self.blocks = _resolve(root, runner.blocks)
        if not isinstance(self.blocks, nn.ModuleList) or len(self.blocks) == 0:
            raise UnsupportedUpstreamError(
                f"{family}: expected a non-empty ModuleList at {runner.blocks}, found "
                f"{type(self.blocks).__name__}"
            )
        for path, value in runner.requires:
            found = _resolve(root, path)
            if found != value:
                raise UnsupportedUpstreamError(
                    f"{family}: calibration tokens need {path} = {value!r} (one block per "
                    f"runner call), found {found!r}"
                )
        bad = [kind for kind in runner.layout if kind not in ("frames", "frame", "global")]
        if bad or not runner.layout or (runner.sizes and len(runner.sizes) != 3):
            raise UnsupportedUpstreamError(f"{family}: malformed prompt target {runner!r}")
        if "global" in runner.layout and not runner.sizes and runner.frames is None:
            raise UnsupportedUpstreamError(f"{family}: a global layout needs `frames`")
        if runner.select is None:
            self.owners = list(self.blocks)
        else:
            owner = _resolve(root, runner.owner)
            if owner is None:
                raise UnsupportedUpstreamError(f"{family}: expected a module at {runner.owner}")
            self.owners = [owner]
        self.signatures = [_signature(family, o, runner, runner.attribute) for o in self.owners]
        needed = {runner.tokens_argument, *runner.sizes}
        needed |= {name for name in (runner.pos_argument, runner.select) if name is not None}
        missing = needed - set(runner.signature)
        if missing:
            raise UnsupportedUpstreamError(
                f"{family}: {runner.attribute} has no argument(s) {sorted(missing)}"
            )


def inject_calibration_tokens(
    model: nn.Module, tokens: CalibrationTokens | None = None, *, t: int = 4
) -> TokenHandle:
    """Insert calibration tokens before every block of ``model`` (``BackboneSpec.prompt_target``).

    Args:
        model: a registered backbone that declares a prompt target (DA3, VGGT, Pi3, Pi3X).
        tokens: tokens to use (loaded, or from a fit); default: fresh ones, ``t`` per block.

    Raises:
        UnsupportedUpstreamError: no prompt target, or upstream does not match it.
        AlreadyAppliedError: ``model`` carries calibration tokens already.
        AdapterError: ``tokens`` do not fit this model's blocks or width.
    """
    from raytun3r_plugin.registry import spec_for

    spec, root = spec_for(model)
    target = spec.prompt_target
    if target is None:
        raise UnsupportedUpstreamError(f"{spec.family}: declares no place for calibration tokens")
    if model in _ACTIVE:
        raise AlreadyAppliedError(
            "this model carries calibration tokens already; remove them first"
        )
    plans = [_Plan(spec.family, root, runner) for runner in target.runners()]
    block_lists = tuple((plan.runner.blocks, len(plan.blocks)) for plan in plans)
    total = sum(length for _, length in block_lists)
    info = spec.describe(root)
    if tokens is None:
        tokens = CalibrationTokens(
            total,
            t,
            info.embed_dim,
            patch_size=info.patch_size,
            backbone=info.name,
            block_lists=block_lists,
        )
    elif tuple(tokens.tokens.shape[::2]) != (total, info.embed_dim):
        raise AdapterError(
            f"calibration tokens of shape {tuple(tokens.tokens.shape)} do not fit {total} "
            f"blocks of width {info.embed_dim}"
        )
    elif tokens.block_lists and tokens.block_lists != block_lists:
        raise AdapterError(
            f"calibration tokens made for the blocks {tokens.block_lists}, this model has "
            f"{block_lists}"
        )
    handle = TokenHandle(model, tokens)
    frames: dict[tuple[str, str, str], threading.local] = {}
    runners: list[_Runner] = []
    offset = 0
    for plan in plans:
        declared = plan.runner.frames
        if declared is not None and declared not in frames:
            frames[declared] = threading.local()  # per thread: one model may serve several
            runners.append(_frames_runner(spec.family, root, declared, frames[declared]))
        cell = frames.get(declared) if declared is not None else None
        for k, (owner, signature) in enumerate(zip(plan.owners, plan.signatures, strict=True)):
            fixed = k if plan.runner.select is None else None
            call = _block_call(handle, plan, signature, offset, fixed, cell)
            runners.append(_Runner(owner, plan.runner.attribute, call))
        offset += len(plan.blocks)
    _ACTIVE[model] = handle
    try:
        for runner in runners:
            handle._runners.append(runner)
            runner.install()
    except BaseException:
        handle.remove()
        raise
    return handle


def _frames_runner(
    family: str, root: nn.Module, declared: tuple[str, str, str], cell: threading.local
) -> _Runner:
    """Wrap the method whose argument gives S while it runs (for the blocks' global layout)."""
    path, attribute, argument = declared
    owner = _resolve(root, path)
    if owner is None:
        raise UnsupportedUpstreamError(f"{family}: expected a module at {path!r}")
    signature = _signature(family, owner, None, attribute)
    if argument not in signature.parameters:
        raise UnsupportedUpstreamError(f"{family}: {attribute} has no argument {argument!r}")

    def call(live: Any, inner: Callable[..., Any], args: tuple, kwargs: dict) -> Any:
        bound = signature.bind(live, *args, **kwargs)
        bound.apply_defaults()
        value = bound.arguments[argument]
        previous = getattr(cell, "frames", None)
        cell.frames = value if isinstance(value, int) and not isinstance(value, bool) else None
        try:
            return inner(*args, **kwargs)
        finally:
            cell.frames = previous  # nested or re-entrant calls see their own S

    return _Runner(owner, attribute, call)


def _block_call(
    handle: TokenHandle,
    plan: _Plan,
    signature: inspect.Signature,
    offset: int,
    fixed: int | None,
    cell: threading.local | None,
) -> Callable[..., Any]:
    """The work of one runner: find the block, widen tokens and positions, run, narrow."""
    runner, blocks = plan.runner, plan.blocks
    index_of = {id(block): k for k, block in enumerate(blocks)}
    at = runner.insert_at

    def which(arguments: dict) -> int | None:
        if fixed is not None:
            return fixed
        chosen = arguments[runner.select]
        if isinstance(chosen, nn.Module):
            return index_of.get(id(chosen))
        if isinstance(chosen, int) and not isinstance(chosen, bool) and 0 <= chosen < len(blocks):
            return chosen
        return None

    def call(live: Any, inner: Callable[..., Any], args: tuple, kwargs: dict) -> Any:
        if not handle._enabled:
            return inner(*args, **kwargs)
        bound = signature.bind(live, *args, **kwargs)
        bound.apply_defaults()
        arguments = bound.arguments
        k = which(arguments)
        if k is None:  # not one of the covered blocks
            return inner(*args, **kwargs)
        if arguments.get("attn_mask") is not None:
            raise InputError("calibration tokens do not support an attention mask")
        x = arguments[runner.tokens_argument]
        b, s, n = _frame_sizes(runner, runner.layout[k % len(runner.layout)], arguments, x, cell)
        extra = handle.tokens.tokens[offset + k].to(device=x.device, dtype=x.dtype)
        count = extra.shape[0]
        arguments[runner.tokens_argument] = _widen(x, b, s, n, at, count, extra)
        name = runner.pos_argument
        if name is not None and arguments.get(name) is not None:
            arguments[name] = _widen(arguments[name], b, s, n, at, count, None)
        if runner.sizes:
            arguments[runner.sizes[2]] = n + count
        out = inner(*bound.args[1:], **bound.kwargs)
        return _narrow(out, b, s, n + count, at, count)

    return call


def _frame_sizes(
    runner: PromptTarget,
    layout: str,
    arguments: dict,
    x: torch.Tensor,
    cell: threading.local | None,
) -> tuple[int, int, int]:
    """(B, S, N) of one call: batch, frames, tokens per frame of the tokens argument."""
    if runner.sizes:
        b, s, n = (int(arguments[name]) for name in runner.sizes)
    elif layout == "frames" and x.ndim == 4:
        b, s, n = x.shape[:3]
    elif layout == "frame" and x.ndim == 3:
        b, s, n = x.shape[0], 1, x.shape[1]  # each row is one frame; S does not matter
    elif layout == "global" and x.ndim == 3:
        frames = getattr(cell, "frames", None)
        if frames is None or frames < 1 or x.shape[1] % frames:
            raise InputError(
                f"calibration tokens: a global-attention block ran with tokens {tuple(x.shape)} "
                f"outside {runner.frames[1] if runner.frames else 'its caller'}, or with a "
                f"frame count ({frames}) that does not divide them"
            )
        b, s, n = x.shape[0], frames, x.shape[1] // frames
    else:
        raise InputError(
            f"calibration tokens: tokens of shape {tuple(x.shape)} are not the {layout!r} layout"
        )
    if n < runner.insert_at or x.numel() != b * s * n * x.shape[-1] or x.shape[-2] % n:
        raise InputError(
            f"calibration tokens: tokens of shape {tuple(x.shape)} are not {b} x {s} frames "
            f"of {n} tokens"
        )
    return b, s, n


def _widen(
    x: torch.Tensor, b: int, s: int, n: int, at: int, count: int, extra: torch.Tensor | None
) -> torch.Tensor:
    """Insert ``count`` tokens at index ``at`` of every frame; ``extra`` (count, C), or None:
    copies of the frame's token 0 (positions: the special tokens' RoPE position)."""
    frames = x.reshape(b, s, n, x.shape[-1])
    if extra is None:
        fill = frames[:, :, :1].expand(b, s, count, x.shape[-1])
    else:
        fill = extra.expand(b, s, count, x.shape[-1])
    wide = torch.cat([frames[:, :, :at], fill, frames[:, :, at:]], dim=2)
    shape = list(x.shape)
    shape[-2] = x.shape[-2] // n * (n + count)
    return wide.reshape(shape)


def _narrow(out: Any, b: int, s: int, wide: int, at: int, count: int) -> Any:
    """Cut the inserted tokens out of every token tensor in ``out`` (tensors, tuples, lists);
    anything else (an index, a tensor of another shape) passes through."""
    if isinstance(out, torch.Tensor):
        if out.ndim < 3 or out.shape[-2] % wide or out.numel() != b * s * wide * out.shape[-1]:
            return out
        frames = out.reshape(b, s, wide, out.shape[-1])
        kept = torch.cat([frames[:, :, :at], frames[:, :, at + count :]], dim=2)
        shape = list(out.shape)
        shape[-2] = out.shape[-2] // wide * (wide - count)
        return kept.reshape(shape)
    if type(out) in (tuple, list):
        return type(out)(_narrow(item, b, s, wide, at, count) for item in out)
    return out
