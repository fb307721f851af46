"""The paper's cost table on DA3-Small: trainable parameters and inference time per frame,
relative to vanilla, every method timed in the same run (round-robin, order rotating).

Methods measured: vanilla (unpatched), raytun3r (a nonzero adapter, every correction on) and
LoRA (r=8, alpha=16 on the ViT's qkv, unmerged: a forward hook per block). Multi-PH and
calibration tokens are not implemented yet and are listed as such.

    python benchmarks/cost_table.py [--size 504] [--repeats 5] [--views 2]
"""

from __future__ import annotations

import argparse
import copy
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))


import raytun3r_plugin as rt  # noqa: E402
from raytun3r_plugin.baselines import inject_lora  # noqa: E402


def main() -> None:
    from overhead import da3_small_with_a_pe, fisheye, timed, trained_looking

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=504)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--views", type=int, default=2)
    args = parser.parse_args()

    vanilla = da3_small_with_a_pe()
    patched, lora = copy.deepcopy(vanilla), copy.deepcopy(vanilla)
    camera = fisheye(args.size)
    adapter = trained_looking(rt.Adapter.for_model(patched, camera))
    handle = rt.apply(patched, camera, adapter)
    lora_handle = inject_lora(lora)
    with torch.no_grad():
        for b in lora_handle.weights.lora_B:
            b.normal_(0, 0.01)
    models = {"vanilla": vanilla, "raytun3r": patched, "LoRA r=8 (unmerged)": lora}
    parameters = {
        "vanilla": 0,
        "raytun3r": adapter.num_parameters()["total"],
        "LoRA r=8 (unmerged)": lora_handle.weights.num_parameters(),
    }
    images = torch.rand(
        1, args.views, 3, args.size, args.size, generator=torch.Generator().manual_seed(1)
    )
    times: dict[str, list[float]] = {name: [] for name in models}
    names = list(models)
    with torch.inference_mode():
        for name in names:  # warm-up
            timed(models[name], images)
        for repeat in range(args.repeats):
            order = names[repeat % len(names) :] + names[: repeat % len(names)]
            for name in order:
                times[name].append(timed(models[name], images) / args.views)
    handle.remove()
    lora_handle.remove()
    base = statistics.median(times["vanilla"])
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, da3-small, {args.size}x{args.size}, "
        f"{args.views} views, {args.repeats} round-robin repeats; time per frame, median"
    )
    print("| method | trainable parameters | time per frame (s) | relative to vanilla |")
    print("|---|---|---|---|")
    for name in names:
        median = statistics.median(times[name])
        print(f"| {name} | {parameters[name]:,} | {median:.3f} | {median / base:.2f}x |")
    print("| Multi-PH (5 pinhole views) | 0 | not implemented | - |")
    print(
        "| calibration tokens (t=4; 12 x 4 x 384, by arithmetic) | 18,432 | not implemented | - |"
    )


if __name__ == "__main__":
    main()
