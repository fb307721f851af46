#!/usr/bin/env python
"""Train raytun3r's built-in default network ``raytun3r-da3-tiny`` from scratch (issue 7).

A small ``DepthAnything3Net`` made of the real ``depth_anything_3`` classes
(``raytun3r_plugin.patches.da3.build_tiny_network``) is trained on procedurally rendered
PINHOLE sequences only (fields of view 50-90 degrees, indoor rooms and outdoor streets from
``raytun3r_plugin.synthetic``), so it carries exactly the pinhole bias raytun3r is meant to remove.

Supervision (all in the frame of the first view of a sample, DA3's convention):

* depth: z-depth (upstream's pinhole convention), normalised per sample by the median valid
  z-depth of the first view; loss = scale-invariant L1 of log depth + 0.25 x plain L1 of log
  depth (keeps the normalised scale, which the translations share) + a small aleatoric term
  that trains ``depth_conf``. Sky pixels are excluded;
* rays: DualDPT's auxiliary 6-channel ray map (direction ``R_c2w K^-1 (u, v, 1)`` and camera
  centre, both in the first view's frame; translation in the normalised scale), L1;
* pose: the camera decoder's 9-number encoding (translation, quaternion, field of view) decoded
  with DA3's own ``pose_encoding_to_extri_intri``: chordal rotation loss, L1 translation, L1 fov,
  plus (``--w-quat``) an L1 loss on the raw quaternion, which keeps its norm at 1.

Optional training-only auxiliaries and recipes (issue 13; all off by default):

* ``--aux-flow W``: a dense token-flow head on the tokens of the cross-view (global-attention)
  blocks, supervised with ground-truth correspondences from the renderer (for every patch token
  of a view, where its centre lands in the partner view, from GT z-depth + GT relative pose +
  camera). The global blocks carry no relative position (RoPE is zeroed there), so the camera
  decoder gets no gradient towards cross-view matching until some matching exists; this head
  provides it. The head lives outside the network (``<out>/aux.safetensors``) and is never
  exported, so the shipped architecture is unchanged;
* ``--aux-attn W``: a cross-entropy on the global blocks' own attention logits (queries and
  keys recomputed with the block's weights), pushing each patch token to attend to its true
  match in the partner view; no parameters, nothing to export. With ``--aux-flow`` this is what
  took the camera decoder's rotation off chance (docs/model_card_raytun3r_da3_tiny.md, "Issue 13");
* ``--rot-aug-deg D --rot-aug-frac F``: turn every view of a fraction F of the samples by its
  own random rotation, by the exact pinhole homography (zoomed so no border shows);
* ``--w-tdir W``: a translation-direction loss (1 - cosine) of the camera decoder;
* ``--pose-only``: run only the backbone and the camera decoder (no DPT head, no depth/ray
  losses): about 5x cheaper per step, for pose pre-training before a joint run (``--init``);
* ``--jitter-frac F --jitter-deg D``: render a fraction F of the training sequences with an extra
  random rotation (std D degrees per axis) per frame, so relative rotations are larger and varied;
* ``--val-seqs N``: render N validation sequences (seeds ``VAL_SEED_BASE`` ..; disjoint from the
  training seeds and from the held-out seeds 500-523 of ``scripts/eval_default_network.py``) and
  log their pair (k, k + 2) rotation ratio, translation-direction error and depth AbsRel every
  ``--val-every`` steps in ``log.csv``;
* ``--device``: torch device (``cpu`` default).

``--pe-std`` starts the absolute PE table as a low-frequency 2D sin-cos map instead of DA3's
zeros (or the builder's tiny random init): a network trained from scratch otherwise learns to
ignore absolute position, and then the PE adapter has nothing to act on
(``experiments/leverage.py`` measures this).

Phases: (1) render a training set into ``<out>/train_data.npz`` (re-used when it exists and
matches the arguments), (2) train. Every batch is a pure function of (seed, step), so a run is
deterministic for a seed and resuming from a checkpoint gives the same result as not stopping.
Checkpoints: ``<out>/checkpoint.safetensors`` (weights), ``<out>/optimizer.safetensors``
(AdamW moments) and ``<out>/checkpoint.json`` (step, arguments, optimizer hyper-parameters);
nothing is ever unpickled. Progress goes to ``<out>/log.csv`` (one row per logged step).

Example (the shipped run, see docs/model_card_raytun3r_da3_tiny.md)::

    python scripts/train_default_network.py --out runs/da3_tiny --n-seq 300 --steps 6000 \
        --warmup 100 --w-pose 2 --w-quat 10 --pe-std 0.5 --threads 1 --ckpt-every 200 \
        --log-every 50 --export raytun3r_plugin/data/raytun3r-da3-tiny.safetensors
    (the same command again resumes an interrupted run from its last checkpoint)

Smoke test::

    python scripts/train_default_network.py --out /tmp/smoke --steps 2 --tiny
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

TRAIN_SEED_BASE = (
    10_000  # training scenes use seeds TRAIN_SEED_BASE + k; held-out ones are below 10_000
)
# Validation scenes logged during training (--val-seqs): below TRAIN_SEED_BASE and disjoint from
# the held-out seeds 500-523 that scripts/eval_default_network.py reports, so recipes are chosen
# on these and the held-out numbers stay untouched by the choice.
VAL_SEED_BASE = 600
VAL_GAP = 2  # pairs (k, k + VAL_GAP), as in the held-out evaluation
MODEL_KWARGS = dict(
    embed_dim=128,
    depth=6,
    num_heads=4,
    alt_start=2,
    out_layers=[2, 3, 4, 5],
    head_features=32,
    head_channels=[16, 32, 64, 64],
    camera_encoder=False,  # the encoder of known poses: training never passes any
    seed=0,
)
TINY_KWARGS = dict(
    embed_dim=32,
    depth=4,
    num_heads=2,
    alt_start=2,
    out_layers=[0, 1, 2, 3],
    head_features=8,
    head_channels=[8, 8, 16, 16],
    camera_encoder=False,
    seed=0,
)


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
    from raytun3r_plugin._io import atomic_path

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


# ----------------------------------------------------------------------------------------------
# Targets and losses
# ----------------------------------------------------------------------------------------------


def relative_c2w(cam_from_world: torch.Tensor) -> torch.Tensor:
    """``world_from_cam`` of every view with the world = the first view: ``T_0 inv(T_k)``."""
    inv = torch.linalg.inv(cam_from_world)
    return cam_from_world[:, :1] @ inv


def targets(batch: dict) -> dict:
    """Normalised depth, c2w poses (first view = identity) and ray maps for a batch."""
    depth = batch["depth"].float()
    B, S, H, W = depth.shape
    valid = depth > 0
    scale = torch.stack(
        [
            depth[b, 0][valid[b, 0]].median() if valid[b, 0].any() else depth.new_tensor(1.0)
            for b in range(B)
        ]
    ).clamp(min=1e-3)
    c2w = relative_c2w(batch["cam_from_world"])  # float64
    c2w[..., :3, 3] /= scale.double()[:, None, None]
    fov = torch.deg2rad(batch["fov"])
    focal = (W / 2.0) / torch.tan(fov / 2.0)
    return {
        "depth": depth / scale[:, None, None, None],
        "valid": valid,
        "c2w": c2w.float(),
        "fov": fov.float(),
        "focal": focal.float(),
        "scale": scale,
    }


def ray_targets(tg: dict, h_r: int, w_r: int, H: int, W: int) -> torch.Tensor:
    """(B, S, h_r, w_r, 6): world (= first view) direction ``R K^-1 (u, v, 1)`` and centre."""
    c2w, f = tg["c2w"], tg["focal"]
    dev = c2w.device
    u = (torch.arange(w_r, dtype=torch.float32, device=dev) + 0.5) * (W / w_r) - 0.5
    v = (torch.arange(h_r, dtype=torch.float32, device=dev) + 0.5) * (H / h_r) - 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    cx, cy = (W - 1) / 2.0, (H - 1) / 2.0
    fb = f[:, None, None]
    x, y = (uu - cx) / fb, (vv - cy) / fb  # B,h,w
    d_cam = torch.stack([x, y, torch.ones_like(x)], -1)  # B,h,w,3
    R = c2w[..., :3, :3]  # B,S,3,3
    d = torch.einsum("bsij,bhwj->bshwi", R, d_cam)
    o = c2w[..., :3, 3][:, :, None, None, :].expand_as(d)
    return torch.cat([d, o], -1)


def partner_views(S: int) -> list[int]:
    """The view each view's tokens are matched into: 0 <-> 1, every later view -> 0."""
    return [1] + [0] * (S - 1)


