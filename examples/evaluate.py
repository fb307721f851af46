"""Evaluate vanilla, Center-PH and raytun3r (with an adapter) on a synthetic fisheye sequence.

    python examples/evaluate.py --adapter my_camera.safetensors [--frames 12]
"""

from __future__ import annotations

import argparse

import raytun3r_plugin as rt
from raytun3r_plugin import synthetic
from raytun3r_plugin.demo import default_network
from raytun3r_plugin.evaluation import format_table, headline, run_method, score


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--adapter", required=True)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--size", type=int, default=112)
    args = parser.parse_args()

    model = default_network()[0]
    adapter = rt.Adapter.load(args.adapter)
    camera = adapter.camera.resized(args.size, round(args.size * adapter.camera.height / adapter.camera.width))
    seq = synthetic.render_sequence("indoor", camera, n_frames=args.frames, seed=2024)  # held-out seed
    rows = []
    for method in ("vanilla", "center-ph", "raytun3r"):
        output = run_method(model, seq, method, adapter=adapter if method == "raytun3r" else None)
        rows.append({"method": method, **headline(score(seq, output))})
    print(format_table(rows, ["method", "rot_deg", "trans_deg", "d_reproj_px", "abs_rel", "delta_1.25", "coverage"]))


if __name__ == "__main__":
    main()
