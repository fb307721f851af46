"""Adaptation windows: frame selection, correspondences + pose targets per window, disk cache.

The adaptation set of a fisheye segment (docs/conventions.md section 7) is a list of short windows (by
default 30 windows of 3 frames). For every window and every *ordered* pair of its frames we
store the matcher's correspondences and a MAGSAC++ relative-pose target; windows whose mean
correspondence displacement is below ``min_motion_px`` (2 px) are static and skipped.

Pair keys are **window-local** indices ``(a, b)`` into ``Window.frames`` (``a != b``), for
a 3-frame window in the order ``(0, 1), (1, 0), (1, 2), (2, 1), (0, 2), (2, 0)`` (neighbours
first, both directions); ``Window.global_pair(a, b)`` gives the global frame indices.
``pairs[(a, b)]`` matches frame ``frames[a]`` (``uv_i``) to frame ``frames[b]`` (``uv_j``) and
``targets[(a, b)]`` is ``cam_b_from_cam_a``.

Static test: the mean pixel displacement ``|uv_j - uv_i|`` over all matches of the window's
forward pairs (``a < b``); a window with no matches at all counts as static. A window that is
kept may still hold pairs whose target failed (``targets[p].ok`` false): the loss must skip
those pose terms.

Cache: with ``cache_dir`` set, the result is stored in one ``.npz`` file (no pickle) named by a
sha256 over the sequence identity (``sequence_id`` or a hash of the image bytes), the camera
JSON, the matcher name and settings, the window parameters and the pose-target parameters. A
second call with the same inputs loads it and calls neither the matcher nor the estimator.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from raytun3r_plugin.adaptation.matchers import Matcher, Matches
from raytun3r_plugin.adaptation.pose_targets import PoseTarget, estimate_relative_pose
from raytun3r_plugin.atomic_files import atomic_path
from raytun3r_plugin.errors import InputError

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

__all__ = [
    "AdaptationSet",
    "Window",
    "build_windows",
    "prepare_adaptation_set",
    "window_pairs",
]

logger = logging.getLogger(__name__)

CACHE_FORMAT = 1
"""Version of the cache layout; part of the cache key."""


def build_windows(
    n_frames: int,
    n_windows: int = 30,
    window_size: int = 3,
    stride: int = 1,
    start: int = 0,
    stop: int | None = None,
) -> list[tuple[int, ...]]:
    """Windows of ``window_size`` frames ``(s, s + stride, ..., s + (window_size-1) * stride)``.

    The start frames ``s`` are spread evenly over the segment ``[start, stop)`` (``stop``
    exclusive, default ``n_frames``): the first window starts at ``start``, the last one ends at
    ``stop - 1`` when possible. When the segment holds fewer than ``n_windows`` distinct
    windows, every possible window is returned (so the result may be shorter than
    ``n_windows``). Windows overlap when they must.

    Raises:
        InputError: bad arguments, or the segment is shorter than one window.
    """
    stop = n_frames if stop is None else stop
    if n_frames < 1:
        raise InputError(f"n_frames must be >= 1, got {n_frames}")
    if n_windows < 1:
        raise InputError(f"n_windows must be >= 1, got {n_windows}")
    if window_size < 2:
        raise InputError(f"window_size must be >= 2, got {window_size}")
    if stride < 1:
        raise InputError(f"stride must be >= 1, got {stride}")
    if not 0 <= start < stop <= n_frames:
        raise InputError(f"need 0 <= start < stop <= n_frames, got {start}, {stop}, {n_frames}")
    span = (window_size - 1) * stride
    last = stop - 1 - span
    if last < start:
        raise InputError(
            f"segment [{start}, {stop}) has {stop - start} frames, a window needs {span + 1} "
            f"(window_size={window_size}, stride={stride})"
        )
    n_possible = last - start + 1
    if n_windows >= n_possible:
        starts = list(range(start, last + 1))
    else:
        starts = sorted({int(s) for s in np.rint(np.linspace(start, last, n_windows))})
    return [tuple(s + k * stride for k in range(window_size)) for s in starts]


def window_pairs(window_size: int = 3) -> list[tuple[int, int]]:
    """Window-local ordered pairs, by increasing frame gap, each pair followed by its reverse.

    ``window_pairs(3) == [(0, 1), (1, 0), (1, 2), (2, 1), (0, 2), (2, 0)]``.
    """
    out: list[tuple[int, int]] = []
    for gap in range(1, window_size):
        for a in range(window_size - gap):
            out += [(a, a + gap), (a + gap, a)]
    return out


@dataclass
class Window:
    """One adaptation window.

    Attributes:
        frames: global frame indices, increasing (length ``window_size``, 3 by default).
        pairs: ``(a, b) -> Matches`` for every ordered pair of window-local indices ``a != b``
            (``uv_i`` in frame ``frames[a]``, ``uv_j`` in frame ``frames[b]``).
        targets: ``(a, b) -> PoseTarget`` (``cam_b_from_cam_a``, unit translation; check
            ``ok``).
        motion_px: mean over the forward pairs of their mean image motion (``Matches.mean_motion_px``), pixels.
    """

    frames: tuple[int, ...]
    pairs: dict[tuple[int, int], Matches] = field(default_factory=dict)
    targets: dict[tuple[int, int], PoseTarget] = field(default_factory=dict)
    motion_px: float = 0.0

    def global_pair(self, a: int, b: int) -> tuple[int, int]:
        """Global frame indices of the window-local pair ``(a, b)``."""
        return self.frames[a], self.frames[b]


@dataclass
class AdaptationSet:
    """Windows ready for adaptation.

    Attributes:
        windows: the non-static windows, in segment order.
        skipped_static: number of candidate windows skipped as static.
        static_windows: frames of the skipped windows.
        cache_key: sha256 (hex) of everything that determines the content.
        cache_path: the ``.npz`` file, or ``None`` without a cache directory.
        from_cache: the content was loaded from ``cache_path``.
        settings: the parameters that entered ``cache_key`` (JSON-able).
    """

    windows: list[Window]
    skipped_static: int
    static_windows: list[tuple[int, ...]]
    cache_key: str
    cache_path: Path | None = None
    from_cache: bool = False
    settings: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.windows)

    def __iter__(self) -> Iterator[Window]:
        return iter(self.windows)


# --------------------------------------------------------------------------------------------
# Inputs and cache keys
# --------------------------------------------------------------------------------------------


def _as_images(images: Any) -> np.ndarray:
    if isinstance(images, torch.Tensor):
        images = images.detach().cpu().numpy()
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise InputError(f"images must be (N, H, W, 3), got shape {images.shape}")
    if images.dtype != np.float32:
        raise InputError(f"images must be float32 in [0, 1], got {images.dtype}")
    if images.size and (float(images.min()) < 0.0 or float(images.max()) > 1.0):
        raise InputError("images must lie in [0, 1]")
    return images


def _camera_json(camera: Camera) -> str:
    payload = camera.to_json()
    if isinstance(payload, str):
        try:
            payload = json.loads(payload)
        except json.JSONDecodeError:
            return payload
    return json.dumps(payload, sort_keys=True, default=str)


def _valid_mask(camera: Camera, valid: Any, shape: tuple[int, int]) -> np.ndarray:
    if valid is None:
        valid = camera.valid_mask()
    if isinstance(valid, torch.Tensor):
        valid = valid.detach().cpu().numpy()
    mask = np.asarray(valid).astype(bool)
    if mask.shape != shape:
        raise InputError(f"valid mask has shape {mask.shape}, images are {shape}")
    return mask


def _images_digest(images: np.ndarray) -> str:
    h = hashlib.sha256()
    h.update(str(images.shape).encode())
    h.update(str(images.dtype).encode())
    h.update(np.ascontiguousarray(images).data)
    return h.hexdigest()


# --------------------------------------------------------------------------------------------
# Cache file
# --------------------------------------------------------------------------------------------


def _save(
    path: Path,
    payload: str,
    windows: list[Window],
    static: list[tuple[int, ...]],
    window_size: int,
) -> None:
    # Store each global pair once; windows refer to pairs by global frame indices.
    pair_index: dict[tuple[int, int], tuple[Matches, PoseTarget]] = {}
    for w in windows:
        for key, m in w.pairs.items():
            pair_index.setdefault(w.global_pair(*key), (m, w.targets[key]))
    keys = list(pair_index)
    sizes = [len(pair_index[k][0]) for k in keys]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

    def cat(arrays: list[np.ndarray], shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        return np.concatenate(arrays).astype(dtype) if arrays else np.zeros(shape, dtype)

    arrays: dict[str, Any] = {
        "payload": np.array(payload),
        "window_frames": np.array([w.frames for w in windows], np.int64).reshape(-1, window_size),
        "window_motion": np.array([w.motion_px for w in windows], np.float64),
        "static_frames": np.array(static, np.int64).reshape(-1, window_size),
        "pair_frames": np.array(keys, np.int64).reshape(-1, 2),
        "pair_offsets": offsets,
        "uv_i": cat([pair_index[k][0].uv_i for k in keys], (0, 2), np.float32),
        "uv_j": cat([pair_index[k][0].uv_j for k in keys], (0, 2), np.float32),
        "confidence": cat([pair_index[k][0].confidence for k in keys], (0,), np.float32),
        "inlier": cat([pair_index[k][1].inlier_mask for k in keys], (0,), bool),
        "R": np.array([pair_index[k][1].R for k in keys], np.float64).reshape(-1, 3, 3),
        "t": np.array([pair_index[k][1].t for k in keys], np.float64).reshape(-1, 3),
        "n_inliers": np.array([pair_index[k][1].n_inliers for k in keys], np.int64),
        "ok": np.array([pair_index[k][1].ok for k in keys], bool),
        "reason": np.array([pair_index[k][1].reason for k in keys], dtype=str),
    }
    with atomic_path(path) as temporary, open(temporary, "wb") as handle:
        np.savez(handle, **arrays)


def _load(path: Path, payload: str, window_size: int) -> tuple[list[Window], list[tuple]] | None:
    """Read a cache file; ``None`` when it is missing, unreadable or made for other inputs."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data["payload"][()]) != payload:
                logger.warning("adaptation cache %s was made for other inputs; recomputing", path)
                return None
            d = {k: data[k] for k in data.files}
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        logger.warning("adaptation cache %s is unreadable (%s); recomputing", path, exc)
        return None
    offsets = d["pair_offsets"]
    pairs: dict[tuple[int, int], tuple[Matches, PoseTarget]] = {}
    for p, (gi, gj) in enumerate(d["pair_frames"].tolist()):
        s, e = int(offsets[p]), int(offsets[p + 1])
        m = Matches(d["uv_i"][s:e], d["uv_j"][s:e], d["confidence"][s:e])
        tgt = PoseTarget(
            d["R"][p],
            d["t"][p],
            d["inlier"][s:e],
            int(d["n_inliers"][p]),
            bool(d["ok"][p]),
            str(d["reason"][p]),
        )
        pairs[(gi, gj)] = (m, tgt)
    windows = []
    for frames, motion in zip(
        d["window_frames"].tolist(), d["window_motion"].tolist(), strict=True
    ):
        w = Window(tuple(int(f) for f in frames), motion_px=float(motion))
        for a, b in window_pairs(window_size):
            m, tgt = pairs[w.global_pair(a, b)]
            w.pairs[(a, b)] = m
            w.targets[(a, b)] = tgt
        windows.append(w)
    static = [tuple(int(f) for f in s) for s in d["static_frames"].tolist()]
    return windows, static


