"""Effect of each parameter-free correction (no adapter), per component set.

    python benchmarks/components.py                    # the demo's sequence
    python benchmarks/components.py --dev-sequences 5  # 5 development sequences per benchmark cell

Prints one row per component set: vanilla, each correction alone, and all of them. With
``--dev-sequences N`` the rows are means over N sequences of every (camera, scene) cell of the
benchmark, rendered from development seeds (80000 + 100 k + 10 camera + scene, never the
benchmark's 90000+), with on how many sequences each metric is lower than vanilla's.
"""

from __future__ import annotations

import argparse

from raytun3r_plugin import synthetic
from raytun3r_plugin.apps.benchmark import CAMERAS, SCENES, make_camera
from raytun3r_plugin.apps.demo import default_network, demo_camera
from raytun3r_plugin.apps.evaluation import format_table, headline, run_method, score
from raytun3r_plugin.registry import quiet_upstream

SETS = (
    ["patch_resample"],
    ["border_tokens"],
    ["grid"],
    ["patch_resample", "grid"],
    ["patch_resample", "border_tokens", "grid"],
)
METRICS = ("d_reproj_px", "abs_rel", "delta_1.25")
DEV_SEED = 80_000


def score_sets(model, seq, held_out: list[int]) -> dict[str, dict[str, float]]:
    """{component set label: headline scores} on the held-out frames of one sequence."""
    scores = {
        "vanilla (unpatched)": headline(
            score(seq, run_method(model, seq, "vanilla", frames=held_out))
        )
    }
    for components in SETS:
        output = run_method(model, seq, "raytun3r", frames=held_out, components=components)
        scores[" + ".join(components)] = headline(score(seq, output))
    return scores


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--dev-sequences",
        type=int,
        default=0,
        help="sequences per benchmark cell (0: the demo's sequence)",
    )
    args = parser.parse_args()
    model, description = default_network()
    print(f"network: {description}")
    if not args.dev_sequences:
        seq = synthetic.render_sequence("indoor", demo_camera(112), n_frames=36, seed=1000)
        scores = score_sets(model, seq, list(range(24, 36)))
        print(
            format_table(
                [{"components": label, **row} for label, row in scores.items()],
                ["components", *METRICS],
            )
        )
        return
    per_sequence = []
    for camera_index, spec in enumerate(CAMERAS):
        camera = make_camera(spec, 112)
        for scene_index, scene in enumerate(SCENES):
            for k in range(args.dev_sequences):
                seed = DEV_SEED + 100 * k + 10 * camera_index + scene_index
                seq = synthetic.render_sequence(scene, camera, n_frames=36, seed=seed)
                per_sequence.append(score_sets(model, seq, list(range(24, 36))))
    rows = []
    for label in per_sequence[0]:
        row = {"components": label}
        for key in METRICS:
            row[key] = sum(s[label][key] for s in per_sequence) / len(per_sequence)
        if label != "vanilla (unpatched)":
            lower = {
                key: sum(s[label][key] < s["vanilla (unpatched)"][key] for s in per_sequence)
                for key in ("d_reproj_px", "abs_rel")
            }
            row["lower_than_vanilla"] = ", ".join(
                f"{key} {n}/{len(per_sequence)}" for key, n in lower.items()
            )
        rows.append(row)
    print(
        f"{len(per_sequence)} development sequences ({args.dev_sequences} per camera and scene), 112 px, frames 24-35 scored; means:"
    )
    print(format_table(rows, ["components", *METRICS, "lower_than_vanilla"]))


if __name__ == "__main__":
    with quiet_upstream():  # no per-forward INFO lines from the backbone's own logger
        main()
