"""``apply`` / ``remove``: reversible, per-instance patching of a frozen backbone.

Modelled on accelerate's hooks and pytest's monkeypatch: each replaced method is recorded once,
installed as an instance attribute (so other instances of the same class are untouched), and
undone in reverse order. ``apply`` validates everything first and mutates last; a failure while
installing rolls back what was installed, so the model is never left half patched.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import threading
import weakref
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from raytun3r_plugin.adapter import Adapter, normalise_components, pe_fingerprint
from raytun3r_plugin.errors import AdapterError, AlreadyAppliedError, CameraError, NotAppliedError
from raytun3r_plugin.geometry import (
    DEFAULT_KNEE_DEG,
    DEFAULT_MAX_STRETCH,
    GeometryCache,
    SizeGeometry,
    resize_mask,
)
from raytun3r_plugin.registry import BackboneInfo, BackboneSpec, resolve_targets, spec_for

# Hook kind -> the components it serves (a hook is installed when any of them is on).
_HOOK_COMPONENTS = {
    "pe": ("pe",),
    "rope": ("rope",),
    "patch_embed": ("patch_resample", "border_tokens"),
    "grid": ("grid",),
}
_WRAPPER_MARK = "__raytun3r_wrapper__"

# Handles disabled in the current thread / context (see RaytunHandle.disabled).
_DISABLED: contextvars.ContextVar[frozenset[int]] = contextvars.ContextVar("raytun3r_disabled", default=frozenset())

_ACTIVE: weakref.WeakKeyDictionary[nn.Module, RaytunHandle] = weakref.WeakKeyDictionary()
_ACTIVE_LOCK = threading.Lock()


class PatchState:
    """What the installed wrappers read at run time (one per patched model)."""

    def __init__(self, camera, adapter: Adapter | None, components: dict[str, bool], info: BackboneInfo, mask: torch.Tensor | None, knee_deg: float, max_stretch: float):
        self.camera = camera
        self.adapter = adapter
        self.components = components
        self.info = info
        self.geometry_cache = GeometryCache(camera, info.patch_size, mask, knee_deg, max_stretch)

    @property
    def active(self) -> bool:
        return id(self) not in _DISABLED.get()

    def uses(self, component: str) -> bool:
        """True when ``component`` is on and the handle is not disabled in this context."""
        if not self.components.get(component, False) or not self.active:
            return False
        if component == "pe":
            return self.adapter is not None
        if component == "rope":
            return self.adapter is not None and self.adapter.rope is not None
        return True

    def geometry(self, height: int, width: int) -> SizeGeometry:
        return self.geometry_cache.at(int(height), int(width))

    def pe_correction(self, geometry: SizeGeometry, device, dtype) -> torch.Tensor:
        """(hw, C) PE update t_r(rho) + rho d_theta(theta) for the current grid."""
        adapter = self.adapter
        radial, angular = geometry.pe_weights(adapter.n_r, adapter.n_theta, device, dtype)
        return radial @ adapter.pe["radial"].to(device, dtype) + angular @ adapter.pe["angular"].to(device, dtype)

    def rope_displacement(self, geometry: SizeGeometry, device, dtype) -> torch.Tensor:
        """(hw, 2) RoPE position displacement in (y, x) token units along the outward direction."""
        weights, direction = geometry.rope_basis(self.adapter.n_r_rope, device, dtype)
        return (weights @ self.adapter.rope["radial"].to(device, dtype))[:, None] * direction


@dataclass
class _Installed:
    owner: object
    attribute: str
    had_own: bool
    previous: object


class RaytunHandle:
    """A live patch on one model: ``.remove()``, context manager, ``.disabled()``."""

    def __init__(self, model: nn.Module, root: nn.Module, spec: BackboneSpec, state: PatchState, installed: list[_Installed]):
        self.model = model
        self.root = root
        self.spec = spec
        self._state = state
        self._installed = installed
        self._removed = False

    @property
    def camera(self):
        return self._state.camera

    @property
    def adapter(self) -> Adapter | None:
        return self._state.adapter

    @property
    def components(self) -> dict[str, bool]:
        return dict(self._state.components)

    @property
    def is_active(self) -> bool:
        return not self._removed

    @property
    def patched(self) -> list[str]:
        """``owner_path.attribute`` of every replaced method, in install order."""
        return [f"{type(item.owner).__name__}.{item.attribute}" for item in self._installed]

    def remove(self) -> None:
        """Undo every replacement in reverse order; idempotent."""
        with _ACTIVE_LOCK:
            if self._removed:
                return
            _undo(self._installed)
            self._removed = True
            if _ACTIVE.get(self.model) is self:
                del _ACTIVE[self.model]

    @contextlib.contextmanager
    def disabled(self) -> Iterator[None]:
        """Plain upstream behaviour inside the block (in this thread / context only)."""
        token = _DISABLED.set(_DISABLED.get() | {id(self._state)})
        try:
            yield
        finally:
            _DISABLED.reset(token)

    def __enter__(self) -> RaytunHandle:
        return self

    def __exit__(self, *exc) -> None:
        self.remove()

    def __repr__(self) -> str:
        status = "active" if self.is_active else "removed"
        return f"RaytunHandle({self.spec.family}, {status}, camera={self.camera!r}, components={[k for k, v in self.components.items() if v]})"


def _undo(installed: list[_Installed]) -> None:
    for item in reversed(installed):
        if item.had_own:
            object.__setattr__(item.owner, item.attribute, item.previous)
        else:
            delattr(item.owner, item.attribute)
    installed.clear()


def _same_camera(a, b) -> bool:
    if a is None or b is None:
        return a is b
    if (a.width, a.height) != (b.width, b.height):
        a = a.resized(b.width, b.height)
    if a.model != b.model:
        return False
    return bool(torch.allclose(a.params.detach().double(), b.params.detach().double(), rtol=1e-6, atol=1e-6))


def _check_adapter(adapter: Adapter, info: BackboneInfo, camera, strict: bool) -> None:
    if adapter.backbone != info.name:
        raise AdapterError(f"adapter was made for backbone {adapter.backbone!r}, this model is {info.name!r}")
    if adapter.embed_dim != info.embed_dim:
        raise AdapterError(f"adapter has embed_dim {adapter.embed_dim}, this model has {info.embed_dim}")
    if adapter.patch_size != info.patch_size:
        raise AdapterError(f"adapter has patch_size {adapter.patch_size}, this model has {info.patch_size}")
    if bool(adapter.n_r_rope) and not info.has_rope:
        raise AdapterError(f"adapter has a RoPE table but {info.name!r} has no RoPE")
    if strict:
        found = pe_fingerprint(info.pos_embed)
        if adapter.pe_fingerprint and adapter.pe_fingerprint != found:
            raise AdapterError(
                f"adapter was fitted on other weights of {info.name!r} (pe_fingerprint {adapter.pe_fingerprint}, "
                f"this model has {found}); pass strict=False to apply it anyway"
            )
        if adapter.camera is not None and camera is not None and not _same_camera(adapter.camera, camera):
            raise AdapterError(f"adapter was fitted on {adapter.camera!r}, not on {camera!r}; pass strict=False to apply it anyway")


def _components_for(components, adapter: Adapter | None) -> dict[str, bool]:
    if components is None and adapter is not None:
        return dict(adapter.components)
    return normalise_components(components)


def _checked_mask(mask: Any, camera: Any) -> torch.Tensor:
    """The scene mask as (H, W) bool, refused when it cannot belong to ``camera``.

    It may be at the camera's size or at another size of the same aspect ratio (it is resized
    with the camera to every input); a different aspect ratio or nothing left inside the lens is
    a mistake that would otherwise show only as worse depth.
    """
    mask = torch.as_tensor(mask).bool()
    if mask.ndim != 2:
        raise CameraError(f"mask must be (H, W), got shape {tuple(mask.shape)}")
    height, width = mask.shape
    if abs(height * camera.width - width * camera.height) > 0.01 * width * camera.height:
        raise CameraError(f"mask is {width}x{height} px but the camera is {camera.width}x{camera.height}: the aspect ratios differ")
    valid = camera.valid_mask().cpu()
    if not bool((resize_mask(mask, valid.shape) & valid).any()):
        raise CameraError("mask leaves no pixel inside the camera's valid region")
    return mask


def apply(
    model: nn.Module,
    camera=None,
    adapter: Adapter | str | None = None,
    *,
    components: Mapping[str, bool] | list[str] | None = None,
    strict: bool = True,
    mask: torch.Tensor | None = None,
    knee_deg: float = DEFAULT_KNEE_DEG,
    max_stretch: float = DEFAULT_MAX_STRETCH,
) -> RaytunHandle:
    """Make ``model`` fisheye-aware for ``camera``; returns a :class:`RaytunHandle`.

    Args:
        model: a supported backbone instance (see ``raytun3r_plugin.registry.specs()``).
        camera: the camera of the native images (a ``raytun3r_plugin.cameras.Camera``); rescaled to
            the network input size on every forward. Defaults to the adapter's camera.
        adapter: an :class:`Adapter`, a path to an adapter file, or None for the parameter-free
            corrections only.
        components: which corrections are on (``adapter.COMPONENTS``); defaults to the
            adapter's recorded set, or all.
        strict: refuse an adapter fitted on other weights (PE fingerprint) or another camera.
        mask: optional (H, W) bool mask of valid pixels, combined with the camera's valid region.
        knee_deg, max_stretch: parameters of the fisheye-to-pinhole map and patch resampling.

    Everything is validated before the model is touched; a failure while installing rolls back.
    Applying the same camera and adapter again returns the existing handle.
    """
    from raytun3r_plugin.cameras import Camera

    if isinstance(adapter, str) or hasattr(adapter, "__fspath__"):
        adapter = Adapter.load(adapter)
    if adapter is not None and not isinstance(adapter, Adapter):
        raise AdapterError(f"adapter must be an Adapter, a path or None, got {type(adapter).__name__}")
    if camera is None and adapter is not None:
        camera = adapter.camera
    if camera is None:
        raise CameraError("apply needs a camera (or an adapter that carries one)")
    if not isinstance(camera, Camera):
        raise CameraError(f"camera must be a raytun3r_plugin.cameras.Camera, got {type(camera).__name__}")
    if mask is not None:
        mask = _checked_mask(mask, camera)

    spec, root = spec_for(model)
    info = spec.describe(root)
    if adapter is not None:
        _check_adapter(adapter, info, camera, strict)
    wanted = _components_for(components, adapter)

    with _ACTIVE_LOCK:
        existing = _ACTIVE.get(model)
        if existing is not None:
            same = _same_camera(existing.camera, camera) and (
                (existing.adapter is None and adapter is None)
                or (existing.adapter is not None and adapter is not None and existing.adapter.same_as(adapter))
            ) and existing.components == wanted
            if same:
                return existing
            raise AlreadyAppliedError(f"{type(model).__name__} is already patched ({existing!r}); call remove() first")

        if spec.check is not None:
            spec.check(root)
        hooks = {hook for hook, served in _HOOK_COMPONENTS.items() if any(wanted.get(c) for c in served)}
        resolved = resolve_targets(spec, root, hooks)
        state = PatchState(camera, adapter, wanted, info, mask, knee_deg, max_stretch)
        for _target, path, owner in resolved:
            current = owner.__dict__.get(_target.attribute)
            if getattr(current, _WRAPPER_MARK, False):
                raise AlreadyAppliedError(f"{path}.{_target.attribute} is already wrapped by raytun3r")
        # Build every replacement before installing any, so a build error changes nothing.
        planned = []
        for target, _path, owner in resolved:
            original = getattr(owner, target.attribute)
            replacement = target.build(original, owner, state)
            replacement = functools.wraps(original)(replacement)
            setattr(replacement, _WRAPPER_MARK, True)
            planned.append((owner, target.attribute, replacement))

        installed: list[_Installed] = []
        try:
            for owner, attribute, replacement in planned:
                _install(installed, owner, attribute, replacement)
        except BaseException:
            _undo(installed)
            raise
        handle = RaytunHandle(model, root, spec, state, installed)
        _ACTIVE[model] = handle
        return handle


def _install(installed: list[_Installed], owner, attribute: str, replacement) -> None:
    had_own = attribute in owner.__dict__
    record = _Installed(owner, attribute, had_own, owner.__dict__.get(attribute))
    # object.__setattr__: nn.Module.__setattr__ would be fine for plain functions, but this keeps
    # the write an ordinary instance attribute for every owner type.
    object.__setattr__(owner, attribute, replacement)
    installed.append(record)


def remove(model: nn.Module) -> None:
    """Remove the raytun3r patch from ``model`` (no handle needed)."""
    handle = _ACTIVE.get(model)
    if handle is None:
        raise NotAppliedError(f"{type(model).__name__} carries no raytun3r patch")
    handle.remove()


def handle_of(model: nn.Module) -> RaytunHandle | None:
    """The live handle of ``model``, or None."""
    return _ACTIVE.get(model)
