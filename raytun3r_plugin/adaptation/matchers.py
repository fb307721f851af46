"""Correspondence sources for online adaptation.

A matcher turns an ordered image pair ``(i -> j)`` into pixel correspondences with a confidence
per match (:class:`Matches`). Everything here works in the raw (fisheye) image: flow and
descriptors are camera-model agnostic, the camera is only used later to lift pixels to rays.

Conventions (docs/conventions.md section 2): images are ``(H, W, 3)`` float32 RGB in ``[0, 1]``; pixel
``(u, v)`` has the centre of the top-left pixel at ``(0, 0)``, ``u`` to the right, ``v`` down
(the OpenCV convention, so OpenCV keypoints and flow fields need no offset).

Built-in matchers need no weights:

* :class:`DISFlowMatcher` -- dense DIS optical flow (OpenCV) with a forward-backward check,
  sampled on a regular pixel grid. Best for small baselines (consecutive frames).
* :class:`SIFTMatcher` -- SIFT keypoints, brute-force 2-NN matching, Lowe ratio test, optional
  mutual-nearest-neighbour check. Sparse, but tolerates larger baselines.

Learned flow networks plug in from *local* weight files through :class:`TorchFlowMatcher`
(never downloading); any other object with ``name``, ``settings()`` and ``match()`` works too
(see :class:`Matcher` and ``docs/matching.md``). Matchers are registered by name in
:data:`MATCHERS` (:func:`register_matcher`, :func:`get_matcher`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np
import torch

from raytun3r_plugin.errors import InputError, WeightsError

__all__ = [
    "MATCHERS",
    "DISFlowMatcher",
    "Matcher",
    "Matches",
    "SIFTMatcher",
    "TorchFlowMatcher",
    "appearance_check",
    "get_matcher",
    "matches_from_flows",
    "register_matcher",
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


def _check_pair(
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
        mask = _as_bool_mask(valid)
        if mask.shape != (h, w):
            raise InputError(f"valid mask has shape {mask.shape}, images are {(h, w)}")
    return arrays[0], arrays[1], mask


def _as_bool_mask(valid: Any) -> np.ndarray:
    if isinstance(valid, torch.Tensor):
        valid = valid.detach().cpu().numpy()
    return np.asarray(valid).astype(bool)


def _to_gray_u8(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) float RGB in [0, 1] -> (H, W) uint8 luminance."""
    rgb = np.clip(np.asarray(image, dtype=np.float32) * 255.0 + 0.5, 0.0, 255.0).astype(np.uint8)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def _erode(mask: np.ndarray, border_px: int) -> np.ndarray:
    """Shrink a bool mask by ``border_px`` pixels (keeps matches off the lens-circle edge)."""
    if border_px <= 0:
        return mask
    size = 2 * int(border_px) + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    # Pixels outside the image count as invalid, so the image border is eroded too.
    out = cv2.erode(mask.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return out.astype(bool)


def _sample_bilinear(field: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample an (H, W, C) float32 field at (M, 2) pixel positions (bilinear, edge-clamped)."""
    if uv.shape[0] == 0:
        return np.zeros((0, field.shape[2]), np.float32)
    map_x = np.ascontiguousarray(uv[:, 0].reshape(-1, 1).astype(np.float32))
    map_y = np.ascontiguousarray(uv[:, 1].reshape(-1, 1).astype(np.float32))
    out = cv2.remap(field, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(uv.shape[0], field.shape[2])


def _inside(uv: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(M,) bool: the pixel nearest to each position lies in the image and inside ``mask``."""
    h, w = mask.shape
    ui = np.rint(uv[:, 0]).astype(np.int64)
    vi = np.rint(uv[:, 1]).astype(np.int64)
    ok = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    ok[ok] = mask[vi[ok], ui[ok]]
    return ok


def _grid(mask: np.ndarray, stride: int) -> np.ndarray:
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
    uv_i = _grid(valid, stride)
    if uv_i.shape[0] == 0:
        return Matches.empty()
    ui = uv_i[:, 0].astype(np.int64)
    vi = uv_i[:, 1].astype(np.int64)
    uv_j = uv_i + flow_fw[vi, ui]
    finite = np.isfinite(uv_j).all(axis=1)
    uv_i, uv_j = uv_i[finite], uv_j[finite]
    inside = _inside(uv_j, valid)
    uv_i, uv_j = uv_i[inside], uv_j[inside]
    back = uv_j + _sample_bilinear(flow_bw, uv_j)
    fb = np.linalg.norm(back - uv_i, axis=1)
    keep = fb < fb_threshold_px
    conf = np.exp(-2.0 * (fb[keep] / fb_threshold_px) ** 2)
    return Matches(uv_i[keep], uv_j[keep], conf)


def _patches(gray: np.ndarray, uv: np.ndarray, radius: int) -> np.ndarray:
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


def _zncc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
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
    patch_i = _patches(fi, uv_i, radius)
    patch_j = _patches(fj, uv_j, radius)
    score = _zncc(patch_i, patch_j)
    keep = (score >= zncc_min) & (patch_i.std(axis=1) > min_std) & (patch_j.std(axis=1) > min_std)
    for angle in np.arange(8) * (np.pi / 4):
        shift = np.array([np.cos(angle), np.sin(angle)], np.float32) * shift_px
        keep &= score - _zncc(patch_i, _patches(fj, uv_j + shift, radius)) > margin
    return keep


# --------------------------------------------------------------------------------------------
# DIS optical flow
# --------------------------------------------------------------------------------------------

_DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


class DISFlowMatcher:
    """Dense DIS optical flow (OpenCV) with a forward-backward consistency check.

    Flow is computed on 8-bit luminance in both directions (``i -> j`` and ``j -> i``); start
    points are the pixel centres of a ``stride`` grid inside the (eroded) valid mask, end points
    follow the forward flow and must land inside the mask; a match survives when following the
    backward flow from its end point (bilinear) returns within ``fb_threshold_px`` of the start.
    Confidence: ``exp(-2 (fb / fb_threshold_px)^2)``.

    Args:
        preset: ``"ultrafast" | "fast" | "medium"`` (OpenCV DIS presets).
        finest_scale: override the preset's finest pyramid level (0 = full resolution). The
            ``medium`` preset stops at level 1 (half resolution); on 160x160 synthetic fisheye
            frames level 0 cuts the median end-point error from ~0.54 px to ~0.20 px for ~2.5x
            the time (``docs/matching.md``), hence the default 0. ``None`` keeps the preset's.
        stride: grid spacing in pixels (160x160 at stride 4 gives up to 1600 matches).
        fb_threshold_px: forward-backward error threshold in pixels.
        border_px: erode the valid mask by this many pixels (the black area outside the lens
            circle is static and drags the flow of nearby pixels towards zero).
        appearance_check: reject matches whose two patches do not look alike, or look just as
            alike a few pixels away (:func:`appearance_check`). DIS returns nearly zero flow
            where the true motion exceeds what its pyramid can reach (about 8 px outdoors and
            16 px indoors at 112 px), and the forward-backward check keeps those matches,
            because the backward flow is nearly zero as well; on the benchmark's development
            sequences 28-44 % of outdoor matches were then more than 2 px off, and zero flow
            reads as "far". The check removes them (``docs/matching.md``, displacement bins).
        zncc_min: smallest zero-mean normalised cross-correlation of the two
            ``(2 r + 1)^2`` patches (``patch_radius`` r) for a match to be kept.
        distinct_margin: the correlation at the match must exceed the best correlation at
            ``distinct_shift_px`` in 8 directions by this much (the match is a distinct peak,
            not a point on an edge or in a flat region, where a wrong match also correlates).
        min_patch_std: patches flatter than this (grey levels in [0, 1]) are rejected.
    """

    name = "dis"

    def __init__(
        self,
        preset: str = "medium",
        finest_scale: int | None = 0,
        stride: int = 4,
        fb_threshold_px: float = 1.0,
        border_px: int = 4,
        appearance_check: bool = True,
        zncc_min: float = 0.8,
        distinct_margin: float = 0.2,
        distinct_shift_px: float = 2.0,
        patch_radius: int = 3,
        min_patch_std: float = 0.02,
    ) -> None:
        if preset not in _DIS_PRESETS:
            raise InputError(f"DIS preset must be one of {sorted(_DIS_PRESETS)}, got {preset!r}")
        if finest_scale is not None and int(finest_scale) < 0:
            raise InputError(f"finest_scale must be >= 0 or None, got {finest_scale}")
        if int(stride) < 1:
            raise InputError(f"stride must be >= 1, got {stride}")
        if not fb_threshold_px > 0:
            raise InputError(f"fb_threshold_px must be > 0, got {fb_threshold_px}")
        if int(border_px) < 0:
            raise InputError(f"border_px must be >= 0, got {border_px}")
        self.preset = preset
        self.finest_scale = None if finest_scale is None else int(finest_scale)
        self.stride = int(stride)
        self.fb_threshold_px = float(fb_threshold_px)
        self.border_px = int(border_px)
        if int(patch_radius) < 1 or not distinct_shift_px > 0 or not -1.0 <= zncc_min <= 1.0:
            raise InputError(
                "appearance check: patch_radius >= 1, distinct_shift_px > 0 and zncc_min in [-1, 1] are required"
            )
        self.appearance_check = bool(appearance_check)
        self.zncc_min = float(zncc_min)
        self.distinct_margin = float(distinct_margin)
        self.distinct_shift_px = float(distinct_shift_px)
        self.patch_radius = int(patch_radius)
        self.min_patch_std = float(min_patch_std)

    def settings(self) -> dict:
        out = {
            "name": self.name,
            "preset": self.preset,
            "finest_scale": self.finest_scale,
            "stride": self.stride,
            "fb_threshold_px": self.fb_threshold_px,
            "border_px": self.border_px,
            "opencv": cv2.__version__,
        }
        if self.appearance_check:
            out["appearance_check"] = {
                "zncc_min": self.zncc_min,
                "distinct_margin": self.distinct_margin,
                "distinct_shift_px": self.distinct_shift_px,
                "patch_radius": self.patch_radius,
                "min_patch_std": self.min_patch_std,
                "motion_px": "before the check",
            }
        return out

    def flow(self, gray_i: np.ndarray, gray_j: np.ndarray) -> np.ndarray:
        """Dense flow ``i -> j``: ``(H, W, 2)`` float32 pixels, from two ``(H, W)`` uint8 images."""
        dis = cv2.DISOpticalFlow_create(_DIS_PRESETS[self.preset])
        if self.finest_scale is not None:
            dis.setFinestScale(self.finest_scale)
        return dis.calc(gray_i, gray_j, None)

    def match(
        self, image_i: np.ndarray, image_j: np.ndarray, valid: np.ndarray | None = None
    ) -> Matches:
        image_i, image_j, mask = _check_pair(image_i, image_j, valid)
        gray_i, gray_j = _to_gray_u8(image_i), _to_gray_u8(image_j)
        flow_fw = self.flow(gray_i, gray_j)
        flow_bw = self.flow(gray_j, gray_i)
        matches = matches_from_flows(
            flow_fw, flow_bw, _erode(mask, self.border_px), self.stride, self.fb_threshold_px
        )
        if not self.appearance_check or len(matches) == 0:
            return matches
        keep = appearance_check(
            gray_i,
            gray_j,
            matches.uv_i,
            matches.uv_j,
            radius=self.patch_radius,
            zncc_min=self.zncc_min,
            margin=self.distinct_margin,
            shift_px=self.distinct_shift_px,
            min_std=self.min_patch_std,
        )
        kept = matches.select(keep)
        kept.motion_px = float(matches.displacement().mean())
        return kept

    def __repr__(self) -> str:
        return f"DISFlowMatcher({self.settings()})"


# --------------------------------------------------------------------------------------------
# SIFT
# --------------------------------------------------------------------------------------------


class SIFTMatcher:
    """SIFT keypoints + brute-force L2 2-NN matching + Lowe ratio test (+ mutual check).

    Keypoints are detected on 8-bit luminance inside the (eroded) valid mask. A match
    ``i -> j`` is kept when ``d1 < ratio * d2`` (nearest / second-nearest descriptor distance in
    ``j``) and, with ``mutual=True``, when the keypoint in ``i`` is also the nearest neighbour of
    its partner in ``j``. Confidence: ``1 - d1 / d2`` (so in ``(1 - ratio, 1]``). Keypoints that
    SIFT duplicates with several orientations give one match (the most confident).

    Args:
        n_features: keep the best ``n_features`` keypoints per image (0 = all).
        ratio: Lowe ratio threshold.
        mutual: require mutual nearest neighbours.
        border_px: erode the valid mask by this many pixels before detection.
        contrast_threshold: SIFT contrast threshold (OpenCV default 0.04; lower finds more
            keypoints in low-texture or small images).
    """

    name = "sift"

    def __init__(
        self,
        n_features: int = 4000,
        ratio: float = 0.8,
        mutual: bool = True,
        border_px: int = 4,
        contrast_threshold: float = 0.02,
    ) -> None:
        if int(n_features) < 0:
            raise InputError(f"n_features must be >= 0, got {n_features}")
        if not 0.0 < ratio <= 1.0:
            raise InputError(f"ratio must be in (0, 1], got {ratio}")
        if int(border_px) < 0:
            raise InputError(f"border_px must be >= 0, got {border_px}")
        if not contrast_threshold > 0:
            raise InputError(f"contrast_threshold must be > 0, got {contrast_threshold}")
        self.n_features = int(n_features)
        self.ratio = float(ratio)
        self.mutual = bool(mutual)
        self.border_px = int(border_px)
        self.contrast_threshold = float(contrast_threshold)

    def settings(self) -> dict:
        return {
            "name": self.name,
            "n_features": self.n_features,
            "ratio": self.ratio,
            "mutual": self.mutual,
            "border_px": self.border_px,
            "contrast_threshold": self.contrast_threshold,
            "opencv": cv2.__version__,
        }

    def _detect(self, gray: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sift = cv2.SIFT_create(nfeatures=self.n_features, contrastThreshold=self.contrast_threshold)
        keypoints, desc = sift.detectAndCompute(gray, mask.astype(np.uint8) * 255)
        if desc is None or not keypoints:
            return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32)
        pts = np.array([kp.pt for kp in keypoints], dtype=np.float32)
        return pts, np.asarray(desc, dtype=np.float32)

    def match(
        self, image_i: np.ndarray, image_j: np.ndarray, valid: np.ndarray | None = None
    ) -> Matches:
        image_i, image_j, mask = _check_pair(image_i, image_j, valid)
        mask = _erode(mask, self.border_px)
        pts_i, desc_i = self._detect(_to_gray_u8(image_i), mask)
        pts_j, desc_j = self._detect(_to_gray_u8(image_j), mask)
        if len(pts_i) < 1 or len(pts_j) < 2:
            return Matches.empty()
        bf = cv2.BFMatcher(cv2.NORM_L2)
        knn = bf.knnMatch(desc_i, desc_j, k=2)
        qi, tj, d1, d2 = [], [], [], []
        for pair in knn:
            if len(pair) < 2:
                continue
            m, n = pair
            if m.distance < self.ratio * n.distance:
                qi.append(m.queryIdx)
                tj.append(m.trainIdx)
                d1.append(m.distance)
                d2.append(n.distance)
        if not qi:
            return Matches.empty()
        qi_a = np.asarray(qi, np.int64)
        tj_a = np.asarray(tj, np.int64)
        ratio = np.asarray(d1, np.float64) / np.maximum(np.asarray(d2, np.float64), 1e-12)
        if self.mutual:
            back = bf.match(desc_j, desc_i)
            nn_back = np.full(len(pts_j), -1, np.int64)
            for m in back:
                nn_back[m.queryIdx] = m.trainIdx
            ok = nn_back[tj_a] == qi_a
            qi_a, tj_a, ratio = qi_a[ok], tj_a[ok], ratio[ok]
        conf = np.clip(1.0 - ratio, 0.0, 1.0)
        uv_i, uv_j = pts_i[qi_a], pts_j[tj_a]
        # Deduplicate identical (uv_i, uv_j) (SIFT repeats keypoints with several orientations):
        # sort by decreasing confidence, keep the first occurrence, then restore a stable order.
        order = np.lexsort((np.arange(len(conf)), -conf))
        rows = np.concatenate([uv_i, uv_j], axis=1)[order]
        _, first = np.unique(rows, axis=0, return_index=True)
        keep = np.sort(order[first])
        return Matches(uv_i[keep], uv_j[keep], conf[keep])

    def __repr__(self) -> str:
        return f"SIFTMatcher({self.settings()})"


# --------------------------------------------------------------------------------------------
# Learned flow networks from local weight files
# --------------------------------------------------------------------------------------------


def _load_state_dict(path: Path) -> dict[str, torch.Tensor]:
    """Read a state dict from a local ``.safetensors`` or torch file; never downloads."""
    if not path.is_file():
        raise WeightsError(f"weight file not found: {path}")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state: Any = load_file(str(path), device="cpu")
        else:
            state = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupt file, pickled objects refused by weights_only, ...
        raise WeightsError(f"cannot read weights from {path}: {exc}") from exc
    # Common checkpoint wrappers: {"state_dict": {...}} / {"model": {...}}.
    for key in ("state_dict", "model"):
        if isinstance(state, Mapping) and isinstance(state.get(key), Mapping):
            state = state[key]
    if not isinstance(state, Mapping) or not all(
        isinstance(v, torch.Tensor) for v in state.values()
    ):
        raise WeightsError(f"{path} does not hold a state dict of tensors")
    return dict(state)


def _state_dict_digest(module: torch.nn.Module) -> str:
    """sha256 over names, shapes, dtypes and bytes of a module's parameters and buffers."""
    h = hashlib.sha256()
    for name, tensor in sorted(module.state_dict().items()):
        t = tensor.detach().cpu().contiguous()
        h.update(name.encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(str(t.dtype).encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


class TorchFlowMatcher:
    """Any dense flow network (``torch.nn.Module``) used as a matcher; weights from a local file.

    The user constructs the network (e.g. ``torchvision.models.optical_flow.raft_small(
    weights=None)`` or a UFM/RoMa wrapper that outputs flow); this class loads a *local* weight
    file into it -- ``.safetensors`` via ``safetensors.torch.load_file``, anything else via
    ``torch.load(path, weights_only=True)`` (no pickled code is executed) -- and never downloads.

    Network contract: ``network(image_i, image_j)`` with ``(B, 3, H, W)`` float32 images
    (``input_range="unit"``: ``[0, 1]``; ``"symmetric"``: ``[-1, 1]``, what RAFT expects) returns
    the flow ``i -> j`` in pixels as ``(B, 2, H, W)``, or a list/tuple of such refinements (the
    last is used), or a dict with key ``"flow"``. Images are edge-padded to a multiple of
    ``pad_multiple`` (RAFT: 8). Forward and backward flow run as one batch of 2; matches then
    follow exactly the :class:`DISFlowMatcher` rules (grid, valid mask, forward-backward check,
    confidence).

    Args:
        network: the flow network (moved to ``device`` and put in eval mode).
        weights_path: local ``.safetensors`` / ``.pt`` / ``.pth`` file, or ``None`` to use the
            network's current weights. Checkpoints wrapped as ``{"state_dict": ...}`` or
            ``{"model": ...}`` are unwrapped.
        name: matcher name (enters the cache key).
        strict: passed to ``load_state_dict``.
        stride, fb_threshold_px, border_px: as in :class:`DISFlowMatcher`.
        input_range: ``"unit"`` or ``"symmetric"``.
        pad_multiple: pad H and W up to a multiple of this (1 = no padding).
        device: torch device for inference.

    The cache key includes a sha256 of the loaded state dict, so new weights invalidate cached
    matches.
    """

    def __init__(
        self,
        network: torch.nn.Module,
        weights_path: str | Path | None = None,
        *,
        name: str = "torch_flow",
        strict: bool = True,
        stride: int = 4,
        fb_threshold_px: float = 1.0,
        border_px: int = 4,
        input_range: str = "unit",
        pad_multiple: int = 8,
        device: str | torch.device = "cpu",
    ) -> None:
        if not isinstance(network, torch.nn.Module):
            raise InputError(f"network must be a torch.nn.Module, got {type(network).__name__}")
        if input_range not in ("unit", "symmetric"):
            raise InputError(f"input_range must be 'unit' or 'symmetric', got {input_range!r}")
        if int(stride) < 1 or int(pad_multiple) < 1 or int(border_px) < 0:
            raise InputError("stride and pad_multiple must be >= 1, border_px >= 0")
        if not fb_threshold_px > 0:
            raise InputError(f"fb_threshold_px must be > 0, got {fb_threshold_px}")
        self.name = str(name)
        self.device = torch.device(device)
        self.weights_path = None if weights_path is None else Path(weights_path)
        if self.weights_path is not None:
            state = _load_state_dict(self.weights_path)
            try:
                network.load_state_dict(state, strict=strict)
            except RuntimeError as exc:
                raise WeightsError(
                    f"weights in {self.weights_path} do not fit {type(network).__name__}: {exc}"
                ) from exc
        self.network = network.to(self.device).eval()
        self.stride = int(stride)
        self.fb_threshold_px = float(fb_threshold_px)
        self.border_px = int(border_px)
        self.input_range = input_range
        self.pad_multiple = int(pad_multiple)
        self._digest = _state_dict_digest(self.network)

    def settings(self) -> dict:
        return {
            "name": self.name,
            "network": type(self.network).__name__,
            "weights_sha256": self._digest,
            "stride": self.stride,
            "fb_threshold_px": self.fb_threshold_px,
            "border_px": self.border_px,
            "input_range": self.input_range,
            "pad_multiple": self.pad_multiple,
        }

    @staticmethod
    def _flow_output(out: Any) -> torch.Tensor:
        if isinstance(out, Mapping):
            out = out["flow"]
        if isinstance(out, (list, tuple)):
            out = out[-1]
        if not isinstance(out, torch.Tensor):
            raise InputError(f"flow network returned {type(out).__name__}, expected a tensor")
        return out

    def flows(self, image_i: np.ndarray, image_j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward and backward flow, each ``(H, W, 2)`` float32 pixels."""
        h, w = image_i.shape[:2]
        a = torch.from_numpy(np.ascontiguousarray(image_i, dtype=np.float32)).permute(2, 0, 1)
        b = torch.from_numpy(np.ascontiguousarray(image_j, dtype=np.float32)).permute(2, 0, 1)
        first = torch.stack([a, b]).to(self.device)
        second = torch.stack([b, a]).to(self.device)
        if self.input_range == "symmetric":
            first, second = first * 2.0 - 1.0, second * 2.0 - 1.0
        ph = (-h) % self.pad_multiple
        pw = (-w) % self.pad_multiple
        if ph or pw:
            first = torch.nn.functional.pad(first, (0, pw, 0, ph), mode="replicate")
            second = torch.nn.functional.pad(second, (0, pw, 0, ph), mode="replicate")
        with torch.inference_mode():
            flow = self._flow_output(self.network(first, second))
        if flow.ndim != 4 or flow.shape[0] != 2 or flow.shape[1] != 2:
            raise InputError(f"flow network must return (B, 2, H, W), got {tuple(flow.shape)}")
        flow = flow[:, :, :h, :w].float().permute(0, 2, 3, 1).cpu().numpy()
        return np.ascontiguousarray(flow[0]), np.ascontiguousarray(flow[1])

    def match(
        self, image_i: np.ndarray, image_j: np.ndarray, valid: np.ndarray | None = None
    ) -> Matches:
        image_i, image_j, mask = _check_pair(image_i, image_j, valid)
        flow_fw, flow_bw = self.flows(image_i, image_j)
        return matches_from_flows(
            flow_fw, flow_bw, _erode(mask, self.border_px), self.stride, self.fb_threshold_px
        )

    def __repr__(self) -> str:
        return f"TorchFlowMatcher(name={self.name!r}, network={type(self.network).__name__})"


# --------------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------------

MATCHERS: dict[str, Callable[..., Matcher]] = {}
"""Matcher factories by name; ``get_matcher(name, **kw)`` calls ``MATCHERS[name](**kw)``."""


def register_matcher(
    name: str, factory: Callable[..., Matcher], *, overwrite: bool = False
) -> None:
    """Make ``get_matcher(name, **kw)`` return ``factory(**kw)``.

    Raises:
        InputError: ``name`` is already registered and ``overwrite`` is false, or ``factory`` is
            not callable.
    """
    if not isinstance(name, str) or not name:
        raise InputError("matcher name must be a non-empty string")
    if not callable(factory):
        raise InputError(f"matcher factory for {name!r} is not callable")
    if name in MATCHERS and not overwrite:
        raise InputError(f"matcher {name!r} is already registered (pass overwrite=True)")
    MATCHERS[name] = factory


def get_matcher(name: str, **kwargs: Any) -> Matcher:
    """Build a registered matcher: ``"dis"``, ``"sift"``, ``"torch_flow"`` or a user name."""
    if name not in MATCHERS:
        raise InputError(f"unknown matcher {name!r}; registered: {sorted(MATCHERS)}")
    try:
        return MATCHERS[name](**kwargs)
    except TypeError as exc:
        raise InputError(f"bad arguments for matcher {name!r}: {exc}") from exc


register_matcher("dis", DISFlowMatcher)
register_matcher("sift", SIFTMatcher)
register_matcher("torch_flow", TorchFlowMatcher)
