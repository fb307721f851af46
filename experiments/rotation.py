"""Rotation, the paper's headline: what the tables can do for pose (the pose oracle), and which
parameter-free correction raises the network's rotation error.

On the benchmark's held-out wide-lens sequences (KB4 185 and DS 195, indoor and outdoor, seeds
90010+ / 90020+; v3 at 112 px; frames 0-23 for fitting, 24-35 scored), the rotation error of
consecutive scored pairs for:

* ``vanilla`` (the unpatched network), ``center-ph``, and the zero adapter with every correction;
* the zero adapter with one correction switched off at a time (``no <component>``), which shows
  which correction raises rotation;
* ``pose oracle``: the tables fitted to the ground-truth relative poses of frames 0-23
  (``adapt(..., poses=...)``, recipe ``pose-oracle``: the pose term through the network's own
  pose head, no depth term), the rotation the tables can reach;
* with ``--with-default``, the default recipe's fit too.

    python experiments/rotation.py [--cells "KB4 185 indoor" ...] [--out runs/rotation.json]

The decision it serves and its numbers: docs/decisions.md, "Rotation: the pose oracle and the
components".
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.adapter import COMPONENTS
from raytun3r_plugin.apps.benchmark import (
    CAMERAS,
    HELD_OUT_SEED,
    SCENES,
    SEQUENCES_PER_CELL,
    make_camera,
    sequence_seed,
)
from raytun3r_plugin.apps.demo import DEFAULT_NETWORK, default_network
from raytun3r_plugin.apps.evaluation import headline, run_method, score
from raytun3r_plugin.apps.fits import adapt_config
from raytun3r_plugin.registry import quiet_upstream

SIZE, N_ADAPT, N_EVAL = 112, 24, 12
WIDE = ("KB4 185", "DS 195")


def rotation(model, seq, method: str, held_out: list[int], **kwargs) -> float:
    return float(
        headline(score(seq, run_method(model, seq, method, frames=held_out, **kwargs)))["rot_deg"]
    )


def one_sequence(model, spec, scene: str, seed: int, with_default: bool) -> dict[str, float]:
    camera = make_camera(spec, SIZE)
    seq = synthetic.render_sequence(scene, camera, n_frames=N_ADAPT + N_EVAL, seed=seed)
    held_out = list(range(N_ADAPT, N_ADAPT + N_EVAL))
    row = {
        "vanilla": rotation(model, seq, "vanilla", held_out),
        "center-ph": rotation(model, seq, "center-ph", held_out),
        "zero adapter": rotation(model, seq, "raytun3r", held_out),
    }
    for component in COMPONENTS:
        kept = [c for c in COMPONENTS if c != component]
        row[f"no {component}"] = rotation(model, seq, "raytun3r", held_out, components=kept)
    oracle = adapt(
        model,
        camera,
        seq.first_images(N_ADAPT),
        adapt_config(SIZE, 300, recipe="pose-oracle", seed=0),
        poses=seq.cam_from_world[:N_ADAPT],
        progress=False,
    )
    row["pose oracle"] = rotation(model, seq, "raytun3r", held_out, adapter=oracle)
    if with_default:
        fitted = adapt(
            model,
            camera,
            seq.first_images(N_ADAPT),
            adapt_config(SIZE, 300, seed=0),
            progress=False,
        )
        row["default recipe"] = rotation(model, seq, "raytun3r", held_out, adapter=fitted)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cells = [f"{label} {scene}" for label in WIDE for scene in SCENES]
    parser.add_argument("--cells", nargs="+", default=cells, choices=cells)
    parser.add_argument("--sequences", type=int, default=SEQUENCES_PER_CELL)
    parser.add_argument("--with-default", action="store_true")
    parser.add_argument("--out", default="runs/rotation.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    model, _ = default_network(DEFAULT_NETWORK)
    rows = []
    with quiet_upstream():
        for c, spec in enumerate(CAMERAS):
            for s, scene in enumerate(SCENES):
                if f"{spec.label} {scene}" not in args.cells:
                    continue
                for k in range(args.sequences):
                    seed = sequence_seed(c, s, k, HELD_OUT_SEED)
                    row = one_sequence(model, spec, scene, seed, args.with_default)
                    rows.append({"camera": spec.label, "scene": scene, "seed": seed, **row})
                    print(json.dumps(rows[-1]), flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(rows, indent=1))
    methods = [key for key in rows[0] if key not in ("camera", "scene", "seed")]
    print("| cell | " + " | ".join(methods) + " |")
    for cell in args.cells:
        mine = [r for r in rows if f"{r['camera']} {r['scene']}" == cell]
        means = [statistics.mean(r[m] for r in mine) for m in methods]
        print(f"| {cell} | " + " | ".join(f"{v:.2f}" for v in means) + " |")


if __name__ == "__main__":
    main()