# --------------------------------------------------------------------------------------------
# Main entry point
# --------------------------------------------------------------------------------------------


def prepare_adaptation_set(
    images: np.ndarray,
    camera: Camera,
    matcher: Matcher,
    n_windows: int = 30,
    stride: int = 1,
    cache_dir: str | os.PathLike | None = None,
    sequence_id: str | None = None,
    min_motion_px: float = 2.0,
    *,
    window_size: int = 3,
    start: int = 0,
    stop: int | None = None,
    max_angle_deg: float = 80.0,
    threshold_px: float = 1.0,
    seed: int = 0,
    min_inliers: int = 15,
    refine: bool = True,
    valid: np.ndarray | None = None,
) -> AdaptationSet:
    """Build (or load from cache) the adaptation set of a fisheye segment.

    Args:
        images: ``(N, H, W, 3)`` float32 RGB in ``[0, 1]``, the segment (a torch tensor of the
            same layout is accepted).
        camera: raytun3r camera of the images (``width == W``, ``height == H``).
        matcher: a :class:`~raytun3r_plugin.adaptation.matchers.Matcher`.
        n_windows, stride, window_size, start, stop: see :func:`build_windows`.
        cache_dir: folder of the ``.npz`` cache (created if needed); ``None`` = no cache.
        sequence_id: caller's identity of the images (e.g. dataset/sequence/first-last frame);
            must change whenever the images change. ``None`` hashes the image bytes.
        min_motion_px: windows whose mean correspondence displacement is below this are
            static and skipped.
        max_angle_deg, threshold_px, seed, min_inliers, refine: passed to
            :func:`~raytun3r_plugin.adaptation.pose_targets.estimate_relative_pose`.
        valid: ``(H, W)`` bool mask of pixels seeing the scene; default ``camera.valid_mask()``.

    Returns:
        :class:`AdaptationSet` (pair keys are window-local; see the module docstring).
    """
    images = _as_images(images)
    n, h, w = images.shape[:3]
    if (int(camera.width), int(camera.height)) != (w, h):
        raise InputError(
            f"camera is {camera.width}x{camera.height} but images are {w}x{h}; rescale the "
            "camera (camera.scaled) to the image size first"
        )
    for attr in ("match", "settings"):
        if not callable(getattr(matcher, attr, None)):
            raise InputError(f"matcher {matcher!r} has no {attr}() method")
    mask = _valid_mask(camera, valid, (h, w))
    candidates = build_windows(n, n_windows, window_size, stride, start, stop)

    pose = {
        "max_angle_deg": max_angle_deg,
        "threshold_px": threshold_px,
        "seed": seed,
        "min_inliers": min_inliers,
        "refine": refine,
    }
    windowing = {
        "n_windows": n_windows,
        "window_size": window_size,
        "stride": stride,
        "start": start,
        "stop": stop,
        "min_motion_px": float(min_motion_px),
    }
    settings = _cache_settings(images, camera, matcher, mask, sequence_id, windowing, pose)
    payload = json.dumps(settings, sort_keys=True, default=str)
    key = hashlib.sha256(payload.encode()).hexdigest()
    path = None if cache_dir is None else Path(cache_dir) / f"adaptation_{key[:32]}.npz"

    if path is not None:
        loaded = _load(path, payload, window_size)
        if loaded is not None:
            windows, static = loaded
            logger.info("adaptation set loaded from %s (%d windows)", path, len(windows))
            return AdaptationSet(windows, len(static), static, key, path, True, settings)

    windows, static, matcher_calls = _moving_windows(
        images, camera, matcher, mask, candidates, window_size, min_motion_px, pose
    )
    logger.info(
        "adaptation set: %d windows, %d static skipped, %d matcher calls",
        len(windows),
        len(static),
        matcher_calls,
    )
    if path is not None:
        _save(path, payload, windows, static, window_size)
    return AdaptationSet(windows, len(static), static, key, path, False, settings)


