"""Synthetic sequences: trajectory + procedural scene + rendering, deterministic for a seed."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from raytun3r_plugin.datasets.sequence import Sequence
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.poses import relative_pose
from raytun3r_plugin.synthetic.render import Renderer
from raytun3r_plugin.synthetic.scene import Scene, make_scene
from raytun3r_plugin.synthetic.trajectory import (
    calibrate_step,
    driving_trajectory,
    handheld_trajectory,
)

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

__all__ = [
    "FLOW_PX",
    "camera_centres",
    "make_trajectory",
    "median_flow",
    "render_rig",
    "render_sequence",
    "scene_of",
]

# Typical scene range (m) at which the apparent motion of a trajectory is measured.
_DEPTH_SCALE = {"indoor": 2.5, "outdoor": 16.0}


#: Default median apparent motion between consecutive frames (px) that the renderer chooses its
#: time step for; the benchmark renders with it. A render at another size keeps the same camera
#: path with ``FLOW_PX * size / 112`` (112 px being the benchmark's input).
FLOW_PX = 6.0


def camera_centres(cam_from_world: np.ndarray) -> np.ndarray:
    """Camera centres in the world (N, 3) from ``cam_from_world`` (N, 4, 4)."""
    R = cam_from_world[:, :3, :3]
    return -np.einsum("nji,nj->ni", R, cam_from_world[:, :3, 3])


def median_flow(
    camera: Camera, cam_from_world: np.ndarray, depth: float, n_rays: int = 256
) -> float:
    """Median image motion (pixels) between consecutive poses of points at range ``depth`` (m)
    along ``n_rays`` rays spread over the camera's valid region (a scene-independent estimate
    of the optical flow of a trajectory)."""
    rays, valid = camera.ray_table(dtype=torch.float64)
    rays = rays.detach().cpu().numpy().reshape(-1, 3)
    ok = np.flatnonzero(valid.detach().cpu().numpy().reshape(-1))
    if ok.size == 0 or cam_from_world.shape[0] < 2:
        return 0.0
    pick = ok[np.linspace(0, ok.size - 1, min(n_rays, ok.size)).astype(np.int64)]
    X = depth * rays[pick]
    uv0, ok0 = camera.project(torch.from_numpy(X))
    uv0 = uv0.detach().cpu().numpy()
    meds = []
    for k in range(cam_from_world.shape[0] - 1):
        T = relative_pose(cam_from_world, k, k + 1)
        uv1, ok1 = camera.project(torch.from_numpy(X @ T[:3, :3].T + T[:3, 3]))
        m = (ok0 & ok1).detach().cpu().numpy()
        if m.any():
            meds.append(
                float(np.median(np.linalg.norm(uv1.detach().cpu().numpy()[m] - uv0[m], axis=1)))
            )
    return float(np.median(meds)) if meds else 0.0


def make_trajectory(
    kind: str, motion: str, camera: Camera, n_frames: int, seed: int, flow_px: float = FLOW_PX
) -> tuple[np.ndarray, float]:
    """Poses (N, 4, 4) for ``motion`` ("handheld" | "driving") in a ``kind`` scene, with the
    time step chosen so the median apparent motion between frames is about ``flow_px`` pixels.
    Returns ``(cam_from_world, step)``."""
    if motion == "handheld":
        if kind == "indoor":
            kw = {"center": (0.0, -1.5, 0.0), "amplitude": (1.2, 0.2, 1.5)}
        else:
            kw = {"center": (0.0, -1.6, 0.0), "amplitude": (2.0, 0.2, 3.0)}

        def make(n: int, step: float) -> np.ndarray:
            return handheld_trajectory(n, seed, step=step, **kw)
    elif motion == "driving":
        start = (0.0, -1.3, -3.0) if kind == "indoor" else (2.0, -1.6, 0.0)

        def make(n: int, step: float) -> np.ndarray:
            return driving_trajectory(n, seed, step=step, start=start)
    else:
        raise InputError(f"unknown motion {motion!r}; expected 'handheld' or 'driving'")
    depth = _DEPTH_SCALE[kind]
    step = calibrate_step(make, n_frames, lambda poses: median_flow(camera, poses, depth), flow_px)
    return make(n_frames, step), step


def scene_of(seq: Sequence) -> Scene:
    """The analytic scene of a synthetic sequence (rebuilt from its generator parameters and
    camera path when it is not held in ``seq.meta["scene"]``)."""
    scene = seq.meta.get("scene")
    if isinstance(scene, Scene):
        return scene
    gen = seq.meta.get("synthetic")
    if not gen or seq.cam_from_world is None:
        raise InputError(f"sequence {seq.name!r} is not a raytun3r synthetic sequence")
    path = np.asarray(gen.get("path", camera_centres(seq.cam_from_world)), dtype=np.float64)
    scene = make_scene(gen["kind"], int(gen["seed"]), path)
    seq.meta["scene"] = scene
    return scene


def render_sequence(
    kind: str,
    camera: Camera,
    n_frames: int = 10,
    seed: int = 0,
    motion: str | None = None,
    *,
    flow_px: float = FLOW_PX,
    supersample: int = 2,
    adaptive: bool = True,
    fps: float = 10.0,
    name: str | None = None,
    num_threads: int | None = 1,
) -> Sequence:
    """Render a synthetic sequence.

    Args:
        kind: "indoor" (furnished room) or "outdoor" (street).
        camera: any ``raytun3r_plugin.cameras`` model (FoV beyond 180 degrees is fine).
        n_frames: number of frames.
        seed: seed of scene and trajectory (same seed and arguments -> identical output).
        motion: "handheld", "driving" or None (handheld indoors, driving outdoors).
        flow_px: target median apparent motion between consecutive frames, in pixels.
        supersample: sub-pixel rays per axis at edges (see :class:`Renderer`).
        adaptive: supersample only edge pixels (default) or every pixel.
        fps: frame rate used for ``timestamps`` (k / fps seconds).
        name: sequence name (default ``synthetic-<kind>-<motion>-s<seed>``).
        num_threads: torch threads while rendering (see :class:`Renderer`; default 1).

    Returns:
        A :class:`Sequence` with ``images`` (N, H, W, 3) float32, ``depth`` (N, H, W) float32
        range (metres along the ray, 0 = invalid), ``mask`` (N, H, W) lens-valid & hit,
        ``cam_from_world`` (N, 4, 4) and ``meta`` holding the scene object (``"scene"``), the
        generator parameters and camera path (``"synthetic"``) and, under ``"per_frame"``,
        z-depth (``"z_depth"``, N x H x W float32) and sky masks (``"sky"``, N x H x W bool).
    """
    if kind not in _DEPTH_SCALE:
        raise InputError(f"unknown scene kind {kind!r}; expected 'indoor' or 'outdoor'")
    if n_frames < 1:
        raise InputError("n_frames must be >= 1")
    motion = motion or ("handheld" if kind == "indoor" else "driving")
    poses, step = make_trajectory(kind, motion, camera, n_frames, seed, flow_px)
    path = camera_centres(poses)
    scene = make_scene(kind, seed, path)
    seq = _render_path(
        kind,
        camera,
        poses,
        scene,
        supersample=supersample,
        adaptive=adaptive,
        fps=fps,
        num_threads=num_threads,
    )
    seq.name = name or f"synthetic-{kind}-{motion}-s{seed}"
    rendered = seq.meta["synthetic"]
    seq.meta["synthetic"] = {
        "kind": kind,
        "seed": int(seed),
        "motion": motion,
        "flow_px": float(flow_px),
        "step": float(step),
        **{key: rendered[key] for key in ("supersample", "adaptive", "fps", "path")},
    }
    return seq


def _render_path(
    kind: str,
    camera: Camera,
    poses: np.ndarray,
    scene: Scene,
    *,
    supersample: int = 2,
    adaptive: bool = True,
    fps: float = 10.0,
    num_threads: int | None = 1,
) -> Sequence:
    """Render ``scene`` from the (N, 4, 4) ``cam_from_world`` poses: a :class:`Sequence`."""
    n_frames = len(poses)
    renderer = Renderer(camera, supersample=supersample, adaptive=adaptive, num_threads=num_threads)
    h, w = int(camera.height), int(camera.width)
    images = np.zeros((n_frames, h, w, 3), dtype=np.float32)
    depth = np.zeros((n_frames, h, w), dtype=np.float32)
    zdepth = np.zeros((n_frames, h, w), dtype=np.float32)
    mask = np.zeros((n_frames, h, w), dtype=bool)
    sky = np.zeros((n_frames, h, w), dtype=bool)
    for k in range(n_frames):
        f = renderer.render(scene, poses[k])
        images[k], depth[k], zdepth[k], mask[k], sky[k] = f.rgb, f.range, f.z_depth, f.valid, f.sky
    gen = {
        "kind": kind,
        "supersample": int(supersample),
        "adaptive": bool(adaptive),
        "fps": float(fps),
        "path": camera_centres(poses).tolist(),
    }
    return Sequence(
        name=f"synthetic-{kind}",
        camera=camera,
        timestamps=np.arange(n_frames, dtype=np.float64) / float(fps),
        cam_from_world=poses,
        images=images,
        depth=depth,
        depth_kind="range",
        mask=mask,
        meta={"synthetic": gen, "scene": scene, "per_frame": {"z_depth": zdepth, "sky": sky}},
    )


def stereo_extrinsics(baseline_m: float = 0.1, toe_out_deg: float = 0.0) -> dict[str, np.ndarray]:
    """``cam_from_rig`` of a forward-looking stereo pair: ``"left"`` (the reference) and
    ``"right"``, ``baseline_m`` to its right (+x), each turned outwards by ``toe_out_deg``
    about the vertical (y) axis (0: parallel optical axes)."""
    angle = np.radians(toe_out_deg)
    right = np.eye(4)
    right[:3, :3] = np.array(
        [[np.cos(angle), 0.0, -np.sin(angle)], [0.0, 1.0, 0.0], [np.sin(angle), 0.0, np.cos(angle)]]
    )
    # rig -> right camera: the right camera's centre is at +baseline on the rig's x axis.
    right[:3, 3] = -right[:3, :3] @ np.array([baseline_m, 0.0, 0.0])
    return {"left": np.eye(4), "right": right}


def render_rig(
    kind: str,
    cameras: Mapping[str, Camera],
    cam_from_rig: Mapping[str, np.ndarray] | None = None,
    n_frames: int = 10,
    seed: int = 0,
    motion: str | None = None,
    **kwargs: Any,
):
    """Render a synthetic multi-camera rig: every camera sees one scene at the same instants.

    Args:
        kind, n_frames, seed, motion: as :func:`render_sequence`; the trajectory is the
            reference (first) camera's, planned for its lens.
        cameras: camera name -> camera; the first is the rig's reference (its frame is the
            rig frame). All need one image size (:meth:`Rig.views`).
        cam_from_rig: camera name -> (4, 4) rig-to-camera transform (default: a
            :func:`stereo_extrinsics` pair for two cameras named ``"left"`` and ``"right"``).
        kwargs: ``flow_px``, ``supersample``, ``adaptive``, ``fps``, ``num_threads`` as
            :func:`render_sequence`.

    Returns:
        A :class:`~raytun3r_plugin.datasets.rig.Rig` whose sequences carry images, range depth,
        masks and ground-truth poses ``cam_from_rig[c] @ rig_from_world``, with the scene in
        every sequence's ``meta`` (``scene_of`` works on each).
    """
    from raytun3r_plugin.datasets.rig import Rig

    if not cameras:
        raise InputError("render_rig needs at least one camera")
    names = list(cameras)
    if cam_from_rig is None:
        if names != ["left", "right"]:
            raise InputError(
                "give cam_from_rig for every camera (the default is the stereo pair 'left', 'right')"
            )
        cam_from_rig = stereo_extrinsics()
    missing = [name for name in names if name not in cam_from_rig]
    if missing:
        raise InputError(f"render_rig: no cam_from_rig for {missing}")
    sizes = {(int(c.width), int(c.height)) for c in cameras.values()}
    if len(sizes) != 1:
        raise InputError(f"render_rig: the cameras need one image size, got {sorted(sizes)}")
    if kind not in _DEPTH_SCALE:
        raise InputError(f"unknown scene kind {kind!r}; expected 'indoor' or 'outdoor'")
    motion = motion or ("handheld" if kind == "indoor" else "driving")
    flow_px = float(kwargs.pop("flow_px", 6.0))
    fps = float(kwargs.pop("fps", 10.0))
    reference = cameras[names[0]]
    rig_from_world, step = make_trajectory(kind, motion, reference, n_frames, seed, flow_px)
    poses = {
        name: np.asarray(cam_from_rig[name], dtype=np.float64)[None] @ rig_from_world
        for name in names
    }
    # One scene for the whole rig, kept clear of every camera's path; each sequence records
    # that joint path, so scene_of() rebuilds the same scene from any of them.
    path = np.concatenate([camera_centres(p) for p in poses.values()])
    scene = make_scene(kind, seed, path)
    sequences = {}
    for name in names:
        seq = _render_path(kind, cameras[name], poses[name], scene, fps=fps, **kwargs)
        seq.name = f"synthetic-rig-{kind}-{motion}-s{seed}/{name}"
        rendered = seq.meta["synthetic"]
        seq.meta["synthetic"] = {
            "kind": kind,
            "seed": int(seed),
            "motion": motion,
            "flow_px": flow_px,
            "step": float(step),
            **{key: rendered[key] for key in ("supersample", "adaptive", "fps")},
            "path": path.tolist(),
            "rig_camera": name,
        }
        sequences[name] = seq
    extrinsics = {name: np.asarray(cam_from_rig[name], dtype=np.float64) for name in names}
    return Rig(
        f"synthetic-rig-{kind}-{motion}-s{seed}",
        sequences,
        extrinsics,
        {"synthetic": {"kind": kind, "seed": int(seed), "motion": motion, "step": float(step)}},
    )
