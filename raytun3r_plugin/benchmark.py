"""Synthetic fisheye benchmark: vanilla vs Center-PH vs raytun3r, nothing downloaded.

Held-out synthetic sequences (seeds the default network never saw) through three lenses, indoor
and outdoor. For each sequence raytun3r fits an adapter on the first frames (default adaptation:
30 windows) and every method is scored on the remaining frames, on the same pair list.
Used by ``benchmarks/fisheye_synthetic.py`` and ``raytun3r bench``.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

from raytun3r_plugin.demo import adapt_config
from raytun3r_plugin.evaluation import format_table, headline, run_method, score

HELD_OUT_SEED = 90_000  # training of the default network uses seeds far below this


@dataclass(frozen=True)
class BenchCamera:
    label: str
    model: str
    fov_deg: float


CAMERAS = (
    BenchCamera("KB4 120", "kb4", 120.0),
    BenchCamera("KB4 185", "kb4", 185.0),
    BenchCamera("DS 195", "ds", 195.0),
)
SCENES = ("indoor", "outdoor")
ZERO_ADAPTER = "raytun3r, no adapter"
COLUMNS = ["camera", "scene", "method", "rot_deg", "trans_deg", "d_reproj_px", "abs_rel", "delta_1.25", "coverage", "adapt_s"]


def make_camera(spec: BenchCamera, size: int):
    """A square camera whose image circle (``spec.fov_deg``) fills the image width."""
    from raytun3r_plugin.cameras import DoubleSphere, KannalaBrandt4

    half = math.radians(spec.fov_deg / 2)
    centre = (size - 1) / 2
    if spec.model == "kb4":
        k1 = 0.02
        focal = (size / 2) / (half * (1 + k1 * half**2))
        return KannalaBrandt4(size, size, {"fx": focal, "fy": focal, "cx": centre, "cy": centre, "k1": k1, "k2": 0.0, "k3": 0.0, "k4": 0.0}, max_fov_deg=spec.fov_deg)
    xi, alpha = -0.15, 0.6
    # Radius of the boundary ray in the normalised DS image plane, then the focal that puts it at the edge.
    x, z = math.sin(half), math.cos(half)
    d1 = 1.0
    k = xi * d1 + z
    d2 = math.sqrt(x * x + k * k)
    radius = x / (alpha * d2 + (1 - alpha) * k)
    focal = (size / 2) / radius
    return DoubleSphere(size, size, {"fx": focal, "fy": focal, "cx": centre, "cy": centre, "xi": xi, "alpha": alpha}, max_fov_deg=spec.fov_deg)


def run_benchmark(model, out_dir: str | Path, *, size: int = 112, n_adapt: int = 24, n_eval: int = 12, steps: int = 300, cameras=CAMERAS, scenes=SCENES, network: str = "", progress: bool = False) -> str:
    """Run every (camera, scene) and return the markdown table (also written to ``out_dir``)."""
    from raytun3r_plugin import synthetic
    from raytun3r_plugin.adaptation.train import adapt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows, began = [], time.perf_counter()
    for camera_index, spec in enumerate(cameras):
        camera = make_camera(spec, size)
        for scene_index, scene in enumerate(scenes):
            seed = HELD_OUT_SEED + 10 * camera_index + scene_index
            seq = synthetic.render_sequence(scene, camera, n_frames=n_adapt + n_eval, seed=seed)
            held_out = list(range(n_adapt, len(seq)))
            for method in ("vanilla", "center-ph"):
                rows.append({"camera": spec.label, "scene": scene, "method": method, **headline(score(seq, run_method(model, seq, method, frames=held_out))), "adapt_s": math.nan})
            # The patch with a zero adapter: the parameter-free corrections alone, so the table
            # shows what the fitted tables add on top of them.
            zero = headline(score(seq, run_method(model, seq, "raytun3r", frames=held_out)))
            rows.append({"camera": spec.label, "scene": scene, "method": ZERO_ADAPTER, **zero, "adapt_s": math.nan})
            config = adapt_config(size, steps, seed=0)
            start = time.perf_counter()
            adapter = adapt(model, camera, seq.images[:n_adapt], config, out_path=out / f"{spec.label.replace(' ', '_')}_{scene}.safetensors", resume=False, progress=progress)
            seconds = time.perf_counter() - start
            rows.append({"camera": spec.label, "scene": scene, "method": "raytun3r", **headline(score(seq, run_method(model, seq, "raytun3r", adapter=adapter, frames=held_out))), "adapt_s": seconds})
            print(f"[{time.perf_counter() - began:6.0f} s] {spec.label} {scene}: done", flush=True)
    table = format_table(rows, COLUMNS)
    header = (
        f"Network: {network or 'see model card'}; input {size}x{size} px; {n_adapt} adaptation frames "
        f"(30 windows, {steps} steps) and {n_eval} held-out frames per sequence; seeds from {HELD_OUT_SEED}.\n"
        "rot/trans: mean relative-pose errors (deg, signed translation direction) on consecutive held-out pairs; "
        "d_reproj: mean px with GT pose and a robust per-pair scale; AbsRel, delta<1.25: per-image median scale, "
        "range depth, sky excluded; coverage: fraction of the fisheye's valid pixels with a depth; adapt_s: wall time of adaptation; "
        f"'{ZERO_ADAPTER}': the patch without fitting (parameter-free corrections only).\n"
    )
    (out / "results.md").write_text(header + "\n" + table + "\n")
    (out / "results.json").write_text(json.dumps(rows, indent=2, default=float))
    return header + "\n" + table