def flow_targets(batch: dict, patch: int = 14) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the centre of every patch token lands in its partner view (:func:`partner_views`).

    From the GT z-depth at the patch centre (mean of the central 2 x 2 pixels, all valid), the
    GT relative pose and the centred pinhole of the batch (``fov``). Occlusion is not tested.

    Returns:
        flow (B, S, h * w, 2) float32: displacement (u_b - u_a, v_b - v_a) in units of half the
        image width; valid (B, S, h * w) bool: depth known, in front of and inside the partner.
    """
    depth = batch["depth"].double()
    B, S, H, W = depth.shape
    h, w = H // patch, W // patch
    mid = patch // 2
    z4 = depth[:, :, : h * patch, : w * patch].reshape(B, S, h, patch, w, patch)
    z4 = z4[:, :, :, mid - 1 : mid + 1, :, mid - 1 : mid + 1]
    ok = (z4 > 0).all(dim=3).all(dim=-1)  # B,S,h,w
    z = z4.mean(dim=(3, 5))
    f = ((W / 2.0) / torch.tan(torch.deg2rad(batch["fov"].double()) / 2.0))[:, None, None, None]
    cx, cy = (W - 1) / 2.0, (H - 1) / 2.0
    u = (torch.arange(w, dtype=torch.float64) * patch + (patch - 1) / 2.0)[None, None, None, :]
    v = (torch.arange(h, dtype=torch.float64) * patch + (patch - 1) / 2.0)[None, None, :, None]
    X = torch.stack([(u - cx) / f * z, (v - cy) / f * z, z], -1)  # B,S,h,w,3 in view a
    P = batch["cam_from_world"].double()
    P_b = P[:, partner_views(S)]
    T = P_b @ torch.linalg.inv(P)  # B,S,4,4: view a -> partner view b
    Xb = torch.einsum("bsij,bshwj->bshwi", T[..., :3, :3], X) + T[..., None, None, :3, 3]
    zb = Xb[..., 2]
    ub = f * Xb[..., 0] / zb.clamp(min=1e-6) + cx
    vb = f * Xb[..., 1] / zb.clamp(min=1e-6) + cy
    ok = ok & (zb > 1e-3) & (ub > -0.5) & (ub < W - 0.5) & (vb > -0.5) & (vb < H - 0.5)
    flow = torch.stack([ub - u, vb - v], -1) / (W / 2.0)
    flow = torch.where(ok[..., None], flow, torch.zeros_like(flow))
    return flow.reshape(B, S, h * w, 2).float(), ok.reshape(B, S, h * w)


def global_layer_positions(model) -> list[int]:
    """Indices into the backbone's output list whose block attends across views (global)."""
    vit = model.backbone.pretrained
    layers = list(model.backbone.out_layers)
    return [k for k, i in enumerate(layers) if vit.alt_start != -1 and i >= vit.alt_start and i % 2]


def token_grid(H: int, W: int, patch: int = 14) -> torch.Tensor:
    """(h * w, 2) patch-centre positions (u, v) relative to the image centre, in half-widths."""
    h, w = H // patch, W // patch
    u = (torch.arange(w, dtype=torch.float32) * patch + (patch - 1) / 2.0 - (W - 1) / 2.0) / (W / 2)
    v = (torch.arange(h, dtype=torch.float32) * patch + (patch - 1) / 2.0 - (H - 1) / 2.0) / (W / 2)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu.reshape(-1), vv.reshape(-1)], -1)


