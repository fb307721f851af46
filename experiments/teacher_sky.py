"""Issue 37, measuring (deciding nothing): do the pinhole-view teacher's samples on sky hold the
outdoor fits back?

The teacher's targets cover every valid pixel its views see, sky included, where the built-in
networks (trained with sky pixels left out) predict about three times the median depth and the
benchmark scores nothing. For each outdoor wide-lens development sequence (KB4 185 and DS 195,
seeds 80000+, never the benchmark's 90000+; frames 0-23 fitted, 24-35 scored at 112 px) this fits
the default recipe as ``adapt()`` builds it for the network, and the same fit with the teacher's
samples on ground-truth sky dropped (an oracle no user has: it reads the renderer's sky mask),
and scores both with the zero adapter beside them.

    python experiments/teacher_sky.py --network raytun3r-da3-tiny --out runs/teacher_sky.json
    PYTHONPATH=$PWD:$PWD/tests/stubs python experiments/teacher_sky.py --weights W --out ...

One process of one thread; about 5 minutes a sequence here. A rerun skips the sequences its
output already holds.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation import train
from raytun3r_plugin.apps.benchmark import (
    CAMERAS,
    DEVELOPMENT_SEED,
    SCENES,
    fit_and_score,
    make_camera,
    sequence_seed,
)
from raytun3r_plugin.apps.demo import default_network
from raytun3r_plugin.apps.fits import adapt_config
from raytun3r_plugin.registry import quiet_upstream

SIZE, N_ADAPT, N_EVAL = 112, 24, 12
LENSES = ("KB4 185", "DS 195")


class _SkyDropped:
    """``train.teacher_targets`` with the samples on the current sequence's sky left out."""

    def __init__(self) -> None:
        self.original = train.teacher_targets
        self.sky: torch.Tensor | None = None  # (N, H, W) bool, None: the library's own targets

    def __call__(self, model, problem, *args, **kwargs):
        targets = self.original(model, problem, *args, **kwargs)
        if self.sky is None:
            return targets
        grid = tuple(next(iter(problem.inputs.values())).shape[-2:])
        if grid != tuple(self.sky.shape[-2:]):
            # The samples are network-input pixels: the mask must be on the same grid.
            raise SystemExit(f"the sky mask is {tuple(self.sky.shape[-2:])}, the input {grid}")
        kept = {}
        for index, frames in targets.items():
            window = problem.windows[index][0].frames
            kept[index] = []
            for k, (uv, value, view) in enumerate(frames):
                on_sky = self.sky[int(window[k])][uv[:, 1].long(), uv[:, 0].long()]
                kept[index].append((uv[~on_sky], value[~on_sky], view[~on_sky]))
        return kept


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
    parser.add_argument("--sequences", type=int, default=5, help="per lens")
    parser.add_argument("--out", required=True, help="results JSON (one row per sequence)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    dropped = _SkyDropped()
    train.teacher_targets = dropped
    try:
        _run(args, dropped)
    finally:
        train.teacher_targets = dropped.original  # the library as it was


def _run(args: argparse.Namespace, dropped: _SkyDropped) -> None:
    """Fit and score every sequence not yet in ``args.out``, then print the cells' means."""
    out = Path(args.out)
    rows = json.loads(out.read_text()) if out.is_file() else []
    done = {row["seed"] for row in rows}
    if args.weights:
        from raytun3r_plugin.apps.trained_networks import load_trained_network

        model, description = load_trained_network(args.weights)
    else:
        model, description = default_network(args.network)
    print(f"network: {description}")
    for k in range(args.sequences):
        for label in LENSES:
            lens = [spec.label for spec in CAMERAS].index(label)
            seed = sequence_seed(lens, SCENES.index("outdoor"), k, DEVELOPMENT_SEED)
            if seed in done:
                continue
            camera = make_camera(CAMERAS[lens], SIZE)
            seq = synthetic.render_sequence("outdoor", camera, n_frames=N_ADAPT + N_EVAL, seed=seed)
            frames = list(range(N_ADAPT, N_ADAPT + N_EVAL))
            fit = (camera, seq.images[:N_ADAPT], adapt_config(SIZE, 300, seed=0, model=model), None)
            row = {"cell": f"{label} outdoor", "seed": seed}
            dropped.sky = None
            row["zero"] = fit_and_score(model, seq, frames)["abs_rel"]
            row["default"] = fit_and_score(model, seq, frames, fit)["abs_rel"]
            dropped.sky = torch.from_numpy(np.asarray(seq.meta["per_frame"]["sky"], bool))
            row["no_sky_teacher"] = fit_and_score(model, seq, frames, fit)["abs_rel"]
            dropped.sky = None
            rows.append(row)
            print(json.dumps(row), flush=True)
            out.write_text(json.dumps(rows, indent=1))
    for label in LENSES:
        cell = [row for row in rows if row["cell"] == f"{label} outdoor"]
        if cell:
            means = {
                key: np.mean([row[key] for row in cell])
                for key in ("zero", "default", "no_sky_teacher")
            }
            worse = sum(row["no_sky_teacher"] > row["default"] for row in cell)
            print(
                f"{label} outdoor, {len(cell)} sequences: AbsRel zero {means['zero']:.4f}, default "
                f"{means['default']:.4f}, teacher without sky {means['no_sky_teacher']:.4f} "
                f"({100 * (means['no_sky_teacher'] / means['default'] - 1):+.1f} %, worse on {worse})"
            )


if __name__ == "__main__":
    with quiet_upstream():
        main()
