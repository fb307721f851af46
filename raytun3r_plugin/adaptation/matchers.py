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

from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from raytun3r_plugin.adaptation.matches import (
    Matcher,
    Matches,
    appearance_check,
    check_pair,
    erode_mask,
    matches_from_flows,
    to_gray_u8,
)
from raytun3r_plugin.adaptation.torch_flow import TorchFlowMatcher
from raytun3r_plugin.errors import InputError

# Matches, Matcher, appearance_check, matches_from_flows (matches.py) and TorchFlowMatcher
# (torch_flow.py) are part of this module's public face, where users have always found them.
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
        image_i, image_j, mask = check_pair(image_i, image_j, valid)
        gray_i, gray_j = to_gray_u8(image_i), to_gray_u8(image_j)
        flow_fw = self.flow(gray_i, gray_j)
        flow_bw = self.flow(gray_j, gray_i)
        matches = matches_from_flows(
            flow_fw, flow_bw, erode_mask(mask, self.border_px), self.stride, self.fb_threshold_px
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
        image_i, image_j, mask = check_pair(image_i, image_j, valid)
        mask = erode_mask(mask, self.border_px)
        pts_i, desc_i = self._detect(to_gray_u8(image_i), mask)
        pts_j, desc_j = self._detect(to_gray_u8(image_j), mask)
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