def _cache_settings(
    images: np.ndarray,
    camera: Camera,
    matcher: Matcher,
    mask: np.ndarray,
    sequence_id: str | None,
    windowing: dict[str, Any],
    pose: dict[str, Any],
) -> dict[str, Any]:
    """Everything the adaptation set depends on, the cache's key: the images (or the caller's
    id of them), camera, mask, matcher, windowing and the pose targets' settings."""
    return {
        "format": CACHE_FORMAT,
        "sequence": str(sequence_id) if sequence_id is not None else _images_digest(images),
        "sequence_id_given": sequence_id is not None,
        "image_shape": list(images.shape),
        "camera": _camera_json(camera),
        "valid_mask": hashlib.sha256(np.packbits(mask).tobytes()).hexdigest(),
        "matcher": {
            "name": str(getattr(matcher, "name", type(matcher).__name__)),
            "settings": matcher.settings(),
        },
        "windows": windowing,
        "pose": {
            "max_angle_deg": float(pose["max_angle_deg"]),
            "threshold_px": float(pose["threshold_px"]),
            "seed": int(pose["seed"]),
            "min_inliers": int(pose["min_inliers"]),
            "refine": bool(pose["refine"]),
            "method": "USAC_MAGSAC",
        },
    }


def _moving_windows(
    images: np.ndarray,
    camera: Camera,
    matcher: Matcher,
    mask: np.ndarray,
    candidates: list[tuple[int, ...]],
    window_size: int,
    min_motion_px: float,
    pose: dict[str, Any],
) -> tuple[list[Window], list[tuple[int, ...]], int]:
    """Match and pose every candidate window that moves: (windows, static windows skipped,
    matcher calls). Each frame pair is matched, and its pose target estimated, once."""
    match_memo: dict[tuple[int, int], Matches] = {}
    target_memo: dict[tuple[int, int], PoseTarget] = {}

    def matches_for(gi: int, gj: int) -> Matches:
        if (gi, gj) not in match_memo:
            m = matcher.match(images[gi], images[gj], mask)
            if not isinstance(m, Matches):
                raise InputError(f"matcher {matcher!r} returned {type(m).__name__}, not Matches")
            match_memo[(gi, gj)] = m
        return match_memo[(gi, gj)]

    def target_for(gi: int, gj: int) -> PoseTarget:
        if (gi, gj) not in target_memo:
            target_memo[(gi, gj)] = estimate_relative_pose(matches_for(gi, gj), camera, **pose)
        return target_memo[(gi, gj)]

    pairs = window_pairs(window_size)
    windows: list[Window] = []
    static: list[tuple[int, ...]] = []
    for frames in candidates:
        win = Window(frames)
        # Forward pairs first: enough to decide whether the window is static.
        forward = [(a, b) for a, b in pairs if a < b]
        motion = [matches_for(*win.global_pair(a, b)).mean_motion_px() for a, b in forward]
        win.motion_px = float(np.mean(motion)) if motion else 0.0
        if win.motion_px < min_motion_px:
            static.append(frames)
            continue
        for a, b in pairs:
            g = win.global_pair(a, b)
            win.pairs[(a, b)] = matches_for(*g)
            win.targets[(a, b)] = target_for(*g)
        windows.append(win)
    return windows, static, len(match_memo)
