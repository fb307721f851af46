"""Issue 12: the evidence behind ``AdaptConfig.min_parallax_px`` (the parallax gate).

For every development sequence of the benchmark (its 3 cameras x 2 scenes, seeds 80000 + 100 k
+ 10 camera + scene, k < ``--sequences``; never the benchmark's 90000+), rendered and windowed
exactly as the benchmark fits them (36 frames, frames 0-23 for adaptation, the demo's
configuration at 112 px), the per-window median depth parallax of the matches with the zero
adapter (``parallax.window_parallax``: input pixels of reprojection per unit log depth), and how
many windows a threshold drops.

    python experiments/parallax_gate.py               # 5 sequences per cell, about 3 minutes
    python experiments/parallax_gate.py --held-out    # the same on the benchmark's seeds
    python experiments/parallax_gate.py --native 448 --scenes outdoor    # about 10 minutes
        # frames rendered at 448 px (the same camera path: the per-frame motion target scaled
        # with the size) and matched there, the network still at 112 px: does a sharper native
        # image give the matches a depth signal outdoors?
    python experiments/parallax_gate.py --stride 8 --scenes outdoor
        # windows of frames 8 apart (the fit's `stride`): does a longer baseline give the far
        # matches that remain outdoors enough parallax?
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.parallax import window_parallax
from raytun3r_plugin.adaptation.problem import prepare_problem
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.apps.benchmark import (
    CAMERAS,
    DEVELOPMENT_SEED,
    HELD_OUT_SEED,
    SCENES,
    make_camera,
    sequence_seed,
)
from raytun3r_plugin.apps.demo import default_network
from raytun3r_plugin.apps.fits import adapt_config
from raytun3r_plugin.registry import quiet_upstream


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", type=int, default=5)
    parser.add_argument("--threshold", type=float, default=0.3)
    parser.add_argument(
        "--held-out",
        action="store_true",
        help="the benchmark's held-out seeds (90000+): which of their windows the gate drops",
    )
    parser.add_argument(
        "--native",
        type=int,
        default=112,
        help="render and match at this size (px); the network input stays 112 px",
    )
    parser.add_argument("--scenes", default=",".join(SCENES), help="comma-separated scenes")
    parser.add_argument(
        "--stride",
        type=int,
        default=1,
        help="frames between the views of a window (the fit's stride)",
    )
    args = parser.parse_args()
    scenes = [scene for scene in args.scenes.split(",") if scene]
    unknown = sorted(set(scenes) - set(SCENES))
    if unknown:
        parser.error(f"unknown scenes {unknown}; choose from {list(SCENES)}")
    torch.set_num_threads(1)
    base = HELD_OUT_SEED if args.held_out else DEVELOPMENT_SEED
    kind = "held-out" if args.held_out else "development"
    model, description = default_network()
    print(
        f"network: {description}; {args.sequences} {kind} sequences per cell, rendered and matched at "
        f"{args.native} px, network input 112 px, window stride {args.stride}; "
        f"window medians of the depth parallax (px per unit log depth), zero adapter; "
        f"threshold {args.threshold} px\n"
    )
    print(
        "| camera | scene | windows | smallest | 5th pct | median | largest | dropped | sequences with every window dropped |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for camera_index, spec in enumerate(CAMERAS):
        camera = make_camera(spec, args.native)
        for scene_index, scene in enumerate(SCENES):
            if scene not in scenes:
                continue
            medians, gated = [], 0
            for k in range(args.sequences):
                seed = sequence_seed(camera_index, scene_index, k, base)
                # The renderer picks the step that gives this median motion in pixels, so
                # scaling it with the size keeps the camera path of the 112 px benchmark.
                seq = synthetic.render_sequence(
                    scene,
                    camera,
                    n_frames=36,
                    seed=seed,
                    flow_px=synthetic.FLOW_PX * args.native / 112,
                )
                config = adapt_config(112, 300, seed=0, stride=args.stride)
                problem = prepare_problem(camera, seq.images[:24], config)
                values = window_parallax(model, Adapter.for_model(model, None), problem, config)
                values = [v for v in values if math.isfinite(v)]
                medians += values
                gated += all(v < args.threshold for v in values)
            m = np.asarray(medians)
            dropped = int((m < args.threshold).sum())
            print(
                f"| {spec.label} | {scene} | {m.size} | {m.min():.3f} | {np.percentile(m, 5):.3f} "
                f"| {np.median(m):.3f} | {m.max():.3f} | {dropped} | {gated}/{args.sequences} |",
                flush=True,
            )


if __name__ == "__main__":
    with quiet_upstream():
        main()
