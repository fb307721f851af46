"""What raytun3r costs once deployed for one camera, from the same script every time.

Two comparisons, each patched against unpatched on the same weights and the same path:

* **Exported** (ONNX Runtime, CPU): ``deploy.freeze`` + ``deploy.export_onnx`` of the patched
  model (190-degree KB4 lens, a trained-looking nonzero adapter, every correction on) against
  the same freeze and export of the unpatched model (no adapter, no corrections). Goal: at most
  1.01x, since every correction is a constant in the graph.
* **Compiled** (``torch.compile``, backend ``--backend``, default inductor): the patched model
  against the unpatched one. Goal: at most 1.02x.

The model is ``da3-small`` (DA3's real configuration, random weights, a random-filled
``pos_embed``) or, with ``--model built-in``, raytun3r's built-in network. Each repeat times
both variants (order alternating), after warm-up; the median ratio is printed per size.

    python benchmarks/deploy_cost.py [--sizes 280 504] [--views 2] [--repeats 5]
        [--threads 1] [--backend inductor] [--model da3-small] [--docs docs/deployment.md]

With ``--docs`` the table replaces the block between the page's ``deploy-cost`` markers. Run
it alone: other jobs on the machine change every number.
"""

from __future__ import annotations

import argparse
import copy
import platform
import statistics
import tempfile
import time
from pathlib import Path

import torch
from docs_block import write_block

import raytun3r_plugin as rt
from raytun3r_plugin.cameras import fisheye
from raytun3r_plugin.deploy import export_onnx, freeze
from raytun3r_plugin.deploy.onnx import INPUT_NAME, onnx_session
from raytun3r_plugin.registry import quiet_upstream


def build(name: str) -> torch.nn.Module:
    if name == "built-in":
        return rt.load_backbone("raytun3r-da3-tiny-v3")
    from raytun3r_plugin.patches.da3_networks import build_network

    torch.manual_seed(0)
    model = build_network(name).eval()
    with torch.no_grad():  # DA3's constructor leaves the PE table at zero
        model.backbone.pretrained.pos_embed.normal_(0, 0.02)
    return model


def trained_looking(adapter: rt.Adapter) -> rt.Adapter:
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        rho = torch.linspace(0, 1, adapter.n_r)[:, None]
        adapter.pe["radial"].copy_(
            rho**2 * torch.randn(1, adapter.embed_dim, generator=generator) * 0.05
        )
        adapter.pe["angular"].normal_(0, 0.01, generator=generator)
        if adapter.rope is not None:
            adapter.rope["radial"].copy_(torch.linspace(0, 1, adapter.n_r_rope) ** 2)
    return adapter


def interleaved(run_a, run_b, repeats: int) -> tuple[float, float, float]:
    """Median seconds of ``run_a`` and ``run_b`` and the median of their per-repeat ratio."""
    times_a, times_b, ratios = [], [], []
    for repeat in range(repeats):
        order = [(run_a, times_a), (run_b, times_b)]
        for run, times in order if repeat % 2 == 0 else order[::-1]:
            start = time.perf_counter()
            run()
            times.append(time.perf_counter() - start)
        ratios.append(times_a[-1] / times_b[-1])
    return statistics.median(times_a), statistics.median(times_b), statistics.median(ratios)


def pair(model_name: str, size: int, views: int) -> tuple[torch.nn.Module, torch.nn.Module]:
    """(patched, unpatched) with the same weights."""
    plain = build(model_name)
    patched = copy.deepcopy(plain)
    camera = fisheye(size, 190.0, "kb4", k=(0.0, 0.0, 0.0, 0.0))
    rt.apply(patched, camera, trained_looking(rt.Adapter.for_model(patched, camera)))
    return patched, plain


def exported_row(model_name: str, size: int, views: int, repeats: int, threads: int) -> dict:
    patched, plain = pair(model_name, size, views)
    images = torch.rand(1, views, 3, size, size, generator=torch.Generator().manual_seed(1))
    feed = {INPUT_NAME: images.numpy()}
    with tempfile.TemporaryDirectory() as folder:
        sessions = []
        for name, model in (("patched", patched), ("plain", plain)):
            start = time.perf_counter()
            path = export_onnx(freeze(model, (size, size), views), Path(folder) / f"{name}.onnx")
            print(f"  exported {name} at {size} px in {time.perf_counter() - start:.0f} s")
            sessions.append(onnx_session(path, threads))
        for session in sessions:
            session.run(None, feed)  # warm-up
        a, b, ratio = interleaved(
            lambda: sessions[0].run(None, feed), lambda: sessions[1].run(None, feed), repeats
        )
    return {
        "path": "exported (ONNX Runtime)",
        "size": size,
        "patched": a,
        "plain": b,
        "ratio": ratio,
    }


def compiled_row(model_name: str, size: int, views: int, repeats: int, backend: str) -> dict:
    patched, plain = pair(model_name, size, views)
    images = torch.rand(1, views, 3, size, size, generator=torch.Generator().manual_seed(1))
    torch._dynamo.reset()
    runs = []
    for name, model in (("patched", patched), ("plain", plain)):
        compiled = torch.compile(model, backend=backend)
        start = time.perf_counter()
        with torch.no_grad():
            rt.predict(compiled, images)  # compiles
            rt.predict(compiled, images)
        print(f"  compiled {name} at {size} px in {time.perf_counter() - start:.0f} s")
        runs.append(compiled)

    def run(model):
        def call():
            with torch.no_grad():
                rt.predict(model, images)

        return call

    a, b, ratio = interleaved(run(runs[0]), run(runs[1]), repeats)
    return {"path": f"compiled ({backend})", "size": size, "patched": a, "plain": b, "ratio": ratio}


def table(rows: list[dict], args) -> str:
    lines = [
        f"Measured by `benchmarks/deploy_cost.py --model {args.model} --views {args.views} "
        f"--repeats {args.repeats} --threads {args.threads} --backend {args.backend}` on "
        f"{platform.machine()} CPU, torch {torch.__version__}, {args.threads} thread(s); "
        f"{args.note}",
        "",
        "Seconds per forward are medians; the ratio is the median of the per-repeat ratios "
        "(each repeat times both variants, order alternating).",
        "",
        "| path | input | patched (s) | unpatched (s) | patched / unpatched | goal |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        goal = "<= 1.01" if row["path"].startswith("exported") else "<= 1.02"
        lines.append(
            f"| {row['path']} | {row['size']} px, {args.views} views | {row['patched']:.3f} | "
            f"{row['plain']:.3f} | {row['ratio']:.3f}x | {goal} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="da3-small", help="da3-small (random) or built-in")
    parser.add_argument("--sizes", type=int, nargs="+", default=[280, 504])
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--backend", default="inductor", help="torch.compile backend")
    parser.add_argument("--skip", choices=("exported", "compiled"), default=None)
    parser.add_argument("--note", default="", help="a remark printed under the table")
    parser.add_argument("--docs", type=Path, default=None)
    parser.add_argument("--block", default="deploy-cost", help="the docs block to replace")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    with quiet_upstream():
        for size in args.sizes:
            if args.skip != "exported":
                rows.append(exported_row(args.model, size, args.views, args.repeats, args.threads))
                print(rows[-1])
            if args.skip != "compiled":
                rows.append(compiled_row(args.model, size, args.views, args.repeats, args.backend))
                print(rows[-1])
    text = table(rows, args)
    print(text)
    if args.docs is not None:
        write_block(args.docs, args.block, text)
        print(f"wrote the table into {args.docs}")


if __name__ == "__main__":
    main()
