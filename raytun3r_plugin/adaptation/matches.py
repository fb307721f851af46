"""What every matcher shares: the :class:`Matches` type, the :class:`Matcher` protocol, and the
pixel tools the built-in matchers are made of (masks, bilinear sampling, grids, forward-backward
flow checks, patch correlation).

Conventions (docs/conventions.md section 2): images are ``(H, W, 3)`` float32 RGB in ``[0, 1]``;
pixel ``(u, v)`` has the centre of the top-left pixel at ``(0, 0)``, ``u`` to the right, ``v``
down (the OpenCV convention). The matchers themselves and their registry are in
:mod:`raytun3r_plugin.adaptation.matchers`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np
import torch

from raytun3r_plugin.errors import InputError

__all__ = [
    "Matcher",
    "Matches",
    "appearance_check",
    "as_bool_mask",
    "check_pair",
    "erode_mask",
    "grid_points",
    "points_inside",
    "matches_from_flows",
    "patch_samples",
    "bilinear_at",
    "to_gray_u8",
    "zncc",
]


# --------------------------------------------------------------------------------------------
# Data and protocol
# --------------------------------------------------------------------------------------------


@dataclass
class Matches:
    """Correspondences of an ordered frame pair ``(i -> j)``.

    Attributes:
        uv_i: ``(M, 2)`` float32 pixel coordinates ``(u, v)`` in frame ``i``.
        uv_j: ``(M, 2)`` float32 pixel coordinates of the same scene points in frame ``j``.
        confidence: ``(M,)`` float32 in ``[0, 1]``; 1 = most reliable. Its scale is
            matcher-specific (documented per matcher); use it as a relative weight.
        motion_px: the pair's mean image motion in pixels when the matcher knows it better than
            the kept matches do (DIS measures it on every flow-consistent match, before the
            appearance check removes the large motions it got wrong), else None; what decides
            whether a window is static.
    """

    uv_i: np.ndarray
    uv_j: np.ndarray
    confidence: np.ndarray
    motion_px: float | None = None

    def __post_init__(self) -> None:
        self.uv_i = np.ascontiguousarray(np.asarray(self.uv_i, dtype=np.float32).reshape(-1, 2))
        self.uv_j = np.ascontiguousarray(np.asarray(self.uv_j, dtype=np.float32).reshape(-1, 2))
        self.confidence = np.ascontiguousarray(
            np.asarray(self.confidence, dtype=np.float32).reshape(-1)
        )
        n = self.uv_i.shape[0]
        if self.uv_j.shape[0] != n or self.confidence.shape[0] != n:
            raise InputError(
                f"Matches: uv_i {self.uv_i.shape}, uv_j {self.uv_j.shape} and confidence "
                f"{self.confidence.shape} must have the same length M"
            )
        if n and (
            not np.isfinite(self.uv_i).all()
            or not np.isfinite(self.uv_j).all()
            or not np.isfinite(self.confidence).all()
        ):
            raise InputError("Matches: coordinates and confidences must be finite")
        if n and (self.confidence.min() < 0.0 or self.confidence.max() > 1.0):
            raise InputError("Matches: confidence must lie in [0, 1]")

    def __len__(self) -> int:
        return int(self.uv_i.shape[0])

    @classmethod
    def empty(cls) -> Matches:
        """No correspondences (``M = 0``)."""
        return cls(
            np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
        )

    def select(self, keep: np.ndarray) -> Matches:
        """The subset given by a boolean mask ``(M,)`` or an index array."""
        keep = np.asarray(keep)
        return Matches(self.uv_i[keep], self.uv_j[keep], self.confidence[keep])

    def reversed(self) -> Matches:
        """The same correspondences read as the pair ``(j -> i)``."""
        return Matches(self.uv_j.copy(), self.uv_i.copy(), self.confidence.copy())

    def displacement(self) -> np.ndarray:
        """``(M,)`` float32 pixel displacement ``|uv_j - uv_i|``."""
        return np.linalg.norm(self.uv_j - self.uv_i, axis=1).astype(np.float32)

    def mean_motion_px(self) -> float:
        """:attr:`motion_px` when set, else the mean displacement of the matches (0 if none)."""
        if self.motion_px is not None:
            return float(self.motion_px)
        return float(self.displacement().mean()) if len(self) else 0.0


@runtime_checkable
class Matcher(Protocol):
    """What the adaptation code needs from a correspondence source.

    ``name`` is a short identifier; ``settings()`` returns a JSON-serialisable dict of everything
    that changes the output (it enters the adaptation cache key, so include weight hashes and
    library versions); ``match`` returns :class:`Matches` for the ordered pair ``(i -> j)``.
    ``valid`` is the ``(H, W)`` bool mask of pixels that see the scene (the lens circle); a
    matcher must only return matches with both ends inside it.
    """

    name: str

    def settings(self) -> dict: ...

    def match(
        self, image_i: np.ndarray, image_j: np.ndarray, valid: np.ndarray | None = None
    ) -> Matches: ...


# --------------------------------------------------------------------------------------------
# Shared helpers
# --------------------------------------------------------------------------------------------


def check_pair(
    image_i: np.ndarray, image_j: np.ndarray, valid: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate an image pair and the valid mask; return (image_i, image_j, valid (H, W) bool)."""
    arrays = []
    for name, image in (("image_i", image_i), ("image_j", image_j)):
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3:
            raise InputError(f"{name} must be an (H, W, 3) RGB array, got shape {image.shape}")
        if not np.issubdtype(image.dtype, np.floating):
            raise InputError(f"{name} must be float in [0, 1], got dtype {image.dtype}")
        arrays.append(image)
    if arrays[0].shape != arrays[1].shape:
        raise InputError(f"image shapes differ: {arrays[0].shape} vs {arrays[1].shape}")
    h, w = arrays[0].shape[:2]
    if valid is None:
        mask = np.ones((h, w), dtype=bool)
    else:
        mask = as_bool_mask(valid)
        if mask.shape != (h, w):
            raise InputError(f"valid mask has shape {mask.shape}, images are {(h, w)}")
    return arrays[0], arrays[1], mask


