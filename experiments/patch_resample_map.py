"""Patch resampling's local map: the central pinhole's (today) against a pinhole turned to look
along each patch's own ray (the paper's stated aim, "a pinhole crop from the same viewing
direction"), measured for rotation and depth on the benchmark's sequences.

``central`` resamples each patch with the local inverse Jacobian of the map to a pinhole on the
lens axis. Away from the axis that pinhole stretches the image radially by 1/cos^2 of the ray
angle, so the local map zooms each rim patch in (its singular values clamped at 1/2): a patch
reads about a quarter of its own footprint, and the content between patches reaches no token.
``turned`` takes the Jacobian against a pinhole of the same focal length turned (by the smallest
rotation) to look along the patch centre's ray: no perspective stretch, so a rim patch is
resampled to the lens's own local scale and keeps its content (the components switch
``"resample_turned"``; both are ``geometry.patch_resample_grid(..., local_map=NAME)``). Every
fit and score of a row runs under the map it names.

    python experiments/patch_resample_map.py --coverage
    python experiments/patch_resample_map.py [--development] [--cells ...] [--recipes default]
        [--network v3] [--out runs/resample.json]

The decision it serves: docs/decisions.md, "Patch resampling's local map".
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import torch

from raytun3r_plugin import geometry, synthetic
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.adapter import COMPONENTS
from raytun3r_plugin.apps.benchmark import (
    CAMERAS,
    DEVELOPMENT_SEED,
    HELD_OUT_SEED,
    SCENES,
    SEQUENCES_PER_CELL,
    cell_sequences,
    make_camera,
)
from raytun3r_plugin.apps.demo import DEFAULT_NETWORK, default_network
from raytun3r_plugin.apps.evaluation import headline, run_method, score
from raytun3r_plugin.apps.fits import adapt_config
from raytun3r_plugin.registry import quiet_upstream

SIZE, N_ADAPT, N_EVAL, STEPS = 112, 24, 12, 300
MAPS = ("central", "turned")


def switches(name: str) -> list[str]:
    """``components=`` of every correction with patch resampling's ``name`` map."""
    return [*COMPONENTS, "resample_turned"] if name == "turned" else list(COMPONENTS)


def one_sequence(model, spec, scene: str, seed: int, recipes: list[str]) -> dict:
    """Rotation (deg), AbsRel and d_reproj (px) of every method on one sequence, per local map."""
    camera = make_camera(spec, SIZE)
    seq = synthetic.render_sequence(scene, camera, n_frames=N_ADAPT + N_EVAL, seed=seed)
    held_out = list(range(N_ADAPT, N_ADAPT + N_EVAL))
    row: dict[str, dict[str, float]] = {}

    def record(name: str, method: str, **kwargs) -> None:
        numbers = headline(score(seq, run_method(model, seq, method, frames=held_out, **kwargs)))
        row[name] = {k: float(numbers[k]) for k in ("rot_deg", "abs_rel", "d_reproj_px")}

    record("vanilla", "vanilla")
    record("center-ph", "center-ph")
    for name in MAPS:
        record(f"zero adapter, {name}", "raytun3r", components=switches(name))
        for recipe in recipes:
            config = adapt_config(SIZE, STEPS, recipe=recipe, seed=0, components=switches(name))
            fitted = adapt(model, camera, seq.first_images(N_ADAPT), config, progress=False)
            # Scored with the components the adapter file records, as ``apply`` uses them.
            record(f"{recipe} recipe, {name}", "raytun3r", adapter=fitted)
    return row


def _print_means(rows: list[dict], cells: list[str]) -> None:
    methods = [m for m in rows[0] if m not in ("camera", "scene", "seed")]
    for metric in ("rot_deg", "abs_rel", "d_reproj_px"):
        print(f"\n{metric}, mean over the cell's sequences")
        print("| cell | " + " | ".join(methods) + " |")
        for cell in cells:
            mine = [r for r in rows if f"{r['camera']} {r['scene']}" == cell]
            if mine:
                means = [statistics.mean(r[m][metric] for r in mine) for m in methods]
                print(f"| {cell} ({len(mine)}) | " + " | ".join(f"{v:.3f}" for v in means) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cells = [f"{spec.label} {scene}" for spec in CAMERAS for scene in SCENES]
    parser.add_argument("--coverage", action="store_true", help="print coverage only")
    parser.add_argument("--cells", nargs="+", default=cells, choices=cells)
    parser.add_argument("--sequences", type=int, default=SEQUENCES_PER_CELL)
    parser.add_argument("--development", action="store_true", help="development seeds (80000+)")
    parser.add_argument("--recipes", nargs="*", default=["default"])
    parser.add_argument("--network", default=DEFAULT_NETWORK)
    parser.add_argument("--out", default="runs/resample.json")
    args = parser.parse_args()
    if args.coverage:
        for size in (112, 504):
            for spec in CAMERAS:
                camera = make_camera(spec, size)
                shares = ", ".join(
                    f"{m} {geometry.resampled_share(camera, size, size, 14, m):.3f}" for m in MAPS
                )
                print(f"{spec.label} at {size} px: share of the lens's pixels read: {shares}")
        return
    torch.set_num_threads(1)
    model, _ = default_network(args.network)
    rows = []
    base = DEVELOPMENT_SEED if args.development else HELD_OUT_SEED
    with quiet_upstream():
        for spec, scene, seed in cell_sequences(args.cells, args.sequences, base):
            row = one_sequence(model, spec, scene, seed, args.recipes)
            rows.append({"camera": spec.label, "scene": scene, "seed": seed, **row})
            print(json.dumps(rows[-1]), flush=True)
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            Path(args.out).write_text(json.dumps(rows, indent=1))
    _print_means(rows, args.cells)


if __name__ == "__main__":
    main()
