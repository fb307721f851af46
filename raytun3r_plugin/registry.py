"""One registry of supported backbones; each ``patches/<backbone>.py`` registers itself here.

A backbone module declares, as data, the upstream code it wraps (:class:`PatchTarget`: where the
method lives, what it is, the signature it must have; :class:`UpstreamVersion`: the release or
commit this was checked against; its RoPE classes and frequency attribute) and how to recognise,
describe, load and run the model (:class:`BackboneSpec`). The core iterates over the registered
specs and knows no backbone by name. The checklist for a new backbone is
``docs/adding_a_backbone.md``.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import inspect
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, ExitStack, contextmanager
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from raytun3r_plugin.errors import (
    BackboneRegistrationError,
    DuplicateBackboneError,
    UnsupportedUpstreamError,
)

#: Hook kinds of docs/conventions.md section 1 -> the components (adapter.COMPONENTS, and the
#: ablation switches of adapter.ABLATION_SWITCHES that need a hook of their own) each serves;
#: a hook is installed when any of its components is on. ``pe_radial_only`` only modifies
#: ``pe`` and ``resample_turned`` only ``patch_resample``, so they install nothing themselves.
HOOK_COMPONENTS: dict[str, tuple[str, ...]] = {
    "pe": ("pe", "pe_naive_remap"),
    "rope": ("rope",),
    "patch_embed": ("patch_resample", "border_tokens"),
    "grid": ("grid",),
}
HOOK_KINDS = tuple(HOOK_COMPONENTS)


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
            :class:`raytun3r_plugin.patch_state.PatchState`; the installed wrapper calls
            ``behaviour(original, *args, **kwargs)`` with the upstream method bound to the owner,
            looked up at call time. The behaviour must hold neither ``original`` nor ``owner``
            (see :mod:`raytun3r_plugin.hooks`).
        optional: when True an absent owner (missing attribute or ``None``) just means the model
            has no such hook (e.g. a DA3 mono model has no RoPE); otherwise it is an error.
        per_view: the behaviour gives each view of a multi-camera forward its own camera
            (``apply(model, [camera_a, camera_b, ...])``, docs/rigs.md). False where upstream
            computes one value for every view (VGGT-Omega's RoPE table, Pi3X's uv channels):
            ``apply`` then refuses a rig of different cameras while this hook is on, naming it.
    """

    name: str
    hook: str
    owners: tuple[str, ...]
    attribute: str
    signature: tuple[str, ...]
    owner_classes: tuple[str, ...]
    build: Callable[..., Callable]
    optional: bool = False
    per_view: bool = True


@dataclass(frozen=True)
class PromptTarget:
    """Where a baseline inserts extra tokens before each transformer block (calibration tokens).

    A *runner* is an upstream method that runs one block of ``blocks``; the baseline wraps it
    (an instance attribute, removed again), widens its token and position arguments by the
    extra tokens and cuts them out of every token tensor it returns.

    Attributes:
        owner: dotted path of the module whose ``attribute`` is the runner (DA3:
            ``process_attention``). Ignored when ``select`` is None.
        attribute: that method; ``signature`` its parameter names after ``self``, as upstream.
        blocks: dotted path of the ``ModuleList`` of the blocks it runs (one token set each).
        insert_at: token index of each frame the extra tokens go to (after the special
            tokens); they take the position of the frame's token 0.
        select: the argument that says which block runs: one of ``blocks`` (a module) or its
            index (an int). None: the runner is ``attribute`` of each block itself.
        tokens_argument, pos_argument: the arguments holding the tokens (..., C) and their
            RoPE positions (..., 2) (``pos_argument`` None or the value None: no positions).
        layout: how the tokens argument is laid out, per block (cycled over ``blocks``):
            ``"frames"`` (B, S, N, C); ``"frame"`` (B*S, N, C); ``"global"`` (B, S*N, C).
        sizes: the arguments giving B, S and N, for a runner that takes them (then ``layout`` is
            not used, and the N argument is passed on as N + t).
        frames: (owner path, method, argument) whose value is S while that method runs, for the
            ``"global"`` layout ("" is the root).
        requires: (dotted path, value) pairs the model must match (e.g. one block per runner call).
        more: further runners; their blocks follow this one's in the token tensor.
    """

    owner: str
    attribute: str
    signature: tuple[str, ...]
    blocks: str
    insert_at: int = 1
    select: str | None = "block"
    tokens_argument: str = "x"
    pos_argument: str | None = "pos"
    layout: tuple[str, ...] = ("frames",)
    sizes: tuple[str, ...] = ()
    frames: tuple[str, str, str] | None = None
    requires: tuple[tuple[str, Any], ...] = ()
    more: tuple[PromptTarget, ...] = ()

    def runners(self) -> tuple[PromptTarget, ...]:
        """This runner and the ``more`` ones, in token-tensor order."""
        return (self, *(runner for more in self.more for runner in more.runners()))