FLOW_KINDS = ("regress", "corr", "both")


class FlowAux(torch.nn.Module):
    """Training-only token-flow heads on the global-attention output layers.

    Each reads the post-global-attention half of the ``cat_token`` features (B, S, N, C) and
    predicts, per token, the displacement of its centre into the partner view (2 numbers, units
    of half the image width). Never exported: it only shapes the backbone's cross-view tokens.

    * ``regress``: an MLP per layer regresses the displacement from the token alone, so the
      global attention itself must find the match and carry its position;
    * ``corr``: a projection per layer gives unit descriptors of the tokens that ENTER the
      global block (the ``local`` half of ``cat_token`` features: the last frame-attention
      output, from which that block's queries and keys are made); the softmax of their scaled
      dot products with the partner view's tokens (a cost volume, (B, S, N, N) logits) gives a
      soft-argmax position on the known token grid. This makes the global block's inputs
      matchable, so its attention can find the match the ``regress`` head asks for;
    * ``both``: both heads on every layer.
    """

    def __init__(self, embed_dim: int, n_layers: int, kind: str = "regress", dim: int = 64):
        super().__init__()
        if kind not in FLOW_KINDS:
            raise ValueError(f"flow head kind {kind!r} not in {FLOW_KINDS}")
        self.embed_dim, self.kind = embed_dim, kind
        if kind in ("regress", "both"):
            self.mlps = torch.nn.ModuleList(
                torch.nn.Sequential(
                    torch.nn.LayerNorm(embed_dim),
                    torch.nn.Linear(embed_dim, 2 * embed_dim),
                    torch.nn.GELU(),
                    torch.nn.Linear(2 * embed_dim, 2),
                )
                for _ in range(n_layers)
            )
        if kind in ("corr", "both"):
            self.projs = torch.nn.ModuleList(
                torch.nn.Sequential(torch.nn.LayerNorm(embed_dim), torch.nn.Linear(embed_dim, dim))
                for _ in range(n_layers)
            )
            # log of the inverse softmax temperature of the cosine similarities
            self.log_scale = torch.nn.Parameter(torch.full((n_layers,), math.log(10.0)))

    def forward(self, tokens: list[torch.Tensor], grid: torch.Tensor) -> list[dict]:
        """Per head: ``flow`` (B, S, N, 2) and, for ``corr``, ``logits`` (B, S, N, N)."""
        outs = []
        for k, t in enumerate(tokens):
            x = t[..., -self.embed_dim :]  # after the global block
            x_in = t[..., : self.embed_dim]  # its input (= x without cat_token)
            if self.kind in ("regress", "both"):
                outs.append({"flow": self.mlps[k](x), "logits": None})
            if self.kind in ("corr", "both"):
                f = torch.nn.functional.normalize(self.projs[k](x_in), dim=-1)
                fb = f[:, partner_views(f.shape[1])]
                scale = self.log_scale[k].clamp(max=math.log(100.0)).exp()
                logits = torch.einsum("bsnd,bsmd->bsnm", f, fb) * scale
                flow = logits.softmax(-1) @ grid - grid
                outs.append({"flow": flow, "logits": logits})
        return outs


def flow_loss(
    preds: list[dict], flow: torch.Tensor, valid: torch.Tensor, grid: torch.Tensor, w: int
) -> torch.Tensor:
    """Mean over heads of the smooth-L1 flow error (beta 0.05 half-widths) on valid tokens,
    plus, for cost-volume heads, 0.1 x the cross-entropy of the partner token nearest to the
    true position (a sharp gradient even while the soft-argmax is still flat)."""
    n = valid.sum().clamp(min=1)
    index = nearest_partner_token(flow, grid, w)
    terms = []
    for p in preds:
        e = torch.nn.functional.smooth_l1_loss(p["flow"], flow, reduction="none", beta=0.05).sum(-1)
        term = torch.where(valid, e, torch.zeros_like(e)).sum() / n
        if p["logits"] is not None:
            ce = torch.nn.functional.cross_entropy(
                p["logits"].flatten(0, 2), index.flatten(), reduction="none"
            ).view_as(e)
            term = term + 0.1 * torch.where(valid, ce, torch.zeros_like(ce)).sum() / n
        terms.append(term)
    return torch.stack(terms).mean()


