"""What Ray costs and gives on the fleet's fits (docs/fleet.md, "Scaling").

The same 8 fits of the built-in network (rendered indoor segments through the benchmark's KB4
185-degree lens, the ``default`` recipe at ``--steps``, ``--size`` px, one thread each) run

1. in one plain process, one after the other (the reference: no Ray at all);
2. on an embedded Ray cluster with 1 worker, then with 2 workers (``raytun3r_plugin.cluster``);

and the script prints each wall time, the throughput ratio (2 workers over 1), Ray's start-up
(``ray.init`` of the embedded cluster), its per-task overhead (the mean wall time of no-op
tasks) and the overhead of 1 Ray worker against the plain process (network loading in the worker,
object store, scheduling). The fits themselves are the same code in every case, seeded alike.

    OMP_NUM_THREADS=1 python benchmarks/fleet_scaling.py               # the recipe's 300 steps
    OMP_NUM_THREADS=1 python benchmarks/fleet_scaling.py --steps 20    # a quick look

Run it on a quiet machine: two workers on two cores only double the throughput when nothing
else runs.
"""

from __future__ import annotations

import argparse
import os
import time

FITS = 8


def _network():
    import torch

    from raytun3r_plugin.apps.demo import default_network

    torch.set_num_threads(1)
    return default_network()[0]


def fit_one(model, seed: int, size: int, steps: int, frames: int) -> float:
    """Render one segment and fit an adapter to it; returns the fit's wall time (s)."""
    from raytun3r_plugin import synthetic
    from raytun3r_plugin.adaptation.train import adapt
    from raytun3r_plugin.apps.benchmark import CAMERAS, make_camera
    from raytun3r_plugin.apps.fits import adapt_config

    camera = make_camera(CAMERAS[1], size)
    seq = synthetic.render_sequence("indoor", camera, n_frames=frames, seed=seed)
    start = time.perf_counter()
    adapt(
        model,
        camera,
        seq.first_images(frames),
        adapt_config(size, steps, model=model),
        progress=False,
    )
    return time.perf_counter() - start


def nothing(state, k: int) -> int:
    return k


def main() -> None:
    import torch

    from raytun3r_plugin.cluster import ClusterSpec, connected, run_tasks

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=300, help="fit steps (the recipe's: 300)")
    parser.add_argument("--size", type=int, default=112, help="network input, px")
    parser.add_argument("--frames", type=int, default=24, help="frames per segment")
    parser.add_argument("--noops", type=int, default=50, help="no-op tasks for the overhead")
    parser.add_argument(
        "--docs", default=None, help="write the result into this page's fleet-scaling block"
    )
    args = parser.parse_args()
    lines: list[str] = []

    def say(text: str) -> None:
        print(text, flush=True)
        lines.append(text)

    torch.set_num_threads(1)
    tasks = [(95_000 + k, args.size, args.steps, args.frames) for k in range(FITS)]
    say(
        f"{FITS} fits: built-in network, {args.size} px, {args.frames} frames, "
        f"{args.steps} steps; CPUs {len(os.sched_getaffinity(0))}; OMP_NUM_THREADS="
        f"{os.environ.get('OMP_NUM_THREADS')}"
    )

    from raytun3r_plugin.registry import quiet_upstream

    start = time.perf_counter()
    model = _network()
    with quiet_upstream():  # as in a Ray worker (raytun3r_plugin.cluster)
        plain_fits = [fit_one(model, *task) for task in tasks]
    plain = time.perf_counter() - start
    say(
        f"plain process:   {plain:7.1f} s ({sum(plain_fits) / FITS:.1f} s per fit, "
        "network loaded once)"
    )

    walls = {}
    for workers in (1, 2):
        started = time.perf_counter()
        with connected(ClusterSpec(workers=workers)):
            startup = time.perf_counter() - started
            begin = time.perf_counter()
            # workers=2 in the task spec: the Ray path; the cluster's CPUs bound the tasks at once.
            outcomes = list(run_tasks(fit_one, tasks, ClusterSpec(workers=2), initializer=_network))
            walls[workers] = time.perf_counter() - begin
            failed = [o.error for o in outcomes if not o.ok]
            assert not failed, failed
            fits = [o.value for o in outcomes]
            overhead = None
            if workers == 1:
                noop_start = time.perf_counter()
                list(run_tasks(nothing, [(k,) for k in range(args.noops)], ClusterSpec(workers=2)))
                overhead = (time.perf_counter() - noop_start) / args.noops
        say(
            f"Ray, {workers} worker{'s' if workers > 1 else ' '}:   {walls[workers]:7.1f} s "
            f"({sum(fits) / FITS:.1f} s per fit inside the task); ray.init {startup:.1f} s"
            + (f"; no-op task {1000 * overhead:.0f} ms each" if overhead is not None else "")
        )
    say(f"throughput, 2 workers over 1: {walls[1] / walls[2]:.2f}x")
    say(
        f"1 Ray worker over the plain process: {walls[1] / plain:.3f}x "
        f"({(walls[1] - plain) / FITS:+.2f} s per fit)"
    )
    if args.docs:
        from docs_block import write_block

        command = "OMP_NUM_THREADS=1 python benchmarks/fleet_scaling.py " + " ".join(
            f"--{k} {v}" for k, v in vars(args).items() if k != "docs"
        )
        write_block(
            args.docs, "fleet-scaling", f"`{command}`:\n\n```\n" + "\n".join(lines) + "\n```"
        )


if __name__ == "__main__":
    main()
