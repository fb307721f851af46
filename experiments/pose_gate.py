"""The pose gate: how far each built-in network's relative rotations are from the MAGSAC++ targets
on its own adaptation set, against "no rotation" (``adaptation.pose_gate.pose_agreement``).

On the benchmark's 30 development sequences (seeds 80000+, the adaptation frames 0-23 at 112 px,
the default recipe's windows and matches, the zero adapter), per network: the median rotation
error of the network's relative poses, that of "no rotation", and their ratio. The rule for the
threshold, written before this ran, is in docs/decisions.md ("The pose gate").

    python experiments/pose_gate.py [--out runs/pose_gate.json] [--sequences K]
        [--weights FILE ...]   # networks from scripts/train_default_network.py (a VGGT one
                               # needs PYTHONPATH=tests/stubs)

Besides the error ratio it prints each network's responsiveness: the median angle of its own
relative rotations over the targets' median angle (near 0 for a head that answers "no
rotation" whatever the input).
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import torch

from raytun3r_plugin import Adapter, synthetic
from raytun3r_plugin.adaptation.pose_gate import pose_agreement
from raytun3r_plugin.adaptation.problem import prepare_problem
from raytun3r_plugin.apps.benchmark import (
    CAMERAS,
    DEVELOPMENT_SEED,
    HELD_OUT_SEED,
    NEW_LENSES,
    SCENES,
    SEQUENCES_PER_CELL,
    make_camera,
    sequence_seed,
)
from raytun3r_plugin.apps.demo import BUILT_IN_NETWORKS, default_network
from raytun3r_plugin.apps.fits import adapt_config
from raytun3r_plugin.registry import quiet_upstream

SIZE = 112


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/pose_gate.json")
    parser.add_argument("--sequences", type=int, default=SEQUENCES_PER_CELL)
    parser.add_argument("--weights", nargs="*", default=[], help="trained networks to add")
    parser.add_argument(
        "--held-out",
        action="store_true",
        help="the benchmark's held-out seeds (to check which fits the gate would change; "
        "it measures the gate's input, no outcome)",
    )
    parser.add_argument("--new-lenses", action="store_true", help="UCM 200 and EUCM 210 too")
    args = parser.parse_args()
    torch.set_num_threads(1)
    models = {name: default_network(name)[0] for name in BUILT_IN_NETWORKS}
    if args.weights:
        from raytun3r_plugin.apps.trained_networks import load_trained_network

        for path in args.weights:
            models[Path(path).stem] = load_trained_network(path)[0]
    rows = []
    with quiet_upstream():
        base = HELD_OUT_SEED if args.held_out else DEVELOPMENT_SEED
        lenses = (*CAMERAS, *NEW_LENSES) if args.new_lenses else CAMERAS
        for c, spec in enumerate(lenses):
            camera = make_camera(spec, SIZE)
            for s, scene in enumerate(SCENES):
                for k in range(args.sequences):
                    seed = sequence_seed(c, s, k, base)
                    seq = synthetic.render_sequence(scene, camera, n_frames=36, seed=seed)
                    config = adapt_config(SIZE, 300, seed=0)
                    problem = prepare_problem(camera, seq.first_images(24), config)
                    for name, model in models.items():
                        zero = Adapter.for_model(model, camera)
                        row = {"network": name, "camera": spec.label, "scene": scene, "seed": seed}
                        row.update(pose_agreement(model, zero, problem, config))
                        rows.append(row)
                        print(json.dumps(row), flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(rows, indent=1))
    for name in models:
        for key in ("ratio", "responsiveness"):
            values = [r[key] for r in rows if r["network"] == name and r["pairs"]]
            print(
                f"{name}: {key} over {len(values)} sequences: median "
                f"{statistics.median(values):.3f}, range {min(values):.3f}-{max(values):.3f}"
            )


if __name__ == "__main__":
    main()