def nearest_partner_token(flow: torch.Tensor, grid: torch.Tensor, w: int) -> torch.Tensor:
    """(B, S, N) index of the partner token nearest to where each token's centre lands."""
    target = grid[None, None] + flow
    spacing = float(grid[1, 0] - grid[0, 0]) if grid.shape[0] > 1 else 1.0
    col = ((target[..., 0] - grid[0, 0]) / spacing).round().clamp(0, w - 1)
    row = ((target[..., 1] - grid[0, 1]) / spacing).round().clamp(0, grid.shape[0] // w - 1)
    return (row * w + col).long()


def attention_match_loss(
    model, feats: list, flow: torch.Tensor, valid: torch.Tensor, grid: torch.Tensor, heads: int
) -> torch.Tensor:
    """Cross-entropy of the network's OWN global-attention logits towards the true match.

    For every global block among the output layers, its queries and keys are recomputed from
    the block's input (the ``local`` half of the ``cat_token`` features: the raw output of the
    frame block before it) with the block's own ``norm1``, ``qkv`` and q/k norms. The global
    blocks' RoPE positions are all equal, which leaves dot products unchanged, so these are the
    logits the block uses (camera and register tokens left out). For the first ``heads`` heads,
    each patch token of a view is pushed to attend, among the patch tokens of its own view and
    of its partner view, to the partner token nearest to where its centre lands. No parameter is
    added: this trains the shipped attention to match across views.
    """
    vit = model.backbone.pretrained
    layers = list(model.backbone.out_layers)
    B, S, N = valid.shape
    w = int(round(math.sqrt(N)))
    index = nearest_partner_token(flow, grid, w) + N  # keys: [own view, partner view]
    n = valid.sum().clamp(min=1)
    terms = []
    for k in global_layer_positions(model):
        blk = vit.blocks[layers[k]]
        x = blk.norm1(feats[k][0][..., : vit.embed_dim])  # B,S,N,C: the global block's input
        C, nh = x.shape[-1], blk.attn.num_heads
        q, key, _ = blk.attn.qkv(x).reshape(B, S, N, 3, nh, C // nh).unbind(3)
        q, key = blk.attn.q_norm(q[..., :heads, :]), blk.attn.k_norm(key[..., :heads, :])
        keys = torch.cat([key, key[:, partner_views(S)]], dim=2)  # B,S,2N,h,d
        logits = torch.einsum("bsnhd,bsmhd->bshnm", q, keys) * blk.attn.scale
        ce = torch.nn.functional.cross_entropy(
            logits.flatten(0, 3),
            index[:, :, None].expand(B, S, heads, N).flatten(),
            reduction="none",
        ).view(B, S, heads, N)
        terms.append(torch.where(valid[:, :, None], ce, torch.zeros_like(ce)).sum() / (n * heads))
    return torch.stack(terms).mean()


def forward_train(
    model, images: torch.Tensor, pose_only: bool = False
) -> tuple[dict | None, torch.Tensor, list]:
    """The network's own forward, split to keep DualDPT's ray map and the raw pose encoding.

    Returns the head's outputs (None with ``pose_only``: the DPT head is skipped), the raw pose
    encoding (B, S, 9) and the backbone's per-layer (tokens (B, S, N, 2C), camera token).
    """
    from raytun3r_plugin.prediction import imagenet_normalise

    H, W = images.shape[-2:]
    feats, _ = model.backbone(imagenet_normalise(images), cam_token=None, export_feat_layers=[])
    out = None if pose_only else model.head(feats, H, W, patch_start_idx=0)
    pose_enc = model.cam_dec(feats[-1][1])
    return out, pose_enc, feats


def losses(out: dict | None, pose_enc: torch.Tensor, tg: dict, weights: dict) -> dict:
    """Loss terms and logged batch metrics; ``out`` None (``--pose-only``) drops depth and rays."""

    if out is None:
        ls = pose_losses(pose_enc, tg, weights, zero=pose_enc.new_zeros(()))
        del ls["_pose_term"], ls["_quat_term"]  # already in ls["loss"]
        return ls
    pred, gt, valid = out["depth"], tg["depth"], tg["valid"]
    H, W = pred.shape[-2:]
    n = valid.sum(dim=(-1, -2)).clamp(min=1)
    diff = torch.where(
        valid,
        torch.log(pred.clamp(min=1e-6)) - torch.log(gt.clamp(min=1e-6)),
        torch.zeros_like(pred),
    )
    mean = diff.sum(dim=(-1, -2)) / n
    l_si = (
        torch.where(valid, (diff - mean[..., None, None]).abs(), torch.zeros_like(diff)).sum(
            dim=(-1, -2)
        )
        / n
    ).mean()
    l_abs = (diff.abs().sum(dim=(-1, -2)) / n).mean()
    conf = out["depth_conf"]
    err = diff.abs().detach()
    l_conf = (
        torch.where(valid, conf * err - 0.05 * torch.log(conf), torch.zeros_like(conf)).sum(
            dim=(-1, -2)
        )
        / n
    ).mean()

    ray = out["ray"]  # B,S,h,w,6
    ray_gt = ray_targets(tg, ray.shape[2], ray.shape[3], H, W)
    l_ray = (ray - ray_gt).abs().mean()
    ls = pose_losses(pose_enc, tg, weights, zero=pred.new_zeros(()))
    # summed in the order of earlier versions, so default runs stay bit-identical to them
    ls["loss"] = (
        weights["depth"] * (l_si + 0.25 * l_abs)
        + weights["conf"] * l_conf
        + weights["ray"] * l_ray
        + ls.pop("_pose_term")
        + ls.pop("_quat_term")
    )
    if weights.get("tdir", 0.0) > 0:
        ls["loss"] = ls["loss"] + weights["tdir"] * ls["tdir"]
    ls.update(depth_si=l_si, depth_abs=l_abs, conf=l_conf, ray=l_ray)
    return ls


def pose_losses(pose_enc: torch.Tensor, tg: dict, weights: dict, zero: torch.Tensor) -> dict:
    """Pose + quaternion terms of the camera decoder; depth/ray entries are ``zero``."""
    from depth_anything_3.model.utils.transform import pose_encoding_to_extri_intri

    H, W = tg["depth"].shape[-2:]
    c2w_pred, _ = pose_encoding_to_extri_intri(pose_enc, (H, W))  # B,S,3,4 world_from_cam
    R_p, t_p = c2w_pred[..., :3, :3], c2w_pred[..., :3, 3]
    R_g, t_g = tg["c2w"][..., :3, :3], tg["c2w"][..., :3, 3]
    l_rot = (R_p - R_g).pow(2).sum(dim=(-1, -2)).add(1e-8).sqrt().mean()
    l_trans = (t_p - t_g).abs().sum(-1).mean()
    l_fov = (pose_enc[..., 7:9] - tg["fov"][:, None, None]).abs().mean()
    # The decoder normalises the raw quaternion, so a loss on the rotation matrix alone lets its
    # norm grow, which shrinks the gradient of the imaginary part and locks the head at the
    # identity (all earlier runs: raw w about 9.5, rotation error = no-rotation error). A loss on
    # the raw encoding, as VGGT's camera loss does, pins the norm to 1 and keeps that gradient.
    l_quat = (pose_enc[..., 3:7] - quaternion_target(R_g)).abs().sum(-1).mean()
    pose_term = weights["pose"] * (l_rot + l_trans + 0.5 * l_fov)
    quat_term = weights["quat"] * l_quat
    total = pose_term + quat_term
    # Translation direction (1 - cosine) of the later views: the normalised translations are
    # small (about 0.1), so the L1 term is nearly met by predicting none, in any direction.
    moving = t_g[:, 1:].norm(dim=-1) > 1e-4
    cos_t = torch.nn.functional.cosine_similarity(t_p[:, 1:], t_g[:, 1:], dim=-1, eps=1e-6)
    l_tdir = torch.where(moving, 1.0 - cos_t, torch.zeros_like(cos_t)).sum() / moving.sum().clamp(
        min=1
    )
    if weights.get("tdir", 0.0) > 0:
        total = total + weights["tdir"] * l_tdir
    with torch.no_grad():
        from raytun3r_plugin.metrics import rotation_error_deg

        rot_deg = rotation_error_deg(R_p[:, 1:].double(), R_g[:, 1:].double()).mean()
        rot_gt_deg = rotation_error_deg(
            torch.eye(3, dtype=torch.float64, device=R_g.device).expand_as(R_g[:, 1:]),
            R_g[:, 1:].double(),
        ).mean()
        # translation direction of the second view (signed, 0..180 degrees)
        cos = torch.nn.functional.cosine_similarity(t_p[:, 1:].double(), t_g[:, 1:].double(), -1)
        trans_deg = torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0))).mean()
    return {
        "loss": total,
        "_pose_term": pose_term,
        "_quat_term": quat_term,
        "depth_si": zero,
        "depth_abs": zero,
        "conf": zero,
        "ray": zero,
        "rot": l_rot,
        "trans": l_trans,
        "fov": l_fov,
        "quat": l_quat,
        "tdir": l_tdir,
        "rot_deg": rot_deg,
        "rot_gt_deg": rot_gt_deg,
        "trans_deg": trans_deg,
    }


