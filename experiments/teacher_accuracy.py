"""Issue 37, measuring (deciding nothing): how right is the pinhole-view teacher, and where?

The teacher's targets are the unpatched network's depth on three 110-degree pinhole views of each
window, mapped back to the fisheye. For the first two development sequences of each wide-lens
cell (seeds 80000+; the 24 adaptation frames, every third window) this scores those targets
against the ground-truth range, median-aligned per frame and view as the teacher term aligns
them (one free scale per view):

* by the angle between a pixel's ray and its view's axis (under 30, 30-45, 45 degrees and over):
  is the teacher worse where a view's perspective stretch is largest?
* with each view's depth averaged with the depth of its mirror image (flip averaging, a common
  way to get more from one network): does a second look make the teacher more right?

No fit is made.

    python experiments/teacher_accuracy.py --network raytun3r-da3-tiny
    PYTHONPATH=$PWD:$PWD/tests/stubs python experiments/teacher_accuracy.py --weights W
    python experiments/teacher_accuracy.py --teacher-views centre --teacher-fov 80

One process of one thread; about 15 s a sequence here.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.problem import prepare_problem
from raytun3r_plugin.adaptation.teacher import teacher_views
from raytun3r_plugin.apps.benchmark import (
    CAMERAS,
    DEVELOPMENT_SEED,
    SCENES,
    make_camera,
    sequence_seed,
)
from raytun3r_plugin.apps.fits import adapt_config
from raytun3r_plugin.apps.sequence_methods import ground_truth_depth
from raytun3r_plugin.apps.trained_networks import network_from
from raytun3r_plugin.pinhole_views import resample_to_view, view_depth_to_fisheye, view_lookup
from raytun3r_plugin.prediction import predict
from raytun3r_plugin.registry import quiet_upstream

SIZE, N_ADAPT, N_EVAL = 112, 24, 12
LENSES = ("KB4 185", "DS 195")
#: Angle from the view's axis, degrees: (label, low, high).
BANDS = (("under 30", 0.0, 30.0), ("30-45", 30.0, 45.0), ("45 and over", 45.0, 180.0))


def sequence_accuracy(model, camera, seq, config) -> dict[str, float]:
    """The teacher's AbsRel on ``seq``'s adaptation frames: per angle band, all pixels, and with
    flip averaging (all pixels); summed over pixels, each (frame, view) aligned on its own."""
    problem = prepare_problem(camera, seq.images[:N_ADAPT], config, 14)
    truth = torch.from_numpy(ground_truth_depth(seq, N_ADAPT))
    lens = problem.layout.camera
    valid = problem.valid.cpu().bool()
    sums = {name: [0.0, 0] for name in [band for band, _, _ in BANDS] + ["all", "flip averaged"]}
    with torch.no_grad():
        for index in range(0, len(problem.windows), 3):
            images = problem.batch(index)
            frames = problem.windows[index][0].frames
            for view in teacher_views(lens, config.teacher_views, config.teacher_fov_deg):
                virtual = resample_to_view(images, lens, view.camera, view.rotation)
                plain = predict(model, virtual[None]).depth[0].float()
                mirrored = predict(model, virtual.flip(-1)[None]).depth[0].float().flip(-1)
                _, cosine, _ = view_lookup(lens, view.camera, view.rotation)
                angle = torch.rad2deg(torch.arccos(cosine.clamp(-1.0, 1.0))).float()
                for name, depth in (("all", plain), ("flip averaged", 0.5 * (plain + mirrored))):
                    ranges, inside = view_depth_to_fisheye(depth, lens, view.camera, view.rotation)
                    for k in range(images.shape[0]):
                        right = truth[int(frames[k])]
                        usable = inside & valid & torch.isfinite(ranges[k]) & (ranges[k] > 0)
                        usable &= right > 0
                        taught, right, where = ranges[k][usable], right[usable], angle[usable]
                        if taught.numel() == 0:
                            continue
                        error = (torch.median(right / taught) * taught - right).abs() / right
                        sums[name][0] += float(error.sum())
                        sums[name][1] += int(error.numel())
                        if name == "all":
                            for band, low, high in BANDS:
                                inband = (where >= low) & (where < high)
                                sums[band][0] += float(error[inband].sum())
                                sums[band][1] += int(inband.sum())
    return {name: total / count for name, (total, count) in sums.items() if count}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--network", default="raytun3r-da3-tiny")
    parser.add_argument(
        "--weights",
        default=None,
        metavar="FILE",
        help="instead of --network, one exported by scripts/train_default_network.py (a VGGT "
        "one needs PYTHONPATH=tests/stubs)",
    )
    parser.add_argument("--sequences", type=int, default=2, help="per wide-lens cell")
    # The option names of `raytun3r adapt` and the benchmark for the same settings.
    parser.add_argument(
        "--teacher-views", nargs="+", default=None, help="teacher views (default: the recipe's)"
    )
    parser.add_argument(
        "--teacher-fov",
        type=float,
        default=None,
        help="the views' width, degrees (default: the recipe's)",
    )
    args = parser.parse_args()
    changes: dict = {}
    if args.teacher_views:
        changes["teacher_views"] = tuple(args.teacher_views)
    if args.teacher_fov is not None:
        changes["teacher_fov_deg"] = args.teacher_fov
    torch.set_num_threads(1)
    model, description = network_from(args.network, args.weights)
    print(f"network: {description}; teacher changes {changes or 'none'}")
    rows = []
    for k in range(args.sequences):
        for label in LENSES:
            for scene in SCENES:
                lens = [spec.label for spec in CAMERAS].index(label)
                seed = sequence_seed(lens, SCENES.index(scene), k, DEVELOPMENT_SEED)
                camera = make_camera(CAMERAS[lens], SIZE)
                # The benchmark's sequence (36 frames), of which the fit sees the first 24.
                seq = synthetic.render_sequence(scene, camera, n_frames=N_ADAPT + N_EVAL, seed=seed)
                config = adapt_config(SIZE, 300, seed=0, model=model, **changes)
                row = sequence_accuracy(model, camera, seq, config)
                rows.append(row)
                print(
                    f"{label} {scene} {seed}: " + ", ".join(f"{n} {v:.4f}" for n, v in row.items())
                )
    names = list(rows[0])
    print(
        f"mean over {len(rows)} sequences: "
        + ", ".join(f"{name} {np.mean([row[name] for row in rows]):.4f}" for name in names)
    )


if __name__ == "__main__":
    with quiet_upstream():
        main()
