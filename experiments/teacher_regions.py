"""Issue 12: where in the image is the AbsRel gap, and how good is each teacher view there?

For development sequences (80000 + 100 k + 10 camera + scene; never the benchmark's 90000+), fitted
on frames 0-23 and scored on frames 24-35 at 112 px:

* **regions**: each scored pixel's AbsRel term (the benchmark's per-frame median alignment) summed
  per region and divided by the number of scored pixels, so a region's numbers add up to the
  image's AbsRel. Regions: the pixels the 110-degree centre view covers, those only the left or
  right view adds, those only the pitched-down view adds, the rest; and the top and bottom
  halves. Methods: the zero adapter, the shipped fit (``adapt_config``), the fit with the centre,
  left and right teacher views, and the supervised fit (the upper bound).
* **views**: for each Multi-PH view (centre, left, right, down), the AbsRel over the pixels it
  covers of the unpatched network's depth on that view (mapped back to the fisheye, the teacher's
  targets), of the zero adapter and of the supervised fit, each median-aligned on those pixels.

    python experiments/teacher_regions.py                      # the three probed sequences, ~4 min
    python experiments/teacher_regions.py --sequences "KB4 185,outdoor,0"
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.teacher import teacher_views, view_range
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.apps.benchmark import (
    CAMERAS,
    DEVELOPMENT_SEED,
    SCENES,
    ground_truth_depth,
    make_camera,
    sequence_seed,
)
from raytun3r_plugin.apps.demo import default_network
from raytun3r_plugin.apps.evaluation import run_method
from raytun3r_plugin.apps.fits import adapt_config, supervised_config
from raytun3r_plugin.baselines.multi_ph import view_lookup
from raytun3r_plugin.metrics import align_scale
from raytun3r_plugin.registry import quiet_upstream

SIZE, N_ADAPT, N_EVAL, STEPS = 112, 24, 12, 300
VIEWS = ("centre", "left", "right", "down")
DEFAULT_SEQUENCES = ("KB4 185,outdoor,0", "KB4 185,indoor,0", "DS 195,outdoor,0")


def per_pixel_abs_rel(depth: np.ndarray, gt: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """|s d - g| / g per pixel (0 outside ``valid``), s the per-frame median ratio; (N, H, W)."""
    errors = np.zeros_like(gt)
    for f in range(gt.shape[0]):
        used = valid[f] & (depth[f] > 0)
        if used.any():
            scale = align_scale(depth[f], gt[f], used)
            errors[f][used] = np.abs(scale * depth[f][used] - gt[f][used]) / gt[f][used]
    return errors


def teacher_range(model, seq, camera, view, frames: list[int]) -> np.ndarray:
    """The unpatched network's depth on ``view`` of ``frames`` (windows of 3), as fisheye range."""
    ranges = np.zeros((len(frames), camera.height, camera.width), np.float32)
    with torch.no_grad():
        for start in range(0, len(frames), 3):
            group = frames[start : start + 3]
            images = torch.from_numpy(np.stack([seq.image(k) for k in group])).permute(0, 3, 1, 2)
            mapped, _ = view_range(model, images.float(), camera, view)
            ranges[start : start + len(group)] = mapped.numpy()
    return ranges


def probe(model, label: str, scene: str, k: int) -> None:
    camera_index = [spec.label for spec in CAMERAS].index(label)
    seed = sequence_seed(camera_index, SCENES.index(scene), k, DEVELOPMENT_SEED)
    camera = make_camera(CAMERAS[camera_index], SIZE)
    seq = synthetic.render_sequence(scene, camera, n_frames=N_ADAPT + N_EVAL, seed=seed)
    frames = list(range(N_ADAPT, N_ADAPT + N_EVAL))
    images = seq.images[:N_ADAPT]
    fits = {
        "shipped": adapt_config(SIZE, STEPS, seed=0),
        "3 views": adapt_config(SIZE, STEPS, seed=0, teacher_views=("centre", "left", "right")),
    }
    adapters = {"no adapter": None}
    adapters.update(
        {
            name: adapt(model, camera, images, config, progress=False)
            for name, config in fits.items()
        }
    )
    adapters["supervised"] = adapt(
        model,
        camera,
        images,
        supervised_config(SIZE, STEPS),
        depth=ground_truth_depth(seq, N_ADAPT),
        progress=False,
    )
    depth = {
        name: run_method(model, seq, "raytun3r", adapter, frames=frames).depth[frames]
        for name, adapter in adapters.items()
    }
    gt = seq.depth[frames]
    sky = np.asarray(seq.meta["per_frame"]["sky"], bool)[frames]
    lens = camera.valid_mask().numpy()
    valid = lens[None] & (gt > 0) & ~sky
    views = teacher_views(camera, VIEWS, 110.0)
    cover = {
        view.name: view_lookup(camera, view.camera, view.rotation)[2].numpy() for view in views
    }
    side = (cover["left"] | cover["right"]) & ~cover["centre"]
    down = cover["down"] & ~(cover["centre"] | cover["left"] | cover["right"])
    top = np.zeros_like(lens)
    top[: lens.shape[0] // 2] = True
    regions = {
        "centre view": cover["centre"],
        "left/right only": side,
        "down only": down,
        "rest": ~(cover["centre"] | side | down),
        "top half": top,
        "bottom half": ~top,
    }
    errors = {name: per_pixel_abs_rel(d, gt, valid) for name, d in depth.items()}
    scored = int(valid.sum())
    print(f"\n{label} {scene} k={k} (seed {seed}): AbsRel contribution per region")
    print("| region | pixels | " + " | ".join(depth) + " |")
    print("|---|---|" + "---|" * len(depth))
    print(
        "| image | 1.00 | "
        + " | ".join(f"{errors[name].sum() / scored:.4f}" for name in depth)
        + " |"
    )
    for region, mask in regions.items():
        inside = valid & mask[None]
        print(
            f"| {region} | {inside.sum() / scored:.2f} | "
            + " | ".join(f"{errors[name][inside].sum() / scored:.4f}" for name in depth)
            + " |"
        )
    print("\nAbsRel over each view's pixels (median-aligned there)")
    print("| view | lens covered | teacher | no adapter | supervised |")
    print("|---|---|---|---|---|")
    for view in views:
        teacher = teacher_range(model, seq, camera, view, frames)
        usable = valid & cover[view.name][None] & (teacher > 0)
        values = [
            per_pixel_abs_rel(d, gt, usable)[usable].mean()
            for d in (teacher, depth["no adapter"], depth["supervised"])
        ]
        print(
            f"| {view.name} | {cover[view.name][lens].mean():.2f} | "
            + " | ".join(f"{v:.3f}" for v in values)
            + " |",
            flush=True,
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sequences",
        nargs="+",
        default=list(DEFAULT_SEQUENCES),
        help='"camera label,scene,k" development sequences',
    )
    args = parser.parse_args()
    model, description = default_network()
    print(f"network: {description}; input {SIZE} px, {STEPS} steps, development seeds")
    for item in args.sequences:
        label, scene, k = item.split(",")
        if label not in [spec.label for spec in CAMERAS] or scene not in SCENES:
            parser.error(f"unknown camera or scene in {item!r}")
        probe(model, label, scene, int(k))


if __name__ == "__main__":
    with quiet_upstream():
        main()
