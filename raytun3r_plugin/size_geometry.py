"""The per-(camera, input size) geometry that every patched hook reads, computed once and cached.

:mod:`raytun3r_plugin.geometry` holds the maps themselves, each a pure function of the camera;
this module holds their cache: :class:`GeometryCache` gives one :class:`SizeGeometry` per input
size, whose tensors are built lazily in float64 on CPU and copied once per device and dtype, so a
patched forward pass only reads them.
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING

import torch

from raytun3r_plugin.errors import InputError
from raytun3r_plugin.geometry import (
    DEFAULT_KNEE_DEG,
    DEFAULT_MAX_STRETCH,
    TokenPolar,
    angular_weights,
    camera_for_input,
    head_uv_grid,
    map_is_identity,
    naive_pe_positions,
    patch_resample_grid,
    radial_weights,
    resize_mask,
    token_polar,
    token_validity,
)

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera


class SizeGeometry:
    """Everything the hooks need for one (camera, input size, patch size); float64, CPU.

    Derived tensors are computed lazily and then cached on this object; device/dtype copies are
    cached too, so a forward pass only pays a table add and one ``grid_sample``.
    """

    def __init__(
        self,
        camera: Camera,
        height: int,
        width: int,
        patch: int,
        mask: torch.Tensor | None,
        knee_deg: float,
        max_stretch: float,
    ):
        if height % patch or width % patch:
            raise InputError(
                f"input of {width}x{height} px is not a multiple of the patch size {patch}"
            )
        self.camera = camera_for_input(camera, height, width)
        self.height, self.width, self.patch = height, width, patch
        self.knee_deg, self.max_stretch = knee_deg, max_stretch
        self._mask = mask
        self._lock = threading.RLock()
        self._cache: dict = {}

    def memo(self, key, build):
        """Cache ``build()`` under ``key`` for this camera and input size (thread-safe)."""
        return self._get(key, build)

    def _get(self, key, build):
        value = self._cache.get(key, self)
        if value is self:
            with self._lock:
                value = self._cache.get(key, self)
                if value is self:
                    value = build()
                    self._cache[key] = value
        return value

    @property
    def identity(self) -> bool:
        return self._get("identity", lambda: map_is_identity(self.camera, self.knee_deg))

    @property
    def polar(self) -> TokenPolar:
        return self._get(
            "polar", lambda: token_polar(self.camera, self.height, self.width, self.patch)
        )

    def pe_weights(
        self, n_r: int, n_theta: int, device, dtype
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(hw, n_r) radial and (hw, n_theta) rho-scaled angular interpolation matrices."""

        def build():
            polar = self.polar
            radial = radial_weights(polar.rho, n_r)
            angular = angular_weights(polar.theta, n_theta) * polar.rho[:, None]
            return radial.to(device=device, dtype=dtype), angular.to(device=device, dtype=dtype)

        return self._get(("pe", n_r, n_theta, device, dtype), build)

    def naive_pe_grid(self, device, dtype) -> torch.Tensor | None:
        """``grid_sample`` grid (1, h, w, 2), ``align_corners=True``, of :func:`naive_pe_positions`
        over the (h, w) PE table of this input, or None when it is the identity."""

        def build():
            positions = naive_pe_positions(self.camera, self.height, self.width, self.patch)
            if positions is None:
                return None
            rows, cols = self.height // self.patch, self.width // self.patch
            # align_corners=True: -1 and 1 are the centres of the first and last table entries.
            x = 2 * positions[:, 0] / (cols - 1) - 1 if cols > 1 else positions[:, 0] * 0
            y = 2 * positions[:, 1] / (rows - 1) - 1 if rows > 1 else positions[:, 1] * 0
            grid = torch.stack((x, y), dim=-1).reshape(1, rows, cols, 2)
            return grid.to(device=device, dtype=dtype)

        return self._get(("naive_pe", device, dtype), build)

    def rope_basis(self, n_bins: int, device, dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """Radial weights (hw, n_bins) and outward directions (hw, 2) in (y, x) order."""

        def build():
            polar = self.polar
            return (
                radial_weights(polar.rho, n_bins).to(device=device, dtype=dtype),
                polar.direction_yx.to(device=device, dtype=dtype),
            )

        return self._get(("rope", n_bins, device, dtype), build)

    def resample_grid(self, device, dtype, local_map: str = "central") -> torch.Tensor | None:
        """:func:`patch_resample_grid` of this input with ``local_map``, or None (identity)."""

        def build():
            if self.identity:
                return None
            grid = patch_resample_grid(
                self.camera,
                self.height,
                self.width,
                self.patch,
                self.knee_deg,
                self.max_stretch,
                local_map,
            )
            return None if grid is None else grid.to(device=device, dtype=dtype)

        return self._get(("resample", local_map, device, dtype), build)

    def valid_pixels(self) -> torch.Tensor:
        def build():
            valid = self.camera.valid_mask().to("cpu").bool()
            if self._mask is not None:
                valid = valid & resize_mask(self._mask.to("cpu"), valid.shape)
            return valid

        return self._get("valid_pixels", build)

    def token_valid(self, device) -> torch.Tensor | None:
        """(hw,) bool validity, or None when every token is valid (nothing to replace)."""

        def build():
            valid = token_validity(self.valid_pixels(), self.patch)
            if bool(valid.all()):
                return None
            if not bool(valid.any()):
                raise InputError("no patch of the image is inside the camera's valid region")
            return valid.to(device)

        return self._get(("token_valid", device), build)

    def uv_grid(self, cells_h: int, cells_w: int, device, dtype) -> torch.Tensor | None:
        """Camera-aware head grid (cells_h, cells_w, 2), or None when upstream's is already right."""

        def build():
            if self.identity:
                return None
            grid = head_uv_grid(
                self.camera, self.height, self.width, cells_h, cells_w, self.knee_deg
            )
            return grid.to(device=device, dtype=dtype)

        return self._get(("uv", cells_h, cells_w, device, dtype), build)


class GeometryCache:
    """Per-handle cache of :class:`SizeGeometry` keyed by (input height, width)."""

    def __init__(
        self,
        camera: Camera,
        patch: int,
        mask: torch.Tensor | None = None,
        knee_deg: float = DEFAULT_KNEE_DEG,
        max_stretch: float = DEFAULT_MAX_STRETCH,
    ):
        self.camera = camera
        self.patch = patch
        self.mask = mask
        self.knee_deg = knee_deg
        self.max_stretch = max_stretch
        self._sizes: dict[tuple[int, int], SizeGeometry] = {}
        self._lock = threading.RLock()

    def at(self, height: int, width: int) -> SizeGeometry:
        geometry = self._sizes.get((height, width))
        if geometry is None:
            with self._lock:
                geometry = self._sizes.get((height, width))
                if geometry is None:
                    geometry = SizeGeometry(
                        self.camera,
                        height,
                        width,
                        self.patch,
                        self.mask,
                        self.knee_deg,
                        self.max_stretch,
                    )
                    self._sizes[(height, width)] = geometry
        return geometry
