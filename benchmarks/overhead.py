"""Inference overhead of raytun3r on da3-small: patched vs unpatched forward, interleaved.

The patched model carries a trained-looking nonzero adapter with every correction on and a
195-degree fisheye camera; the unpatched one is a second instance with the same weights. Each
repeat times both (order alternating) after warm-up, so drift of the machine hits both alike.
Prints the median ratio per input size. Goal: <= 1.03 at 504 px.

    python benchmarks/overhead.py [--sizes 504 280] [--repeats 7] [--views 2]
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time

import torch
from raytun3r_plugin.patches.da3_networks import build_network

import raytun3r_plugin as rt
from raytun3r_plugin import cameras
from raytun3r_plugin.cameras import KannalaBrandt4


def fisheye(size: int) -> KannalaBrandt4:
    """195-degree ideal equidistant KB4 whose image circle fills the image."""
    return cameras.fisheye(size, 195.0, "kb4", k=(0.0, 0.0, 0.0, 0.0))


def trained_looking(adapter: rt.Adapter) -> rt.Adapter:
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        rho = torch.linspace(0, 1, adapter.n_r)[:, None]
        adapter.pe["radial"].copy_(
            rho**2 * torch.randn(1, adapter.embed_dim, generator=generator) * 0.05
        )
        adapter.pe["angular"].copy_(
            torch.randn(adapter.pe["angular"].shape, generator=generator) * 0.01
        )
        if adapter.rope is not None:
            adapter.rope["radial"].copy_(torch.linspace(0, 1, adapter.n_r_rope) ** 2)
    return adapter


def da3_small_with_a_pe() -> torch.nn.Module:
    """da3-small in eval mode with a random PE table (its constructor leaves it at zero)."""
    torch.manual_seed(0)
    model = build_network("da3-small").eval()
    with torch.no_grad():
        model.backbone.pretrained.pos_embed.normal_(0, 0.02)
    return model


def timed(model, images) -> float:
    start = time.perf_counter()
    rt.predict(model, images)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[504, 280])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--views", type=int, default=2)
    args = parser.parse_args()

    plain = da3_small_with_a_pe()
    patched = copy.deepcopy(plain)
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, da3-small, {args.views} views, {args.repeats} interleaved repeats"
    )
    print("| input | unpatched (s) | patched (s) | median ratio |")
    print("|---|---|---|---|")
    with torch.inference_mode():
        for size in args.sizes:
            camera = fisheye(size)
            adapter = trained_looking(rt.Adapter.for_model(patched, camera))
            images = torch.rand(
                1, args.views, 3, size, size, generator=torch.Generator().manual_seed(size)
            )
            with rt.apply(patched, camera, adapter):
                for _ in range(2):  # warm-up: fills the per-size geometry cache and allocator
                    timed(plain, images), timed(patched, images)
                ratios, plain_times, patched_times = [], [], []
                for repeat in range(args.repeats):
                    if repeat % 2:
                        b, a = timed(patched, images), timed(plain, images)
                    else:
                        a, b = timed(plain, images), timed(patched, images)
                    plain_times.append(a)
                    patched_times.append(b)
                    ratios.append(b / a)
            print(
                f"| {size}x{size} | {statistics.median(plain_times):.3f} | {statistics.median(patched_times):.3f} | {statistics.median(ratios):.3f} |"
            )


if __name__ == "__main__":
    main()
