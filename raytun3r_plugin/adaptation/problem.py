"""The adaptation problem, prepared once: input layout, windows and their pairs in network-input
pixels, resized frames, valid region, token geometry and (supervised fit) depth targets.

Part of :mod:`raytun3r_plugin.adaptation.train` (which re-exports the public names here).
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from raytun3r_plugin.adaptation.config import AdaptConfig
from raytun3r_plugin.adaptation.losses import inside_mask, to_input_pixels
from raytun3r_plugin.adaptation.matchers import get_matcher
from raytun3r_plugin.adaptation.windows import AdaptationSet, Window, prepare_adaptation_set
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.preprocess import InputLayout, input_layout
from raytun3r_plugin.size_geometry import GeometryCache

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

__all__ = [
    "MAX_DEPTH_SAMPLES",
    "AdaptationProblem",
    "prepare_problem",
    "scene_mask",
    "split_segments",
]


def scene_mask(mask: Any, camera: Camera) -> np.ndarray:
    """A user mask of the native frames, checked and combined with the camera's valid region.

    Args:
        mask: (H, W) array-like, True (non-zero) where a pixel sees the scene; False marks what
            never should be matched or supervised (the vehicle's body, a lens mount).
        camera: camera of the native frames (``width == W``, ``height == H``).

    Returns:
        (H, W) bool: ``mask & camera.valid_mask()``.

    Raises:
        InputError: wrong shape, or no pixel left inside the lens.
    """
    array = np.asarray(mask.detach().cpu() if isinstance(mask, torch.Tensor) else mask)
    expected = (int(camera.height), int(camera.width))
    if array.shape != expected:
        raise InputError(
            f"mask must be (H, W) = {expected} like the frames, got shape {array.shape}"
        )
    combined = (array != 0) & camera.valid_mask().cpu().numpy().astype(bool)
    if not combined.any():
        raise InputError("mask leaves no pixel inside the camera's valid region")
    return combined


# --------------------------------------------------------------------------------------------
# Frames and pairs
# --------------------------------------------------------------------------------------------


def _frames_array(frames: Any) -> tuple[np.ndarray, dict[str, Any]]:
    """Accept (N, H, W, 3) float32 arrays/tensors or a ``datasets.Sequence``; return the array
    and a description of the segment."""
    info: dict[str, Any] = {}
    if hasattr(frames, "images") and hasattr(frames, "camera"):
        info["name"] = str(getattr(frames, "name", ""))
        images = frames.images
        if images is None:
            images = np.stack([frames.image(i) for i in range(len(frames))])
        frames = images
    if isinstance(frames, torch.Tensor):
        frames = frames.detach().cpu().numpy()
    array = np.asarray(frames)
    if array.ndim != 4 or array.shape[-1] != 3:
        raise InputError(f"frames must be (N, H, W, 3) RGB in [0, 1], got shape {array.shape}")
    array = array.astype(np.float32, copy=False)
    info.update(n_frames=int(array.shape[0]), width=int(array.shape[2]), height=int(array.shape[1]))
    return array, info


@dataclass
class _Pair:
    """One ordered pair of a window, in network-input pixels, filtered to usable matches."""

    a: int
    b: int
    uv_i: torch.Tensor  # (M, 2) input pixels in frame a
    uv_j: torch.Tensor  # (M, 2) input pixels in frame b
    confidence: torch.Tensor  # (M,)
    rays_i: torch.Tensor  # (M, 3) unit rays of uv_i
    rays_j: torch.Tensor  # (M, 3) unit rays of uv_j
    rotation: torch.Tensor | None  # (3, 3) float64 target R (cam_b_from_cam_a), None if unusable
    direction: torch.Tensor | None  # (3,) float64 unit target translation


def _prepare_pairs(window: Window, layout: InputLayout, valid: torch.Tensor) -> list[_Pair]:
    camera = layout.camera
    pairs = []
    for (a, b), matches in window.pairs.items():
        uv_i = to_input_pixels(
            torch.from_numpy(matches.uv_i).float(),
            layout.native_size,
            (layout.width, layout.height),
            layout.offset,
        )
        uv_j = to_input_pixels(
            torch.from_numpy(matches.uv_j).float(),
            layout.native_size,
            (layout.width, layout.height),
            layout.offset,
        )
        with torch.no_grad():
            rays_i, ok_i = camera.unproject(uv_i)
            rays_j, ok_j = camera.unproject(uv_j)
        keep = ok_i & ok_j & inside_mask(uv_i, valid) & inside_mask(uv_j, valid)
        target = window.targets.get((a, b))
        usable = target is not None and target.ok
        pairs.append(
            _Pair(
                a,
                b,
                uv_i[keep],
                uv_j[keep],
                torch.from_numpy(matches.confidence).float()[keep],
                rays_i[keep].float(),
                rays_j[keep].float(),
                torch.from_numpy(target.R).double() if usable else None,
                torch.from_numpy(target.t).double() if usable else None,
            )
        )
    return pairs


# --------------------------------------------------------------------------------------------
# Prepared problem
# --------------------------------------------------------------------------------------------


@dataclass
class AdaptationProblem:
    """Everything a step needs, prepared once: input layout, windows with their pairs in
    network-input pixels, resized frames, valid region and token geometry.

    Attributes:
        layout: :class:`InputLayout` of the frames.
        adaptation: the :class:`~raytun3r_plugin.adaptation.windows.AdaptationSet`.
        windows: ``[(window, pairs)]`` with the pairs filtered to usable matches.
        inputs: ``{frame index: (3, h, w) network input in [0, 1]}`` for every used frame.
        valid: (h, w) bool valid region at the input size.
        geometry: :class:`raytun3r_plugin.size_geometry.SizeGeometry` at the input size.
        segment: description of the frames (name, count, size).
        mask: the user mask of the (cropped) native frames, (H, W) bool, or None; the model is
            patched with it during adaptation.
        pe_scale: divisor of the PE regularisers (set by :func:`adapt` from the backbone).
        depth_targets: supervised mode: ``{frame: (uv (K, 2) input pixels, depth (K,))}``.
        supervision: description of the ground truth (kind, coverage), or None.
        teacher: the pinhole-view teacher's samples per window
            (:func:`~raytun3r_plugin.adaptation.teacher.teacher_targets`), or None.
        reproject: per window, whether its matches enter the reprojection term (False for the
            windows the parallax gate finds without depth signal when the teacher keeps them);
            None = every window.
    """

    layout: InputLayout
    adaptation: AdaptationSet
    windows: list[tuple[Window, list[_Pair]]]
    inputs: dict[int, torch.Tensor]
    valid: torch.Tensor
    geometry: Any
    segment: dict[str, Any]
    mask: torch.Tensor | None = None
    pe_scale: float = 1.0
    depth_targets: dict[int, tuple[torch.Tensor, torch.Tensor]] | None = None
    supervision: dict[str, Any] | None = None
    teacher: dict[int, list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]] | None = None
    reproject: list[bool] | None = None

    def batch(self, index: int) -> torch.Tensor:
        """(S, 3, h, w) network input of window ``index``."""
        return torch.stack([self.inputs[frame] for frame in self.windows[index][0].frames])

    def window_depth(self, index: int) -> list[tuple[torch.Tensor, torch.Tensor]] | None:
        """Supervised mode: the depth samples of window ``index``'s frames, in window order."""
        if self.depth_targets is None:
            return None
        return [self.depth_targets[frame] for frame in self.windows[index][0].frames]

    def window_teacher(self, index: int) -> list[tuple[torch.Tensor, ...]] | None:
        """The pinhole-view teacher's samples of window ``index``'s frames, or None."""
        return None if self.teacher is None else self.teacher[index]

    def window_reprojects(self, index: int) -> bool:
        """Whether window ``index``'s matches enter the reprojection term."""
        return True if self.reproject is None else self.reproject[index]


#: Most ground-truth depth samples kept per frame (a seeded subset; 112 px frames have fewer).
MAX_DEPTH_SAMPLES = 8192


def _depth_targets(
    depth: Any,
    frames: list[int],
    layout: InputLayout,
    native_valid: np.ndarray | None,
    shape: tuple[int, ...],
    seed: int,
) -> tuple[dict[int, tuple[torch.Tensor, torch.Tensor]], dict[str, Any]]:
    """Ground-truth depth of the native frames -> per-frame samples at network-input pixels.

    ``depth`` is (N, H, W) like the frames (a dense map, or a sparse one such as projected LiDAR
    points: 0, negative or NaN = unknown). Each known pixel centre becomes a sample at the
    input-pixel position of that centre (``to_input_pixels``, so a crop is honoured), where the
    prediction is read bilinearly; no resampling of the ground truth blurs depth edges.
    """
    array = np.asarray(
        depth.detach().cpu() if isinstance(depth, torch.Tensor) else depth, dtype=np.float64
    )
    if array.shape != tuple(shape):
        raise InputError(
            f"depth must be (N, H, W) = {tuple(shape)} like the frames, got shape {array.shape}"
        )
    width, height = layout.native_size
    x0, y0 = layout.offset
    lens = layout.native_camera.valid_mask().cpu().numpy().astype(bool)
    region = (
        lens if native_valid is None else lens & native_valid[y0 : y0 + height, x0 : x0 + width]
    )
    generator = np.random.default_rng(seed)
    targets, known = {}, []
    for frame in frames:
        values = array[frame, y0 : y0 + height, x0 : x0 + width]
        ok = np.isfinite(values) & (values > 0) & region
        rows, cols = np.nonzero(ok)
        known.append(ok.sum() / max(1, lens.sum()))
        if rows.size > MAX_DEPTH_SAMPLES:
            keep = np.sort(generator.choice(rows.size, MAX_DEPTH_SAMPLES, replace=False))
            rows, cols = rows[keep], cols[keep]
        uv = torch.from_numpy(np.stack([cols + x0, rows + y0], axis=1).astype(np.float32))
        uv = to_input_pixels(uv, layout.native_size, (layout.width, layout.height), layout.offset)
        targets[frame] = (uv, torch.from_numpy(values[rows, cols].astype(np.float32)))
    coverage = float(np.mean(known)) if known else 0.0
    if coverage == 0.0:
        raise InputError(
            "depth has no positive, finite value inside the lens on the adaptation frames"
        )
    return targets, {
        "kind": "depth",
        "coverage": round(coverage, 4),
        "dense": coverage > 0.5,
        "frames": len(frames),
    }


def split_segments(frames: Any, depth: Any = None) -> tuple[list[Any], list[Any]] | None:
    """Several segments of one camera, or None when ``frames`` is one segment.

    ``frames`` holds several segments when it is a list or tuple whose items are each a whole
    segment: an (N, H, W, 3) array or tensor, or a ``datasets.Sequence``. A list of (H, W, 3)
    frames stays one segment. ``depth`` is then None (self-supervised) or a list of the same
    length, one (N, H, W) depth per segment.

    Returns:
        ``(segments, depths)`` with ``depths`` a list of None for a self-supervised fit.

    Raises:
        InputError: an empty list, a mix of segments and single frames, or a depth list that does
            not pair one depth with each segment.
    """
    if not isinstance(frames, (list, tuple)) or not frames:
        if isinstance(frames, (list, tuple)):
            raise InputError("frames is an empty list: give at least one segment")
        return None

    def whole(item: Any) -> bool:
        return (hasattr(item, "images") and hasattr(item, "camera")) or np.ndim(item) == 4

    kinds = [whole(item) for item in frames]
    if not any(kinds):
        return None
    if not all(kinds):
        raise InputError(
            "frames mixes whole segments ((N, H, W, 3) arrays or Sequences) with other items; "
            "give one segment, or a list of segments"
        )
    if depth is None:
        return list(frames), [None] * len(frames)
    if not isinstance(depth, (list, tuple)) or len(depth) != len(frames):
        found = f"a list of {len(depth)}" if isinstance(depth, (list, tuple)) else "one array"
        raise InputError(
            f"frames holds {len(frames)} segments, so depth must be a list of {len(frames)} "
            f"(N, H, W) depths, one per segment; found {found}"
        )
    if any(item is None for item in depth):
        raise InputError(
            "depth has None for some segments: a fit is supervised on every segment or on none"
        )
    return list(frames), list(depth)


def _merged(problems: list[AdaptationProblem]) -> AdaptationProblem:
    """One problem from the problems of several segments of one camera.

    Frame indices are renumbered into one range (segment k's frames follow segment k - 1's), so a
    window never spans two segments; layout, valid region, geometry and mask are the first
    segment's (the same camera and mask made them all).
    """
    windows, inputs, static, depth_targets = [], {}, [], {}
    offset = 0
    for problem in problems:
        shifted = {}
        for window in problem.adaptation.windows:
            shifted[id(window)] = dataclasses.replace(
                window, frames=tuple(frame + offset for frame in window.frames)
            )
        windows += [(shifted[id(window)], pairs) for window, pairs in problem.windows]
        inputs.update({frame + offset: image for frame, image in problem.inputs.items()})
        static += [
            tuple(f + offset for f in frames) for frames in problem.adaptation.static_windows
        ]
        if problem.depth_targets is not None:
            depth_targets.update({f + offset: t for f, t in problem.depth_targets.items()})
        offset += problem.segment["n_frames"]
    sets = [problem.adaptation for problem in problems]
    adaptation = AdaptationSet(
        windows=[window for window, _ in windows],
        skipped_static=sum(s.skipped_static for s in sets),
        static_windows=static,
        cache_key=hashlib.sha256("+".join(s.cache_key for s in sets).encode()).hexdigest(),
        from_cache=all(s.from_cache for s in sets),
        settings={**sets[0].settings, "segments": [s.cache_key for s in sets]},
    )
    first = problems[0]
    segment = {
        "segments": [problem.segment for problem in problems],
        "n_frames": offset,
        "width": first.segment["width"],
        "height": first.segment["height"],
        "sequence_id": first.segment.get("sequence_id"),
    }
    if "mask" in first.segment:
        segment["mask"] = first.segment["mask"]
    merged = AdaptationProblem(
        first.layout, adaptation, windows, inputs, first.valid, first.geometry, segment, first.mask
    )
    if first.supervision is not None:
        frames = [problem.supervision["frames"] for problem in problems]
        coverage = sum(
            problem.supervision["coverage"] * n for problem, n in zip(problems, frames, strict=True)
        ) / max(1, sum(frames))
        merged.depth_targets = depth_targets
        merged.supervision = {
            **first.supervision,
            "coverage": round(coverage, 4),
            "dense": coverage > 0.5,
            "frames": sum(frames),
            "segments": len(problems),
        }
    return merged


def prepare_problem(
    camera: Camera,
    frames: Any,
    config: AdaptConfig,
    patch: int = 14,
    mask: Any = None,
    depth: Any = None,
) -> AdaptationProblem:
    """Match, estimate targets (or load them from the cache) and lay the segment out for training.

    ``mask`` (optional, (H, W) like the frames, True where the scene is seen) keeps matches,
    reprojection and smoothness off the pixels it excludes (:func:`scene_mask`). ``depth``
    (optional, (N, H, W) like the frames) switches to the supervised fit (:func:`adapt`).

    ``frames`` may also be a list of segments of the camera (:func:`split_segments`), with
    ``depth`` a list of their depths: each segment gets ``config.n_windows`` windows of its own,
    matched and cached on its own (``config.sequence_id``, when given, gets the suffix ``[k]``),
    and one problem holds them all.
    """
    several = split_segments(frames, depth)
    if several is not None:
        segments, depths = several
        problems = []
        for k, (segment, segment_depth) in enumerate(zip(segments, depths, strict=True)):
            own = (
                config
                if config.sequence_id is None
                else dataclasses.replace(config, sequence_id=f"{config.sequence_id}[{k}]")
            )
            try:
                problems.append(_prepare_one(camera, segment, own, patch, mask, segment_depth))
            except InputError as error:
                raise InputError(f"segment {k} of {len(segments)}: {error}") from error
        return problems[0] if len(problems) == 1 else _merged(problems)
    return _prepare_one(camera, frames, config, patch, mask, depth)


def _prepare_one(
    camera: Camera,
    frames: Any,
    config: AdaptConfig,
    patch: int,
    mask: Any,
    depth: Any,
) -> AdaptationProblem:
    images, segment = _frames_array(frames)
    if (segment["width"], segment["height"]) != (int(camera.width), int(camera.height)):
        raise InputError(
            f"frames are {segment['width']}x{segment['height']} px but the camera is {camera.width}x{camera.height}"
        )
    native_valid = None if mask is None else scene_mask(mask, camera)
    segment["sequence_id"] = config.sequence_id
    if config.input_size is None:
        raise InputError(
            "AdaptConfig.input_size is None (the backbone's own): resolve it with the model first "
            "(adapt() does; registry.native_input_size(model)), or give it"
        )
    layout = input_layout(camera, config.input_size, patch)
    adaptation = prepare_adaptation_set(
        images,
        camera,
        get_matcher(config.matcher, **config.matcher_options),
        n_windows=config.n_windows,
        stride=config.stride,
        cache_dir=config.cache_dir,
        sequence_id=config.sequence_id,
        min_motion_px=config.min_motion_px,
        window_size=config.window_size,
        seed=config.seed,
        valid=native_valid,
    )
    if len(adaptation) == 0:
        raise InputError(
            f"no usable adaptation window: all {adaptation.skipped_static} candidate windows are static "
            f"(mean correspondence displacement below {config.min_motion_px} px)"
        )
    valid = layout.camera.valid_mask().bool()
    native_mask = None
    if native_valid is not None:
        native_mask = layout.native_mask(native_valid)
        valid = valid & layout.mask(native_valid)
        segment["mask"] = {
            "valid_fraction": round(float(native_valid.mean()), 4),
            "sha256": hashlib.sha256(np.packbits(native_valid).tobytes()).hexdigest(),
        }
    used = sorted({frame for window in adaptation.windows for frame in window.frames})
    inputs = dict(zip(used, layout.frames(images[used]), strict=True))
    windows = [(window, _prepare_pairs(window, layout, valid)) for window in adaptation.windows]
    geometry = GeometryCache(layout.native_camera, patch).at(layout.height, layout.width)
    problem = AdaptationProblem(
        layout, adaptation, windows, inputs, valid, geometry, segment, native_mask
    )
    if depth is not None:
        problem.depth_targets, problem.supervision = _depth_targets(
            depth, used, layout, native_valid, tuple(images.shape[:3]), config.seed
        )
    return problem


def with_pose_targets(problem: AdaptationProblem, cam_from_world: Any) -> AdaptationProblem:
    """``problem`` with every pair's pose target replaced by the ground-truth relative pose
    (the pose-oracle fit: the pose term through the network's own pose head, against the truth).

    Args:
        problem: a prepared problem of ONE segment (its windows' frame indices index the poses).
        cam_from_world: (N, 4, 4) ground-truth world-to-camera poses of the segment's frames.

    Returns:
        the same problem (changed in place): ``pair.rotation`` (3, 3) and ``pair.direction`` (3,)
        of every pair, float64; a pair whose frames did not move keeps no target (None).

    Raises:
        InputError: poses of the wrong shape or count, or not finite.
    """
    from raytun3r_plugin.poses import relative_pose

    poses = torch.as_tensor(np.asarray(cam_from_world), dtype=torch.float64)
    used = max((frame for window, _ in problem.windows for frame in window.frames), default=-1)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or poses.shape[0] <= used:
        raise InputError(
            f"poses must be (N, 4, 4) cam_from_world for the segment's frames (at least "
            f"{used + 1}), got shape {tuple(poses.shape)}"
        )
    if not bool(torch.isfinite(poses).all()):
        raise InputError("poses hold values that are not finite")
    for window, pairs in problem.windows:
        for pair in pairs:
            relative = relative_pose(poses, window.frames[pair.a], window.frames[pair.b])
            length = float(relative[:3, 3].norm())
            pair.rotation = relative[:3, :3].clone() if length > 0 else None
            pair.direction = relative[:3, 3] / length if length > 0 else None
    problem.supervision = {"kind": "poses", "frames": int(poses.shape[0])}
    return problem