@dataclass(frozen=True)
class BackboneInfo:
    """What the adapter and the checks need to know about one model instance.

    ``pos_embed`` is the absolute PE table, or None for a backbone that has none (RoPE only,
    e.g. VGGT-Omega): the ``pe`` component then has nothing to act on and the adapter's
    ``pe_fingerprint`` is empty.
    """

    name: str
    embed_dim: int
    patch_size: int
    has_rope: bool
    pos_embed: torch.Tensor | None
    has_grid: bool = True


@dataclass(frozen=True)
class UpstreamVersion:
    """The upstream code a backbone's targets were checked against (OpenTelemetry's ``_instruments``).

    Attributes:
        source: a PyPI distribution (``"depth-anything-3"``) or a GitHub ``owner/name``.
        version: the release (``"0.1.1"``) or, for a GitHub source, the full commit SHA.
        module: the top-level import name (``"depth_anything_3"``).
        note: optional provenance, e.g. the GitHub commit a PyPI release was cut from.
    """

    source: str
    version: str
    module: str
    note: str = ""

    @property
    def is_commit(self) -> bool:
        """True for a GitHub checkout pinned by commit (not installable by version)."""
        return "/" in self.source

    def installed(self) -> str | None:
        """The installed release of a PyPI source (None for a GitHub source or when absent)."""
        if self.is_commit:
            return None
        try:
            return importlib.metadata.version(self.source)
        except importlib.metadata.PackageNotFoundError:
            return None

    def __str__(self) -> str:
        text = f"{self.source} {self.version[:7] if self.is_commit else self.version}"
        return f"{text} ({self.note})" if self.note else text


@dataclass(frozen=True)
class BackboneSpec:
    """Everything raytun3r knows about one backbone family.

    A backbone module (``patches/<name>.py``) builds one spec per family and passes it to
    :func:`register`; ``docs/adding_a_backbone.md`` is the checklist.

    Attributes:
        family: e.g. ``"da3"``; unique among the registered specs.
        upstream: the upstream release or commit the targets were checked against.
        recognise: ``recognise(model) -> root | None``: the module to patch (unwrapping wrapper
            classes), or None when ``model`` is not of this family. Must not import upstream.
        describe: ``describe(root) -> BackboneInfo``.
        targets: the patch targets, as data.
        predict: ``predict(root, images, **kwargs) -> Prediction`` for images in [0, 1].
        builders: ``{model_name: build(path | None) -> nn.Module}`` for :func:`load_backbone`.
        rope_classes: upstream class names of the RoPE modules. Every instance of them in a model
            must be an owner of a ``rope`` target, or :func:`resolve_targets` refuses the model
            (an upstream that adds a RoPE copy would otherwise be patched only in part).
        rope_base_attribute: the attribute of a RoPE instance holding its frequency base (e.g.
            ``"base_frequency"``), which the continuous-angle evaluation reuses; read with
            :func:`rope_base`, never defaulted.
        check: extra structural checks run before anything is changed (raise
            :class:`UnsupportedUpstreamError`).
        quiet: ``quiet() -> context manager`` that holds back the upstream's routine per-forward
            output (not its warnings) while it is entered; used by the command line and the
            benchmark scripts (:func:`quiet_upstream`), never by the library.
        transformer_blocks: dotted paths (from the root) of the ``ModuleList`` s that hold the
            backbone's own transformer blocks, each with a fused ``attn.qkv`` linear layer; the
            baselines that tune those blocks (:mod:`raytun3r_plugin.baselines`) read them.
            Empty: the family offers no such baseline.
        prompt_target: where the calibration-token baseline inserts its tokens, or None.
        branches: for a model made of several networks, ``(path, family)`` per patch root: the
            dotted path from the root to one network and the registered family whose spec
            patches it (its targets, checks and ``describe``). One ``apply`` patches them all
            under one handle. The first is the *main* branch: ``describe(root)`` must describe
            it, and it alone receives an adapter's learned tables; the others receive the
            parameter-free corrections. A spec with branches declares no ``targets`` of its own.
            Empty (the default): the root is the one patch root.
        input_size: the long side, in pixels, at which upstream runs the family by default (DA3
            and Pi3: 504, VGGT: 518, VGGT-Omega: 512): the input size of a fit and of inference when none is
            given. A model instance may carry its own as ``raytun3r_input_size`` (the built-in
            networks, trained at 112); :func:`native_input_size` reads both.
        recipe_changes: ``{recipe name: {AdaptConfig field: value}}``: the settings this family
            needs that differ from a fit recipe's (:mod:`raytun3r_plugin.adaptation.recipes`),
            applied by ``AdaptConfig.from_recipe(name, model=...)``. Each entry must be justified
            by a measurement written beside it (the DA3 family's, ``patches/da3.py``).
        composites: specs of models made of several networks of this family (DA3's nested
            model), each with ``branches``. They are part of the family, not families of their
            own: :func:`specs` lists the family once, :func:`spec_for` tries them before the
            family's own ``recognise``, and their builders are the family's.
    """

    family: str
    upstream: UpstreamVersion
    recognise: Callable[[nn.Module], nn.Module | None]
    describe: Callable[[nn.Module], BackboneInfo]
    targets: tuple[PatchTarget, ...]
    predict: Callable[..., Any]
    builders: dict[str, Callable[..., nn.Module]] = field(default_factory=dict)
    rope_classes: tuple[str, ...] = ()
    rope_base_attribute: str | None = None
    check: Callable[[nn.Module], None] | None = None
    quiet: Callable[[], AbstractContextManager] | None = None
    transformer_blocks: tuple[str, ...] = ()
    prompt_target: PromptTarget | None = None
    branches: tuple[tuple[str, str], ...] = ()
    composites: tuple[BackboneSpec, ...] = ()
    input_size: int = 504
    recipe_changes: dict[str, dict[str, Any]] = field(default_factory=dict)


