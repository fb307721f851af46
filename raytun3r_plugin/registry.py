"""One registry of supported backbones; each ``patches/<backbone>.py`` registers itself here.

A backbone module declares, as data, the upstream code it wraps (:class:`PatchTarget`: where the
method lives, what it is, the signature it must have) and how to recognise, describe, load and
run the model (:class:`BackboneSpec`). The core iterates over the registered specs and knows no
backbone by name.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, ExitStack, contextmanager
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from raytun3r_plugin.errors import UnsupportedUpstreamError

#: Hook kinds of docs/conventions.md section 1 and the components (adapter.COMPONENTS) each can serve.
HOOK_KINDS = ("pe", "rope", "patch_embed", "grid")


@dataclass(frozen=True)
class PatchTarget:
    """One upstream method replaced per instance.

    Attributes:
        name: short identifier used in messages, e.g. ``"pe_interpolation"``.
        hook: hook kind, one of :data:`HOOK_KINDS`.
        owners: dotted attribute paths, from the patched root module, of the instances owning
            ``attribute`` (several when upstream keeps copies, e.g. two RoPE instances).
        attribute: the method name replaced on each owner instance.
        signature: the upstream method's parameter names after ``self``, in order.
        owner_classes: accepted class names of the owners (checked along the MRO).
        build: ``build(owner, state) -> behaviour``, with ``state`` the
            :class:`raytun3r_plugin.patching.PatchState`; the installed wrapper calls
            ``behaviour(original, *args, **kwargs)`` with the upstream method bound to the owner,
            looked up at call time. The behaviour must hold neither ``original`` nor ``owner``
            (see :mod:`raytun3r_plugin.hooks`).
        optional: when True an absent owner (missing attribute or ``None``) just means the model
            has no such hook (e.g. a DA3 mono model has no RoPE); otherwise it is an error.
    """

    name: str
    hook: str
    owners: tuple[str, ...]
    attribute: str
    signature: tuple[str, ...]
    owner_classes: tuple[str, ...]
    build: Callable[..., Callable]
    optional: bool = False


@dataclass(frozen=True)
class BackboneInfo:
    """What the adapter and the checks need to know about one model instance."""

    name: str
    embed_dim: int
    patch_size: int
    has_rope: bool
    pos_embed: torch.Tensor
    has_grid: bool = True


@dataclass(frozen=True)
class BackboneSpec:
    """Everything raytun3r knows about one backbone family.

    Attributes:
        family: e.g. ``"da3"``.
        supports: human-readable upstream versions the targets were checked against.
        recognise: ``recognise(model) -> root | None``: the module to patch (unwrapping wrapper
            classes), or None when ``model`` is not of this family. Must not import upstream.
        describe: ``describe(root) -> BackboneInfo``.
        targets: the patch targets, as data.
        predict: ``predict(root, images, **kwargs) -> Prediction`` for images in [0, 1].
        builders: ``{model_name: build(path | None) -> nn.Module}`` for :func:`load_backbone`.
        check: extra structural checks run before anything is changed (raise
            :class:`UnsupportedUpstreamError`).
        quiet: ``quiet() -> context manager`` that holds back the upstream's routine per-forward
            output (not its warnings) while it is entered; used by the command line and the
            benchmark scripts (:func:`quiet_upstream`), never by the library.
    """

    family: str
    supports: str
    recognise: Callable[[nn.Module], nn.Module | None]
    describe: Callable[[nn.Module], BackboneInfo]
    targets: tuple[PatchTarget, ...]
    predict: Callable[..., Any]
    builders: dict[str, Callable[..., nn.Module]] = field(default_factory=dict)
    check: Callable[[nn.Module], None] | None = None
    quiet: Callable[[], AbstractContextManager] | None = None


_SPECS: dict[str, BackboneSpec] = {}
_BUILTINS_LOADED = False


def register(spec: BackboneSpec) -> BackboneSpec:
    """Register (or replace) the spec of a backbone family."""
    _SPECS[spec.family] = spec
    return spec


def _load_builtins() -> None:
    global _BUILTINS_LOADED
    if not _BUILTINS_LOADED:
        _BUILTINS_LOADED = True
        importlib.import_module("raytun3r_plugin.patches")


def specs() -> dict[str, BackboneSpec]:
    _load_builtins()
    return dict(_SPECS)


@contextmanager
def quiet_upstream() -> Iterator[None]:
    """Enter every registered backbone's ``quiet`` context (application code only)."""
    with ExitStack() as stack:
        for spec in specs().values():
            if spec.quiet is not None:
                stack.enter_context(spec.quiet())
        yield


def spec_for(model: nn.Module) -> tuple[BackboneSpec, nn.Module]:
    """The registered spec that recognises ``model`` and the root module to patch."""
    _load_builtins()
    for spec in _SPECS.values():
        root = spec.recognise(model)
        if root is not None:
            return spec, root
    known = ", ".join(f"{s.family} ({s.supports})" for s in _SPECS.values())
    raise UnsupportedUpstreamError(f"no raytun3r patch recognises a {type(model).__module__}.{type(model).__qualname__}; supported: {known}")


def resolve_path(root: nn.Module, path: str) -> Any:
    """Follow a dotted attribute path; returns None when any step is missing or None."""
    node: Any = root
    for part in path.split("."):
        node = getattr(node, part, None)
        if node is None:
            return None
    return node


def _class_names(obj: Any) -> list[str]:
    return [klass.__name__ for klass in type(obj).__mro__]


def upstream_signature(owner: Any, attribute: str) -> tuple[str, ...] | None:
    """Parameter names (after ``self``) of the class-level method ``attribute`` of ``owner``."""
    function = getattr(type(owner), attribute, None)
    if function is None:
        return None
    function = inspect.unwrap(function)
    try:
        parameters = list(inspect.signature(function).parameters)
    except (TypeError, ValueError):
        return None
    return tuple(parameters[1:]) if parameters and parameters[0] == "self" else tuple(parameters)


def resolve_targets(spec: BackboneSpec, root: nn.Module, wanted_hooks: set[str]) -> list[tuple[PatchTarget, str, Any]]:
    """Check every target against the live model, without changing anything.

    Returns ``(target, owner_path, owner)`` for every owner to patch. Raises
    :class:`UnsupportedUpstreamError` saying what was expected and what was found.
    """
    found: list[tuple[PatchTarget, str, Any]] = []
    for target in spec.targets:
        if target.hook not in wanted_hooks:
            continue
        for path in target.owners:
            owner = resolve_path(root, path)
            where = f"{spec.family} patch {target.name!r} ({type(root).__name__}.{path}.{target.attribute})"
            if owner is None:
                if target.optional:
                    continue
                raise UnsupportedUpstreamError(f"{where}: expected a {' or '.join(target.owner_classes)} at '{path}', found nothing")
            names = _class_names(owner)
            if not set(names) & set(target.owner_classes):
                raise UnsupportedUpstreamError(f"{where}: expected a {' or '.join(target.owner_classes)} at '{path}', found {type(owner).__module__}.{type(owner).__qualname__}")
            signature = upstream_signature(owner, target.attribute)
            if signature is None:
                raise UnsupportedUpstreamError(f"{where}: expected method {target.attribute}{target.signature}, found no such method on {type(owner).__qualname__}")
            if signature != target.signature:
                raise UnsupportedUpstreamError(f"{where}: expected signature {target.attribute}({', '.join(target.signature)}), found {target.attribute}({', '.join(signature)})")
            found.append((target, path, owner))
    return found
