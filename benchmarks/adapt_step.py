"""Cost of one adaptation step against the minimal backward pass, and of a default adaptation.

Model: DA3's real ``da3-small`` configuration (``depth_anything_3.cfg.create_object(load_config(
MODEL_REGISTRY["da3-small"]))``) with random weights and a random-filled ``pos_embed`` (DA3's
constructor leaves it at zero). Data: a synthetic indoor fisheye segment (190-degree
Kannala-Brandt camera, ``--size`` x ``--size`` px native = network input), matches from the
default DIS matcher, MAGSAC++ targets, all prepared once before timing.

1. Time per step (interleaved, alternating order, median over ``--repeats``):
   * ``adapt``: one full adaptation step on a 3-frame window (patched forward, every loss term,
     backward, gradient clipping, Adam step) -- ``raytun3r_plugin.adaptation.train.adaptation_step``;
   * ``plain``: the same patched model on the same window, loss = mean depth, backward into the
     same adapter (the minimal backward any adaptation needs).
   Printed: wall-clock and process CPU time (``time.process_time``, summed over both threads)
   per variant, and the ratios adapt/plain as median of per-repeat ratios, ratio of medians and
   ratio of minima (goal <= 1.15). On a shared machine the wall time is noisy; the CPU time and
   the minima are less sensitive to other processes.
2. Peak memory: each variant runs in a fresh subprocess doing identical setup (model, cached
   adaptation set, patch) and then ``--memory-steps`` steps. Method: the kernel's peak resident
   set size ``VmHWM`` (``/proc/self/status``), reset to the current RSS after the setup by writing
   5 to ``/proc/self/clear_refs``, read after the steps; minus ``VmRSS`` right before the first
   step. (Not ``ru_maxrss``: it survives ``fork``/``exec`` and would report the parent's peak.)
   Printed: the step's peak increase per variant, its ratio, and the ratio of whole-process peaks
   (goal <= 1.2).
3. Wall time of a default adaptation (``AdaptConfig(input_size=size)``: 300 steps over 30
   windows): a fresh ``adapt()`` run of ``--steps`` steps is timed end to end with a cold
   matcher cache; the wall time of 300 steps is extrapolated as preparation time + 300 x mean
   step time (the step time being the median of the logged steps), and labelled as such.

    python benchmarks/adapt_step.py [--size 280] [--repeats 5] [--steps 6] [--frames 32]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

BACKBONE = "da3-small"


def camera(size: int):
    """190-degree equidistant-like KB4 fisheye whose image circle fits the image."""
    from raytun3r_plugin.cameras import fisheye

    return fisheye(size, 190.0, "kb4", k=(0.0, 0.0, 0.0, 0.0))


def build_model() -> torch.nn.Module:
    """``da3-small`` from DA3's own config, random weights, random-filled ``pos_embed``."""
    from depth_anything_3.cfg import create_object, load_config
    from depth_anything_3.registry import MODEL_REGISTRY

    torch.manual_seed(0)
    model = create_object(load_config(MODEL_REGISTRY[BACKBONE]))
    with torch.no_grad():
        torch.nn.init.trunc_normal_(model.backbone.pretrained.pos_embed, std=0.02)
    model.eval()
    for parameter in model.parameters():
        parameter.requires_grad_(False)
    return model


def frames(size: int, n_frames: int, cache_dir: str):
    """The synthetic segment (N, H, W, 3) float32, rendered once and kept as .npy in ``cache_dir``."""
    import numpy as np

    path = Path(cache_dir) / f"frames-indoor-s0-{size}-{n_frames}.npy"
    if path.is_file():
        return np.load(path, allow_pickle=False)
    from raytun3r_plugin import synthetic

    images = synthetic.render_sequence(
        "indoor", camera(size), n_frames=n_frames, seed=0, supersample=1
    ).images
    np.save(path, images, allow_pickle=False)
    return images


def setup(size: int, n_frames: int, cache_dir: str, config_changes: dict | None = None):
    """Model, prepared problem, zero adapter applied, Adam. Returns (model, problem, adapter, optimizer, config, handle)."""
    from raytun3r_plugin import Adapter, apply
    from raytun3r_plugin.adaptation.config import AdaptConfig
    from raytun3r_plugin.adaptation.problem import prepare_problem

    model = build_model()
    config = AdaptConfig(
        input_size=size,
        cache_dir=cache_dir,
        sequence_id=f"bench-indoor-s0-{size}-{n_frames}",
        **(config_changes or {}),
    ).resolved_for(model)
    problem = prepare_problem(camera(size), frames(size, n_frames, cache_dir), config)
    adapter = Adapter.for_model(model, problem.layout.native_camera)
    handle = apply(model, problem.layout.native_camera, adapter)
    optimizer = torch.optim.Adam(list(adapter.parameters()), lr=config.step_size())
    return model, problem, adapter, optimizer, config, handle


