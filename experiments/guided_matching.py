"""Issue 12, outdoors: prediction-guided matching, and why the translation scale collapses.

Outdoors the adapted fit does not beat the zero adapter (README, held-out table). This script
measures the two causes found after the appearance check (docs/adaptation.md section 6) and
one remedy that was tried and not adopted, on development sequences (80000+, never the
benchmark's 90000+), with the built-in network at 112 px:

1. **scale collapse**: the per-pair pixel-optimal translation scale of the zero adapter's depth
   (the default objective's choice) divided by the scale consistent with that depth (true
   translation length times the median ratio of predicted to true depth), median over pairs;
2. **guided matching**: DIS started from the flow that the zero adapter's depth and the
   MAGSAC++ pose predict, for 16 scale candidates per pair, keeping the candidate whose matches
   move most after the forward-backward check and an appearance check whose patches in frame j
   are warped by the local Jacobian of the flow (a patch of the near road grows between two
   frames, so a square 7x7 patch no longer correlates); its displacement bins against the
   renderer's correspondences, like ``matching_quality.py --bins``;
3. **fits**: held-out AbsRel and d_reproj of the zero adapter, the default self-supervised fit
   and the same fit with the guided matches, frames 0-23 fitted and 24-35 scored.

    python -m experiments.guided_matching            # 3 outdoor sequences + 1 indoor, ~10 min
"""

from __future__ import annotations

import time

import cv2
import numpy as np
import torch

# Helpers of two sibling scripts, imported as modules of the repository (run this from its root
# with ``python -m experiments.guided_matching``).
from benchmarks.matching_quality import BINS, gt_end_points  # noqa: E402
from experiments.objective_causes import zero_adapter_depth  # noqa: E402
from raytun3r_plugin import synthetic  # noqa: E402
from raytun3r_plugin.adaptation import problem as problem_module  # noqa: E402
from raytun3r_plugin.adaptation import train  # noqa: E402
from raytun3r_plugin.adaptation.losses import (
    backproject,
    pixel_optimal_scale,
    sample_bilinear,
)
from raytun3r_plugin.adaptation.matches import (  # noqa: E402
    bilinear_at,
    erode_mask,
    matches_from_flows,
    patch_samples,
    to_gray_u8,
    zncc,
)
from raytun3r_plugin.apps.benchmark import CAMERAS, ground_truth_depth, make_camera  # noqa: E402
from raytun3r_plugin.apps.demo import default_network  # noqa: E402
from raytun3r_plugin.apps.evaluation import headline, run_method, score  # noqa: E402
from raytun3r_plugin.apps.fits import adapt_config  # noqa: E402
from raytun3r_plugin.registry import quiet_upstream  # noqa: E402

SEQUENCES = (
    ("KB4 120", "outdoor", 80_001),
    ("KB4 185", "outdoor", 80_011),
    ("DS 195", "outdoor", 80_021),
    ("KB4 185", "indoor", 80_010),
)
SCALE_FACTORS = np.exp(np.linspace(np.log(0.003), np.log(1.0), 16))  # times the median depth


def predicted_flow(camera, depth: torch.Tensor, rotation, translation) -> np.ndarray:
    """(H, W, 2) flow i -> j that range ``depth`` of frame i and the pose predict (0 where
    nothing projects)."""
    rays, ok = camera.ray_table(dtype=torch.float64)
    points = rays * depth.double()[..., None]
    uv, projected = camera.project(points @ rotation.T + translation)
    flow = (uv - camera.pixel_grid(dtype=torch.float64)).float()
    good = ok & projected & torch.isfinite(flow).all(-1)
    flow[~good] = 0
    return flow.numpy()


