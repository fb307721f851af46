"""Issue 12, outdoors: do sharper matches or a longer baseline give the self-supervised fit a signal?

Outdoors (forward driving, 112 px) the parallax gate drops every window and the fit stops with
"no signal": the matches that survive are far, and a far match's reprojection hardly moves when
its depth changes (docs/adaptation.md section 6). Two ways to get more parallax out of the same
camera path, each fitted with the demo's settings (300 steps, network input 112 px, the gate on):

* ``native 448``: the frames rendered at 448 px along the same path (the renderer's per-frame
  motion target scaled with the size) and matched there, so the near road is four times
  better sampled; the network still reads 112 px;
* ``stride 8``: windows of frames 8 apart (``AdaptConfig.stride``) at 112 px, eight times the
  baseline of the default windows;
* ``photometric``: the default windows at 112 px with the dense photometric term on
  (``LossWeights.photo`` = 100, frames blurred by 1 px, 4,096 pixels per pair and step; with it
  the gate keeps every window), which needs no match on the near road;
* ``photometric scale``: the default windows and terms at 112 px, but each pair's target
  translation scaled to the length that best aligns the two frames densely
  (``AdaptConfig.scale = "photometric"``) instead of the matches' pixel-optimal length, which
  far matches shrink to 1-2 % of the true one outdoors;

beside ``no adapter`` (what the gated fit gives outdoors) and ``supervised`` (the tables fitted to
the sequence's own ground-truth depth on the same frames: the upper bound). Each is fitted on
frames 0-23 and scored on frames 24-35 of the 112 px render. Development seeds only (80000 + 100 k
+ 10 camera + scene, never the benchmark's 90000+).

Decision rule, fixed before the first run: a variant is recommended for outdoor segments (README
and docs/adaptation.md) only if on these sequences it is below no adapter on both AbsRel and
d_reproj on at least 80 % of them, never more than 5 % worse on AbsRel, and closes at least a
tenth of the AbsRel gap between no adapter and supervised on average. The photometric variant
was added later under the same rule, fixed before its 15-sequence run (its weight was chosen on
two of these sequences, KB4 185 k=0 and KB4 120 k=0), and so was the photometric-scale
variant (no setting was tuned for it; it was tried on KB4 185 k=0 and KB4 120 k=0 first).

    python experiments/outdoor_signal.py              # 5 seeds x 3 cameras, ~90 min, 2 jobs
    python experiments/outdoor_signal.py --methods photometric   # one variant, ~30 min
    python experiments/outdoor_signal.py --sequences 1 --steps 30 --jobs 1
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from raytun3r_plugin import synthetic
from raytun3r_plugin.apps.benchmark import (
    CAMERAS,
    DEVELOPMENT_SEED,
    SCENES,
    fit_and_score,
    ground_truth_depth,
    make_camera,
    sequence_line,
    sequence_seed,
)
from raytun3r_plugin.apps.demo import default_network
from raytun3r_plugin.apps.fits import adapt_config, supervised_config
from raytun3r_plugin.apps.workers import cpu_jobs
from raytun3r_plugin.cluster import ClusterSpec, map_tasks
from raytun3r_plugin.registry import quiet_upstream

SIZE, NATIVE, STRIDE, N_ADAPT, N_EVAL = 112, 448, 8, 24, 12
PHOTO_WEIGHT = 100.0
VARIANTS = (f"native {NATIVE}", f"stride {STRIDE}", "photometric", "photometric scale")
METHODS = ("no adapter", *VARIANTS, "supervised")


def _load_network():
    return default_network()[0]


def photometric_config(steps: int):
    """The demo's fit settings with the dense photometric term on at :data:`PHOTO_WEIGHT`."""
    config = adapt_config(SIZE, steps, seed=0)
    return dataclasses.replace(
        config, weights=dataclasses.replace(config.weights, photo=PHOTO_WEIGHT)
    )


