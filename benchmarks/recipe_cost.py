"""What the default recipe's fit costs on this machine, from the same script every time.

* ``da3-small`` (DA3's real configuration, random weights, a random-filled ``pos_embed``) at each
  of ``--sizes`` px: ``adapt()`` with the default recipe and ``--steps`` steps on a synthetic
  indoor segment through a 190-degree KB4 lens (so the lens-gated teacher is on), with a cold
  cache. Measured: the preparation (matching, MAGSAC++, the teacher's pinhole views, the parallax
  gate, saving) and the time of each step; the full 300-step fit is EXTRAPOLATED as preparation +
  300 x the median step, and labelled so.
* The built-in networks at their own 112 px: the full default fit (300 steps) on one such
  segment, run and timed end to end.

    python benchmarks/recipe_cost.py [--sizes 280 504] [--steps 6] [--docs docs/recipes.md]

With ``--docs`` the table replaces the block between the file's ``recipe-cost`` markers, so the
docs show what this script measured. Run it alone: other jobs on the machine change every number.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import torch
from docs_block import write_block

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.checkpoint import read_loss_log
from raytun3r_plugin.adaptation.config import AdaptConfig
from raytun3r_plugin.adaptation.recipes import get_recipe
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.apps.demo import BUILT_IN_NETWORKS, default_network
from raytun3r_plugin.cameras import fisheye
from raytun3r_plugin.registry import quiet_upstream

FRAMES = 24


def da3_small() -> torch.nn.Module:
    """``da3-small`` from DA3's own config, random weights, random-filled ``pos_embed``."""
    from depth_anything_3.cfg import create_object, load_config
    from depth_anything_3.registry import MODEL_REGISTRY

    torch.manual_seed(0)
    model = create_object(load_config(MODEL_REGISTRY["da3-small"]))
    with torch.no_grad():
        torch.nn.init.trunc_normal_(model.backbone.pretrained.pos_embed, std=0.02)
    return model.eval()


def timed_fit(model: torch.nn.Module, size: int, steps: int) -> dict:
    """One default-recipe fit of ``steps`` steps at ``size`` px, cold cache: the timings."""
    camera = fisheye(size, 190.0, "kb4")
    images = synthetic.render_sequence("indoor", camera, n_frames=FRAMES, seed=0).images
    with tempfile.TemporaryDirectory(prefix="raytun3r-recipe-cost-") as folder:
        out = Path(folder) / "adapter.safetensors"
        # The fit a user gets: the recipe with the model's backbone family's changes.
        config = AdaptConfig.from_recipe(
            "default",
            model=model,
            input_size=size,
            steps=steps,
            cache_dir=folder,
            checkpoint_every=0,
        )
        began = time.perf_counter()
        adapter = adapt(model, camera, images, config, out_path=out, progress=False)
        total = time.perf_counter() - began
        step_times = [record["time_s"] for record in read_loss_log(out)]
    teacher = adapter.training_info.get("teacher") or {}
    return {
        "total_s": total,
        "preparation_s": total - sum(step_times),
        "step_s": statistics.median(step_times) if step_times else float("nan"),
        "steps": len(step_times),
        "teacher": bool(teacher.get("used")),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[280, 504])
    parser.add_argument("--steps", type=int, default=6, help="steps run on da3-small")
    parser.add_argument("--skip-built-in", action="store_true")
    parser.add_argument("--docs", default=None, help="write the table into this markdown file")
    args = parser.parse_args()
    recipe = get_recipe("default")
    full = AdaptConfig().steps
    rows = []
    for size in args.sizes:
        cost = timed_fit(da3_small(), size, args.steps)
        extrapolated = cost["preparation_s"] + full * cost["step_s"]
        rows.append(
            f"| da3-small (random weights) | {size} | {cost['preparation_s']:.0f} | "
            f"{cost['step_s']:.2f} | {full} | {extrapolated:.0f} ({extrapolated / 60:.1f} min), "
            f"extrapolated from {cost['steps']} steps | {'on' if cost['teacher'] else 'off'} |"
        )
        print(rows[-1], flush=True)
    if not args.skip_built_in:
        for name in BUILT_IN_NETWORKS:
            model, _ = default_network(name)
            cost = timed_fit(model, 112, full)
            rows.append(
                f"| {name} | 112 | {cost['preparation_s']:.0f} | {cost['step_s']:.3f} | "
                f"{cost['steps']} | {cost['total_s']:.0f}, run | "
                f"{'on' if cost['teacher'] else 'off'} |"
            )
            print(rows[-1], flush=True)
    table = "\n".join(
        [
            f"`python benchmarks/recipe_cost.py` (recipe '{recipe.name}' v{recipe.version}; "
            f"{torch.get_num_threads()} torch threads, {os.cpu_count()} CPUs; a synthetic "
            f"{FRAMES}-frame indoor segment through a 190-degree KB4 lens, cold cache):",
            "",
            "| network | input (px) | preparation (s) | s per step | steps | fit (s) | teacher |",
            "|---|---|---|---|---|---|---|",
            *rows,
        ]
    )
    print("\n" + table)
    if args.docs:
        write_block(args.docs, "recipe-cost", table)


if __name__ == "__main__":
    with quiet_upstream():
        main()
