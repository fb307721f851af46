"""The synthetic fisheye benchmark (issues 7, 15): vanilla vs Center-PH vs Multi-PH vs raytun3r
(and, with --baselines, LoRA and calibration tokens fitted on the same frames) on held-out
sequences of three lenses (KB4 120, KB4 185, double sphere 195 deg), indoor and outdoor; every
row with its trainable parameters and time per frame relative to vanilla.

    python benchmarks/fisheye_synthetic.py [--out runs/bench] [--readme README.md]
    python benchmarks/fisheye_synthetic.py --sequences 1 --baselines lora,caltok
    python benchmarks/fisheye_synthetic.py --development --out runs/dev   # seeds 80000+, for choosing settings

With --readme the table replaces the block between the README's bench markers, so the README
shows what this script produced, not typed numbers.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from raytun3r_plugin.adaptation.config import POSE_SOURCES
from raytun3r_plugin.apps.benchmark import (
    BASELINES,
    DEVELOPMENT_SEED,
    HELD_OUT_SEED,
    SEQUENCES_PER_CELL,
    run_benchmark,
)
from raytun3r_plugin.apps.cli import parse_view_weights
from raytun3r_plugin.apps.demo import DEFAULT_NETWORK, NETWORK_FIT, default_network
from raytun3r_plugin.baselines.multi_ph import VIEW_NAMES
from raytun3r_plugin.registry import quiet_upstream

START, END = "<!-- bench:start -->", "<!-- bench:end -->"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/bench")
    parser.add_argument("--size", type=int, default=112)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument(
        "--sequences",
        type=int,
        default=SEQUENCES_PER_CELL,
        help="held-out sequences per camera and scene",
    )
    parser.add_argument("--readme", default=None)
    parser.add_argument(
        "--baselines",
        default="",
        help=f"comma-separated baselines to fit and score per sequence: {', '.join(BASELINES)}",
    )
    parser.add_argument(
        "--development",
        action="store_true",
        help="development seeds (80000+) instead of the held-out ones; never with --readme",
    )
    parser.add_argument(
        "--network",
        default=DEFAULT_NETWORK,
        choices=sorted(NETWORK_FIT),
        help="built-in network (v2 = raytun3r-da3-tiny measured the README's older tables)",
    )
    parser.add_argument(
        "--pose-source",
        default=None,
        choices=POSE_SOURCES,
        help="pose source of the self-supervised fits (default: the network's, demo.NETWORK_FIT)",
    )
    parser.add_argument(
        "--pose-weight",
        type=float,
        default=None,
        help="weight of the pose term in the self-supervised fits (default: the network's with its own "
        "pose source, 1 with another)",
    )
    parser.add_argument(
        "--teacher-weight",
        type=float,
        default=None,
        help="weight of the pinhole-view teacher term in the self-supervised fits (default: the "
        "network's, demo.NETWORK_FIT)",
    )
    parser.add_argument(
        "--teacher-views",
        nargs="+",
        default=None,
        choices=VIEW_NAMES,
        help="views of the pinhole-view teacher (default: the library's, the centre view)",
    )
    parser.add_argument(
        "--teacher-view-weights",
        nargs="+",
        default=None,
        metavar="VIEW=WEIGHT",
        help="each teacher view's weight, one per view of --teacher-views (default: their mean)",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="worker processes of one thread each (run_benchmark(jobs=)); the timing columns "
        "are then one thread's beside the other workers",
    )
    args = parser.parse_args()
    if args.development and args.readme:
        parser.error(
            "--development tables are for choosing settings; the README shows held-out seeds"
        )
    model, description = default_network(args.network)
    table = run_benchmark(
        model,
        args.out,
        size=args.size,
        steps=args.steps,
        sequences=args.sequences,
        network=description,
        progress=False,
        base_seed=DEVELOPMENT_SEED if args.development else HELD_OUT_SEED,
        baselines=tuple(name for name in args.baselines.split(",") if name),
        pose_source=args.pose_source or NETWORK_FIT[args.network]["pose_source"],
        pose_weight=args.pose_weight
        if args.pose_weight is not None or args.pose_source
        else NETWORK_FIT[args.network]["pose_weight"],
        teacher_weight=args.teacher_weight,
        teacher_views=tuple(args.teacher_views) if args.teacher_views else None,
        teacher_view_weights=parse_view_weights(args.teacher_view_weights),
        jobs=args.jobs,
    )
    print(table)
    if args.readme:
        readme = Path(args.readme)
        text = readme.read_text()
        block = f"{START}\n{table}\n{END}"
        text = (
            re.sub(re.escape(START) + ".*?" + re.escape(END), lambda _: block, text, flags=re.S)
            if START in text
            else text + "\n" + block + "\n"
        )
        readme.write_text(text)


if __name__ == "__main__":
    with quiet_upstream():  # no per-forward INFO lines from the backbone's own logger
        main()
