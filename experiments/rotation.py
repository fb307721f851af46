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
* with ``--recipes NAME ...``, self-supervised fits of those recipes (``trajectory-candidate``,
  the oracle's settings with the MAGSAC++ targets in place of the ground truth, was the
  ``trajectory`` recipe before it was adopted).

AbsRel of every row is kept beside its rotation (``abs_rel`` in each JSON row).
``--development`` uses the development seeds (80000+), for choosing; ``--no-components`` skips
the rows with one correction off.

    python experiments/rotation.py [--cells "KB4 185 indoor" ...] [--development]
        [--no-components] [--recipes default trajectory-candidate] [--weights FILE]
        [--out runs/rotation.json]

The decisions it serves and their numbers: docs/decisions.md, "Rotation: the pose oracle and the
components" and "A trajectory recipe".
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
    DEVELOPMENT_SEED,
    HELD_OUT_SEED,
    SCENES,
    SEQUENCES_PER_CELL,
    cell_sequences,
    make_camera,
)
from raytun3r_plugin.apps.demo import DEFAULT_NETWORK
from raytun3r_plugin.apps.evaluation import headline, run_method, score
from raytun3r_plugin.apps.fits import adapt_config
from raytun3r_plugin.apps.trained_networks import network_from
from raytun3r_plugin.registry import quiet_upstream

SIZE, N_ADAPT, N_EVAL = 112, 24, 12
WIDE = ("KB4 185", "DS 195")
STEPS = 300
#: The pose oracle's settings fitted to the MAGSAC++ targets (no ground truth): the candidate of
#: docs/decisions.md, "A trajectory recipe".
CANDIDATE = "trajectory-candidate"


def one_sequence(
    model, spec, scene: str, seed: int, recipes: list[str], components: bool
) -> dict[str, float | dict[str, float]]:
    """Rotation error (deg) of every method on one sequence, and its AbsRel under ``abs_rel``."""
    camera = make_camera(spec, SIZE)
    seq = synthetic.render_sequence(scene, camera, n_frames=N_ADAPT + N_EVAL, seed=seed)
    held_out = list(range(N_ADAPT, N_ADAPT + N_EVAL))
    row: dict = {}
    abs_rel: dict[str, float] = {}

    def record(name: str, method: str, **kwargs) -> None:
        numbers = headline(score(seq, run_method(model, seq, method, frames=held_out, **kwargs)))
        row[name], abs_rel[name] = float(numbers["rot_deg"]), float(numbers["abs_rel"])

    record("vanilla", "vanilla")
    record("center-ph", "center-ph")
    record("zero adapter", "raytun3r")
    if components:
        for component in COMPONENTS:
            kept = [c for c in COMPONENTS if c != component]
            record(f"no {component}", "raytun3r", components=kept)
    frames = seq.first_images(N_ADAPT)
    oracle = adapt_config(SIZE, STEPS, recipe="pose-oracle", seed=0)
    fitted = adapt(
        model, camera, frames, oracle, poses=seq.cam_from_world[:N_ADAPT], progress=False
    )
    record("pose oracle", "raytun3r", adapter=fitted)
    for recipe in recipes:
        config = oracle if recipe == CANDIDATE else adapt_config(SIZE, STEPS, recipe=recipe, seed=0)
        fitted = adapt(model, camera, frames, config, progress=False)
        record(recipe if recipe == CANDIDATE else f"{recipe} recipe", "raytun3r", adapter=fitted)
    return {**row, "abs_rel": abs_rel}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cells = [f"{label} {scene}" for label in WIDE for scene in SCENES]
    parser.add_argument("--cells", nargs="+", default=cells, choices=cells)
    parser.add_argument("--sequences", type=int, default=SEQUENCES_PER_CELL)
    parser.add_argument("--development", action="store_true", help="development seeds (80000+)")
    parser.add_argument("--no-components", action="store_true")
    parser.add_argument("--recipes", nargs="*", default=[], help=f"recipe names, or {CANDIDATE}")
    parser.add_argument(
        "--weights",
        default=None,
        help="a network exported by scripts/train_default_network.py (e.g. the VGGT-architecture "
        f"one) instead of {DEFAULT_NETWORK}",
    )
    parser.add_argument("--out", default="runs/rotation.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    model, _ = network_from(DEFAULT_NETWORK, args.weights)
    rows = []
    base = DEVELOPMENT_SEED if args.development else HELD_OUT_SEED
    with quiet_upstream():
        for spec, scene, seed in cell_sequences(args.cells, args.sequences, base):
            row = one_sequence(model, spec, scene, seed, args.recipes, not args.no_components)
            rows.append({"camera": spec.label, "scene": scene, "seed": seed, **row})
            print(json.dumps(rows[-1]), flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(rows, indent=1))
    methods = list(rows[0]["abs_rel"])
    for title, value in (
        ("rotation, deg", lambda r, m: r[m]),
        ("AbsRel", lambda r, m: r["abs_rel"][m]),
    ):
        print(f"\n{title}, mean over the cell's sequences")
        print("| cell | " + " | ".join(methods) + " |")
        for cell in args.cells:
            mine = [r for r in rows if f"{r['camera']} {r['scene']}" == cell]
            means = [statistics.mean(value(r, m) for r in mine) for m in methods]
            print(f"| {cell} | " + " | ".join(f"{v:.3f}" for v in means) + " |")


if __name__ == "__main__":
    main()
