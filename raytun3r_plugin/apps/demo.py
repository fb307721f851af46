"""``raytun3r demo``: the main job on a built-in default, with nothing to download.

1. render ``--sequences`` (4) synthetic indoor sequences through a 190-degree Kannala-Brandt
   fisheye (seeds 1000 + seed + k);
2. take the built-in network: ``raytun3r-da3-tiny-v3``, a small Depth Anything 3 network trained on
   pinhole renders by ``scripts/train_default_network.py`` (or, if that file is absent from this
   build, a randomly initialised one of the same family, and the demo says so);
3. per sequence, score the unpatched network (vanilla), Center-PH and raytun3r without an adapter,
   fit an adapter on the first 24 frames self-supervised (DIS matches + MAGSAC++) and one to their
   ground-truth depth (the upper bound of the same tables), and score both on the other 12;
4. print the mean over the sequences with per-sequence win counts, and save everything.

The demo's fits are the library's ``default`` recipe, with the DA3 family's step (1e-2 on the
demo's 190-degree lens, where the teacher is on), at a third of its budget: 100 steps instead of
300 (:data:`DEMO_STEPS`; the header says so), to finish in about a minute on two cores. With the
whole budget (``raytun3r demo --steps 300``) the same four sequences take 225 s and reach AbsRel
0.193 against 0.198 (docs/results.md, "The demo").
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from pathlib import Path

import numpy as np

from raytun3r_plugin.apps.evaluation import METRIC_COLUMNS
from raytun3r_plugin.apps.fits import adapt_config, fit_description, supervised_config

#: The built-in network the demo and the benchmarks use: v3, whose pose head beats the
#: no-rotation answer on held-out pairs (issue 13; model card, "Versions"). ``raytun3r-da3-tiny``
#: (v2) stays loadable under its name, and docs/results.md says which tables it measured.
DEFAULT_NETWORK = "raytun3r-da3-tiny-v3"
DEMO_STEPS = 100
DEMO_SEQUENCES = 4
#: The built-in networks (``patches/da3_default.py``). Every one is fitted with the same recipes:
#: nothing in a fit is keyed by a network's name.
BUILT_IN_NETWORKS = ("raytun3r-da3-tiny", "raytun3r-da3-tiny-v3")


def default_network(name: str = DEFAULT_NETWORK):
    """(model, description) of the built-in network ``name`` (:data:`BUILT_IN_NETWORKS`);
    honest about what it is."""
    from raytun3r_plugin.errors import WeightsError
    from raytun3r_plugin.weights import load_backbone

    try:
        return (
            load_backbone(name),
            f"{name}: a small Depth Anything 3 network trained by raytun3r on pinhole renders only (docs/model_card_raytun3r_da3_tiny.md)",
        )
    except WeightsError:
        from raytun3r_plugin.patches.da3_networks import build_tiny_network

        return build_tiny_network(seed=0), (
            "RANDOM-WEIGHT tiny Depth Anything 3 network (the trained default is not in this build): "
            "the numbers below show the pipeline runs, they say nothing about accuracy"
        )


def demo_camera(size: int):
    """The demo's lens: a ``size`` x ``size`` 190-degree KB4 (``k1 = 0.02``) whose image circle
    fills the width (:func:`raytun3r_plugin.cameras.fisheye`)."""
    from raytun3r_plugin.cameras import fisheye

    return fisheye(size, 190.0, "kb4", k=(0.02, 0.0, 0.0, 0.0))


def score_sequence(model, k: int, seed: int, size: int, steps: int, out: Path, labels: dict):
    """Render the demo's sequence ``k`` (render seed ``1000 + seed + k``), score the methods
    without an adapter, fit the self-supervised and the supervised adapter on frames 0-23 and
    score them on 24-35.

    Returns (metric rows, {"adapted": s, "supervised": s} wall time of each fit)."""
    from raytun3r_plugin import synthetic
    from raytun3r_plugin.adaptation.train import adapt
    from raytun3r_plugin.apps.benchmark import ground_truth_depth
    from raytun3r_plugin.apps.evaluation import headline, run_method, score

    camera = demo_camera(size)
    n_adapt, n_eval = 24, 12
    render_seed = 1000 + seed + k
    seq = synthetic.render_sequence("indoor", camera, n_frames=n_adapt + n_eval, seed=render_seed)
    held_out = list(range(n_adapt, len(seq)))
    cell = {"camera": "KB4 190", "scene": "indoor", "seed": render_seed}
    rows, seconds = [], {}
    for method, key in (("vanilla", "vanilla"), ("center-ph", "center-ph"), ("raytun3r", "zero")):
        rows.append(
            {
                **cell,
                "method": labels[key],
                **headline(score(seq, run_method(model, seq, method, frames=held_out))),
            }
        )
    fits = {
        "adapted": (
            adapt_config(size, steps, seed=seed, model=model, cache_dir=str(out / "cache")),
            None,
        ),
        "supervised": (
            supervised_config(size, steps, seed=seed, cache_dir=str(out / "cache")),
            ground_truth_depth(seq, n_adapt),
        ),
    }
    for key, (config, depth) in fits.items():
        began = time.perf_counter()
        name = "adapter.safetensors" if key == "adapted" else "adapter_supervised.safetensors"
        adapter = adapt(
            model,
            camera,
            seq.first_images(n_adapt),
            config,
            out_path=out / f"seq{k}" / name,
            resume=False,
            progress=False,
            depth=depth,
        )
        seconds[key] = time.perf_counter() - began
        rows.append(
            {
                **cell,
                "method": labels[key],
                **headline(
                    score(seq, run_method(model, seq, "raytun3r", adapter=adapter, frames=held_out))
                ),
            }
        )
    return rows, seconds


@functools.cache
def _built_in_network():
    """(model, description) of the default network, once per process: the demo's own process
    and each of its workers (:func:`~raytun3r_plugin.apps.workers.map_in_workers`)."""
    return default_network()


def _built_in_model():
    return _built_in_network()[0]


#: The lines under the demo's table: what each column means and what the table does not show.
_TABLE_NOTES = (
    "rot/trans: relative-pose errors (deg) on consecutive held-out pairs; d_reproj: px, GT pose;",
    "AbsRel, delta<1.25: per-image median scale, range depth; coverage: fraction of fisheye "
    "pixels with depth;",
    "lower_than_no_adapter: on how many sequences the metric is below the zero adapter's (the "
    "parameter-free corrections alone).",
    "The supervised row is the upper bound of the same tables. `raytun3r bench` scores 5 "
    "sequences per camera and scene.",
    "These are indoor sequences. On outdoor driving ones the matches carry no depth signal and the",
    "pinhole-view teacher alone moves the tables, except at 120 degrees (docs/results.md, "
    "synthetic fisheye benchmark).",
)


def _demo_jobs(asked: int | None, count: int) -> int:
    """Worker processes for ``count`` sequences: ``asked``, or one per free CPU, at most one per
    sequence."""
    from raytun3r_plugin.apps.workers import cpu_jobs
    from raytun3r_plugin.errors import InputError

    jobs = cpu_jobs(count) if asked is None else asked
    if jobs < 1:
        raise InputError(f"--jobs must be at least 1, got {jobs}")
    return min(jobs, count)


def run_demo(args: argparse.Namespace) -> int:
    from raytun3r_plugin.apps.benchmark import summarise
    from raytun3r_plugin.apps.evaluation import format_table
    from raytun3r_plugin.apps.workers import map_in_workers

    started = time.perf_counter()
    size = args.size or 112  # the default network's training resolution
    steps = args.steps if args.steps is not None else DEMO_STEPS
    count = args.sequences if getattr(args, "sequences", None) else DEMO_SEQUENCES
    jobs = _demo_jobs(getattr(args, "jobs", None), count)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    model, description = _built_in_network()
    print(f"network: {description}")
    camera = demo_camera(size)
    print(f"camera:  {camera!r}, field of view {camera.fov_deg:.0f} deg")
    print(f"fits:    {fit_description(adapt_config(size, steps, model=model), model)}")
    print(
        f"jobs:    {jobs} process{'es' if jobs > 1 else ''}"
        + (", 1 thread each" if jobs > 1 else "")
    )
    n_adapt, n_eval = 24, 12
    labels = {
        "vanilla": "vanilla (unpatched)",
        "center-ph": "Center-PH (110 deg pinhole)",
        "zero": "raytun3r, no adapter",
        "adapted": f"raytun3r, adapted ({steps} steps)",
        "supervised": f"raytun3r, supervised ({steps} steps, GT depth)",
    }
    tasks = [(k, args.seed, size, steps, out, labels) for k in range(count)]
    results: dict[int, tuple] = {}
    for k, result in map_in_workers(score_sequence, tasks, jobs, initializer=_built_in_model):
        results[k] = result
        print(
            f"[{time.perf_counter() - started:4.0f} s] sequence {k + 1}/{count} (seed {1000 + args.seed + k}) done",
            flush=True,
        )
    rows = [row for k in range(count) for row in results[k][0]]
    seconds = {key: [results[k][1][key] for k in range(count)] for key in ("adapted", "supervised")}

    # Rotation is counted too: the default recipe keeps the pose term on the network's own
    # pose, so the adapter can move it.
    table_rows = summarise(
        rows, reference=labels["zero"], metrics=("rot_deg", "d_reproj_px", "abs_rel")
    )
    for row in table_rows:
        row["lower_than_no_adapter"] = row.pop(f"lower_than_{labels['zero']}", "")
    # The demo's table has one camera and scene: from the method on.
    columns = [*METRIC_COLUMNS[METRIC_COLUMNS.index("method") :], "lower_than_no_adapter"]
    table = format_table(table_rows, columns)
    print()
    print(
        f"Mean over {count} held-out sequences (seeds {1000 + args.seed}-{1000 + args.seed + count - 1}; frames 0-{n_adapt - 1} fitted, {n_adapt}-{n_adapt + n_eval - 1} scored):"
    )
    print(table)
    print()
    print("\n".join(_TABLE_NOTES))
    metrics = {
        "network": description,
        "camera": json.loads(camera.to_json()),
        "rows": rows,
        "summary": table_rows,
        "adapt_seconds": seconds,
        "jobs": jobs,
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float))
    (out / "metrics.md").write_text(table + "\n")
    print(
        f"\nadapters and loss curves: {out}/seq*/ (adapted: {np.mean(seconds['adapted']):.0f} s per fit); total {time.perf_counter() - started:.0f} s"
    )
    return 0
