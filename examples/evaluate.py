"""Evaluate vanilla, Center-PH and raytun3r (with an adapter) on a synthetic fisheye sequence.

python examples/evaluate.py --adapter my_camera.safetensors [--frames 12]
"""

from __future__ import annotations

import argparse

import raytun3r_plugin as rt
from raytun3r_plugin import synthetic
from raytun3r_plugin.apps.demo import default_network
from raytun3r_plugin.apps.evaluation import fit_sequence, format_table, headline, run_method, score
from raytun3r_plugin.preprocess import fitted_source_camera


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--adapter", required=True)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--size", type=int, default=112)
    args = parser.parse_args()

    model = default_network()[0]
    adapter = rt.Adapter.load(args.adapter)
    # Rendered through the camera the adapter was fitted on, then prepared for the network by the
    # rule adaptation used (raytun3r_plugin.preprocess.InputLayout, as `raytun3r eval` does).
    native = synthetic.render_sequence(
        "indoor", fitted_source_camera(adapter), n_frames=args.frames, seed=2024
    )  # held-out seed
    seq = fit_sequence(native, args.size, adapter.patch_size)
    rows = []
    for method in ("vanilla", "center-ph", "raytun3r"):
        output = run_method(model, seq, method, adapter=adapter if method == "raytun3r" else None)
        rows.append({"method": method, **headline(score(seq, output))})
    print(
        format_table(
            rows,
            ["method", "rot_deg", "trans_deg", "d_reproj_px", "abs_rel", "delta_1.25", "coverage"],
        )
    )


if __name__ == "__main__":
    main()
