"""The synthetic fisheye benchmark (issues 7, 15): vanilla vs Center-PH vs Multi-PH vs raytun3r
(and, with --baselines, LoRA and calibration tokens fitted on the same frames) on held-out
sequences of three lenses (KB4 120, KB4 185, double sphere 195 deg), indoor and outdoor; every
row with its trainable parameters and time per frame relative to vanilla.

    python benchmarks/fisheye_synthetic.py [--out runs/bench] [--results docs/results.md]
    python benchmarks/fisheye_synthetic.py --sequences 1 --baselines lora,caltok
    python benchmarks/fisheye_synthetic.py --development --out runs/dev   # seeds 80000+, for choosing settings
    PYTHONPATH=tests/stubs python benchmarks/fisheye_synthetic.py --development \
        --weights runs/vggt_tiny/raytun3r-vggt-small.safetensors   # a network trained with --arch vggt

With --results the table replaces the block between the file's bench markers, so the results
page shows what this script produced, not typed numbers.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from raytun3r_plugin.adaptation.config import POSE_SOURCES, POSE_WINDOWS
from raytun3r_plugin.adaptation.recipes import recipe_names
from raytun3r_plugin.apps.benchmark import (
    BASELINES,
    CAMERAS,
    DEVELOPMENT_SEED,
    HELD_OUT_SEED,
    NEW_LENSES,
    SEQUENCES_PER_CELL,
    run_benchmark,
)
from raytun3r_plugin.apps.cli_adapt import parse_view_weights
from raytun3r_plugin.apps.demo import BUILT_IN_NETWORKS, DEFAULT_NETWORK
from raytun3r_plugin.apps.trained_networks import network_from
from raytun3r_plugin.baselines.multi_ph import VIEW_NAMES
from raytun3r_plugin.registry import quiet_upstream

START, END = "<!-- bench:start -->", "<!-- bench:end -->"


def fit_changes(args: argparse.Namespace) -> dict:
    """The recipe changes the options ask for (``AdaptConfig`` fields)."""
    changes: dict = {}
    weights = {
        term: value
        for term, value in (("pose", args.pose_weight), ("teacher", args.teacher_weight))
        if value is not None
    }
    if weights:
        changes["weights"] = weights
    if args.pose_source:
        changes["pose_source"] = args.pose_source
    if args.pose_windows:
        changes["pose_windows"] = args.pose_windows
    if args.lr is not None:
        changes["lr"] = args.lr
    if args.lr_without_teacher is not None:
        changes["lr_without_teacher"] = args.lr_without_teacher
    if args.teacher_views:
        changes["teacher_views"] = tuple(args.teacher_views)
    view_weights = parse_view_weights(args.teacher_view_weights)
    if view_weights is not None:
        changes["teacher_view_weights"] = view_weights
    return changes


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
    parser.add_argument(
        "--results", default=None, help="write the table into this file's bench markers"
    )
    parser.add_argument(
        "--baselines",
        default="",
        help=f"comma-separated baselines to fit and score per sequence: {', '.join(BASELINES)}",
    )
    parser.add_argument(
        "--development",
        action="store_true",
        help="development seeds (80000+) instead of the held-out ones; never with --results",
    )
    parser.add_argument(
        "--new-lenses",
        action="store_true",
        help="the lens models no setting was chosen on (UCM 200, EUCM 210) instead of the "
        "benchmark's three; held-out seeds only, reported apart",
    )
    parser.add_argument(
        "--network",
        default=None,
        choices=BUILT_IN_NETWORKS,
        help=f"built-in network (default {DEFAULT_NETWORK}; v2 = raytun3r-da3-tiny measured the "
        "older tables of docs/results.md)",
    )
    parser.add_argument(
        "--first-sequence",
        type=int,
        default=0,
        help="start each cell at its K-th sequence (the seeds of a run with more sequences)",
    )
    parser.add_argument(
        "--cameras",
        nargs="+",
        default=None,
        metavar="LABEL",
        help="only these lenses of the run's set, by label (e.g. 'KB4 185' 'DS 195'); each "
        "sequence keeps the seed it has in the full run",
    )
    parser.add_argument(
        "--weights",
        default=None,
        metavar="FILE",
        help="instead of a built-in network, one exported by scripts/train_default_network.py "
        "(its JSON sidecar names the architecture; a VGGT one needs PYTHONPATH=tests/stubs)",
    )
    parser.add_argument(
        "--recipe",
        default="default",
        choices=recipe_names(),
        help="fit recipe of the self-supervised fits and the baselines (default: default)",
    )
    parser.add_argument(
        "--pose-source",
        default=None,
        choices=POSE_SOURCES,
        help="change the recipe's pose source",
    )
    parser.add_argument(
        "--pose-weight", type=float, default=None, help="change the recipe's pose-term weight"
    )
    parser.add_argument(
        "--pose-windows",
        default=None,
        choices=POSE_WINDOWS,
        help="change which windows the recipe's pose term scores",
    )
    parser.add_argument(
        "--lr", type=float, default=None, help="change the recipe's Adam learning rate"
    )
    parser.add_argument(
        "--lr-without-teacher",
        type=float,
        default=None,
        help="the step size of fits whose teacher term is off (AdaptConfig.lr_without_teacher)",
    )
    parser.add_argument(
        "--teacher-weight",
        type=float,
        default=None,
        help="change the recipe's pinhole-view teacher weight",
    )
    parser.add_argument(
        "--teacher-views",
        nargs="+",
        default=None,
        choices=VIEW_NAMES,
        help="change the recipe's teacher views",
    )
    parser.add_argument(
        "--teacher-view-weights",
        nargs="+",
        default=None,
        metavar="VIEW=WEIGHT",
        help="each teacher view's weight, one per view of --teacher-views",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="Ray workers of one thread each (run_benchmark(jobs=); 1: in this process); the timing columns "
        "are then one thread's beside the other workers",
    )
    args = parser.parse_args()
    if args.new_lenses and (args.development or args.results):
        parser.error(
            "--new-lenses is a held-out run, reported apart: no --development, no --results"
        )
    if args.development and args.results:
        parser.error(
            "--development tables are for choosing settings; the results page shows held-out seeds"
        )
    lenses = NEW_LENSES if args.new_lenses else CAMERAS
    if args.cameras:
        unknown = sorted(set(args.cameras) - {spec.label for spec in lenses})
        if unknown:
            parser.error(f"--cameras: unknown {unknown}; this run's: {[s.label for s in lenses]}")
        lenses = tuple(spec for spec in lenses if spec.label in args.cameras)
    if args.weights and args.network:
        parser.error("--weights names the network: no --network with it")
    model, description = network_from(args.network or DEFAULT_NETWORK, args.weights)
    table = run_benchmark(
        model,
        args.out,
        size=args.size,
        steps=args.steps,
        sequences=args.sequences,
        first_sequence=args.first_sequence,
        network=description,
        progress=False,
        base_seed=DEVELOPMENT_SEED if args.development else HELD_OUT_SEED,
        baselines=tuple(name for name in args.baselines.split(",") if name),
        recipe=args.recipe,
        fit_changes=fit_changes(args),
        jobs=args.jobs,
        cameras=lenses,
    )
    print(table)
    if args.results:
        results = Path(args.results)
        text = results.read_text()
        block = f"{START}\n{table}\n{END}"
        text = (
            re.sub(re.escape(START) + ".*?" + re.escape(END), lambda _: block, text, flags=re.S)
            if START in text
            else text + "\n" + block + "\n"
        )
        results.write_text(text)


if __name__ == "__main__":
    with quiet_upstream():  # no per-forward INFO lines from the backbone's own logger
        main()