_SPECS: dict[str, BackboneSpec] = {}
_BUILTINS_LOADED = False


def _validate(spec: BackboneSpec, parent: BackboneSpec | None = None) -> None:
    """Refuse a spec whose parts contradict each other (PEFT's ``register_peft_method`` checks)."""
    where = f"backbone spec {spec.family!r}"
    if not isinstance(spec.family, str) or not spec.family:
        raise BackboneRegistrationError(
            f"a backbone spec needs a non-empty family name, got {spec.family!r}"
        )
    if not isinstance(spec.upstream, UpstreamVersion):
        raise BackboneRegistrationError(
            f"{where}: upstream must be an UpstreamVersion, got {type(spec.upstream).__name__}"
        )
    if spec.branches:
        _validate_branches(spec, where, parent)
        return
    for composite in spec.composites:
        if not composite.branches or composite.builders or composite.composites:
            raise BackboneRegistrationError(
                f"{where}: composite {composite.family!r} must declare branches, and no builders "
                "or composites of its own"
            )
        if composite.family == spec.family or composite.family in _SPECS:
            raise BackboneRegistrationError(
                f"{where}: composite {composite.family!r} reuses a registered family name"
            )
        _validate(composite, spec)
    if not spec.targets:
        raise BackboneRegistrationError(f"{where}: declares no patch targets")
    seen: set[tuple[str, str]] = set()
    for target in spec.targets:
        if target.hook not in HOOK_KINDS:
            raise BackboneRegistrationError(
                f"{where}: target {target.name!r} has hook {target.hook!r}; expected one of {', '.join(HOOK_KINDS)}"
            )
        for path in target.owners:
            if (path, target.attribute) in seen:
                raise BackboneRegistrationError(
                    f"{where}: {path}.{target.attribute} is the target of two PatchTargets"
                )
            seen.add((path, target.attribute))
    rope_targets = [target for target in spec.targets if target.hook == "rope"]
    if rope_targets:
        if not spec.rope_classes or not spec.rope_base_attribute:
            raise BackboneRegistrationError(
                f"{where}: has rope targets, so it must declare rope_classes and rope_base_attribute"
            )
        if not any(set(target.owner_classes) & set(spec.rope_classes) for target in rope_targets):
            raise BackboneRegistrationError(
                f"{where}: no rope target patches one of the rope_classes ({', '.join(spec.rope_classes)}), "
                "so no RoPE instance could count as covered"
            )


