#!/usr/bin/env python
"""Held-out evaluation of ``raytun3r-da3-tiny`` (issue 7).

Scenes: seeds ``--seed-base`` .. ``--seed-base + --n-seq - 1`` (below 10_000, so disjoint from
the training seeds of ``scripts/train_default_network.py``, which start at 10_000), same
indoor/outdoor mix and 50-90 degree pinhole fields of view as training, 5 frames each; the
network sees frame pairs (k, k + 2) like in training (two views, world = first view).

Per camera:

* depth: AbsRel and delta < 1.25 after per-image median scale alignment
  (``raytun3r_plugin.metrics``), sky excluded, against a constant-depth predictor (which after
  alignment predicts the median ground truth everywhere). Pinhole: z-depth; fisheye: the
  network's depth read as range along the ray (docs/conventions.md section 2), against the range;
* pose: geodesic rotation error of the relative pose (``relative_pose_errors``) against
  predicting no rotation, plus the translation-direction error (signed, 0..180 degrees).

Cameras: the pinhole views (the targets apply there: AbsRel ratio <= 0.6, rotation ratio <= 0.5)
and, to show the pinhole bias, the same scenes through equidistant Kannala-Brandt fisheyes of
120 and 190 degrees (image circle inscribed in the square frame), fed to the unpatched network.

Writes ``raytun3r_plugin/data/raytun3r-da3-tiny.metrics.json`` (``--out``) and, with ``--card``,
rewrites the block between ``<!-- metrics:begin -->`` and ``<!-- metrics:end -->`` of the model card.

    python scripts/eval_default_network.py --card docs/model_card_raytun3r_da3_tiny.md
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
# Siblings in scripts/ (the folder of a script run directly is on sys.path already).
from default_network_data import pinhole_camera, sequence_spec  # noqa: E402
from train_default_network import TRAIN_SEED_BASE  # noqa: E402

TARGETS = {"abs_rel_ratio": 0.6, "rotation_ratio": 0.5}
CAMERAS = ("pinhole", "kb4_120", "kb4_190")
GAP = 2

PACKAGED_METRICS = ROOT / "raytun3r_plugin" / "data" / "raytun3r-da3-tiny.metrics.json"


def log(msg: str) -> None:
    print(time.strftime("%H:%M:%S"), msg, flush=True)


def kb4_camera(size: int, fov_deg: float):
    """Equidistant fisheye (k1..k4 = 0) whose ``fov_deg`` image circle fills the square frame."""
    from raytun3r_plugin.cameras import fisheye

    return fisheye(size, fov_deg, "kb4", k=(0.0, 0.0, 0.0, 0.0))


def camera_for(name: str, size: int, seed: int):
    if name == "pinhole":
        return pinhole_camera(size, sequence_spec(seed)["fov"])
    return kb4_camera(size, float(name.split("_")[1]))


def render(name: str, seed: int, size: int, n_frames: int) -> dict:
    from raytun3r_plugin.synthetic import render_sequence

    spec = sequence_spec(seed)
    cam = camera_for(name, size, seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        seq = render_sequence(
            spec["kind"], cam, n_frames=n_frames, seed=seed, flow_px=spec["flow_px"], supersample=2
        )
    gt = seq.meta["per_frame"]["z_depth"] if name == "pinhole" else seq.depth
    valid = seq.mask & ~seq.meta["per_frame"]["sky"] & (gt > 0)
    return {
        "images": seq.images.astype(np.float32),
        "depth": np.where(valid, gt, 0.0).astype(np.float32),
        "poses": seq.cam_from_world.astype(np.float64),
    }


def load_or_render(cache: Path | None, seeds: list[int], size: int, n_frames: int) -> dict:
    key = json.dumps({"seeds": seeds, "size": size, "n_frames": n_frames, "cameras": CAMERAS})
    if cache is not None and cache.is_file():
        with np.load(cache, allow_pickle=False) as data:
            if str(data["key"]) == key:
                log(f"held-out set: cached {cache}")
                return {k: data[k] for k in data.files if k != "key"}
    out = {}
    t0 = time.time()
    for name in CAMERAS:
        seqs = [render(name, s, size, n_frames) for s in seeds]
        for field in ("images", "depth", "poses"):
            out[f"{name}/{field}"] = np.stack([q[field] for q in seqs])
        log(f"rendered {len(seeds)} held-out {name} sequences ({time.time() - t0:.0f} s)")
    if cache is not None:
        from raytun3r_plugin.atomic_files import atomic_path

        # A file handle, not a name: np.savez appends ".npz" to a name that lacks it.
        with atomic_path(cache) as tmp, open(tmp, "wb") as handle:
            np.savez(handle, key=np.array(key), **out)
    return out


def evaluate_camera(
    model, images: np.ndarray, depth: np.ndarray, poses: np.ndarray, ray_pose: bool = False
) -> dict:
    """Metrics over sequences (N, F, ...) using the pairs (k, k + GAP)."""
    from raytun3r_plugin import predict
    from raytun3r_plugin.metrics import abs_rel, delta_125, relative_pose_errors

    ar, ar_c, d1, d1_c, rot, rot_0, trans, rot_ray, rot_ray_0 = [], [], [], [], [], [], [], [], []
    n_seq, n_frames = images.shape[:2]
    for s in range(n_seq):
        for k in range(n_frames - GAP):
            idx = [k, k + GAP]
            x = torch.from_numpy(images[s, idx]).permute(0, 3, 1, 2)[None]
            with torch.no_grad():
                pred = predict(model, x)
            dp = pred.depth[0].numpy().astype(np.float64)
            gt = depth[s, idx].astype(np.float64)
            ok = gt > 0
            const = np.ones_like(gt)
            ar += list(abs_rel(dp, gt, ok))
            ar_c += list(abs_rel(const, gt, ok))
            d1 += list(delta_125(dp, gt, ok))
            d1_c += list(delta_125(const, gt, ok))
            T_pred = pred.cam_from_world[0].numpy().astype(np.float64)
            T_gt = poses[s, idx]
            e = relative_pose_errors(T_pred, T_gt, pairs=[(0, 1)])
            e0 = relative_pose_errors(np.stack([np.eye(4), np.eye(4)]), T_gt, pairs=[(0, 1)])
            rot += list(e["rotation_deg"])
            trans += list(e["translation_deg"])
            rot_0 += list(e0["rotation_deg"])
            if ray_pose and k == 0:
                # DA3's alternative pose path: poses solved from the ray map (RANSAC inside
                # upstream, ~3 s per pair on CPU, so only the first pair of each sequence)
                torch.manual_seed(0)
                with torch.no_grad():
                    T_ray = (
                        predict(model, x, use_ray_pose=True)
                        .cam_from_world[0]
                        .numpy()
                        .astype(np.float64)
                    )
                rot_ray += list(relative_pose_errors(T_ray, T_gt, pairs=[(0, 1)])["rotation_deg"])
                rot_ray_0 += list(e0["rotation_deg"])
    res = {
        "abs_rel": float(np.nanmean(ar)),
        "abs_rel_constant": float(np.nanmean(ar_c)),
        "delta_125": float(np.nanmean(d1)),
        "delta_125_constant": float(np.nanmean(d1_c)),
        "rotation_deg": float(np.nanmean(rot)),
        "rotation_deg_median": float(np.nanmedian(rot)),
        "rotation_deg_no_rotation": float(np.nanmean(rot_0)),
        "translation_deg": float(np.nanmean(trans)),
        "n_images": int(len(ar)),
        "n_pairs": int(len(rot)),
    }
    res["abs_rel_ratio"] = res["abs_rel"] / res["abs_rel_constant"]
    res["rotation_ratio"] = res["rotation_deg"] / res["rotation_deg_no_rotation"]
    # 95 % interval of the rotation ratio, resampling whole sequences (pairs of one sequence
    # are not independent): says whether the held-out set resolves the ratio from a target
    per_seq = n_frames - GAP
    r = np.asarray(rot).reshape(n_seq, per_seq)
    r0 = np.asarray(rot_0).reshape(n_seq, per_seq)
    rng = np.random.default_rng(0)
    draws = rng.integers(0, n_seq, size=(2000, n_seq))
    boot = r[draws].mean(axis=(1, 2)) / r0[draws].mean(axis=(1, 2))
    res["rotation_ratio_ci95"] = [float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))]
    if rot_ray:
        res["ray_pose"] = {
            "rotation_deg": float(np.nanmean(rot_ray)),
            "rotation_deg_no_rotation": float(np.nanmean(rot_ray_0)),
            "rotation_ratio": float(np.nanmean(rot_ray) / np.nanmean(rot_ray_0)),
            "n_pairs": len(rot_ray),
        }
        res["ray_pose"] = {
            k: (round(v, 4) if isinstance(v, float) else v) for k, v in res["ray_pose"].items()
        }
    res["rotation_ratio_ci95"] = [round(v, 4) for v in res["rotation_ratio_ci95"]]
    return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in res.items()}


def card_block(metrics: dict) -> str:
    rows = [
        "| views | AbsRel | AbsRel constant | ratio | delta<1.25 | delta<1.25 constant | rot. err (deg) | no-rotation (deg) | ratio | transl. dir. err (deg) | images / pairs |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    labels = {
        "pinhole": "pinhole 50-90 deg (z-depth)",
        "kb4_120": "KB4 equidistant 120 deg (range)",
        "kb4_190": "KB4 equidistant 190 deg (range)",
    }
    for name in CAMERAS:
        m = metrics["results"][name]
        rows.append(
            f"| {labels[name]} | {m['abs_rel']:.4f} | {m['abs_rel_constant']:.4f} | {m['abs_rel_ratio']:.4f} | "
            f"{m['delta_125']:.4f} | {m['delta_125_constant']:.4f} | {m['rotation_deg']:.4f} | "
            f"{m['rotation_deg_no_rotation']:.4f} | {m['rotation_ratio']:.4f} | {m['translation_deg']:.4f} | "
            f"{m['n_images']} / {m['n_pairs']} |"
        )
    p = metrics["results"]["pinhole"]
    rows += [
        "",
        "Pose from DA3's ray-map path instead (`use_ray_pose=True`; not raytun3r's default), pinhole, "
        f"first pair of each sequence ({p['ray_pose']['n_pairs']} pairs): rotation error "
        f"{p['ray_pose']['rotation_deg']:.4f} deg vs {p['ray_pose']['rotation_deg_no_rotation']:.4f} deg for no rotation "
        f"(ratio {p['ray_pose']['rotation_ratio']:.4f}).",
        "",
        f"Targets on pinhole views: AbsRel ratio <= {TARGETS['abs_rel_ratio']} -> "
        f"{'met' if metrics['targets_met']['abs_rel_ratio'] else 'NOT met'} ({p['abs_rel_ratio']:.4f}); rotation ratio <= "
        f"{TARGETS['rotation_ratio']} -> {'met' if metrics['targets_met']['rotation_ratio'] else 'NOT met'} ({p['rotation_ratio']:.4f}).",
    ]
    return "\n".join(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="held-out evaluation of raytun3r-da3-tiny")
    ap.add_argument(
        "--weights",
        default=None,
        help="weight file (default: the packaged one); a VGGT exported by train_default_network.py "
        "--arch vggt is recognised by its sidecar (needs PYTHONPATH=tests/stubs and --out)",
    )
    ap.add_argument("--seed-base", type=int, default=500)
    ap.add_argument("--n-seq", type=int, default=24)
    ap.add_argument("--n-frames", type=int, default=5)
    ap.add_argument("--size", type=int, default=112)
    ap.add_argument("--cache", default=None, help="npz cache of the rendered held-out set")
    ap.add_argument("--out", default=str(PACKAGED_METRICS))
    ap.add_argument("--card", default=None, help="model card whose metrics block to rewrite")
    ap.add_argument("--render-only", action="store_true")
    ap.add_argument(
        "--cameras",
        nargs="+",
        default=list(CAMERAS),
        choices=CAMERAS,
        help="evaluate only these cameras (the held-out set is still rendered for all; "
        "--card needs all three)",
    )
    ap.add_argument(
        "--no-ray-pose",
        action="store_true",
        help="skip the slow ray-map pose path (about 3 s per pair on CPU; --card needs it)",
    )
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    if args.card and (set(args.cameras) != set(CAMERAS) or args.no_ray_pose):
        raise SystemExit("--card needs every camera and the ray-map pose path")
    torch.set_num_threads(args.threads)
    warnings.filterwarnings("ignore")
    seeds = list(range(args.seed_base, args.seed_base + args.n_seq))
    if max(seeds) >= TRAIN_SEED_BASE:
        raise SystemExit(
            f"held-out seeds must be below {TRAIN_SEED_BASE} (training seeds start there)"
        )
    data = load_or_render(Path(args.cache) if args.cache else None, seeds, args.size, args.n_frames)
    if args.render_only:
        return 0
    network = "raytun3r-da3-tiny"
    side = Path(args.weights).with_suffix(".json") if args.weights else None
    if side is not None and side.is_file() and json.loads(side.read_text()).get("arch") == "vggt":
        # a small VGGT from train_default_network.py --arch vggt (PYTHONPATH=tests/stubs); it
        # has no ray map, so no ray-map pose path, and its metrics never go into the DA3 card
        from raytun3r_plugin.apps.trained_networks import load_trained_network

        if args.card or Path(args.out).resolve() == PACKAGED_METRICS:
            raise SystemExit(
                "a VGGT network's metrics go to an --out of their own, never to the DA3 "
                "network's packaged metrics or model card"
            )
        model, _ = load_trained_network(args.weights)
        network, args.no_ray_pose = Path(args.weights).stem, True
    else:
        from raytun3r_plugin.patches.da3_default import BUILDERS

        model = BUILDERS["raytun3r-da3-tiny"](args.weights)
    results = {}
    for name in [c for c in CAMERAS if c in args.cameras]:
        results[name] = evaluate_camera(
            model,
            data[f"{name}/images"],
            data[f"{name}/depth"],
            data[f"{name}/poses"],
            ray_pose=name == "pinhole" and not args.no_ray_pose,
        )
        log(f"{name}: {results[name]}")
    p = results.get("pinhole", {})
    metrics = {
        "network": network,
        "held_out_seeds": [seeds[0], seeds[-1]],
        "size": args.size,
        "frame_gap": GAP,
        "targets": TARGETS,
        "weights": str(args.weights) if args.weights else "packaged",
        "targets_met": {k: bool(p[k] <= v) for k, v in TARGETS.items() if k in p},
        "results": results,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(metrics, indent=1) + "\n")
    log(f"wrote {out}")
    if args.card:
        block = card_block(metrics)
        print(block)
        card = Path(args.card)
        text = card.read_text()
        begin, end = "<!-- metrics:begin -->", "<!-- metrics:end -->"
        if begin not in text or end not in text:
            raise SystemExit(f"{card} has no {begin} ... {end} block")
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        card.write_text(f"{head}{begin}\n{block}\n{end}{tail}")
        log(f"updated {card}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
