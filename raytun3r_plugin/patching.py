"""``apply`` / ``remove``: reversible, per-instance patching of a frozen backbone.

Modelled on accelerate's hooks and pytest's monkeypatch: each replaced method is recorded once,
installed as an instance attribute (so other instances of the same class are untouched), and
undone in reverse order. ``apply`` validates everything first and mutates last; a failure while
installing rolls back what was installed, so the model is never left half patched.

Lifetime, as accelerate's ``add_hook_to_module``: an installed wrapper
(:class:`~raytun3r_plugin.patch_wrapper.PatchWrapper`) holds its owner by weak reference and
looks the original method up *at call time*, and the handle holds the model by weak reference,
so a patched model is freed like any other. The handle itself lives on
the model (the one attribute of :data:`ADDED_ATTRIBUTES`), which is what lets ``copy.deepcopy``
of a patched model give a patched copy with its own handle that runs its own weights.
"""

from __future__ import annotations

import contextlib
import copy
import threading
import weakref
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.errors import (
    AlreadyAppliedError,
    NotAppliedError,
    PatchedCopyError,
)
from raytun3r_plugin.geometry import (
    DEFAULT_KNEE_DEG,
    DEFAULT_MAX_STRETCH,
)
from raytun3r_plugin.patch_checks import (  # what apply validates before it writes
    _check_adapter,
    _check_branch_width,
    _check_per_view,
    _components_for,
    _same_views,
    _views_of,
)
from raytun3r_plugin.patch_state import (  # the state the wrappers read; re-exported
    _DISABLED,
    PatchState,
)
from raytun3r_plugin.patch_wrapper import NOT_SET, WRAPPER_MARK, PatchWrapper
from raytun3r_plugin.registry import (
    HOOK_COMPONENTS,
    BackboneInfo,
    BackboneSpec,
    PatchTarget,
    branch_roots,
    resolve_targets,
    spec_for,
)

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

#: Where the live handle is kept on the model given to :func:`apply`.
HANDLE_ATTRIBUTE = "_raytun3r_handle"
#: Every attribute ``apply`` adds to the model object itself (accelerate's
#: ``_accelerate_added_attributes``); ``remove`` deletes exactly these.
ADDED_ATTRIBUTES = (HANDLE_ATTRIBUTE,)

# apply / remove of any model, one at a time (the check-then-install of apply must not interleave).
# Never taken with ``with``: an interrupt between a ``with``'s acquire and the start of its block
# leaves the lock held for good. Callers acquire it as the first statement inside a ``try`` whose
# ``finally`` calls :func:`_release`, which asks the lock itself whether this thread holds it
# (an RLock knows its owner), so an interrupt at any point cannot leave it held by a thread that
# has left apply/remove; a leaked level (an interrupt inside the ``finally``) is released by the
# same thread's next apply/remove.
_LOCK = threading.RLock()


def _release() -> None:
    """Release every level of :data:`_LOCK` this thread holds (none: nothing)."""
    while _LOCK._is_owned():  # type: ignore[attr-defined]
        _LOCK.release()


@dataclass
class _Installed:
    owner: weakref.ref
    attribute: str
    had_own: bool
    previous: object