def _validate_branches(spec: BackboneSpec, where: str, parent: BackboneSpec | None) -> None:
    """A spec of several networks: distinct paths, each patched by a registered plain family
    (or by ``parent``, the family it is a composite of, being registered with it)."""
    if spec.targets:
        raise BackboneRegistrationError(
            f"{where}: declares branches and targets; a branched spec patches through its branches only"
        )
    paths = [path for path, _family in spec.branches]
    if len(set(paths)) != len(paths) or not all(isinstance(p, str) and p for p in paths):
        raise BackboneRegistrationError(f"{where}: branch paths must be distinct, got {paths}")
    for path, family in spec.branches:
        other = parent if parent is not None and family == parent.family else _SPECS.get(family)
        if other is None or other.branches:
            raise BackboneRegistrationError(
                f"{where}: branch {path!r} names family {family!r}, which is not a registered "
                "spec without branches (register it first)"
            )


def register(spec: BackboneSpec, *, overwrite: bool = False) -> BackboneSpec:
    """Register the spec of a backbone family after checking it; returns ``spec``.

    Raises:
        DuplicateBackboneError: the family, or one of its builder names, is registered already
            (``overwrite=True`` replaces a family of the same name; registering the very same
            spec object again is a no-op).
        BackboneRegistrationError: the spec is inconsistent (unknown hook kind, the same method
            targeted twice, rope targets without ``rope_classes`` / ``rope_base_attribute``).
    """
    _validate(spec)
    existing = _SPECS.get(spec.family)
    if existing is spec:
        return spec
    if existing is not None and not overwrite:
        raise DuplicateBackboneError(
            f"backbone family {spec.family!r} is already registered (checked against {existing.upstream}); "
            "pass overwrite=True to replace it"
        )
    for other in _SPECS.values():
        clash = (
            sorted(set(other.builders) & set(spec.builders)) if other.family != spec.family else []
        )
        if clash:
            raise DuplicateBackboneError(
                f"backbone spec {spec.family!r}: load_backbone name(s) {clash} are already provided by {other.family!r}"
            )
    _SPECS[spec.family] = spec
    return spec


def _load_builtins() -> None:
    global _BUILTINS_LOADED
    if not _BUILTINS_LOADED:
        _BUILTINS_LOADED = True
        importlib.import_module("raytun3r_plugin.patches")


def specs() -> dict[str, BackboneSpec]:
    """The registered specs by family (loading the built-in backbone modules first)."""
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


def uncompiled(model: nn.Module) -> nn.Module:
    """The module ``torch.compile(module)`` wrapped (its ``_orig_mod``), else ``model`` itself."""
    inner = getattr(model, "_orig_mod", None)
    if type(model).__name__ == "OptimizedModule" and isinstance(inner, nn.Module):
        return inner
    return model


def spec_for(model: nn.Module) -> tuple[BackboneSpec, nn.Module]:
    """The registered spec that recognises ``model`` and the root module to patch.

    A ``torch.compile`` wrapper is recognised as the module it wraps (docs/deployment.md).
    """
    _load_builtins()
    model = uncompiled(model)
    for spec in _SPECS.values():
        for candidate in (*spec.composites, spec):
            root = candidate.recognise(model)
            if root is not None:
                return candidate, root
    known = ", ".join(f"{s.family} ({s.upstream})" for s in _SPECS.values())
    raise UnsupportedUpstreamError(
        f"no raytun3r patch recognises a {type(model).__module__}.{type(model).__qualname__}; supported: {known}"
    )


def native_input_size(model: nn.Module) -> int:
    """The long side, in pixels, at which ``model`` runs by default: its own
    ``raytun3r_input_size`` (set by the builders of networks trained at another size, such as
    the built-in ones), else its family's :attr:`BackboneSpec.input_size`."""
    spec, root = spec_for(model)
    own = getattr(root, "raytun3r_input_size", None) or getattr(model, "raytun3r_input_size", None)
    return int(own) if own else int(spec.input_size)