def run_adapt_step(model, problem, adapter, optimizer, config, step: int) -> None:
    from raytun3r_plugin.adaptation.step import adaptation_step

    adaptation_step(model, adapter, optimizer, problem, config, step, index=0)


def run_plain(model, problem, adapter, optimizer, config, step: int) -> None:
    from raytun3r_plugin import predict

    prediction = predict(model, problem.batch(0)[None])
    optimizer.zero_grad(set_to_none=True)
    prediction.depth.mean().backward()


VARIANTS = {"adapt": run_adapt_step, "plain": run_plain}


def status_kib(field: str) -> int:
    """A ``/proc/self/status`` memory field (``VmRSS``, ``VmHWM``) in KiB."""
    with open("/proc/self/status") as handle:
        for line in handle:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {field}")


def reset_peak() -> bool:
    """Reset this process's peak RSS (VmHWM) to its current RSS (Linux >= 4.0)."""
    try:
        with open("/proc/self/clear_refs", "w") as handle:
            handle.write("5")
        return True
    except OSError:
        return False


def memory_child(variant: str, size: int, n_frames: int, cache_dir: str, steps: int) -> None:
    torch.set_num_threads(2)
    model, problem, adapter, optimizer, config, handle = setup(size, n_frames, cache_dir)
    setup_peak = status_kib("VmHWM")
    reset = reset_peak()
    before = status_kib("VmRSS")
    for step in range(steps):
        VARIANTS[variant](model, problem, adapter, optimizer, config, step)
    peak = status_kib("VmHWM")
    handle.remove()
    print(
        json.dumps(
            {
                "variant": variant,
                "rss_before_kib": before,
                "setup_peak_kib": setup_peak,
                "peak_kib": peak,
                "peak_reset": reset,
            }
        )
    )