def score_outdoor_sequence(
    model, camera_index: int, k: int, steps: int, methods: tuple[str, ...] = METHODS
) -> list[dict]:
    """The rows of ``methods`` (of :data:`METHODS`) for outdoor development sequence ``k`` of
    camera ``camera_index``."""
    spec = CAMERAS[camera_index]
    seed = sequence_seed(camera_index, SCENES.index("outdoor"), k, DEVELOPMENT_SEED)
    camera = make_camera(spec, SIZE)
    seq = synthetic.render_sequence("outdoor", camera, n_frames=N_ADAPT + N_EVAL, seed=seed)
    fits = {
        f"stride {STRIDE}": (
            camera,
            seq.images[:N_ADAPT],
            adapt_config(SIZE, steps, seed=0, stride=STRIDE),
            None,
        ),
        "photometric": (camera, seq.images[:N_ADAPT], photometric_config(steps), None),
        "photometric scale": (
            camera,
            seq.images[:N_ADAPT],
            adapt_config(SIZE, steps, seed=0, scale="photometric"),
            None,
        ),
        "supervised": (
            camera,
            seq.images[:N_ADAPT],
            supervised_config(SIZE, steps),
            ground_truth_depth(seq, N_ADAPT),
        ),
    }
    if f"native {NATIVE}" in methods:
        sharp_camera = make_camera(spec, NATIVE)
        sharp = synthetic.render_sequence(
            "outdoor",
            sharp_camera,
            n_frames=N_ADAPT,
            seed=seed,
            flow_px=synthetic.FLOW_PX * NATIVE / SIZE,
        )
        fits[f"native {NATIVE}"] = (
            sharp_camera,
            sharp.images[:N_ADAPT],
            adapt_config(SIZE, steps, seed=0),
            None,
        )
    held_out = list(range(N_ADAPT, N_ADAPT + N_EVAL))
    return [
        {
            "camera": spec.label,
            "k": k,
            "method": method,
            **fit_and_score(model, seq, held_out, fits.get(method)),
        }
        for method in methods
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", type=int, default=5)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--jobs", type=int, default=cpu_jobs(2))
    parser.add_argument(
        "--methods",
        nargs="+",
        choices=VARIANTS,
        default=list(VARIANTS),
        help="variants to fit (no adapter and supervised are always scored)",
    )
    args = parser.parse_args()
    if args.sequences < 1 or args.steps < 1 or args.jobs < 1:
        parser.error("--sequences, --steps and --jobs must be at least 1")
    variants = tuple(v for v in VARIANTS if v in args.methods)
    methods = ("no adapter", *variants, "supervised")
    _, description = default_network()
    print(
        f"network: {description}; {args.sequences} outdoor development seeds per camera, network "
        f"input {SIZE} px, fitted on frames 0-{N_ADAPT - 1}, scored on frames "
        f"{N_ADAPT}-{N_ADAPT + N_EVAL - 1}; {args.jobs} workers of one thread each (Ray tasks; 1: in this process)\n",
        flush=True,
    )
    tasks = [
        (ci, k, args.steps, methods) for ci in range(len(CAMERAS)) for k in range(args.sequences)
    ]
    rows = []
    for _, sequence_rows in map_tasks(
        score_outdoor_sequence, tasks, ClusterSpec(workers=args.jobs), initializer=_load_network
    ):
        rows += sequence_rows
        first = sequence_rows[0]
        print(sequence_line(f"{first['camera']} k={first['k']}", sequence_rows), flush=True)
    print("\n| camera | method | AbsRel | d_reproj px | fits with a signal | fit s (max) |")
    print("|---|---|---|---|---|---|")
    for spec in CAMERAS:
        for method in methods:
            cell = [r for r in rows if r["camera"] == spec.label and r["method"] == method]
            fitted = [r for r in cell if r["verdict"] != "-"]
            signal = (
                f"{sum(r['verdict'] != 'no signal' for r in fitted)}/{len(fitted)}"
                if fitted
                else "-"
            )
            seconds = f"{max(r['fit_s'] for r in fitted):.0f}" if fitted else "-"
            print(
                f"| {spec.label} | {method} | {np.mean([r['abs_rel'] for r in cell]):.3f} | "
                f"{np.mean([r['d_reproj_px'] for r in cell]):.3f} | {signal} | {seconds} |"
            )
    by = {(r["camera"], r["k"], r["method"]): r for r in rows}
    keys = sorted({(r["camera"], r["k"]) for r in rows})
    need = max(1, round(0.8 * len(keys)))
    print()
    for variant in variants:
        both = sum(
            by[(*key, variant)]["abs_rel"] < by[(*key, "no adapter")]["abs_rel"]
            and by[(*key, variant)]["d_reproj_px"] < by[(*key, "no adapter")]["d_reproj_px"]
            for key in keys
        )
        worst = max(
            by[(*key, variant)]["abs_rel"] / by[(*key, "no adapter")]["abs_rel"] - 1 for key in keys
        )
        gaps = [
            (by[(*key, "no adapter")]["abs_rel"] - by[(*key, variant)]["abs_rel"])
            / (by[(*key, "no adapter")]["abs_rel"] - by[(*key, "supervised")]["abs_rel"])
            for key in keys
            if abs(by[(*key, "no adapter")]["abs_rel"] - by[(*key, "supervised")]["abs_rel"]) > 1e-9
        ]
        closed = float(np.mean(gaps)) if gaps else float("nan")
        # The per-sequence mean explodes where supervised is no better than no adapter (KB4 120
        # outdoors); the pooled fraction over sequences with a gap is printed beside it.
        gapped = [
            key
            for key in keys
            if by[(*key, "no adapter")]["abs_rel"] - by[(*key, "supervised")]["abs_rel"] > 1e-9
        ]
        pooled = sum(
            by[(*key, "no adapter")]["abs_rel"] - by[(*key, variant)]["abs_rel"] for key in gapped
        ) / max(
            sum(
                by[(*key, "no adapter")]["abs_rel"] - by[(*key, "supervised")]["abs_rel"]
                for key in gapped
            ),
            1e-12,
        )
        slowest = max(by[(*key, variant)]["fit_s"] for key in keys)
        met = both >= need and worst <= 0.05 and closed >= 0.1
        print(
            f"{variant}: below no adapter on AbsRel and d_reproj on {both} of {len(keys)} sequences, "
            f"worst {worst * 100:+.1f} % AbsRel, mean fraction of the gap to supervised closed "
            f"{closed:.2f} (rule: at least {need}, never worse than +5 %, at least 0.10 closed: "
            f"{'met' if met else 'not met'}); pooled over the {len(gapped)} sequences where "
            f"supervised is below no adapter: {pooled:.2f} of the gap closed; slowest fit "
            f"{slowest:.0f} s on one thread"
        )


if __name__ == "__main__":
    with quiet_upstream():
        main()