class RaytunHandle:
    """A live patch on one model: ``.remove()``, context manager, ``.disabled()``.

    The handle holds its model by weak reference: it never keeps a model alive, and once the
    model is garbage-collected the handle is inactive and ``remove()`` does nothing.
    """

    def __init__(
        self,
        model: nn.Module,
        root: nn.Module,
        spec: BackboneSpec,
        state: PatchState,
        installed: list[_Installed],
        states: tuple[PatchState, ...] = (),
    ):
        self._model = weakref.ref(model)
        self._root = weakref.ref(root)
        self.spec = spec
        self._state = state  # the main branch's (the adapter's); one per branch in _states
        self._states = states or (state,)
        self._installed = installed
        self._removed = False

    def _alive(self, ref: weakref.ref) -> nn.Module:
        module = ref()
        if module is None:
            raise NotAppliedError("the patched model was garbage-collected")
        return module

    @property
    def model(self) -> nn.Module:
        """The model given to ``apply`` (raises :class:`NotAppliedError` once it is freed)."""
        return self._alive(self._model)

    @property
    def root(self) -> nn.Module:
        """The module that was patched (the network inside a wrapper such as DA3's API class)."""
        return self._alive(self._root)

    @property
    def camera(self):
        """The camera (of a rig: its first camera; all of them in :attr:`cameras`)."""
        return self._state.camera

    @property
    def adapter(self) -> Adapter | None:
        """The adapter (of a rig: its first camera's; all of them in :attr:`adapters`)."""
        return self._state.adapter

    @property
    def cameras(self) -> tuple:
        """One camera per view position of the rig (one entry for a single camera)."""
        return tuple(view.camera for view in self._state.views)

    @property
    def adapters(self) -> tuple[Adapter | None, ...]:
        """One adapter (or None) per view position, like :attr:`cameras`."""
        return tuple(view.adapter for view in self._state.views)

    @property
    def is_rig(self) -> bool:
        """True when the views have different cameras, masks or adapters (docs/rigs.md)."""
        return self._state.rig

    @property
    def components(self) -> dict[str, bool]:
        return dict(self._state.components)

    @property
    def is_active(self) -> bool:
        """False after ``remove()`` or once the model is garbage-collected."""
        return not self._removed and self._model() is not None

    def wrapped(self) -> list[tuple[Any, str]]:
        """``(owner, attribute)`` of every replaced method still alive, in install order."""
        pairs = []
        for item in self._installed:
            owner = item.owner()
            if owner is not None:
                pairs.append((owner, item.attribute))
        return pairs

    @property
    def patched(self) -> list[str]:
        """``OwnerClass.attribute`` of every replaced method, in install order."""
        return [f"{type(owner).__name__}.{attribute}" for owner, attribute in self.wrapped()]

    def remove(self) -> None:
        """Undo every replacement in reverse order and drop the handle from the model; idempotent."""
        try:
            _LOCK.acquire()
            if self._removed:
                return
            _undo(self._installed)
            self._removed = True
            model = self._model()
            if model is not None and vars(model).get(HANDLE_ATTRIBUTE) is self:
                for name in ADDED_ATTRIBUTES:
                    vars(model).pop(name, None)
        finally:
            _release()

    @contextlib.contextmanager
    def disabled(self) -> Iterator[None]:
        """Plain upstream behaviour inside the block (in this thread / context only).

        A compiled model (``torch.compile``) cannot see a thread's context: while a block is
        open it runs upstream's behaviour in every thread (docs/deployment.md).
        """
        token = _DISABLED.set(_DISABLED.get() | {id(state) for state in self._states})
        _count_disabled(self._states, +1)
        try:
            yield
        finally:
            _count_disabled(self._states, -1)
            _DISABLED.reset(token)

    def __enter__(self) -> RaytunHandle:
        return self

    def __exit__(self, *exc) -> None:
        self.remove()

    def __deepcopy__(self, memo: dict) -> RaytunHandle:
        """The handle of a deep copy of the patched model (reached through the model's marker)."""
        model = self._model()
        if model is None or id(model) not in memo:
            raise PatchedCopyError(
                "deepcopy the patched model, not its handle: the copy then gets a handle of its own"
            )
        twin = RaytunHandle.__new__(RaytunHandle)
        memo[id(self)] = twin
        twin._model = weakref.ref(memo[id(model)])
        twin._root = weakref.ref(copy.deepcopy(self.root, memo))
        twin.spec = self.spec
        twin._state = copy.deepcopy(self._state, memo)
        twin._states = tuple(copy.deepcopy(state, memo) for state in self._states)
        twin._installed = [
            _Installed(
                weakref.ref(copy.deepcopy(owner, memo)),
                item.attribute,
                item.had_own,
                copy.deepcopy(item.previous, memo),
            )
            for item in self._installed
            if (owner := item.owner()) is not None
        ]
        twin._removed = self._removed
        return twin

    def __reduce_ex__(self, protocol):
        raise PatchedCopyError(
            "a raytun3r handle cannot be pickled: remove() the patch before saving the model"
        )

    def __repr__(self) -> str:
        status = "active" if self.is_active else "removed"
        cameras = f"cameras={list(self.cameras)!r}" if self.is_rig else f"camera={self.camera!r}"
        return f"RaytunHandle({self.spec.family}, {status}, {cameras}, components={[k for k, v in self.components.items() if v]})"


# Guards the read-modify-write of PatchState.disabled_blocks across threads.
_DISABLED_COUNT_LOCK = threading.Lock()


def _count_disabled(states: tuple[PatchState, ...], step: int) -> None:
    """Add ``step`` to every state's count of open ``disabled()`` blocks (what compiled code reads)."""
    with _DISABLED_COUNT_LOCK:
        for state in states:
            state.disabled_blocks += step


def _undo(installed: list[_Installed]) -> None:
    """Restore every recorded attribute, last first; idempotent, so it can be run again.

    A record is dropped only once its attribute is restored, so an undo that is itself
    interrupted leaves the records still to restore. A record may precede its write (records
    are made before the write, :func:`_install`): restoring an attribute that was never
    replaced changes nothing.
    """
    while installed:
        item = installed[-1]
        owner = item.owner()
        if owner is not None:  # else freed with its model: nothing left to restore
            if item.had_own:
                object.__setattr__(owner, item.attribute, item.previous)
            else:
                vars(owner).pop(item.attribute, None)
        installed.pop()