def quaternion_target(rotation: torch.Tensor) -> torch.Tensor:
    """(..., 4) unit quaternions (x, y, z, w; w >= 0, DA3's encoding order) of (..., 3, 3) rotations."""
    from depth_anything_3.model.utils.transform import mat_to_quat

    return mat_to_quat(rotation)


# ----------------------------------------------------------------------------------------------
# Checkpoints (safetensors + JSON, never pickle)
# ----------------------------------------------------------------------------------------------


def named_trainables(model, aux) -> dict:
    """Parameter name -> parameter of the network and (prefixed ``flowaux.``) the aux head."""
    params = dict(model.named_parameters())
    if aux is not None:
        params.update({f"flowaux.{n}": p for n, p in aux.named_parameters()})
    return params


def save_checkpoint(out: Path, model, opt, step: int, args: dict, aux=None) -> None:
    from safetensors.torch import save_model

    from raytun3r_plugin._io import atomic_path, atomic_save_safetensors, atomic_write_text

    with atomic_path(out / "checkpoint.safetensors") as tmp:
        save_model(model, str(tmp))
    if aux is not None:  # the training-only flow head, kept apart from the network's weights
        atomic_save_safetensors(
            out / "aux.safetensors",
            {k: v.detach().clone().contiguous() for k, v in aux.state_dict().items()},
        )
    names = {id(p): name for name, p in named_trainables(model, aux).items()}
    tensors = {}
    for group in opt.param_groups:
        for p in group["params"]:
            st = opt.state.get(p)
            if not st:
                continue
            for key, value in st.items():
                tensors[f"{names[id(p)]}::{key}"] = value.detach().clone().contiguous()
    atomic_save_safetensors(out / "optimizer.safetensors", tensors)
    hyper = [{k: v for k, v in g.items() if k != "params"} for g in opt.param_groups]
    atomic_write_text(
        out / "checkpoint.json",
        json.dumps({"step": step, "args": args, "param_groups": hyper}, indent=1, default=list),
    )


def load_checkpoint(out: Path, model, opt, aux=None) -> int:
    from raytun3r_plugin.patches.da3 import load_weights
    from safetensors.torch import load_file

    meta = json.loads((out / "checkpoint.json").read_text())
    load_weights(model, out / "checkpoint.safetensors")
    if aux is not None:
        aux.load_state_dict(load_file(str(out / "aux.safetensors")))
    state = load_file(str(out / "optimizer.safetensors"))
    params = named_trainables(model, aux)
    for key, value in state.items():
        name, field = key.split("::")
        # AdamW keeps its step counter on the CPU; the moments live with their parameter
        p = params[name]
        opt.state[p][field] = value if field == "step" else value.to(p.device)
    for group, saved in zip(opt.param_groups, meta["param_groups"], strict=True):
        group.update({k: (tuple(v) if isinstance(v, list) else v) for k, v in saved.items()})
    return int(meta["step"])


def sincos_table(side: int, dim: int, std: float, max_cycles: float = 3.0) -> torch.Tensor:
    """(side * side, dim) 2D sin-cos PE with 0.5..``max_cycles`` cycles across the image, scaled to ``std``.

    A freshly built DA3 has an all-zero PE, and a small random one is ignored by a network trained
    from scratch (it learns position from RoPE and content instead): the PE adapter would then have
    nothing to correct. Starting from a map whose magnitude is comparable to the patch tokens, with
    frequencies the 8x8 token grid of a 112 px input resolves, makes the network rely on absolute
    position the way pretrained DINOv2 backbones do.
    """
    n_freq = dim // 4
    cycles = torch.logspace(math.log10(0.5), math.log10(max_cycles), n_freq, dtype=torch.float64)
    coords = (torch.arange(side, dtype=torch.float64) + 0.5) / side
    yy, xx = torch.meshgrid(coords, coords, indexing="ij")
    parts = []
    for axis in (xx.reshape(-1), yy.reshape(-1)):
        phase = 2 * math.pi * axis[:, None] * cycles[None, :]
        parts += [torch.sin(phase), torch.cos(phase)]
    table = torch.cat(parts, dim=1)
    table = torch.nn.functional.pad(table, (0, dim - table.shape[1]))
    return (table / table.std() * std).float()


