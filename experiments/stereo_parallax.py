"""Issue 12 / 18: would a rig's second camera give the depth signal that outdoor motion does not?

Outdoors (forward driving, 112 px) the temporal matches that survive the checks are far points:
near points move more than DIS can follow, so the reprojection term cannot tell near from far
(docs/adaptation.md section 6) and the parallax gate drops every window. A stereo pair at one
instant has small displacements (the baseline, not the car's motion), so its matches may reach
the near road. This script measures that before any cross-camera loss is written.

For each outdoor development rig (seeds 70100 + k; two identical KB4 185 lenses, 112 px,
parallel axes, baseline B along +x) and each instant, on the DIS matches (the default matcher,
its checks on):

* ``matches``: count per pair; ``disp px``: median displacement between the two ends;
* ``err px``: median distance of the matched end from the ground-truth correspondence (the left
  pixel's ground-truth range, moved by the true relative pose, projected);
* ``parallax px``: median ``losses.depth_parallax_px`` at the true scale (ground-truth depth,
  metric pose): pixels the reprojection moves per unit log depth, what the gate's 0.3 px
  threshold is about;
* ``near %``: share of matches closer than 5 m.

The same columns for the left camera's consecutive frames (``temporal``) give the comparison.
Ground-truth depth and poses are used on purpose: this measures what the matches can carry, not
what a fit with predicted depth makes of it.

    python experiments/stereo_parallax.py              # 3 rigs x 3 baselines, about 2 minutes
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.losses import depth_parallax_px
from raytun3r_plugin.adaptation.matchers import get_matcher
from raytun3r_plugin.apps.benchmark import CAMERAS, make_camera
from raytun3r_plugin.poses import invert_rigid
from raytun3r_plugin.synthetic.correspondence import bilinear_sample

SIZE, FRAMES, SEED = 112, 8, 70_100
NEAR_M = 5.0


def pair_stats(matcher, image_i, image_j, depth_i, camera_i, camera_j, j_from_i) -> dict:
    """The columns of one ordered pair (see the module docstring)."""
    valid_i = camera_i.valid_mask().numpy().astype(bool)
    matches = matcher.match(image_i, image_j, valid_i & camera_j.valid_mask().numpy().astype(bool))
    if len(matches.uv_i) == 0:
        return {"matches": 0}
    depth, sampled = bilinear_sample(depth_i, matches.uv_i)
    rays, ok = camera_i.unproject(torch.from_numpy(matches.uv_i).double())
    keep = ok.numpy() & sampled & np.isfinite(depth) & (depth > 0)
    points = rays[keep] * torch.from_numpy(depth[keep]).double()[:, None]
    pose = torch.from_numpy(j_from_i).double()
    truth, projected = camera_j.project(points @ pose[:3, :3].T + pose[:3, 3])
    error = np.linalg.norm(truth.numpy() - matches.uv_j[keep], axis=-1)[projected.numpy()]
    parallax = depth_parallax_px(points, pose, camera_j).numpy()
    return {
        "matches": int(keep.sum()),
        "disp": float(np.median(np.linalg.norm(matches.uv_j - matches.uv_i, axis=-1))),
        "err": float(np.median(error)) if error.size else float("nan"),
        "parallax": float(np.median(parallax)),
        "near": float(np.mean(depth[keep] < NEAR_M)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rigs", type=int, default=3)
    parser.add_argument("--baselines", default="0.1,0.3,0.5", help="metres, comma-separated")
    args = parser.parse_args()
    torch.set_num_threads(1)
    lens = make_camera(CAMERAS[1], SIZE)  # KB4 185
    matcher = get_matcher("dis")
    rows: dict[str, list[dict]] = {}
    for baseline in (float(b) for b in args.baselines.split(",")):
        extrinsics = synthetic.stereo_extrinsics(baseline)
        for k in range(args.rigs):
            rig = synthetic.render_rig(
                "outdoor", {"left": lens, "right": lens}, extrinsics, n_frames=FRAMES, seed=SEED + k
            )
            left, right = rig.sequences["left"], rig.sequences["right"]
            right_from_left = extrinsics["right"]
            for t in range(FRAMES):
                stats = pair_stats(
                    matcher,
                    left.images[t],
                    right.images[t],
                    left.depth[t],
                    lens,
                    lens,
                    right_from_left,
                )
                rows.setdefault(f"stereo {baseline:g} m", []).append(stats)
                if baseline == float(args.baselines.split(",")[0]) and t + 1 < FRAMES:
                    motion = left.cam_from_world[t + 1] @ invert_rigid(left.cam_from_world[t])
                    rows.setdefault("temporal (left, t -> t+1)", []).append(
                        pair_stats(
                            matcher,
                            left.images[t],
                            left.images[t + 1],
                            left.depth[t],
                            lens,
                            lens,
                            motion,
                        )
                    )
    print(
        f"{args.rigs} outdoor rigs (two KB4 185 lenses, {SIZE} px, seeds {SEED}+), {FRAMES} instants "
        f"each; DIS matches (default checks); medians over pairs of the per-pair medians\n"
    )
    print(
        "| pairs | n | matches | disp px | err px | parallax px | near % | pairs above the gate's 0.3 px |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name, stats in rows.items():
        kept = [s for s in stats if s["matches"]]

        def med(key: str, kept: list[dict] = kept) -> float:
            return float(np.median([s[key] for s in kept])) if kept else float("nan")

        above = sum(s["parallax"] >= 0.3 for s in kept)
        print(
            f"| {name} | {len(stats)} | {med('matches'):.0f} | {med('disp'):.2f} | {med('err'):.2f} | "
            f"{med('parallax'):.3f} | {100 * med('near'):.0f} | {above} of {len(stats)} |"
        )


if __name__ == "__main__":
    main()