def apply(
    model: nn.Module,
    camera: Camera | Sequence[Camera] | None = None,
    adapter: Adapter | str | Sequence[Adapter | str | None] | None = None,
    *,
    components: Mapping[str, bool] | list[str] | None = None,
    strict: bool = True,
    mask: torch.Tensor | Sequence[torch.Tensor | None] | None = None,
    knee_deg: float = DEFAULT_KNEE_DEG,
    max_stretch: float = DEFAULT_MAX_STRETCH,
) -> RaytunHandle:
    """Make ``model`` fisheye-aware for ``camera``; returns a :class:`RaytunHandle`.

    Args:
        model: a supported backbone instance (see ``raytun3r_plugin.registry.specs()``).
        camera: the camera of the native images (a ``raytun3r_plugin.cameras.Camera``); rescaled to
            the network input size on every forward. Defaults to the adapter's camera.
            A list makes a **rig** (docs/rigs.md): view ``s`` of every forward is taken by
            ``camera[s % V]``, so a forward over ``T`` instants of a ``V``-camera rig passes
            ``S = V * T`` views in the order ``(t0 cam0, t0 cam1, ..., t1 cam0, ...)``. All
            cameras of a rig need one aspect ratio (the views share one input size).
        adapter: an :class:`Adapter`, a path to an adapter file, or None for the parameter-free
            corrections only. With a camera list: one per camera (None for a camera without
            one), or a single adapter for every camera. Defaults to none.
        components: which corrections are on (``adapter.COMPONENTS``), plus any ablation
            switch (``adapter.ABLATION_SWITCHES``: ``"pe_radial_only"``, ``"pe_naive_remap"``,
            docs/components.md); defaults to the (first) adapter's recorded set, or all
            corrections. One set for every view.
        strict: refuse an adapter fitted on other weights (PE fingerprint) or another camera.
        mask: optional (H, W) bool mask of valid pixels, combined with the camera's valid region;
            with a camera list, one mask (or None) per camera.
        knee_deg: the knee angle of the fisheye-to-pinhole map, degrees.
        max_stretch: the largest stretch of the patch resampling.

    Everything is validated before the model is touched; a failure while installing rolls back.
    Applying the same camera and adapter again returns the existing handle.
    """
    cameras, adapters, masks = _views_of(camera, adapter, mask)
    camera, adapter, mask = cameras[0], adapters[0], masks[0]

    spec, root = spec_for(model)
    info = spec.describe(root)
    # (path, spec, patch root, description) per patch root, the main one (the adapter's) first.
    branches = [
        (path, branch_spec, branch, branch_spec.describe(branch) if spec.branches else info)
        for path, branch_spec, branch in branch_roots(spec, root)
    ]
    for view_camera, view_adapter in zip(cameras, adapters, strict=True):
        if view_adapter is not None:
            if spec.branches:
                _check_branch_width(view_adapter, spec, branches)
            _check_adapter(view_adapter, info, view_camera, strict)
    wanted = _components_for(components, next((a for a in adapters if a is not None), None))
    views = tuple(zip(cameras, adapters, masks, strict=True))

    # Success is decided after the lock is released: until ``return``, any exception (an
    # interrupt inside the release included) takes a handle this call made off again, so apply
    # never raises with the model patched, nor returns with the lock held.
    existing = handle = None
    try:
        _LOCK.acquire()
        existing = model.__dict__.get(HANDLE_ATTRIBUTE)
        handle = _apply_locked(model, root, spec, branches, views, wanted, knee_deg, max_stretch)
        _release()
        return handle
    except BaseException:
        try:
            if handle is not None and handle is not existing:
                handle.remove()
        finally:
            _release()
        raise


