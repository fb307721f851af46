"""The one image-sequence type every reader, the synthetic renderer and the evaluation share."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from raytun3r_plugin.errors import DatasetError

if TYPE_CHECKING:  # pragma: no cover - typing only
    from raytun3r_plugin.cameras import Camera

__all__ = ["Sequence", "read_image"]


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as (H, W, 3) float32 RGB in [0, 1].

    8-bit and 16-bit files are scaled by their full range; grey images are replicated to three
    channels and an alpha channel is dropped. Raises :class:`DatasetError` if the file is missing
    or cannot be decoded.
    """
    import cv2

    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"{p}: image file not found")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{p}: cannot decode image")
    if img.dtype == np.uint8:
        scale = 255.0
    elif img.dtype == np.uint16:
        scale = 65535.0
    elif img.dtype in (np.float32, np.float64):
        scale = 1.0
    else:
        raise DatasetError(f"{p}: unsupported image dtype {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    elif img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    else:
        raise DatasetError(f"{p}: unsupported channel count {img.shape[2]}")
    return (img.astype(np.float32) / np.float32(scale)).clip(0.0, 1.0)


@dataclass
class Sequence:
    """An ordered image sequence from one camera, with optional ground truth.

    Attributes:
        name: human-readable name (dataset/scene/camera).
        camera: the camera (a ``raytun3r_plugin.cameras`` model) describing every image.
        timestamps: (N,) float64 seconds.
        cam_from_world: (N, 4, 4) float64 world-to-camera ground-truth poses, or None.
        image_paths: N image files read lazily by :meth:`image` (real datasets), or None.
        images: (N, H, W, 3) float32 RGB in [0, 1] held in memory (synthetic), or None.
        depth: (N, H, W) float32 ground-truth depth in metres, range along the unit ray unless
            ``depth_kind == "z"``; 0 means unknown.
        depth_kind: "range" or "z".
        mask: (H, W) or (N, H, W) bool, True where a pixel is valid (lens region, hit).
        meta: free-form information (source files, generator parameters, ...); arrays indexed
            by frame go under ``meta["per_frame"]`` (a dict of (N, ...) arrays), which
            :meth:`subset` slices along with the frames.
    """

    name: str
    camera: Camera
    timestamps: np.ndarray
    cam_from_world: np.ndarray | None
    image_paths: list[Path] | None = None
    images: np.ndarray | None = None
    depth: np.ndarray | None = None
    depth_kind: str = "range"
    mask: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        n = self.timestamps.shape[0]
        if self.cam_from_world is not None:
            self.cam_from_world = np.asarray(self.cam_from_world, dtype=np.float64)
            if self.cam_from_world.shape != (n, 4, 4):
                raise DatasetError(
                    f"sequence {self.name!r}: cam_from_world has shape {self.cam_from_world.shape}, "
                    f"expected ({n}, 4, 4)"
                )
        if self.image_paths is not None:
            self.image_paths = [Path(p) for p in self.image_paths]
            if len(self.image_paths) != n:
                raise DatasetError(
                    f"sequence {self.name!r}: {len(self.image_paths)} image paths for {n} frames"
                )
        for attr in ("images", "depth"):
            arr = getattr(self, attr)
            if arr is not None and arr.shape[0] != n:
                raise DatasetError(
                    f"sequence {self.name!r}: {attr} has {arr.shape[0]} frames, expected {n}"
                )
        if self.mask is not None:
            self.mask = np.asarray(self.mask, dtype=bool)
            if self.mask.ndim == 3 and self.mask.shape[0] != n:
                raise DatasetError(
                    f"sequence {self.name!r}: mask has {self.mask.shape[0]} frames, expected {n}"
                )
        if self.depth_kind not in ("range", "z"):
            raise DatasetError(
                f"sequence {self.name!r}: depth_kind must be 'range' or 'z', got {self.depth_kind!r}"
            )

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def height(self) -> int:
        """Image height in pixels (the camera's)."""
        return int(self.camera.height)

    @property
    def width(self) -> int:
        """Image width in pixels (the camera's)."""
        return int(self.camera.width)

    def first_images(self, count: int) -> np.ndarray:
        """Frames ``0 .. count - 1`` as (count, H, W, 3) float32 RGB in [0, 1] (a copy; read from
        disk for lazy sequences): an adaptation segment."""
        if not 0 < count <= len(self):
            raise IndexError(f"{count} frames asked of a sequence of {len(self)}")
        return np.stack([self.image(i) for i in range(count)])

    def image(self, i: int) -> np.ndarray:
        """Frame ``i`` as (H, W, 3) float32 RGB in [0, 1] (read from disk for lazy sequences)."""
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for a sequence of {n} frames")
        if self.images is not None:
            return self.images[i]
        if self.image_paths is None:
            raise DatasetError(f"sequence {self.name!r} has neither images nor image paths")
        img = read_image(self.image_paths[i])
        if img.shape[:2] != (self.height, self.width):
            raise DatasetError(
                f"{self.image_paths[i]}: image is {img.shape[1]}x{img.shape[0]} px but the camera "
                f"of sequence {self.name!r} is {self.width}x{self.height} px"
            )
        return img

    def frame_mask(self, i: int) -> np.ndarray | None:
        """Validity mask (H, W) bool of frame ``i``, or None."""
        if self.mask is None:
            return None
        return self.mask if self.mask.ndim == 2 else self.mask[i]

    def subset(self, indices: Any) -> Sequence:
        """A new sequence with the frames ``indices`` (a slice, an int array or a bool mask)."""
        idx = np.arange(len(self))[indices]
        idx = np.atleast_1d(idx).astype(np.int64)
        return Sequence(
            name=self.name,
            camera=self.camera,
            timestamps=self.timestamps[idx].copy(),
            cam_from_world=None if self.cam_from_world is None else self.cam_from_world[idx].copy(),
            image_paths=None if self.image_paths is None else [self.image_paths[k] for k in idx],
            images=None if self.images is None else self.images[idx],
            depth=None if self.depth is None else self.depth[idx],
            depth_kind=self.depth_kind,
            mask=None
            if self.mask is None
            else (self.mask if self.mask.ndim == 2 else self.mask[idx]),
            meta=self._subset_meta(idx),
        )

    def _subset_meta(self, idx: np.ndarray) -> dict[str, Any]:
        meta = dict(self.meta)
        per_frame = meta.get("per_frame")
        if isinstance(per_frame, dict):
            meta["per_frame"] = {k: np.asarray(v)[idx] for k, v in per_frame.items()}
        return meta

    def range_depth(self, i: int) -> np.ndarray | None:
        """Ground-truth depth of frame ``i`` as range along the unit ray (H, W) float32, or None.

        z-depth is converted with the camera's rays (range = z / ray_z); pixels whose ray has
        ray_z <= 0 or whose depth is 0 get 0 (unknown).
        """
        if self.depth is None:
            return None
        d = self.depth[i]
        if self.depth_kind == "range":
            return d
        rays, _ = self.camera.ray_table()
        rz = rays[..., 2].detach().cpu().numpy().astype(np.float32)
        out = np.where((rz > 1e-6) & (d > 0), d / np.maximum(rz, 1e-6), 0.0)
        return out.astype(np.float32)