def measure_memory(size: int, n_frames: int, cache_dir: str, steps: int) -> dict[str, dict]:
    out = {}
    for variant in ("plain", "adapt"):
        result = subprocess.run(
            [
                sys.executable,
                __file__,
                "--memory-child",
                variant,
                "--size",
                str(size),
                "--frames",
                str(n_frames),
                "--cache-dir",
                cache_dir,
                "--memory-steps",
                str(steps),
            ],
            check=True,
            capture_output=True,
            text=True,
        )
        out[variant] = json.loads(result.stdout.strip().splitlines()[-1])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=280)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--steps", type=int, default=6, help="steps of the timed adapt() run (extrapolated to 300)"
    )
    parser.add_argument("--frames", type=int, default=32)
    parser.add_argument("--memory-steps", type=int, default=2)
    parser.add_argument("--skip-memory", action="store_true")
    parser.add_argument("--skip-adapt", action="store_true")
    parser.add_argument("--cache-dir", default=None)
    parser.add_argument(
        "--memory-child", choices=sorted(VARIANTS), default=None, help=argparse.SUPPRESS
    )
    args = parser.parse_args()
    if args.memory_child:
        memory_child(args.memory_child, args.size, args.frames, args.cache_dir, args.memory_steps)
        return

    torch.set_num_threads(2)
    cache_dir = args.cache_dir or tempfile.mkdtemp(prefix="raytun3r-bench-")
    print(
        f"# adaptation step benchmark: {BACKBONE} (random weights), {args.size}x{args.size} px input, 3-frame window, torch {torch.__version__}, {torch.get_num_threads()} threads"
    )

    began = time.perf_counter()
    model, problem, adapter, optimizer, config, handle = setup(args.size, args.frames, cache_dir)
    print(
        f"setup (render {args.frames} frames, match, MAGSAC++, build model): {time.perf_counter() - began:.1f} s; "
        f"{len(problem.windows)} windows, window 0 has {sum(p.uv_i.shape[0] for p in problem.windows[0][1])} matches over 6 pairs"
    )

    # 1. interleaved timing
    for run in VARIANTS.values():  # warm-up (allocator, geometry caches)
        run(model, problem, adapter, optimizer, config, 0)
    times: dict[str, list[float]] = {name: [] for name in VARIANTS}
    cpu: dict[str, list[float]] = {name: [] for name in VARIANTS}
    for repeat in range(args.repeats):
        order = ("adapt", "plain") if repeat % 2 == 0 else ("plain", "adapt")
        for name in order:
            start, start_cpu = time.perf_counter(), time.process_time()
            VARIANTS[name](model, problem, adapter, optimizer, config, repeat + 1)
            times[name].append(time.perf_counter() - start)
            cpu[name].append(time.process_time() - start_cpu)
    handle.remove()
    print(f"\n## time per step (s), {args.repeats} interleaved repeats (alternating order)")
    print(
        "| variant | wall median | wall min | wall max | CPU median | CPU min |\n|---|---|---|---|---|---|"
    )
    for name in VARIANTS:
        print(
            f"| {name} | {statistics.median(times[name]):.3f} | {min(times[name]):.3f} | {max(times[name]):.3f} | "
            f"{statistics.median(cpu[name]):.3f} | {min(cpu[name]):.3f} |"
        )
    for label, values in (("wall", times), ("CPU (process_time, both threads)", cpu)):
        ratios = [a / p for a, p in zip(values["adapt"], values["plain"], strict=True)]
        print(
            f"{label}: median of per-repeat ratios adapt/plain {statistics.median(ratios):.3f}, ratio of medians "
            f"{statistics.median(values['adapt']) / statistics.median(values['plain']):.3f}, ratio of minima "
            f"{min(values['adapt']) / min(values['plain']):.3f} (goal <= 1.15)"
        )

    # 2. memory
    if not args.skip_memory:
        memory = measure_memory(args.size, args.frames, cache_dir, args.memory_steps)
        print(
            f"\n## peak memory (fresh process per variant; VmHWM after the steps minus VmRSS before them; peak reset after setup: {memory['adapt']['peak_reset']})"
        )
        print(
            "| variant | setup peak RSS (MiB) | RSS before steps (MiB) | peak RSS (MiB) | step peak increase (MiB) |\n|---|---|---|---|---|"
        )
        increase = {}
        for name in ("plain", "adapt"):
            m = memory[name]
            increase[name] = m["peak_kib"] - m["rss_before_kib"]
            print(
                f"| {name} | {m['setup_peak_kib'] / 1024:.0f} | {m['rss_before_kib'] / 1024:.0f} | {m['peak_kib'] / 1024:.0f} | {increase[name] / 1024:.0f} |"
            )
        print(
            f"step peak increase ratio adapt/plain: {increase['adapt'] / increase['plain']:.3f}; "
            f"whole-process peak ratio: {memory['adapt']['peak_kib'] / memory['plain']['peak_kib']:.3f} (goal <= 1.2)"
        )

    # 3. wall time of a default adaptation, extrapolated
    if not args.skip_adapt:
        from raytun3r_plugin.adaptation.checkpoint import read_loss_log
        from raytun3r_plugin.adaptation.config import AdaptConfig
        from raytun3r_plugin.adaptation.train import adapt

        fresh_cache = tempfile.mkdtemp(prefix="raytun3r-bench-cold-")
        images = frames(args.size, args.frames, cache_dir)
        model = build_model()
        out = Path(fresh_cache) / "adapter.safetensors"
        config = AdaptConfig(
            input_size=args.size, steps=args.steps, cache_dir=fresh_cache, checkpoint_every=0
        )
        start = time.perf_counter()
        adapt(model, camera(args.size), images, config, out_path=out, progress=False)
        total = time.perf_counter() - start
        log = read_loss_log(out)
        step_times = [r["time_s"] for r in log]
        per_step = statistics.median(step_times)
        preparation = total - sum(step_times)
        default_steps = AdaptConfig().steps
        print(
            f"\n## default adaptation ({default_steps} steps, {config.n_windows} windows, {args.size} px)"
        )
        print(
            f"measured: adapt() with steps={args.steps}: {total:.1f} s in total, of which preparation "
            f"(matching, MAGSAC++, resizing, saving) {preparation:.1f} s; step times {', '.join(f'{t:.2f}' for t in step_times)} s"
        )
        print(
            f"EXTRAPOLATED (not run): {default_steps} steps ~ {preparation:.1f} + {default_steps} x {per_step:.2f} = "
            f"{preparation + default_steps * per_step:.0f} s ({(preparation + default_steps * per_step) / 60:.1f} min)"
        )


if __name__ == "__main__":
    from raytun3r_plugin.registry import quiet_upstream

    with (
        quiet_upstream()
    ):  # no per-forward INFO lines from the backbone's own logger (children too)
        main()
