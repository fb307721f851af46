"""The one thing every export writes from: frames, depth, confidence and poses of one camera.

An :class:`ExportScene` holds a prediction at the resolution it is written at (the frames' own,
or the network's), always as **range** (distance along the unit ray of each pixel, the way
raytun3r reads a fisheye prediction; docs/conventions.md section 2). Each writer asks for depth
in the convention the user chose (:meth:`ExportScene.depth_as`) and for 3-D points
(:meth:`ExportScene.sample_points`), which do not depend on that choice.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.poses import MIN_RAY_Z, invert_rigid

__all__ = [
    "DEPTH_CONVENTIONS",
    "ExportScene",
    "PointSample",
    "check_depth_convention",
    "depth_convention_text",
]

#: What ``--depth-convention`` accepts: ``range`` = distance along the pixel's unit ray,
#: ``z`` = distance along the optical axis (the z coordinate of the 3-D point).
DEPTH_CONVENTIONS = ("range", "z")


def check_depth_convention(convention: str) -> str:
    """``convention`` if it is one of :data:`DEPTH_CONVENTIONS`, else :class:`InputError`."""
    if convention not in DEPTH_CONVENTIONS:
        raise InputError(
            f"depth convention must be one of {list(DEPTH_CONVENTIONS)}, got {convention!r}"
        )
    return convention


def depth_convention_text(convention: str) -> str:
    """One sentence saying what a depth value means, written into every export's metadata."""
    if check_depth_convention(convention) == "range":
        return (
            "range: distance from the camera centre along the pixel's unit ray, X = D * ray(u, v)"
        )
    return (
        "z: distance along the optical axis (z of the 3-D point in OpenCV camera axes), "
        "X = D * ray(u, v) / ray_z; 0 where the ray is at or beyond 90 degrees from the axis"
    )


def _rigid(poses: np.ndarray) -> np.ndarray:
    """(S, 4, 4) poses with each rotation projected onto SO(3) (nearest in Frobenius norm).

    A float32 prediction is orthonormal to about 1e-7; every format stores a rotation (a
    quaternion in COLMAP), and only an exact rotation reads back equal to what was written.
    """
    out = poses.copy()
    u, _, vt = np.linalg.svd(poses[:, :3, :3])
    sign = np.sign(np.linalg.det(u @ vt))
    u[:, :, -1] *= sign[:, None]
    out[:, :3, :3] = u @ vt
    out[:, 3] = (0.0, 0.0, 0.0, 1.0)
    return out


@dataclass
class PointSample:
    """3-D points picked from the depth maps, with where each came from.

    Attributes:
        xyz: (N, 3) float64 world points (the backbone's world frame, OpenCV axes).
        rgb: (N, 3) float32 colours in [0, 1].
        frame: (N,) int frame index each point was back-projected from.
        uv: (N, 2) float64 pixel (raytun3r convention: first pixel centre at (0, 0)).
        confidence: (N,) float32, or None when the backbone gives none.
    """

    xyz: np.ndarray
    rgb: np.ndarray
    frame: np.ndarray
    uv: np.ndarray
    confidence: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass
class ExportScene:
    """A prediction ready to be written: one camera, S frames.

    Attributes:
        camera: the camera of the written images (``width x height`` px).
        images: (S, H, W, 3) float32 RGB in [0, 1].
        depth: (S, H, W) float32 **range** in ``depth_unit``; 0 = unknown (outside the camera's
            valid region or the mask, or no prediction there).
        cam_from_world: (S, 4, 4) float64 world-to-camera poses, OpenCV axes.
        names: S frame names (file stems).
        confidence: (S, H, W) float32 or None.
        mask: optional (H, W) bool scene mask (True = scene pixel) the user gave.
        timestamps: (S,) float64 seconds (frame indices when unknown).
        depth_unit: the unit written beside depth values ("m" for metric models).
        resolution: ``"frames"`` (the frames' own size) or ``"network"`` (the network input's).
    """

    camera: Camera
    images: np.ndarray
    depth: np.ndarray
    cam_from_world: np.ndarray
    names: list[str]
    confidence: np.ndarray | None = None
    mask: np.ndarray | None = None
    timestamps: np.ndarray | None = None
    depth_unit: str = "units"
    resolution: str = "frames"
    _rays: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        frames, height, width = np.shape(self.depth)
        if (width, height) != (self.camera.width, self.camera.height):
            raise InputError(
                f"depth maps are {width}x{height} px but the camera is {self.camera.width}x{self.camera.height} px"
            )
        if np.shape(self.images) != (frames, height, width, 3):
            raise InputError(
                f"images must be ({frames}, {height}, {width}, 3), got {np.shape(self.images)}"
            )
        if np.shape(self.cam_from_world) != (frames, 4, 4) or len(self.names) != frames:
            raise InputError(f"need {frames} poses (4x4) and {frames} names")
        if self.confidence is not None and np.shape(self.confidence) != (frames, height, width):
            raise InputError(f"confidence must be ({frames}, {height}, {width})")
        if self.mask is not None and np.shape(self.mask) != (height, width):
            raise InputError(f"mask must be ({height}, {width}), got {np.shape(self.mask)}")
        if self.timestamps is None:
            self.timestamps = np.arange(frames, dtype=np.float64)
        self.cam_from_world = _rigid(np.asarray(self.cam_from_world, dtype=np.float64))

    # ------------------------------------------------------------------ geometry
    def __len__(self) -> int:
        return len(self.names)

    @property
    def rays(self) -> np.ndarray:
        """(H, W, 3) float64 unit rays of the pixel centres (zero where the camera has none)."""
        if self._rays is None:
            rays, valid = self.camera.ray_table(device="cpu", dtype=torch.float64)
            self._rays = np.where(valid.numpy()[..., None], rays.numpy(), 0.0)
        return self._rays

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool: the camera's valid region, within the mask when one is given."""
        valid = self.camera.valid_mask("cpu").numpy().copy()
        if self.mask is not None:
            valid &= np.asarray(self.mask, dtype=bool)
        return valid

    def known(self, frame: int) -> np.ndarray:
        """(H, W) bool: pixels of ``frame`` with a depth (valid region, finite, > 0)."""
        depth = self.depth[frame]
        return self.valid & np.isfinite(depth) & (depth > 0)

    def depth_as(self, convention: str) -> np.ndarray:
        """(S, H, W) float32 depth in ``convention`` (:data:`DEPTH_CONVENTIONS`), 0 = unknown.

        z-depth is ``range * ray_z``; rays at or beyond 90 degrees from the axis (``ray_z <=``
        :data:`~raytun3r_plugin.poses.MIN_RAY_Z`) have no positive z-depth and are written 0.
        """
        check_depth_convention(convention)
        known = np.stack([self.known(k) for k in range(len(self))])
        depth = np.where(known, self.depth, 0.0)
        if convention == "z":
            ray_z = self.rays[..., 2]
            depth = np.where(ray_z > MIN_RAY_Z, depth * ray_z, 0.0)
        return depth.astype(np.float32)

    def world_from_cam(self, frame: int) -> np.ndarray:
        """(4, 4) float64 camera-to-world pose of ``frame``."""
        return invert_rigid(np.asarray(self.cam_from_world[frame], dtype=np.float64))

    def sample_points(
        self,
        max_points: int = 100_000,
        confidence_quantile: float = 0.2,
        max_angle_deg: float | None = None,
        seed: int = 0,
    ) -> PointSample:
        """World points back-projected from the depth maps, filtered and subsampled.

        Args:
            max_points: at most this many points over all frames (uniform random pick, fixed
                ``seed``).
            confidence_quantile: per frame, drop the pixels whose confidence is below this
                quantile of that frame's known pixels (0 keeps all; ignored without confidence).
            max_angle_deg: keep only pixels whose ray is at most this far from the optical axis
                (e.g. below 90 degrees for COLMAP, which cannot project beyond); None = all.
            seed: random seed of the subsampling.
        """
        if not 0.0 <= confidence_quantile < 1.0:
            raise InputError(f"confidence quantile must be in [0, 1), got {confidence_quantile}")
        if max_points < 1:
            raise InputError(f"max_points must be at least 1, got {max_points}")
        rays = self.rays
        angle_ok = (
            np.ones(rays.shape[:2], bool)
            if max_angle_deg is None
            else rays[..., 2] > np.cos(np.radians(max_angle_deg))
        )
        picks = []
        for k in range(len(self)):
            keep = self.known(k) & angle_ok
            if self.confidence is not None and confidence_quantile > 0 and keep.any():
                conf = self.confidence[k]
                keep &= conf >= np.quantile(conf[keep], confidence_quantile)
            rows, cols = np.nonzero(keep)
            picks.append(np.stack([np.full_like(rows, k), rows, cols], -1))
        chosen = np.concatenate(picks) if picks else np.zeros((0, 3), int)
        if len(chosen) > max_points:
            pick = np.random.default_rng(seed).choice(len(chosen), max_points, replace=False)
            chosen = chosen[np.sort(pick)]
        frame, row, col = chosen.T
        points_cam = self.depth[frame, row, col][:, None].astype(np.float64) * rays[row, col]
        xyz = np.empty_like(points_cam)
        for k in np.unique(frame):
            here = frame == k
            pose = self.world_from_cam(int(k))
            xyz[here] = points_cam[here] @ pose[:3, :3].T + pose[:3, 3]
        return PointSample(
            xyz=xyz,
            rgb=self.images[frame, row, col].astype(np.float32),
            frame=frame.astype(np.int64),
            uv=np.stack([col, row], -1).astype(np.float64),
            confidence=None
            if self.confidence is None
            else self.confidence[frame, row, col].astype(np.float32),
        )

    def record(self, convention: str) -> dict:
        """JSON-able description of the written depth (``summary.json``'s ``depth`` entry)."""
        import json

        return {
            "convention": check_depth_convention(convention),
            "meaning": depth_convention_text(convention),
            "resolution": self.resolution,
            "width": self.camera.width,
            "height": self.camera.height,
            "unit": self.depth_unit,
            "unknown_value": 0.0,
            "camera": json.loads(self.camera.to_json()),
        }