@torch.no_grad()
def validate(model, val: dict, pose_only: bool, device: str, chunk: int = 16) -> dict:
    """Validation metrics on pairs (k, k + VAL_GAP) of every validation sequence.

    Same measures as ``scripts/eval_default_network.py`` on its pinhole views: mean geodesic
    rotation error over the error of predicting no rotation (``val_rot_ratio``), mean signed
    translation-direction error (degrees) and, unless ``pose_only``, median-aligned depth AbsRel.
    """
    from depth_anything_3.model.utils.transform import pose_encoding_to_extri_intri

    from raytun3r_plugin.metrics import abs_rel, relative_pose_errors

    n_seq, n_frames = val["images"].shape[:2]
    pairs = [(s, k) for s in range(n_seq) for k in range(n_frames - VAL_GAP)]
    was_training = model.training
    model.eval()
    rot, rot0, trans, ar = [], [], [], []
    for i in range(0, len(pairs), chunk):
        part = pairs[i : i + chunk]
        imgs = np.stack([val["images"][s, [k, k + VAL_GAP]] for s, k in part])
        x = torch.from_numpy(imgs.astype(np.float32) / 255.0).permute(0, 1, 4, 2, 3).to(device)
        out, pose_enc, _ = forward_train(model, x, pose_only=pose_only)
        c2w, _ = pose_encoding_to_extri_intri(pose_enc, x.shape[-2:])
        c2w = c2w.double().cpu().numpy()
        for j, (s, k) in enumerate(part):
            T_pred = np.stack([np.eye(4), np.eye(4)])
            T_pred[:, :3, :] = c2w[j]
            T_pred = np.linalg.inv(T_pred)  # cam_from_world
            T_gt = val["poses"][s, [k, k + VAL_GAP]]
            e = relative_pose_errors(T_pred, T_gt, pairs=[(0, 1)])
            e0 = relative_pose_errors(np.stack([np.eye(4), np.eye(4)]), T_gt, pairs=[(0, 1)])
            rot += list(e["rotation_deg"])
            trans += list(e["translation_deg"])
            rot0 += list(e0["rotation_deg"])
            if out is not None:
                gt = val["depth"][s, [k, k + VAL_GAP]].astype(np.float64)
                dp = out["depth"][j].double().cpu().numpy()
                ar += list(abs_rel(dp, gt, gt > 0))
    model.train(was_training)
    return {
        "val_rot_ratio": float(np.mean(rot) / np.mean(rot0)),
        "val_trans_deg": float(np.mean(trans)),
        "val_abs_rel": float(np.nanmean(ar)) if ar else float("nan"),
    }


def lr_at(step: int, total: int, base: float, warmup: int) -> float:
    if step < warmup:
        return base * (step + 1) / warmup
    p = (step - warmup) / max(1, total - warmup)
    return base * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * min(1.0, p))))