def branch_roots(spec: BackboneSpec, root: nn.Module) -> list[tuple[str, BackboneSpec, nn.Module]]:
    """``(path, spec, module)`` of every patch root of ``root``, the main one first.

    A spec without branches has one: ``("", spec, root)``. For a branched spec each declared
    branch must be found and recognised by its family, else :class:`UnsupportedUpstreamError`.
    """
    if not spec.branches:
        return [("", spec, root)]
    found = []
    for path, family in spec.branches:
        branch_spec = _SPECS[family]
        node = resolve_path(root, path)
        branch = branch_spec.recognise(node) if isinstance(node, nn.Module) else None
        if branch is None:
            what = (
                "nothing" if node is None else f"{type(node).__module__}.{type(node).__qualname__}"
            )
            raise _refuse(
                spec,
                f"{spec.family}: expected a {family} network at '{path}' of {type(root).__qualname__}, found {what}",
            )
        found.append((path, branch_spec, branch))
    return found


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


def _checked_against(spec: BackboneSpec) -> str:
    """'expected X, found Y' for the upstream release, appended to every structural refusal."""
    text = f"the {spec.family} patch was checked against {spec.upstream}"
    installed = spec.upstream.installed()
    if installed is not None and installed != spec.upstream.version:
        text += f", found {spec.upstream.source} {installed} installed"
    return text


def _refuse(spec: BackboneSpec, text: str) -> UnsupportedUpstreamError:
    return UnsupportedUpstreamError(f"{text} ({_checked_against(spec)})")


def rope_base(spec: BackboneSpec, owner: Any) -> float:
    """The frequency base of the RoPE instance ``owner``, read from ``spec.rope_base_attribute``.

    Raises :class:`UnsupportedUpstreamError` ("expected X, found Y") when the attribute is
    missing or not a positive number: a guessed default would give wrong angles silently.
    """
    name = spec.rope_base_attribute
    value = getattr(owner, name, None) if name else None
    if isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0:
        return float(value)
    if name is None:
        found = "no rope_base_attribute declared on the spec"
    elif not hasattr(owner, name):
        numbers = {
            key: item
            for key, item in vars(owner).items()
            if isinstance(item, (int, float)) and not isinstance(item, bool)
        }
        found = f"no attribute {name!r} (its numeric attributes: {', '.join(f'{k}={v!r}' for k, v in numbers.items()) or 'none'})"
    else:
        found = f"{name}={value!r}"
    raise _refuse(
        spec,
        f"{spec.family}: expected the RoPE frequency base as a positive number in {type(owner).__qualname__}.{name}, found {found}",
    )


def _is_rope(spec: BackboneSpec, module: Any) -> bool:
    return bool(set(_class_names(module)) & set(spec.rope_classes))


def check_rope_coverage(spec: BackboneSpec, root: nn.Module) -> None:
    """Refuse a model holding a RoPE instance (``spec.rope_classes``) that no ``rope`` target reaches."""
    if not spec.rope_classes:
        return
    owner_paths = [
        path for target in spec.targets if target.hook == "rope" for path in target.owners
    ]
    covered = {id(resolve_path(root, path)) for path in owner_paths}
    for name, module in root.named_modules():
        if _is_rope(spec, module) and id(module) not in covered:
            raise _refuse(
                spec,
                f"{spec.family}: found a {type(module).__name__} at '{name}' that is not one of the patched RoPE "
                f"instances ({', '.join(owner_paths)}); this upstream version is not supported",
            )


def resolve_targets(
    spec: BackboneSpec, root: nn.Module, wanted_hooks: set[str]
) -> list[tuple[PatchTarget, str, Any]]:
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
                raise _refuse(
                    spec,
                    f"{where}: expected a {' or '.join(target.owner_classes)} at '{path}', found nothing",
                )
            names = _class_names(owner)
            if not set(names) & set(target.owner_classes):
                raise _refuse(
                    spec,
                    f"{where}: expected a {' or '.join(target.owner_classes)} at '{path}', found {type(owner).__module__}.{type(owner).__qualname__}",
                )
            signature = upstream_signature(owner, target.attribute)
            if signature is None:
                raise _refuse(
                    spec,
                    f"{where}: expected method {target.attribute}{target.signature}, found no such method on {type(owner).__qualname__}",
                )
            if signature != target.signature:
                raise _refuse(
                    spec,
                    f"{where}: expected signature {target.attribute}({', '.join(target.signature)}), found {target.attribute}({', '.join(signature)})",
                )
            if target.hook == "rope" and _is_rope(spec, owner):
                rope_base(spec, owner)  # refused here, before anything is built
            found.append((target, path, owner))
    # After the targets, so that a moved owner is reported as such, not as a stray RoPE.
    check_rope_coverage(spec, root)
    return found
