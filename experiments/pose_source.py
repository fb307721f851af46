"""Which pose source, and which pose weight, the default network's self-supervised fits use.

On development sequences of the benchmark's indoor cells (seeds 80000+; outdoors every fit
stops with "no signal", so the choice cannot matter there), fits the adapter once per variant
(``pose_source`` and the pose term's weight, ``--variants``) and scores each fit, vanilla, the
zero adapter and the supervised fit on the held-back frames, as the benchmark does. Prints the
per-sequence rows and, per variant, the mean rotation error and AbsRel with the number of
sequences on which the fit is below the zero adapter. docs/decisions.md states the rule that
this table decides.

    python experiments/pose_source.py [--sequences 3] [--variants targets,hybrid:1,model]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from raytun3r_plugin.adaptation.config import SELF_SUPERVISED_WEIGHTS
from raytun3r_plugin.apps.benchmark import (
    CAMERAS,
    DEVELOPMENT_SEED,
    SUPERVISED,
    ZERO_ADAPTER,
    ground_truth_depth,
    make_camera,
    sequence_seed,
    timed_row,
)
from raytun3r_plugin.apps.demo import DEFAULT_NETWORK, default_network
from raytun3r_plugin.apps.evaluation import format_table
from raytun3r_plugin.apps.fits import adapt_config, supervised_config
from raytun3r_plugin.registry import quiet_upstream

DEFAULT_VARIANTS = "targets,hybrid:0.3,hybrid:1,hybrid:3,model:1"


def parse_variant(text: str) -> tuple[str, float]:
    """``"hybrid:0.3"`` -> ``("hybrid", 0.3)``; a bare pose source keeps the default weight."""
    source, _, weight = text.partition(":")
    return source, float(weight) if weight else SELF_SUPERVISED_WEIGHTS["pose"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sequences", type=int, default=3, help="development seeds per indoor cell"
    )
    parser.add_argument("--variants", default=DEFAULT_VARIANTS)
    parser.add_argument("--network", default=DEFAULT_NETWORK)
    parser.add_argument("--size", type=int, default=112)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--out", default="runs/pose_source")
    parser.add_argument(
        "--no-supervised", action="store_true", help="leave out the supervised fit (a rerun)"
    )
    args = parser.parse_args()
    from raytun3r_plugin import synthetic
    from raytun3r_plugin.adaptation.train import adapt

    variants = [parse_variant(v) for v in args.variants.split(",") if v]
    model, _ = default_network(args.network)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    n_adapt, n_eval = 24, 12
    rows = []
    with quiet_upstream():
        for camera_index, spec in enumerate(CAMERAS):
            camera = make_camera(spec, args.size)
            for k in range(args.sequences):
                seed = sequence_seed(camera_index, 0, k, DEVELOPMENT_SEED)
                seq = synthetic.render_sequence(
                    "indoor", camera, n_frames=n_adapt + n_eval, seed=seed
                )
                held_out = list(range(n_adapt, len(seq)))
                cell = {"camera": spec.label, "seed": seed}
                scored = {
                    "vanilla": timed_row(model, seq, "vanilla", held_out),
                    ZERO_ADAPTER: timed_row(model, seq, "raytun3r", held_out),
                }
                if not args.no_supervised:
                    supervised = adapt(
                        model,
                        camera,
                        seq.images[:n_adapt],
                        supervised_config(args.size, args.steps),
                        resume=False,
                        depth=ground_truth_depth(seq, n_adapt),
                        progress=False,
                    )
                    scored[SUPERVISED] = timed_row(
                        model, seq, "raytun3r", held_out, adapter=supervised
                    )
                for source, weight in variants:
                    config = adapt_config(
                        args.size, args.steps, seed=0, pose_source=source, pose_weight=weight
                    )
                    adapter = adapt(
                        model, camera, seq.images[:n_adapt], config, resume=False, progress=False
                    )
                    scored[f"{source}:{weight:g}"] = timed_row(
                        model, seq, "raytun3r", held_out, adapter=adapter
                    )
                for method, values in scored.items():
                    rows.append(
                        {
                            **cell,
                            "method": method,
                            "rot_deg": values["rot_deg"],
                            "abs_rel": values["abs_rel"],
                            "d_reproj_px": values["d_reproj_px"],
                        }
                    )
                print(format_table(rows[-len(scored) :], list(rows[-1])), flush=True)
    (out / "rows.json").write_text(json.dumps(rows, indent=1))
    print(format_table(summary(rows), list(summary(rows)[0])))


def summary(rows: list[dict]) -> list[dict]:
    """Per method: mean rotation error, AbsRel and d_reproj over the sequences, and on how many
    sequences each is below the zero adapter's."""
    zero = {row["seed"]: row for row in rows if row["method"] == ZERO_ADAPTER}
    methods = list(dict.fromkeys(row["method"] for row in rows))
    table = []
    for method in methods:
        mine = [row for row in rows if row["method"] == method]
        entry = {"method": method, "sequences": len(mine)}
        for key in ("rot_deg", "abs_rel", "d_reproj_px"):
            values = [row[key] for row in mine]
            entry[key] = sum(values) / len(values) if values else math.nan
            below = sum(row[key] < zero[row["seed"]][key] for row in mine)
            entry[f"{key} below zero"] = f"{below}/{len(mine)}"
        table.append(entry)
    return table


if __name__ == "__main__":
    main()
