"""Issue 12, outdoors: does a dense photometric warp find the translation length, and does it
rank true depth first?

On the renderer's ground truth (true range depth of frame 0, true pose of frame j), for frame
pairs (0, j), j = 1, 2, 3, of the benchmark's 112 px renders (development seeds k = 0 of the
three outdoor cells and of KB4 185 indoors):

* **length found / true**: the translation length that
  :func:`~raytun3r_plugin.adaptation.photometric.photometric_optimal_scale` returns along the true
  direction, divided by the true length, with the grey-level difference averaged over the pixels
  that stay in view (what the library does) and, beside it, with pixels that leave the view
  charged ``OUTSIDE_COST`` (the first version);
* **cost true / halfway / flat**: :func:`~raytun3r_plugin.adaptation.photometric.photometric_loss` at
  the true depth, at the depth pulled halfway (in log) to its median, and at a constant depth;
* **in view**: the fraction of frame 0's pixels that the true warp keeps in frame j's view.

Frames blurred by 1 px, every valid pixel with depth, the frames' own lens mask.

    python experiments/photometric_scale.py      # about 1 minute
"""

from __future__ import annotations

import math

import numpy as np
import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.photometric import (
    OUTSIDE_COST,
    blurred_gray,
    photometric_loss,
    photometric_optimal_scale,
    warped_photometric_error,
)
from raytun3r_plugin.apps.benchmark import (
    CAMERAS,
    DEVELOPMENT_SEED,
    SCENES,
    make_camera,
    sequence_seed,
)
from raytun3r_plugin.registry import quiet_upstream

SIZE, SIGMA, OFFSETS = 112, 1.0, (1, 2, 3)
SEQUENCES = (
    ("KB4 120", "outdoor"),
    ("KB4 185", "outdoor"),
    ("DS 195", "outdoor"),
    ("KB4 185", "indoor"),
)


def length_with_outside_cost(points, gray_i, gray_j, rotation, direction, camera, valid) -> float:
    """The first version's search: a pixel warped out of view costs ``OUTSIDE_COST``."""
    centre = float(points.norm(dim=-1).median())
    grid = torch.linspace(math.log(centre * 1e-4), math.log(centre), 41, dtype=points.dtype)
    error, usable = warped_photometric_error(
        points, gray_i, gray_j, rotation, grid.exp()[:, None] * direction[None], camera, valid
    )
    cost = torch.where(usable, error, torch.full_like(error, OUTSIDE_COST)).mean(-1)
    return float(grid[int(torch.argmin(cost))].exp())


def measure(label: str, scene: str) -> list[dict]:
    camera_index = [spec.label for spec in CAMERAS].index(label)
    seed = sequence_seed(camera_index, SCENES.index(scene), 0, DEVELOPMENT_SEED)
    camera = make_camera(CAMERAS[camera_index], SIZE)
    seq = synthetic.render_sequence(scene, camera, n_frames=1 + max(OFFSETS), seed=seed)
    gray = blurred_gray(torch.from_numpy(seq.images).permute(0, 3, 1, 2).double(), SIGMA)
    depth = torch.from_numpy(seq.depth[0]).double()
    valid = camera.valid_mask().bool()
    rows, cols = torch.nonzero(valid & (depth > 0), as_tuple=True)
    pixels = torch.stack((cols, rows), dim=-1)
    rays, ok = camera.unproject(pixels.double())
    pixels, rays = pixels[ok], rays[ok]
    points = rays * depth[pixels[:, 1], pixels[:, 0], None]
    intensity = gray[0][pixels[:, 1], pixels[:, 0]]
    log = depth.clamp_min(1e-3).log()
    median = log[depth > 0].median()
    halfway = torch.where(depth > 0, torch.exp(0.5 * log + 0.5 * median), 0)
    flat = torch.where(depth > 0, median.exp(), 0)
    rows_out = []
    for j in OFFSETS:
        pose = torch.as_tensor(synthetic.relative_pose(seq.cam_from_world, 0, j)).double()
        rotation, length = pose[:3, :3], float(pose[:3, 3].norm())
        direction = pose[:3, 3] / length
        args = (rotation, direction, camera, valid)
        found = float(photometric_optimal_scale(points, intensity, gray[j], *args))
        charged = length_with_outside_cost(points, intensity, gray[j], *args)
        costs = [
            float(photometric_loss(d, rays, pixels, gray[0], gray[j], *args)[0])
            for d in (depth, halfway, flat)
        ]
        _, usable = warped_photometric_error(
            points, intensity, gray[j], rotation, pose[:3, 3][None], camera, valid
        )
        rows_out.append(
            {
                "sequence": f"{label} {scene} {seed}",
                "pair": f"(0, {j})",
                "length_m": length,
                "in_view": float(usable.double().mean()),
                "found": found / length,
                "charged": charged / length,
                "costs": costs,
            }
        )
    return rows_out


def main() -> None:
    torch.set_num_threads(1)
    print(
        f"ground-truth depth and pose, {SIZE} px, blur {SIGMA} px; length found / true along the "
        "true direction\n"
    )
    print(
        "| sequence | pair | true length m | in view | length found / true (in-view mean) | "
        "(out-of-view charged) | cost true | halfway | flat |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    rows = []
    for label, scene in SEQUENCES:
        for row in measure(label, scene):
            rows.append(row)
            true, halfway, flat = row["costs"]
            print(
                f"| {row['sequence']} | {row['pair']} | {row['length_m']:.2f} | "
                f"{row['in_view']:.0%} | {row['found']:.3f} | {row['charged']:.4f} | "
                f"{true:.4f} | {halfway:.4f} | {flat:.4f} |",
                flush=True,
            )
    outdoor = [r for r in rows if "outdoor" in r["sequence"]]
    print(
        f"\noutdoor pairs: in-view mean finds {np.median([r['found'] for r in outdoor]):.3f} of the "
        f"true length (median; range {min(r['found'] for r in outdoor):.3f}-"
        f"{max(r['found'] for r in outdoor):.3f}), charging out-of-view pixels "
        f"{np.median([r['charged'] for r in outdoor]):.4f}; true depth costs less than the "
        f"halfway-flattened depth on {sum(r['costs'][0] < r['costs'][1] for r in outdoor)} and "
        f"less than a constant depth on {sum(r['costs'][0] < r['costs'][2] for r in outdoor)} of "
        f"{len(outdoor)} outdoor pairs"
    )


if __name__ == "__main__":
    with quiet_upstream():
        main()