def _warped_patches(gray, uv, jacobian, radius: int) -> np.ndarray:
    """(M, (2 r + 1)^2) grey levels of patches centred at ``uv`` whose offsets are mapped by the
    (M, 2, 2) ``jacobian`` (bilinear, edge-clamped; one map row per match)."""
    steps = np.arange(-radius, radius + 1, dtype=np.float32)
    offsets = np.stack(np.meshgrid(steps, steps, indexing="xy"), axis=-1).reshape(-1, 2)
    points = (uv[:, None, :] + np.einsum("mij,kj->mki", jacobian, offsets)).astype(np.float32)
    return cv2.remap(
        gray, points[..., 0], points[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )


def warped_check(gray_i, gray_j, uv_i, uv_j, flow, radius=3, zncc_min=0.8, margin=0.2):
    """The appearance check of ``DISFlowMatcher`` with frame j's patch warped by I + d flow."""
    fi, fj = gray_i.astype(np.float32) / 255, gray_j.astype(np.float32) / 255
    step = 2.0
    du = (bilinear_at(flow, uv_i + [step, 0]) - bilinear_at(flow, uv_i - [step, 0])) / 4
    dv = (bilinear_at(flow, uv_i + [0, step]) - bilinear_at(flow, uv_i - [0, step])) / 4
    jacobian = (np.eye(2)[None] + np.stack([du, dv], axis=-1)).astype(np.float32)
    patch_i, patch_j = patch_samples(fi, uv_i, radius), _warped_patches(fj, uv_j, jacobian, radius)
    corr = zncc(patch_i, patch_j)
    keep = (corr >= zncc_min) & (patch_i.std(1) > 0.02) & (patch_j.std(1) > 0.02)
    for angle in np.arange(8) * (np.pi / 4):
        shift = np.array([np.cos(angle), np.sin(angle)], np.float32) * 2.0
        keep &= corr - zncc(patch_i, _warped_patches(fj, uv_j + shift, jacobian, radius)) > margin
    return keep


def bins_row(errors: list, motions: list) -> str:
    error, moved = np.concatenate(errors), np.concatenate(motions)
    cells = []
    for low, high in zip(BINS[:-1], BINS[1:], strict=True):
        inside = (moved >= low) & (moved < high)
        cells.append(
            f"{100 * inside.mean():.0f}% {np.median(error[inside]):.2f}" if inside.any() else "0% -"
        )
    return " | ".join(cells)


def guide(seq, problem, depth) -> tuple[dict, list[float], str]:
    """Replace every usable pair's matches by guided ones; return (counts, scale ratios, bins)."""
    camera = problem.layout.camera
    valid = camera.valid_mask().numpy().astype(bool)
    eroded = erode_mask(valid, 4)
    truth_depth = torch.from_numpy(ground_truth_depth(seq, max(problem.inputs) + 1))
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    dis.setFinestScale(0)
    done: dict = {}
    ratios, errors, motions, before, after = [], [], [], [], []
    for window, pairs in problem.windows:
        for pair in pairs:
            gi, gj = window.global_pair(pair.a, pair.b)
            before.append(len(window.pairs[(pair.a, pair.b)]))
            if pair.rotation is None or pair.uv_i.shape[0] < 5:
                continue
            if (gi, gj) not in done:
                rotation, direction = pair.rotation, pair.direction
                points = backproject(
                    sample_bilinear(depth[gi], pair.uv_i), pair.rays_i, "range"
                ).double()
                chosen = pixel_optimal_scale(
                    points, pair.uv_j.double(), rotation, direction, camera
                )
                known = truth_depth[gi] > 0
                consistent = float(
                    np.linalg.norm(synthetic.relative_pose(seq.cam_from_world, gi, gj)[:3, 3])
                    * torch.median(depth[gi][known] / truth_depth[gi][known])
                )
                ratios.append(float(chosen) / consistent)
                gray_i, gray_j = to_gray_u8(seq.images[gi]), to_gray_u8(seq.images[gj])
                median = float(depth[gi][torch.from_numpy(valid)].median())
                best = (-1.0, window.pairs[(pair.a, pair.b)])
                for factor in SCALE_FACTORS:
                    t = factor * median * direction
                    forward = dis.calc(
                        gray_i, gray_j, predicted_flow(camera, depth[gi], rotation, t)
                    )
                    backward = dis.calc(
                        gray_j,
                        gray_i,
                        predicted_flow(camera, depth[gj], rotation.T, -(rotation.T @ t)),
                    )
                    found = matches_from_flows(forward, backward, eroded, 4, 1.0)
                    if len(found) == 0:
                        continue
                    found = found.select(
                        warped_check(gray_i, gray_j, found.uv_i, found.uv_j, forward)
                    )
                    moved = float(np.linalg.norm(found.uv_j - found.uv_i, axis=1).sum())
                    if moved > best[0]:
                        best = (moved, found)
                done[(gi, gj)] = best[1]
            matches = done[(gi, gj)]
            window.pairs[(pair.a, pair.b)] = matches
            after.append(len(matches))
            gt, has = gt_end_points(seq, gi, gj, matches.uv_i)
            errors.append(np.linalg.norm(gt - matches.uv_j, axis=1)[has])
            motions.append(np.linalg.norm(gt - matches.uv_i, axis=1)[has])
    problem.windows = [
        (window, problem_module._prepare_pairs(window, problem.layout, problem.valid))
        for window, _ in problem.windows
    ]
    counts = {"before": float(np.mean(before)), "after": float(np.mean(after))}
    return counts, ratios, bins_row(errors, motions)


def fit_scores(model, seq, problem=None) -> dict:
    config = adapt_config(112, 300, seed=0)
    original = train.prepare_problem
    if problem is not None:
        train.prepare_problem = lambda *args, **kwargs: problem
    try:
        adapter = train.adapt(model, seq.camera, seq.images[:24], config, progress=False)
    finally:
        train.prepare_problem = original
    return headline(score(seq, run_method(model, seq, "raytun3r", adapter=adapter, frames=HELD)))


HELD = list(range(24, 36))


def main() -> None:
    torch.set_num_threads(1)
    model, description = default_network()
    print(f"network: {description}; input 112 px; frames 0-23 fitted, 24-35 scored\n")
    labels = [
        f"{int(lo)}-{int(hi)} px" if np.isfinite(hi) else f"{int(lo)}+ px"
        for lo, hi in zip(BINS[:-1], BINS[1:], strict=True)
    ]
    print(
        "| sequence | pixel-optimal / consistent scale, median (range) | matches/pair default -> guided | guided: "
        + " | ".join(labels)
        + " | matching s | AbsRel zero / default / guided | d_reproj zero / default / guided |"
    )
    print("|" + "---|" * (5 + len(labels) + 1))
    for label, scene, seed in SEQUENCES:
        camera = make_camera(next(c for c in CAMERAS if c.label == label), 112)
        seq = synthetic.render_sequence(scene, camera, n_frames=36, seed=seed)
        problem = train.prepare_problem(camera, seq.images[:24], adapt_config(112, 300, seed=0))
        depth = zero_adapter_depth(model, problem)
        began = time.perf_counter()
        counts, ratios, bins = guide(seq, problem, depth)
        seconds = time.perf_counter() - began
        zero = headline(score(seq, run_method(model, seq, "raytun3r", frames=HELD)))
        default = fit_scores(model, seq)
        guided = fit_scores(model, seq, problem)
        print(
            f"| {label} {scene} {seed} | {np.median(ratios):.3f} ({min(ratios):.3f}-{max(ratios):.3f}) "
            f"| {counts['before']:.0f} -> {counts['after']:.0f} | {bins} | {seconds:.0f} "
            f"| {zero['abs_rel']:.3f} / {default['abs_rel']:.3f} / {guided['abs_rel']:.3f} "
            f"| {zero['d_reproj_px']:.2f} / {default['d_reproj_px']:.2f} / {guided['d_reproj_px']:.2f} |",
            flush=True,
        )


if __name__ == "__main__":
    with quiet_upstream():
        main()