def _apply_locked(
    model: nn.Module,
    root: nn.Module,
    spec: BackboneSpec,
    branches: list[tuple[str, BackboneSpec, nn.Module, BackboneInfo]],
    views: tuple[tuple[Camera, Adapter | None, torch.Tensor | None], ...],
    wanted: dict[str, bool],
    knee_deg: float,
    max_stretch: float,
) -> RaytunHandle:
    """The check-then-install of :func:`apply`, run while holding :data:`_LOCK`."""
    camera, adapter, mask = views[0]
    existing = handle_of(model)
    if existing is not None:
        if _same_views(existing._state.views, views) and existing.components == wanted:
            return existing
        raise AlreadyAppliedError(
            f"{type(model).__name__} is already patched ({existing!r}); call remove() first"
        )

    if spec.branches and spec.check is not None:
        spec.check(root)
    hooks = {hook for hook, served in HOOK_COMPONENTS.items() if any(wanted.get(c) for c in served)}
    # Every branch is checked and resolved before any wrapper is built, and every wrapper built
    # before any is installed: one failing branch leaves all of them untouched.
    states: list[PatchState] = []
    resolved: list[tuple[PatchTarget, str, Any, PatchState]] = []
    for index, (branch_path, branch_spec, branch, info) in enumerate(branches):
        if branch_spec.check is not None:
            branch_spec.check(branch)
        found = resolve_targets(branch_spec, branch, hooks)
        # Only the main branch gets the adapter: its learned tables have that network's width.
        state = PatchState(
            camera,
            adapter if index == 0 else None,
            wanted,
            info,
            mask,
            knee_deg,
            max_stretch,
            model=model,
            spec=branch_spec,
            views=tuple(
                (view_camera, view_adapter if index == 0 else None, view_mask)
                for view_camera, view_adapter, view_mask in views
            ),
        )
        if state.rig:
            _check_per_view(branch_spec, found, branch_path, state)
        states.append(state)
        prefix = f"{branch_path}." if branch_path else ""
        resolved += [(target, prefix + path, owner, state) for target, path, owner in found]
    for target, path, owner, _state in resolved:
        current = owner.__dict__.get(target.attribute)
        if getattr(current, WRAPPER_MARK, False):
            raise AlreadyAppliedError(f"{path}.{target.attribute} is already wrapped by raytun3r")
    # Build every replacement before installing any, so a build error changes nothing.
    planned = []
    for target, _path, owner, state in resolved:
        previous = owner.__dict__.get(target.attribute, NOT_SET)
        planned.append((owner, target.attribute, PatchWrapper(owner, target, state, previous)))

    # From here on the model changes: everything up to the return is inside the rollback's
    # scope (the installs, the handle's construction and its registration on the model), and
    # the rollback reads what is on the model, not local variables an interrupt may have
    # left unassigned.
    installed: list[_Installed] = []
    try:
        for owner, attribute, replacement in planned:
            _install(installed, owner, attribute, replacement)
        handle = RaytunHandle(model, root, spec, states[0], installed, tuple(states))
        _register(model, handle)
        return handle
    except BaseException:
        _rollback(model, installed)
        raise


def _install(installed: list[_Installed], owner, attribute: str, replacement) -> None:
    """Replace ``owner.attribute`` by ``replacement``, recorded in ``installed`` first.

    Record before write: an interrupt between the two leaves a record of an attribute not yet
    replaced (whose undo changes nothing), never a replacement without a record.
    """
    had_own = attribute in owner.__dict__
    _record(
        installed, _Installed(weakref.ref(owner), attribute, had_own, owner.__dict__.get(attribute))
    )
    _write(owner, attribute, replacement)


def _record(installed: list[_Installed], record: _Installed) -> None:
    installed.append(record)


def _write(owner: Any, attribute: str, value: Any) -> None:
    # object.__setattr__: nn.Module.__setattr__ would be fine for plain functions, but this keeps
    # the write an ordinary instance attribute for every owner type.
    object.__setattr__(owner, attribute, value)


def _register(model: nn.Module, handle: RaytunHandle) -> None:
    """Make ``handle`` the model's live handle (what :func:`handle_of` finds)."""
    object.__setattr__(model, HANDLE_ATTRIBUTE, handle)


def _rollback(model: nn.Module, installed: list[_Installed]) -> None:
    """Undo a failed apply: every recorded replacement and a handle registered on the model.

    Retried when it is itself interrupted (each step is idempotent), so that a second Ctrl-C
    during the rollback does not leave a half-patched model.
    """
    for _attempt in range(100):
        try:
            handle = vars(model).get(HANDLE_ATTRIBUTE)
            if isinstance(handle, RaytunHandle) and handle._installed is installed:
                for name in ADDED_ATTRIBUTES:
                    vars(model).pop(name, None)
            _undo(installed)
            return
        except BaseException:  # a rollback interrupted: run it again
            continue


def remove(model: nn.Module) -> None:
    """Remove the raytun3r patch from ``model`` (no handle needed)."""
    handle = handle_of(model)
    if handle is None:
        raise NotAppliedError(f"{type(model).__name__} carries no raytun3r patch")
    handle.remove()


def handle_of(model: nn.Module) -> RaytunHandle | None:
    """The live handle of ``model`` (also of a deep copy of a patched model), or None."""
    handle = getattr(model, "__dict__", {}).get(HANDLE_ATTRIBUTE)
    # A shallow copy (copy.copy) shares the marker but is not the patched model.
    if isinstance(handle, RaytunHandle) and handle.is_active and handle._model() is model:
        return handle
    return None