# ----------------------------------------------------------------------------------------------


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--out", required=True, help="run directory (checkpoints, log.csv, cached data)"
    )
    ap.add_argument("--steps", type=int, default=900)
    ap.add_argument("--batch", type=int, default=4, help="samples (sequences) per step")
    ap.add_argument("--views", type=int, default=2, help="views per sample")
    ap.add_argument("--size", type=int, default=112, help="square input size (multiple of 14)")
    ap.add_argument("--n-seq", type=int, default=400, help="training sequences to render")
    ap.add_argument("--n-frames", type=int, default=5, help="frames per training sequence")
    ap.add_argument("--max-gap", type=int, default=3, help="largest frame gap inside a sample")
    ap.add_argument("--lr", type=float, default=4e-4)
    ap.add_argument("--warmup", type=int, default=40)
    ap.add_argument("--weight-decay", type=float, default=0.02)
    ap.add_argument("--w-depth", type=float, default=1.0)
    ap.add_argument("--w-conf", type=float, default=0.1)
    ap.add_argument("--w-ray", type=float, default=1.0)
    ap.add_argument("--w-pose", type=float, default=1.0)
    ap.add_argument(
        "--w-quat",
        type=float,
        default=0.0,
        help="weight of the L1 loss on the raw quaternion of the pose encoding",
    )
    ap.add_argument(
        "--w-tdir",
        type=float,
        default=0.0,
        help="weight of the translation-direction loss (1 - cosine) of the camera decoder",
    )
    ap.add_argument(
        "--pe-std",
        type=float,
        default=0.0,
        help="start the PE table as a low-frequency 2D sin-cos map of this std (0 = trunc-normal 0.02)",
    )
    ap.add_argument(
        "--init",
        default=None,
        help="start from these weights (a stage-2 run); the optimizer starts fresh",
    )
    ap.add_argument(
        "--fixed-batch",
        action="store_true",
        help="train on the batch of step 0 at every step: a memorisation check of the losses and targets",
    )
    ap.add_argument(
        "--aux-flow",
        type=float,
        default=0.0,
        help="weight of the training-only token-flow head on the global-attention tokens (0 = off)",
    )
    ap.add_argument(
        "--aux-flow-kind",
        default="regress",
        choices=FLOW_KINDS,
        help="flow head: MLP regression, cost-volume soft-argmax (corr), or both",
    )
    ap.add_argument(
        "--aux-attn",
        type=float,
        default=0.0,
        help="weight of the cross-entropy pushing the global blocks' own attention to the true "
        "match (training-only loss, no parameters; 0 = off)",
    )
    ap.add_argument("--aux-attn-heads", type=int, default=2, help="heads supervised by --aux-attn")
    ap.add_argument(
        "--pose-only",
        action="store_true",
        help="train the backbone and camera decoder only (skip the DPT head and its losses)",
    )
    ap.add_argument(
        "--jitter-frac",
        type=float,
        default=0.0,
        help="fraction of training sequences rendered with per-frame rotation jitter",
    )
    ap.add_argument(
        "--jitter-deg",
        type=float,
        default=0.0,
        help="std (degrees, per axis) of the rotation jitter of --jitter-frac sequences",
    )
    ap.add_argument(
        "--rot-aug-deg",
        type=float,
        default=0.0,
        help="turn the views of --rot-aug-frac of the samples by random rotations of this std "
        "(degrees per axis), by exact pinhole homographies (0 = off)",
    )
    ap.add_argument("--rot-aug-frac", type=float, default=0.5)
    ap.add_argument(
        "--val-seqs",
        type=int,
        default=0,
        help=f"validation sequences (seeds {VAL_SEED_BASE}..) logged in log.csv (0 = none)",
    )
    ap.add_argument("--val-every", type=int, default=None, help="default: --ckpt-every")
    ap.add_argument("--device", default="cpu", help="torch device (cpu, cuda, ...)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--ckpt-every", type=int, default=50)
    ap.add_argument("--log-every", type=int, default=5)
    ap.add_argument(
        "--stop-after",
        type=int,
        default=None,
        help="stop (after checkpointing) at this step; the schedule still targets --steps",
    )
    ap.add_argument("--tiny", action="store_true", help="a very small network (smoke tests)")
    ap.add_argument(
        "--export",
        default=None,
        help="after training, write weights + kwargs JSON to this .safetensors path",
    )
    return ap.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    warnings.filterwarnings("ignore")
    from raytun3r_plugin.patches.da3 import build_tiny_network

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    kwargs = dict(TINY_KWARGS if args.tiny else MODEL_KWARGS)
    kwargs["seed"] = args.seed
    # Arguments that do not change the result (where it runs, how often it reports) stay out
    # of the record, so a run may resume on another device. New options enter the record only
    # when set, so checkpoints of runs made before they existed still resume.
    new_opts = {
        "w_tdir": 0.0,
        "aux_flow": 0.0,
        "aux_flow_kind": "regress",
        "aux_attn": 0.0,
        "aux_attn_heads": 2,
        "pose_only": False,
        "jitter_frac": 0.0,
        "jitter_deg": 0.0,
        "val_seqs": 0,
        "rot_aug_deg": 0.0,
        "rot_aug_frac": 0.5,
        "val_every": None,
    }
    record = {
        k: v
        for k, v in vars(args).items()
        if k not in ("out", "stop_after", "export", "threads", "device")
        and not (k in new_opts and v == new_opts[k])
    }
    if (out / "checkpoint.json").is_file():
        saved = json.loads((out / "checkpoint.json").read_text())["args"]
        if saved != record:
            raise SystemExit(f"{out} holds a run with other arguments: {saved} != {record}")
    data = build_dataset(
        out / "train_data.npz",
        args.n_seq,
        args.size,
        args.n_frames,
        TRAIN_SEED_BASE,
        args.jitter_frac,
        args.jitter_deg,
    )
    val = (
        build_dataset(out / "val_data.npz", args.val_seqs, args.size, args.n_frames, VAL_SEED_BASE)
        if args.val_seqs > 0
        else None
    )
    device = torch.device(args.device)
    model = build_tiny_network(
        **{k: (tuple(v) if isinstance(v, list) else v) for k, v in kwargs.items()}
    ).train()
    if args.pe_std > 0:
        with torch.no_grad():
            table = model.backbone.pretrained.pos_embed
            table[0, 1:] = sincos_table(
                int(round(math.sqrt(table.shape[1] - 1))), table.shape[2], args.pe_std
            )
            table[0, :1] = 0.0
    n_params = sum(p.numel() for p in model.parameters())
    aux = None
    flow_layers = global_layer_positions(model)
    if args.aux_flow > 0 or args.aux_attn > 0:
        if not flow_layers:
            raise SystemExit("--aux-flow/--aux-attn need global-attention blocks among the outputs")
    if args.aux_flow > 0:
        torch.manual_seed(args.seed + 7919)  # built after the network: its init is unchanged
        aux = FlowAux(
            model.backbone.pretrained.embed_dim, len(flow_layers), args.aux_flow_kind
        ).train()
    model.to(device)
    if aux is not None:
        aux.to(device)
    named = named_trainables(model, aux)
    decay = [
        p for n, p in named.items() if p.ndim >= 2 and "pos_embed" not in n and "token" not in n
    ]
    no_decay = [
        p
        for n, p in named.items()
        if not (p.ndim >= 2 and "pos_embed" not in n and "token" not in n)
    ]
    opt = torch.optim.AdamW(
        [
            {"params": decay, "weight_decay": args.weight_decay},
            {"params": no_decay, "weight_decay": 0.0},
        ],
        lr=args.lr,
        betas=(0.9, 0.99),
    )
    step = 0
    if args.init and not (out / "checkpoint.json").is_file():
        from raytun3r_plugin.patches.da3 import load_weights

        load_weights(model, args.init)
        model.to(device)
        log(f"initialised from {args.init}")
        init_aux = Path(args.init).parent / "aux.safetensors"
        if aux is not None and init_aux.is_file():  # a pose-only pre-training run's flow head
            from safetensors.torch import load_file

            aux.load_state_dict(load_file(str(init_aux)))
            log(f"flow head initialised from {init_aux}")
    if (out / "checkpoint.json").is_file():
        step = load_checkpoint(out, model, opt, aux)
        log(f"resumed from step {step}")
    log(f"network: {n_params / 1e6:.3f} M parameters, kwargs {kwargs}")
    weights = {
        "depth": args.w_depth,
        "conf": args.w_conf,
        "ray": args.w_ray,
        "pose": args.w_pose,
        "quat": args.w_quat,
        "tdir": args.w_tdir,
    }
    log_path = out / "log.csv"
    fields = [
        "step",
        "time_s",
        "lr",
        "loss",
        "depth_si",
        "depth_abs",
        "conf",
        "ray",
        "rot",
        "trans",
        "fov",
        "quat",
        "tdir",
        "rot_deg",
        "rot_gt_deg",
        "trans_deg",
        "flow",
        "attn",
        "val_rot_ratio",
        "val_trans_deg",
        "val_abs_rel",
    ]
    n_batch_fields = (
        len(fields) - 6
    )  # step, time_s, lr first; the 3 val_* columns are filled on validation steps only
    val_every = args.val_every or args.ckpt_every
    if not log_path.is_file():
        with log_path.open("w", newline="") as fh:
            csv.writer(fh).writerow(fields)
    stop = args.steps if args.stop_after is None else min(args.steps, args.stop_after)
    t0 = time.time()
    acc: dict[str, float] = {}
    n_acc = 0
    while step < stop:
        lr = lr_at(step, args.steps, args.lr, args.warmup)
        for g in opt.param_groups:
            g["lr"] = lr
        # A fixed batch must be fitted by any network that can represent its targets: if it is
        # not, the targets or the losses are wrong rather than the data too hard.
        batch = make_batch(
            data,
            args.seed,
            0 if args.fixed_batch else step,
            args.batch,
            args.views,
            args.max_gap,
            args.rot_aug_deg,
            args.rot_aug_frac,
        )
        tg = targets(batch)
        tg = {k: (v.to(device) if torch.is_tensor(v) else v) for k, v in tg.items()}
        out_d, pose_enc, feats = forward_train(
            model, batch["images"].to(device), pose_only=args.pose_only
        )
        ls = losses(out_d, pose_enc, tg, weights)
        if aux is not None:
            flow, flow_ok = flow_targets(batch)
            H, W = batch["images"].shape[-2:]
            grid = token_grid(H, W).to(device)
            ls["flow"] = flow_loss(
                aux([feats[k][0] for k in flow_layers], grid),
                flow.to(device),
                flow_ok.to(device),
                grid,
                W // 14,
            )
            ls["loss"] = ls["loss"] + args.aux_flow * ls["flow"]
        else:
            ls["flow"] = pose_enc.new_zeros(())
        if args.aux_attn > 0:
            flow, flow_ok = flow_targets(batch)
            H, W = batch["images"].shape[-2:]
            ls["attn"] = attention_match_loss(
                model,
                feats,
                flow.to(device),
                flow_ok.to(device),
                token_grid(H, W).to(device),
                args.aux_attn_heads,
            )
            ls["loss"] = ls["loss"] + args.aux_attn * ls["attn"]
        else:
            ls["attn"] = pose_enc.new_zeros(())
        if not torch.isfinite(ls["loss"]):
            raise SystemExit(
                f"non-finite loss at step {step}: { {k: float(v) for k, v in ls.items()} }"
            )
        opt.zero_grad(set_to_none=True)
        ls["loss"].backward()
        torch.nn.utils.clip_grad_norm_(list(named.values()), 1.0)
        opt.step()
        step += 1
        for k, v in ls.items():
            acc[k] = acc.get(k, 0.0) + float(v)
        n_acc += 1
        if step % args.log_every == 0 or step == stop:
            row = {k: acc[k] / n_acc for k in acc}
            vals = ["", "", ""]
            if val is not None and (step % val_every == 0 or step == stop):
                vm = validate(model, val, args.pose_only, device)
                vals = [f"{vm[k]:.5f}" for k in fields[3 + n_batch_fields :]]
                log(
                    f"  validation ({args.val_seqs} seqs): rot ratio {vm['val_rot_ratio']:.4f} "
                    f"trans {vm['val_trans_deg']:.2f} deg abs_rel {vm['val_abs_rel']:.4f}"
                )
            with log_path.open("a", newline="") as fh:
                csv.writer(fh).writerow(
                    [step, f"{time.time() - t0:.1f}", f"{lr:.3g}"]
                    + [f"{row[k]:.5f}" for k in fields[3 : 3 + n_batch_fields]]
                    + vals
                )
            log(
                f"step {step}/{args.steps} loss {row['loss']:.4f} si {row['depth_si']:.4f} ray {row['ray']:.4f} "
                f"rot {row['rot_deg']:.2f}/{row['rot_gt_deg']:.2f} deg trans {row['trans']:.3f} "
                f"({row['trans_deg']:.1f} deg) flow {row['flow']:.4f} "
                f"({(time.time() - t0) / max(1, n_acc):.2f} s/step)"
            )
            acc, n_acc = {}, 0
            t0 = time.time()
        if step % args.ckpt_every == 0 or step == stop:
            save_checkpoint(out, model, opt, step, record, aux)
    if args.export and step >= args.steps:
        # only the network: the flow head (aux) is training-only and never exported
        export(model.cpu(), kwargs, Path(args.export), {"steps": step, "args": record})
    return 0


def export(model, kwargs: dict, path: Path, training: dict) -> None:
    """Write the shipped weights and the build-kwargs JSON next to them.

    The weights are stored as float16 (half the size; the loader casts them back to the float32
    parameters), which keeps the packaged file under 5 MB.
    """
    from safetensors.torch import save_file

    from raytun3r_plugin._io import atomic_path
    from raytun3r_plugin.weights import alias_keys

    aliases = alias_keys(model)  # tensors shared with an earlier key are stored once
    state = {
        name: tensor.detach().to(torch.float16).contiguous()
        for name, tensor in model.eval().state_dict().items()
        if name not in aliases
    }
    with atomic_path(path) as tmp:
        save_file(
            state,
            str(tmp),
            metadata={"format": "raytun3r-da3-tiny", "build_kwargs": json.dumps(kwargs)},
        )
        os.chmod(tmp, 0o644)  # a package data file: world-readable
    side = path.with_suffix(".json")
    side.write_text(json.dumps({"build_kwargs": kwargs, "training": training}, indent=1) + "\n")
    log(f"exported {path} ({path.stat().st_size / 1e6:.2f} MB) and {side}")


if __name__ == "__main__":
    sys.exit(main())
