"""``raytun3r demo``: the main job on a built-in default, with nothing to download.

1. render a synthetic indoor sequence through a 190-degree Kannala-Brandt fisheye;
2. take the built-in network: ``raytun3r-da3-tiny``, a small Depth Anything 3 network trained on
   pinhole renders by ``scripts/train_default_network.py`` (or, if that file is absent from this
   build, a randomly initialised one of the same family, and the demo says so);
3. score the unpatched network (vanilla), Center-PH, and raytun3r without an adapter;
4. fit an adapter on the first part of the sequence (self-supervised: DIS matches + MAGSAC++);
5. score raytun3r with the adapter on the held-out rest, print the table, save everything.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

DEFAULT_NETWORK = "raytun3r-da3-tiny"
POSE_SOURCE = "targets"


def adapt_config(size: int, steps: int, **changes):
    """The adaptation settings the demo and the benchmark use with the built-in network.

    Defaults of :class:`AdaptConfig` (30 windows) at input ``size`` px, no intermediate checkpoints,
    relative poses from the MAGSAC++ targets (:data:`POSE_SOURCE`); ``changes`` override any field.
    """
    from raytun3r_plugin.adaptation.train import AdaptConfig

    return AdaptConfig(**{"steps": steps, "input_size": size, "checkpoint_every": 0, "pose_source": POSE_SOURCE, **changes})


def default_network():
    """(model, description) of the built-in network; honest about what it is."""
    from raytun3r_plugin.errors import WeightsError
    from raytun3r_plugin.weights import load_backbone

    try:
        return load_backbone(DEFAULT_NETWORK), f"{DEFAULT_NETWORK}: a small Depth Anything 3 network trained by raytun3r on pinhole renders only (docs/model_card_raytun3r_da3_tiny.md)"
    except WeightsError:
        from raytun3r_plugin.patches.da3 import build_tiny_network

        return build_tiny_network(seed=0), (
            "RANDOM-WEIGHT tiny Depth Anything 3 network (the trained default is not in this build): "
            "the numbers below show the pipeline runs, they say nothing about accuracy"
        )


def demo_camera(size: int):
    from raytun3r_plugin.cameras import KannalaBrandt4

    half = math.radians(95.0)
    focal = (size / 2) / (half * (1 + 0.02 * half**2))
    centre = (size - 1) / 2
    return KannalaBrandt4(size, size, {"fx": focal, "fy": focal, "cx": centre, "cy": centre, "k1": 0.02, "k2": 0.0, "k3": 0.0, "k4": 0.0}, max_fov_deg=190.0)


def run_demo(args: argparse.Namespace) -> int:
    from raytun3r_plugin import synthetic
    from raytun3r_plugin.adaptation.train import adapt
    from raytun3r_plugin.evaluation import format_table, headline, run_method, score

    started = time.perf_counter()
    size = args.size or 112  # the default network's training resolution
    steps = args.steps if args.steps is not None else 300
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    model, description = default_network()
    print(f"network: {description}")
    camera = demo_camera(size)
    print(f"camera:  {camera!r}, field of view {camera.fov_deg:.0f} deg")
    n_adapt, n_eval = 24, 12
    seq = synthetic.render_sequence("indoor", camera, n_frames=n_adapt + n_eval, seed=1000 + args.seed)
    print(f"rendered {len(seq)} frames ({time.perf_counter() - started:.0f} s); adapting on frames 0-{n_adapt - 1}, scoring on {n_adapt}-{len(seq) - 1}")
    held_out = list(range(n_adapt, len(seq)))

    rows = []
    for method, label in (("vanilla", "vanilla (unpatched)"), ("center-ph", "Center-PH (110 deg pinhole)"), ("raytun3r", "raytun3r, no adapter")):
        rows.append({"method": label, **headline(score(seq, run_method(model, seq, method, frames=held_out)))})

    # The default network's pose head is at chance (model card), so adaptation takes relative poses
    # from the MAGSAC++ targets (AdaptConfig.pose_source); the depth path is what it adapts.
    config = adapt_config(size, steps, seed=args.seed, cache_dir=str(out / "cache"))
    began = time.perf_counter()
    adapter = adapt(model, camera, seq.images[:n_adapt], config, out_path=out / "adapter.safetensors", resume=False)
    adapt_seconds = time.perf_counter() - began
    rows.append({"method": f"raytun3r, adapted ({steps} steps, {adapt_seconds:.0f} s)", **headline(score(seq, run_method(model, seq, "raytun3r", adapter=adapter, frames=held_out)))})

    columns = ["method", "rot_deg", "trans_deg", "d_reproj_px", "abs_rel", "delta_1.25", "coverage"]
    table = format_table(rows, columns)
    print()
    print(table)
    print()
    print("rot/trans: relative-pose errors (deg) on consecutive held-out pairs; d_reproj: px, GT pose;")
    print("AbsRel, delta<1.25: per-image median scale, range depth; coverage: fraction of fisheye pixels with depth.")
    print(f"One sequence (seed {1000 + args.seed}; --seed k renders another) decides little; `raytun3r bench` scores 5 per camera and scene.")
    (out / "metrics.json").write_text(json.dumps({"network": description, "camera": json.loads(camera.to_json()), "rows": rows, "adapt_seconds": adapt_seconds}, indent=2, default=float))
    (out / "metrics.md").write_text(table + "\n")
    print(f"\nadapter: {out / 'adapter.safetensors'} ({adapter.num_parameters()['total']:,} parameters); total {time.perf_counter() - started:.0f} s")
    return 0
