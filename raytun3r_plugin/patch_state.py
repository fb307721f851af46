"""What a patched model's wrappers read at run time: the per-view cameras and adapters
(:class:`View`) and, per patch root, the :class:`PatchState` that caches every camera- and
size-dependent quantity. ``apply`` (:mod:`raytun3r_plugin.patching`) builds them; the hooks
(:mod:`raytun3r_plugin.hooks`) read them."""

from __future__ import annotations

import contextvars
import copy
import math
import weakref
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.errors import InputError, PatchedCopyError
from raytun3r_plugin.registry import BackboneInfo, BackboneSpec
from raytun3r_plugin.size_geometry import GeometryCache, SizeGeometry

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

__all__ = ["PatchState", "View"]

# Handles disabled in the current thread / context (see RaytunHandle.disabled). torch.compile
# cannot trace or guard a ContextVar, so compiled code reads PatchState.disabled_blocks instead.
_DISABLED: contextvars.ContextVar[frozenset[int]] = contextvars.ContextVar(
    "raytun3r_disabled", default=frozenset()
)

_PART_COPY_HINT = (
    "copy the whole model that was given to apply(), or call handle.remove() before copying "
    "(a copy of only a part of a patched model would carry wrappers that no handle can remove)"
)


def _same_camera(a, b) -> bool:
    if a is None or b is None:
        return a is b
    if (a.width, a.height) != (b.width, b.height):
        a = a.resized(b.width, b.height)
    if a.model != b.model:
        return False
    # The lens's field-of-view cap changes which rays are valid, so it is part of the camera.
    if (a.max_fov_deg is None) != (b.max_fov_deg is None) or (
        a.max_fov_deg is not None and not math.isclose(a.max_fov_deg, b.max_fov_deg, rel_tol=1e-6)
    ):
        return False
    return bool(
        torch.allclose(a.params.detach().double(), b.params.detach().double(), rtol=1e-6, atol=1e-6)
    )


class View:
    """One camera of a multi-camera (rig) forward: what the hooks read for the views it owns.

    ``apply(model, [camera_a, camera_b], [adapter_a, adapter_b])`` makes one per position of
    the list; view ``s`` of every forward (the ``S`` axis of the (B, S, 3, H, W) input) is
    position ``s % V`` (docs/rigs.md). Positions with the same camera share one geometry cache.
    """

    __slots__ = ("adapter", "camera", "geometry_cache", "mask")

    def __init__(self, camera: Camera, adapter: Adapter | None, mask, geometry_cache):
        self.camera = camera
        self.adapter = adapter
        self.mask = mask
        self.geometry_cache = geometry_cache

    def __repr__(self) -> str:
        return f"View({self.camera!r}, adapter={'yes' if self.adapter is not None else 'none'})"


