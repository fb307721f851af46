"""What the fitted tables add over the parameter-free corrections, per adaptation setting.

On one synthetic fisheye sequence (a development seed, not one of the benchmark's), prints the
held-out scores of the unpatched network, of the patch with a zero adapter, and of adapters
fitted with a few settings, with the size of the fitted tables (rms of the PE tables, in PE
units, and of the RoPE table, in tokens). Settings: the defaults; the paper's objective as this
project had it before issue 12; a 3x learning rate; the defaults without the PE regularisers.

    python experiments/adapter_settings.py [--camera 1] [--scene indoor] [--seed 80010]
"""

from __future__ import annotations

import argparse
import time

import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.config import SELF_SUPERVISED_WEIGHTS
from raytun3r_plugin.adaptation.losses import LossWeights
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.apps.benchmark import CAMERAS, make_camera
from raytun3r_plugin.apps.demo import default_network
from raytun3r_plugin.apps.evaluation import format_table, headline, run_method, score
from raytun3r_plugin.apps.fits import adapt_config
from raytun3r_plugin.registry import quiet_upstream

SETTINGS = {
    "defaults (lr 3e-3; L2 0.02, TV 0.2 relative)": {},
    "paper objective (L1, least-squares scale, L2 2 / TV 20 in PE units, smooth 10, lr 1e-3, unchecked DIS)": {
        "lr": 1e-3,
        "weights": LossWeights(),
        "scale": "least_squares",
        "robust_px": None,
        "pe_regulariser": "absolute",
        "matcher_options": {"appearance_check": False},
    },
    "lr 1e-2": {"lr": 1e-2},
    "no L2/TV": {"weights": LossWeights(**{**SELF_SUPERVISED_WEIGHTS, "l2": 0.0, "tv": 0.0})},
}


def rms(tensor: torch.Tensor) -> float:
    return float(tensor.detach().pow(2).mean().sqrt())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--camera", type=int, default=1, help="0 KB4 120, 1 KB4 185, 2 DS 195")
    parser.add_argument("--scene", default="indoor", choices=("indoor", "outdoor"))
    parser.add_argument(
        "--seed", type=int, default=80_010, help="development seed (the benchmark uses 90000+)"
    )
    parser.add_argument("--steps", type=int, default=300)
    args = parser.parse_args()
    model, description = default_network()
    spec = CAMERAS[args.camera]
    camera = make_camera(spec, 112)
    seq = synthetic.render_sequence(args.scene, camera, n_frames=36, seed=args.seed)
    held_out = list(range(24, 36))
    rows = [
        {
            "method": "vanilla",
            **headline(score(seq, run_method(model, seq, "vanilla", frames=held_out))),
        },
        {
            "method": "raytun3r, no adapter",
            **headline(score(seq, run_method(model, seq, "raytun3r", frames=held_out))),
        },
    ]
    for name, override in SETTINGS.items():
        config = adapt_config(112, args.steps, seed=0, **override)
        began = time.perf_counter()
        adapter = adapt(model, camera, seq.images[:24], config, progress=False)
        seconds = time.perf_counter() - began
        scores = headline(
            score(seq, run_method(model, seq, "raytun3r", adapter=adapter, frames=held_out))
        )
        tables = {
            "pe_rms": rms(torch.cat([adapter.pe["radial"], adapter.pe["angular"]])),
            "rope_rms": rms(adapter.rope["radial"]),
        }
        rows.append({"method": f"raytun3r, {name}", **scores, **tables, "adapt_s": seconds})
    print(f"network: {description}")
    print(f"{spec.label} {args.scene}, seed {args.seed}, 112 px: adapt on frames 0-23, score 24-35")
    print(
        format_table(
            rows,
            ["method", "d_reproj_px", "abs_rel", "delta_1.25", "pe_rms", "rope_rms", "adapt_s"],
        )
    )


if __name__ == "__main__":
    with quiet_upstream():  # no per-forward INFO lines from the backbone's own logger
        main()