def as_bool_mask(valid: Any) -> np.ndarray:
    if isinstance(valid, torch.Tensor):
        valid = valid.detach().cpu().numpy()
    return np.asarray(valid).astype(bool)


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) float RGB in [0, 1] -> (H, W) uint8 luminance."""
    rgb = np.clip(np.asarray(image, dtype=np.float32) * 255.0 + 0.5, 0.0, 255.0).astype(np.uint8)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def erode_mask(mask: np.ndarray, border_px: int) -> np.ndarray:
    """Shrink a bool mask by ``border_px`` pixels (keeps matches off the lens-circle edge)."""
    if border_px <= 0:
        return mask
    size = 2 * int(border_px) + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    # Pixels outside the image count as invalid, so the image border is eroded too.
    out = cv2.erode(mask.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return out.astype(bool)


def bilinear_at(field: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample an (H, W, C) float32 field at (M, 2) pixel positions (bilinear, edge-clamped)."""
    if uv.shape[0] == 0:
        return np.zeros((0, field.shape[2]), np.float32)
    map_x = np.ascontiguousarray(uv[:, 0].reshape(-1, 1).astype(np.float32))
    map_y = np.ascontiguousarray(uv[:, 1].reshape(-1, 1).astype(np.float32))
    out = cv2.remap(field, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(uv.shape[0], field.shape[2])


def points_inside(uv: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(M,) bool: the pixel nearest to each position lies in the image and inside ``mask``."""
    h, w = mask.shape
    ui = np.rint(uv[:, 0]).astype(np.int64)
    vi = np.rint(uv[:, 1]).astype(np.int64)
    ok = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    ok[ok] = mask[vi[ok], ui[ok]]
    return ok


def grid_points(mask: np.ndarray, stride: int) -> np.ndarray:
    """(M, 2) float32 pixel centres of a stride grid (offset stride // 2) inside ``mask``."""
    h, w = mask.shape
    off = stride // 2
    vs, us = np.mgrid[off:h:stride, off:w:stride]
    keep = mask[vs, us]
    return np.stack([us[keep], vs[keep]], axis=1).astype(np.float32)


def matches_from_flows(
    flow_fw: np.ndarray,
    flow_bw: np.ndarray,
    valid: np.ndarray,
    stride: int,
    fb_threshold_px: float,
) -> Matches:
    """Sparse matches from a dense forward/backward flow pair.

    Args:
        flow_fw: ``(H, W, 2)`` flow ``i -> j`` in pixels (``uv_j = uv_i + flow_fw[v_i, u_i]``).
        flow_bw: ``(H, W, 2)`` flow ``j -> i`` in pixels.
        valid: ``(H, W)`` bool; start points are grid pixels inside it and end points must
            land inside it too (already eroded by the caller if wanted).
        stride: grid spacing in pixels.
        fb_threshold_px: keep a match if ``|uv_i - (uv_j + flow_bw(uv_j))| < fb_threshold_px``.

    Returns:
        :class:`Matches` with ``confidence = exp(-2 (fb / fb_threshold_px)^2)`` (1 for a perfect
        round trip, 0.135 at the threshold).
    """
    flow_fw = np.ascontiguousarray(flow_fw, dtype=np.float32)
    flow_bw = np.ascontiguousarray(flow_bw, dtype=np.float32)
    uv_i = grid_points(valid, stride)
    if uv_i.shape[0] == 0:
        return Matches.empty()
    ui = uv_i[:, 0].astype(np.int64)
    vi = uv_i[:, 1].astype(np.int64)
    uv_j = uv_i + flow_fw[vi, ui]
    finite = np.isfinite(uv_j).all(axis=1)
    uv_i, uv_j = uv_i[finite], uv_j[finite]
    inside = points_inside(uv_j, valid)
    uv_i, uv_j = uv_i[inside], uv_j[inside]
    back = uv_j + bilinear_at(flow_bw, uv_j)
    fb = np.linalg.norm(back - uv_i, axis=1)
    keep = fb < fb_threshold_px
    conf = np.exp(-2.0 * (fb[keep] / fb_threshold_px) ** 2)
    return Matches(uv_i[keep], uv_j[keep], conf)


def patch_samples(gray: np.ndarray, uv: np.ndarray, radius: int) -> np.ndarray:
    """``(M, (2 r + 1)^2)`` float32 grey levels of square patches centred at ``uv`` (bilinear,
    edge-clamped; sampled in NumPy because ``cv2.remap`` limits maps to 32767 rows)."""
    steps = np.arange(-radius, radius + 1, dtype=np.float32)
    offsets = np.stack(np.meshgrid(steps, steps, indexing="xy"), axis=-1).reshape(-1, 2)
    points = (uv[:, None, :] + offsets[None]).reshape(-1, 2)
    h, w = gray.shape
    u = np.clip(points[:, 0], 0.0, w - 1.001)
    v = np.clip(points[:, 1], 0.0, h - 1.001)
    u0, v0 = u.astype(np.int64), v.astype(np.int64)
    fu, fv = u - u0, v - v0
    values = (
        gray[v0, u0] * (1 - fu) * (1 - fv)
        + gray[v0, u0 + 1] * fu * (1 - fv)
        + gray[v0 + 1, u0] * (1 - fu) * fv
        + gray[v0 + 1, u0 + 1] * fu * fv
    )
    return values.reshape(uv.shape[0], -1).astype(np.float32)


def zncc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    return (a * b).sum(axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) + 1e-6)


def appearance_check(
    gray_i: np.ndarray,
    gray_j: np.ndarray,
    uv_i: np.ndarray,
    uv_j: np.ndarray,
    *,
    radius: int = 3,
    zncc_min: float = 0.8,
    margin: float = 0.2,
    shift_px: float = 2.0,
    min_std: float = 0.02,
) -> np.ndarray:
    """``(M,)`` bool: matches whose patches agree and form a distinct correlation peak.

    A match is kept when the zero-mean normalised cross-correlation (ZNCC) of the patches at
    ``uv_i`` (frame i) and ``uv_j`` (frame j) is at least ``zncc_min``, it exceeds the ZNCC at
    ``uv_j`` moved by ``shift_px`` in each of 8 directions by ``margin``, and neither patch is
    flatter than ``min_std``. A flow that stopped short of the true motion fails the first test
    on texture and the second on edges and gradients, where it would otherwise pass.

    Args:
        gray_i, gray_j: ``(H, W)`` uint8 or float luminance.
        uv_i, uv_j: ``(M, 2)`` matched pixels.
    """
    scale = 255.0 if gray_i.dtype == np.uint8 else 1.0
    fi = np.asarray(gray_i, np.float32) / scale
    fj = np.asarray(gray_j, np.float32) / scale
    uv_i = np.asarray(uv_i, np.float32)
    uv_j = np.asarray(uv_j, np.float32)
    patch_i = patch_samples(fi, uv_i, radius)
    patch_j = patch_samples(fj, uv_j, radius)
    score = zncc(patch_i, patch_j)
    keep = (score >= zncc_min) & (patch_i.std(axis=1) > min_std) & (patch_j.std(axis=1) > min_std)
    for angle in np.arange(8) * (np.pi / 4):
        shift = np.array([np.cos(angle), np.sin(angle)], np.float32) * shift_px
        keep &= score - zncc(patch_i, patch_samples(fj, uv_j + shift, radius)) > margin
    return keep
