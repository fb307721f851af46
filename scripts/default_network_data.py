"""The training data of the built-in networks (``scripts/train_default_network.py``): procedural
pinhole renders, their sequences and seeds, view rotations and batches."""

from __future__ import annotations

import json
import math
import time
import warnings
from pathlib import Path

import numpy as np
import torch


def log(msg: str) -> None:
    print(time.strftime("%H:%M:%S"), msg, flush=True)


# ----------------------------------------------------------------------------------------------
# Data
# ----------------------------------------------------------------------------------------------


def pinhole_camera(size: int, fov_deg: float):
    """Square pinhole camera of ``size`` px with horizontal = vertical field of view ``fov_deg``."""
    from raytun3r_plugin.cameras import Pinhole

    f = (size / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    c = (size - 1) / 2.0  # pixel centres at integers (docs/conventions.md section 2)
    return Pinhole(size, size, {"fx": f, "fy": f, "cx": c, "cy": c})


def sequence_spec(seed: int, outdoor_fraction: float = 0.3) -> dict:
    """Deterministic rendering parameters of scene ``seed``."""
    rng = np.random.default_rng([int(seed), 77])
    return {
        "kind": "outdoor" if rng.uniform() < outdoor_fraction else "indoor",
        "fov": float(rng.uniform(50.0, 90.0)),
        "flow_px": float(rng.uniform(6.0, 14.0)),
    }


def jitter_rotations(seed: int, n: int, std_deg: float) -> np.ndarray:
    """(n, 3, 3) random rotations: axis-angle vectors with i.i.d. N(0, ``std_deg``) components."""
    from raytun3r_plugin.poses import rotations_from_rotvecs

    rng = np.random.default_rng([int(seed), 91])
    return rotations_from_rotvecs(np.deg2rad(rng.normal(0.0, std_deg, size=(n, 3))))


def render_one(seed: int, size: int, n_frames: int, jitter_deg: float = 0.0) -> dict:
    """One pinhole sequence as plain arrays (images uint8, z-depth with 0 = invalid/sky).

    ``jitter_deg`` > 0 rotates every camera about its own centre by a random rotation
    (:func:`jitter_rotations`) after the trajectory is made: the scene is built around the same
    camera path, and relative rotations between frames become larger than the smooth
    hand-held/driving paths give (a few degrees), which is what the pose head must learn.
    """
    spec = sequence_spec(seed)
    cam = pinhole_camera(size, spec["fov"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if jitter_deg <= 0:
            from raytun3r_plugin.synthetic import render_sequence

            seq = render_sequence(
                spec["kind"],
                cam,
                n_frames=n_frames,
                seed=seed,
                flow_px=spec["flow_px"],
                supersample=2,
            )
            z = seq.meta["per_frame"]["z_depth"].astype(np.float32)
            valid = seq.mask & ~seq.meta["per_frame"]["sky"] & (z > 0)
            rgb, poses = seq.images, seq.cam_from_world
        else:
            from raytun3r_plugin.synthetic.generate import camera_centres, make_trajectory
            from raytun3r_plugin.synthetic.render import Renderer
            from raytun3r_plugin.synthetic.scene import make_scene

            motion = "handheld" if spec["kind"] == "indoor" else "driving"
            poses, _ = make_trajectory(spec["kind"], motion, cam, n_frames, seed, spec["flow_px"])
            scene = make_scene(spec["kind"], seed, camera_centres(poses))  # path before jitter
            poses = poses.copy()
            # [R | t] -> [J R | J t] keeps the centre -R^T t: a rotation about the camera itself
            poses[:, :3, :] = np.einsum(
                "nij,njk->nik", jitter_rotations(seed, n_frames, jitter_deg), poses[:, :3, :]
            )
            renderer = Renderer(cam, supersample=2, adaptive=True, num_threads=1)
            frames = [renderer.render(scene, poses[k]) for k in range(n_frames)]
            rgb = np.stack([f.rgb for f in frames])
            z = np.stack([f.z_depth for f in frames]).astype(np.float32)
            valid = np.stack([f.valid & ~f.sky for f in frames]) & (z > 0)
    return {
        "images": np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8),
        "depth": np.where(valid, z, 0.0).astype(np.float32),
        "poses": np.asarray(poses, dtype=np.float64),
        "fov": spec["fov"],
    }


def jittered(seed: int, jitter_frac: float) -> bool:
    """Whether training sequence ``seed`` gets rotation jitter (a fixed draw per seed)."""
    return bool(jitter_frac > 0 and np.random.default_rng([int(seed), 13]).uniform() < jitter_frac)


def build_dataset(
    path: Path,
    n_seq: int,
    size: int,
    n_frames: int,
    seed_base: int,
    jitter_frac: float = 0.0,
    jitter_deg: float = 0.0,
) -> dict:
    """Render ``n_seq`` sequences (or read the cached file when it matches).

    A fraction ``jitter_frac`` of them (drawn per seed by :func:`jittered`) is rendered with a
    per-frame rotation jitter of ``jitter_deg`` degrees (std per axis).
    """
    meta = {
        "n_seq": n_seq,
        "size": size,
        "n_frames": n_frames,
        "seed_base": seed_base,
        "version": 1,
    }
    if jitter_frac > 0 and jitter_deg > 0:  # keys only when used: older caches stay valid
        meta.update(jitter_frac=jitter_frac, jitter_deg=jitter_deg)
    else:
        jitter_frac = 0.0
    if path.is_file():
        with np.load(path, allow_pickle=False) as data:
            if json.loads(str(data["meta"])) == meta:
                log(f"training set: cached {path}")
                return {k: data[k] for k in ("images", "depth", "poses", "fov")}
    log(f"rendering {n_seq} sequences x {n_frames} frames at {size} px ...")
    t0 = time.time()
    images = np.zeros((n_seq, n_frames, size, size, 3), np.uint8)
    depth = np.zeros((n_seq, n_frames, size, size), np.float32)
    poses = np.zeros((n_seq, n_frames, 4, 4), np.float64)
    fov = np.zeros(n_seq, np.float64)
    for k in range(n_seq):
        seed = seed_base + k
        r = render_one(seed, size, n_frames, jitter_deg if jittered(seed, jitter_frac) else 0.0)
        images[k], depth[k], poses[k], fov[k] = r["images"], r["depth"], r["poses"], r["fov"]
        if (k + 1) % 50 == 0:
            log(f"  rendered {k + 1}/{n_seq} ({time.time() - t0:.0f} s)")
    from raytun3r_plugin.atomic_files import atomic_path

    # A file handle, not a name: np.savez appends ".npz" to a name that lacks it.
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        np.savez(
            handle,
            images=images,
            depth=depth,
            poses=poses,
            fov=fov,
            meta=np.array(json.dumps(meta)),
        )
    log(f"training set rendered in {time.time() - t0:.0f} s -> {path}")
    return {"images": images, "depth": depth, "poses": poses, "fov": fov}


_FLIP = np.diag([-1.0, 1.0, 1.0, 1.0])


def rotate_views(
    im: np.ndarray, de: np.ndarray, po: np.ndarray, fov_deg: float, rots: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Re-render the views of one sample as if each camera were turned by ``rots[s]``.

    A rotation about the camera centre maps a pinhole image to a pinhole image exactly (the
    homography ``K' R K^-1``), so new views with known poses need no re-rendering. The new
    views share one zoom ``z`` >= 1 (focal ``z f``), the smallest on a 0.02 grid that keeps every
    new pixel inside the old image: no border appears, which would give the rotation away.

    Args:
        im: (S, H, W, 3) float images; de: (S, H, W) z-depth (0 = invalid); po: (S, 4, 4)
        cam_from_world; fov_deg: the square pinhole's field of view; rots: (S, 3, 3).

    Returns:
        (images, z-depth, cam_from_world, fov_deg) of the rotated views, or None when no zoom
        up to 2 avoids a border.
    """
    S, H, W = de.shape
    f = (W / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    cx, cy = (W - 1) / 2.0, (H - 1) / 2.0

    def source(u: np.ndarray, v: np.ndarray, z: float, R: np.ndarray):
        d_new = np.stack([(u - cx) / (z * f), (v - cy) / (z * f), np.ones_like(u)], -1)
        d = d_new @ R  # R^T d' as row vectors: the ray in the old camera
        return f * d[..., 0] / d[..., 2] + cx, f * d[..., 1] / d[..., 2] + cy, d[..., 2]

    corners_u, corners_v = np.array([0.0, W - 1, 0.0, W - 1]), np.array([0.0, 0.0, H - 1, H - 1])
    zoom = None
    for z in np.arange(1.0, 2.0001, 0.02):
        ok = True
        for R in rots:
            su, sv, dz = source(corners_u, corners_v, float(z), R)
            ok &= bool((dz > 0).all() and (su >= 0).all() and (su <= W - 1).all())
            ok &= bool((sv >= 0).all() and (sv <= H - 1).all())
        if ok:
            zoom = float(z)
            break
    if zoom is None:
        return None
    vv, uu = np.meshgrid(
        np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij"
    )
    out_im, out_de = np.empty_like(im), np.empty_like(de)
    for k, R in enumerate(rots):
        su, sv, dz = source(uu, vv, zoom, R)
        # grid_sample with align_corners=True: -1 and 1 are the centres of the edge pixels
        grid = torch.from_numpy(np.stack([su / (W - 1) * 2 - 1, sv / (H - 1) * 2 - 1], -1))[None]
        img = torch.from_numpy(np.ascontiguousarray(im[k])).permute(2, 0, 1)[None]
        out_im[k] = (
            torch.nn.functional.grid_sample(img, grid.float(), "bilinear", align_corners=True)[0]
            .permute(1, 2, 0)
            .numpy()
        )
        dep = torch.from_numpy(np.ascontiguousarray(de[k]))[None, None]
        z_old = torch.nn.functional.grid_sample(dep, grid.float(), "nearest", align_corners=True)
        # the same point in the turned camera: z' = z * d'_z / d_z with d'_z = 1
        out_de[k] = (z_old[0, 0].double().numpy() / dz).astype(de.dtype)
    turn = np.tile(np.eye(4), (S, 1, 1))
    turn[:, :3, :3] = rots
    fov_new = math.degrees(2.0 * math.atan((W / 2.0) / (zoom * f)))
    return out_im, out_de, turn @ po, fov_new


def make_batch(
    data: dict,
    seed: int,
    step: int,
    batch: int,
    views: int,
    max_gap: int,
    rot_aug_deg: float = 0.0,
    rot_aug_frac: float = 0.0,
) -> dict:
    """Batch ``step``: ``batch`` samples of ``views`` frames each (a pure function of seed, step).

    Each sample: a random sequence, an ordered frame subset (gaps 1..max_gap, random direction),
    random horizontal flip (pose conjugated by diag(-1, 1, 1)) and a mild colour jitter. With
    ``rot_aug_deg`` > 0, a fraction ``rot_aug_frac`` of the samples has every view turned by its
    own random rotation (std ``rot_aug_deg`` per axis, :func:`rotate_views`): relative rotations
    then no longer follow from the scene, which a network can otherwise memorise.
    """
    rng = np.random.default_rng([int(seed), int(step), 5])
    n_seq, n_frames, size = data["images"].shape[:3]
    imgs, deps, poses, fovs = [], [], [], []
    for _ in range(batch):
        s = int(rng.integers(n_seq))
        idx = [int(rng.integers(n_frames))]
        direction = 1 if rng.uniform() < 0.5 else -1
        for _v in range(views - 1):
            nxt = idx[-1] + direction * int(rng.integers(1, max_gap + 1))
            if not 0 <= nxt < n_frames:
                direction = -direction
                nxt = idx[-1] + direction * int(rng.integers(1, max_gap + 1))
                nxt = int(np.clip(nxt, 0, n_frames - 1))
            idx.append(nxt)
        im = data["images"][s, idx].astype(np.float32) / 255.0
        de = data["depth"][s, idx]
        po = data["poses"][s, idx]
        if rng.uniform() < 0.5:
            im, de = im[:, :, ::-1], de[:, :, ::-1]
            po = _FLIP @ po @ _FLIP
        fov = float(data["fov"][s])
        if rot_aug_deg > 0 and rng.uniform() < rot_aug_frac:
            from raytun3r_plugin.poses import rotations_from_rotvecs

            vec = np.deg2rad(rng.normal(0.0, rot_aug_deg, size=(views, 3)))
            turned = rotate_views(im, de, po, fov, rotations_from_rotvecs(vec))
            if turned is not None:
                im, de, po, fov = turned
        gain = rng.uniform(0.8, 1.2, size=3).astype(np.float32)
        bias = np.float32(rng.uniform(-0.05, 0.05))
        im = np.clip(im * gain + bias, 0.0, 1.0)
        imgs.append(np.ascontiguousarray(im))
        deps.append(np.ascontiguousarray(de))
        poses.append(po)
        fovs.append(fov)
    return {
        "images": torch.from_numpy(np.stack(imgs)).permute(0, 1, 4, 2, 3).contiguous(),  # B,S,3,H,W
        "depth": torch.from_numpy(np.stack(deps)),  # B,S,H,W z-depth, 0 = invalid
        "cam_from_world": torch.from_numpy(np.stack(poses)),  # B,S,4,4 float64
        "fov": torch.tensor(fovs, dtype=torch.float64),  # B
    }
