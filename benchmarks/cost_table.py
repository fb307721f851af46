"""The paper's cost table on DA3-Small: trainable parameters and inference time per frame,
relative to vanilla, every method timed in the same run (round-robin, order rotating).

Methods measured, each on its own copy of the same random-weight network:

- vanilla (unpatched);
- raytun3r: a nonzero adapter, every correction on;
- LoRA (r=8, alpha=16 on the ViT's qkv, unmerged: a forward hook per block, B nonzero);
- calibration tokens (t=4 per block, VPT-deep: 12 x 4 x 384; the sequence is 4 tokens longer
  inside every block);
- Multi-PH: the unpatched network on five virtual pinhole views of every frame (one forward per
  view), with the resampling into the views and the fusion back to the fisheye included; the
  views (and their tilt rule) are computed once per camera, outside the timing, as
  ``run_method`` does once per sequence.

    python benchmarks/cost_table.py [--size 504] [--repeats 5] [--views 2] [--threads 1]
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time

import torch

import raytun3r_plugin as rt
from raytun3r_plugin.baselines import (
    inject_calibration_tokens,
    inject_lora,
    multi_pinhole_views,
    predict_multi_ph,
)


def main() -> None:
    from overhead import da3_small_with_a_pe, fisheye, trained_looking

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=504)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--views", type=int, default=2, help="frames per forward window")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    vanilla = da3_small_with_a_pe()
    patched, lora, tokens = (copy.deepcopy(vanilla) for _ in range(3))
    camera = fisheye(args.size)
    adapter = trained_looking(rt.Adapter.for_model(patched, camera))
    handle = rt.apply(patched, camera, adapter)
    lora_handle = inject_lora(lora)
    with torch.no_grad():
        for b in lora_handle.weights.lora_B:
            b.normal_(0, 0.01)  # B = 0 would be the identity; a fitted LoRA is not
    token_handle = inject_calibration_tokens(tokens)
    views = multi_pinhole_views(camera)
    images = torch.rand(
        1, args.views, 3, args.size, args.size, generator=torch.Generator().manual_seed(1)
    )
    lora_name, token_name, multi_name = (
        "LoRA r=8 (unmerged)",
        "calibration tokens (t=4)",
        f"Multi-PH ({len(views)} pinhole views)",
    )
    forwards = {
        "vanilla": lambda: rt.predict(vanilla, images),
        "raytun3r": lambda: rt.predict(patched, images),
        lora_name: lambda: rt.predict(lora, images),
        token_name: lambda: rt.predict(tokens, images),
        multi_name: lambda: predict_multi_ph(vanilla, images[0], camera, views=views),
    }
    parameters = {
        "vanilla": 0,
        "raytun3r": adapter.num_parameters()["total"],
        lora_name: lora_handle.weights.num_parameters(),
        token_name: token_handle.tokens.num_parameters(),
        multi_name: 0,
    }
    times: dict[str, list[float]] = {name: [] for name in forwards}
    names = list(forwards)
    with torch.inference_mode():
        for name in names:  # warm-up
            forwards[name]()
        for repeat in range(args.repeats):
            order = names[repeat % len(names) :] + names[: repeat % len(names)]
            for name in order:
                start = time.perf_counter()
                forwards[name]()
                times[name].append((time.perf_counter() - start) / args.views)
    handle.remove()
    lora_handle.remove()
    token_handle.remove()
    base = statistics.median(times["vanilla"])
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, da3-small, {args.size}x{args.size}, "
        f"{args.views} frames per window, {args.repeats} round-robin repeats; time per frame, median"
    )
    print("| method | trainable parameters | time per frame (s) | relative to vanilla |")
    print("|---|---|---|---|")
    for name in names:
        median = statistics.median(times[name])
        print(f"| {name} | {parameters[name]:,} | {median:.3f} | {median / base:.2f}x |")


if __name__ == "__main__":
    main()
