"""Multi-PH against Center-PH and vanilla on the demo's sequence: headline scores and cost.

    python benchmarks/multi_ph.py                  # the demo's first sequence (seed 1000)
    python benchmarks/multi_ph.py --sequences 4    # the demo's four (seeds 1000-1003), means

The built-in network (``raytun3r-da3-tiny``) on the demo lens (KB4 190 degrees, 112 px), frames
24-35 of each 36-frame indoor render scored, as in ``raytun3r demo``. Time per frame is the
median over ``--repeats`` runs of :func:`run_method` (round-robin, the order rotating each
repeat, so a slow spell of a shared machine hits every method alike), relative to vanilla's;
"images / frame" counts the images the network runs on per input frame.
"""

from __future__ import annotations

import argparse
import statistics

import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.apps.demo import default_network, demo_camera
from raytun3r_plugin.apps.evaluation import (
    METRIC_COLUMNS,
    format_table,
    headline,
    run_method,
    score,
)

METHODS = ("vanilla", "center-ph", "multi-ph")
#: One demo sequence per run: the table's metric columns without camera and scene.
COLUMNS = [
    *(c for c in METRIC_COLUMNS if c not in ("camera", "scene")),
    "images_per_frame",
    "ms_per_frame",
    "x_vanilla",
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", type=int, default=1, help="demo sequences (seed 1000 + k)")
    parser.add_argument("--size", type=int, default=112, help="input side, px")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per method")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model, description = default_network()
    print(f"network: {description}")
    camera = demo_camera(args.size)
    held_out = list(range(24, 36))
    scores: dict[str, list[dict]] = {m: [] for m in METHODS}
    seconds: dict[str, list[float]] = {m: [] for m in METHODS}
    images: dict[str, int] = {}
    tilt = None
    for k in range(args.sequences):
        seq = synthetic.render_sequence("indoor", camera, n_frames=36, seed=1000 + k)
        for repeat in range(args.repeats):
            order = METHODS[repeat % len(METHODS) :] + METHODS[: repeat % len(METHODS)]
            for method in order:
                output = run_method(model, seq, method, frames=held_out)
                seconds[method].append(output.seconds / len(held_out))
                if repeat == 0:
                    scores[method].append(headline(score(seq, output)))
                    images[method] = int(output.extras.get("forward_images", len(held_out)))
                    tilt = output.extras.get("tilt_deg", tilt)
    base = statistics.median(seconds["vanilla"])
    rows = []
    for method in METHODS:
        per_frame = statistics.median(seconds[method])
        row: dict = {"method": method}
        for key in COLUMNS[1:7]:
            row[key] = sum(s[key] for s in scores[method]) / len(scores[method])
        row["images_per_frame"] = images[method] / len(held_out)
        row["ms_per_frame"] = 1000 * per_frame
        row["x_vanilla"] = per_frame / base
        rows.append(row)
    print(
        f"demo lens {camera!r}; {args.sequences} sequence(s), frames 24-35 scored; "
        f"Multi-PH tilt {tilt:g} deg; torch {torch.__version__}, {torch.get_num_threads()} thread(s), "
        f"median of {args.repeats} runs"
    )
    print(format_table(rows, COLUMNS))


if __name__ == "__main__":
    main()