class PatchState:
    """What the installed wrappers read at run time (one per patch root of a patched model).

    A model of several networks (``BackboneSpec.branches``) has one state per branch, all with
    the same camera and components; only the main branch's state carries the adapter.

    A rig (``views`` of different cameras or adapters) keeps one :class:`View` per position;
    ``camera``, ``adapter``, ``mask`` and :meth:`geometry` are then the first view's, and the
    hooks ask :meth:`view_rows` and the ``*_views`` methods for the per-view values.
    """

    def __init__(
        self,
        camera: Camera,
        adapter: Adapter | None,
        components: dict[str, bool],
        info: BackboneInfo,
        mask: torch.Tensor | None,
        knee_deg: float,
        max_stretch: float,
        model: nn.Module | None = None,
        spec: BackboneSpec | None = None,
        views: tuple[tuple[Camera, Adapter | None, torch.Tensor | None], ...] = (),
    ):
        self.camera = camera
        self.adapter = adapter
        self.components = components
        self.info = info
        self.mask = mask
        self.knee_deg = knee_deg
        self.max_stretch = max_stretch
        # The backbone's declared facts (e.g. its RoPE frequency attribute) for the hook builders.
        self.spec = spec
        self.geometry_cache = GeometryCache(camera, info.patch_size, mask, knee_deg, max_stretch)
        self.views = self._views(views or ((camera, adapter, mask),))
        # Fixed for the patch's life, and read by every hook on every call: decided once here.
        self.rig = self._differ(self.views)
        # Weak: the state is reachable from the model's own wrappers.
        self._model = weakref.ref(model) if model is not None else None
        # Open ``handle.disabled()`` blocks in any thread: what compiled code reads (:attr:`active`).
        self.disabled_blocks = 0

    def _views(self, given) -> tuple[View, ...]:
        caches: list[tuple[Camera, Any, GeometryCache]] = [
            (self.camera, self.mask, self.geometry_cache)
        ]
        views = []
        for camera, adapter, mask in given:
            cache = next(
                (c for cam, m, c in caches if _same_camera(cam, camera) and _same_mask(m, mask)),
                None,
            )
            if cache is None:
                cache = GeometryCache(
                    camera, self.info.patch_size, mask, self.knee_deg, self.max_stretch
                )
                caches.append((camera, mask, cache))
            views.append(View(camera, adapter, mask, cache))
        return tuple(views)

    @staticmethod
    def _differ(views: tuple[View, ...]) -> bool:
        """True when the views differ (camera, mask or adapter): the hooks then work per view."""
        first = views[0]
        return any(
            view.geometry_cache is not first.geometry_cache or view.adapter is not first.adapter
            for view in views[1:]
        )

    def __deepcopy__(self, memo: dict) -> PatchState:
        """The state of a deep copy of the patched model: its own adapter, fresh caches and locks.

        Refused (:class:`PatchedCopyError`) when the model given to ``apply`` is not itself being
        copied, i.e. for a copy of only a part of it.
        """
        model = self._model() if self._model is not None else None
        if model is None or id(model) not in memo:
            raise PatchedCopyError(f"cannot deepcopy a part of a patched model: {_PART_COPY_HINT}")
        twin = PatchState.__new__(PatchState)
        memo[id(self)] = twin
        twin.camera = self.camera  # cameras are immutable
        twin.adapter = copy.deepcopy(self.adapter, memo)
        twin.components = dict(self.components)
        twin.info = copy.deepcopy(self.info, memo)  # pos_embed becomes the copy's own parameter
        twin.mask = copy.deepcopy(self.mask, memo)
        twin.knee_deg, twin.max_stretch = self.knee_deg, self.max_stretch
        twin.spec = self.spec  # immutable registry data
        # Fresh: the cache's locks cannot be copied, and its tensors may sit on the source's device.
        twin.geometry_cache = GeometryCache(
            twin.camera, twin.info.patch_size, twin.mask, twin.knee_deg, twin.max_stretch
        )
        # The memo keeps an adapter shared by several views shared in the copy.
        twin.views = twin._views(
            tuple(
                (view.camera, copy.deepcopy(view.adapter, memo), copy.deepcopy(view.mask, memo))
                for view in self.views
            )
        )
        twin.rig = twin._differ(twin.views)
        twin._model = weakref.ref(memo[id(model)])
        twin.disabled_blocks = 0
        return twin

    @property
    def active(self) -> bool:
        """False inside ``handle.disabled()``: of this thread / context in eager code; under
        ``torch.compile``, of any thread (docs/deployment.md).

        Compiled code cannot read a ``ContextVar`` (a graph break at every hook), so there the
        switch is the plain counter :attr:`disabled_blocks`, which torch.compile guards on: the
        first call inside a ``disabled()`` block compiles the upstream variant once, and both
        variants stay cached.
        """
        if torch.compiler.is_compiling():
            return self.disabled_blocks == 0
        return id(self) not in _DISABLED.get()

    @property
    def resample_map(self) -> str:
        """The local map of patch resampling (``geometry.patch_resample_grid``'s ``local_map``)."""
        return "turned" if self.components.get("resample_turned", False) else "central"

    def uses(self, component: str) -> bool:
        """True when ``component`` is on and the handle is not disabled in this context."""
        if not self.components.get(component, False) or not self.active:
            return False
        if component == "pe":
            return any(view.adapter is not None for view in self.views)
        if component == "rope":
            return any(
                view.adapter is not None and view.adapter.rope is not None for view in self.views
            )
        return True

    def geometry(self, height: int, width: int) -> SizeGeometry:
        return self.geometry_cache.at(int(height), int(width))

    def pe_correction(self, geometry: SizeGeometry, device, dtype) -> torch.Tensor:
        """(hw, C) PE update t_r(rho) + rho d_theta(theta) for the current grid (:meth:`Adapter.pe_correction`).

        The handle's components decide the angular term (``"pe_radial_only"`` drops it), not the
        adapter's recorded ones: ``apply(..., components=...)`` overrides what the file says.
        """
        angular = not self.components.get("pe_radial_only", False)
        assert self.adapter is not None  # the hooks ask only a state that carries an adapter
        return self.adapter.pe_correction(geometry, device, dtype, angular=angular)

    def rope_displacement(self, geometry: SizeGeometry, device, dtype) -> torch.Tensor:
        """(hw, 2) RoPE position displacement in (y, x) token units along the outward direction."""
        return _rope_displacement(self.adapter, geometry, device, dtype)

    # ---- per-view values of a rig (docs/rigs.md) ----------------------------------------

    def view_rows(self, rows: int, where: str, device=None) -> torch.Tensor:
        """(rows,) view index of each image of a call whose images are (B S) in upstream order.

        Raises :class:`InputError` when ``rows`` is not a multiple of the rig's view count: the
        call then cannot be laid out as whole rigs (a head that splits the views into chunks
        whose size the view count does not divide, or a forward of the wrong view count).
        """
        count = len(self.views)
        if rows % count:
            raise InputError(
                f"{where}: a call over {rows} images is not a whole number of rigs of {count} views "
                f"(a rig forward takes S = {count} x T views per sample, in the order of apply's "
                f"camera list; a head that runs the views in chunks of 8 needs a view count that "
                f"divides 8 once S > 8)"
            )
        return torch.arange(rows, device=device) % count

    def check_views(self, frames: int, where: str) -> None:
        """Refuse a forward whose per-sample view count ``frames`` is not a multiple of the rig's."""
        count = len(self.views)
        if frames % count:
            raise InputError(
                f"{where}: {frames} views per sample, but the model is patched for a rig of "
                f"{count} cameras: pass S = {count} x T views, view s taken by camera s % {count}"
            )

    def geometry_views(self, height: int, width: int) -> list[SizeGeometry]:
        """The :class:`SizeGeometry` of each view at the input size (shared between equal cameras)."""
        return [view.geometry_cache.at(int(height), int(width)) for view in self.views]

    def pe_correction_views(self, height: int, width: int, device, dtype) -> torch.Tensor:
        """(V, hw, C) PE update of each view (zero for a view without an adapter)."""
        angular = not self.components.get("pe_radial_only", False)
        corrections = []
        for view, geometry in zip(self.views, self.geometry_views(height, width), strict=True):
            if view.adapter is None:
                hw = (geometry.height // geometry.patch) * (geometry.width // geometry.patch)
                corrections.append(torch.zeros(hw, self.info.embed_dim, device=device, dtype=dtype))
            else:
                corrections.append(
                    view.adapter.pe_correction(geometry, device, dtype, angular=angular)
                )
        return torch.stack(corrections)

    def rope_displacement_views(self, height: int, width: int, device, dtype) -> torch.Tensor:
        """(V, hw, 2) RoPE displacement of each view (zero without an adapter's RoPE table)."""
        return torch.stack(
            [
                _rope_displacement(view.adapter, geometry, device, dtype)
                for view, geometry in zip(
                    self.views, self.geometry_views(height, width), strict=True
                )
            ]
        )


def _rope_displacement(
    adapter: Adapter | None, geometry: SizeGeometry, device, dtype
) -> torch.Tensor:
    """(hw, 2) displacement by ``adapter``'s RoPE table; zero without an adapter or table."""
    if adapter is None or adapter.rope is None:
        hw = (geometry.height // geometry.patch) * (geometry.width // geometry.patch)
        return torch.zeros(hw, 2, device=device, dtype=dtype)
    weights, direction = geometry.rope_basis(adapter.n_r_rope, device, dtype)
    return (weights @ adapter.rope["radial"].to(device, dtype))[:, None] * direction


def _same_mask(a: torch.Tensor | None, b: torch.Tensor | None) -> bool:
    if a is None or b is None:
        return a is b
    return a.shape == b.shape and bool(torch.equal(a, b))
