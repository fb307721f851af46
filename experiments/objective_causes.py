"""Why the paper's self-supervised objective left the tables at zero, and what changed it.

On the three development sequences of issue 12 (KB4 185 indoor 80010, DS 195 indoor 80020, KB4
185 outdoor 80011; the benchmark uses 90000+), with the built-in network at 112 px:

1. **translation scale**: at ground-truth depth, with the MAGSAC++ rotation and unit
   translation of each pair, the mean L1 reprojection error (px) when the translation length is
   the 3-D least-squares scale (``fit_translation_scale``), the pixel-optimal one
   (``pixel_optimal_scale``) and the true one; the same for the zero adapter's depth; and the
   same at ground-truth depth with the matches of DIS without its appearance check;
2. **regularisers**: what the paper's L2/TV (weights 2/20, PE units) and the relative ones
   (0.02/0.2, divided by the backbone's PE energy) charge for the correction a supervised fit
   finds, next to the data terms;
3. **ranking**: the paper's objective (L1, least-squares scale, absolute regularisers, smoothness
   10, DIS without its appearance check) and the new default objective, each evaluated for the
   zero adapter, a quarter of the supervised correction and the supervised correction.

    python experiments/objective_causes.py
"""

from __future__ import annotations

import copy

import numpy as np
import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.losses import (
    LossWeights,
    backproject,
    pe_energy,
    pixel_optimal_scale,
    reprojection_loss,
    sample_bilinear,
)
from raytun3r_plugin.adaptation.pose_terms import (
    fit_translation_scale,
)
from raytun3r_plugin.adaptation.problem import prepare_problem
from raytun3r_plugin.adaptation.step import objective_value
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.apps.benchmark import CAMERAS, ground_truth_depth, make_camera
from raytun3r_plugin.apps.demo import default_network
from raytun3r_plugin.apps.evaluation import format_table
from raytun3r_plugin.apps.fits import adapt_config, supervised_config
from raytun3r_plugin.registry import quiet_upstream, spec_for

SEQUENCES = (
    ("KB4 185", "indoor", 80_010),
    ("DS 195", "indoor", 80_020),
    ("KB4 185", "outdoor", 80_011),
)
PAPER = {
    "weights": LossWeights(),
    "scale": "least_squares",
    "robust_px": None,
    "pe_regulariser": "absolute",
    "matcher_options": {"appearance_check": False},
}


def scale_errors(problem, seq, depth_maps: torch.Tensor) -> dict[str, float]:
    """Mean L1 reprojection error (px) over the pairs with a usable target, per scale choice."""
    errors: dict[str, list[float]] = {"least_squares": [], "pixel_optimal": [], "true": []}
    camera = problem.layout.camera
    for window, pairs in problem.windows:
        for pair in pairs:
            if pair.rotation is None or pair.uv_i.shape[0] < 10:
                continue
            depth = sample_bilinear(depth_maps[window.frames[pair.a]], pair.uv_i)
            usable = torch.isfinite(depth) & (depth > 0)
            points = backproject(
                torch.where(usable, depth, torch.ones_like(depth)), pair.rays_i, "range"
            )[usable].double()
            rotation, direction = pair.rotation, pair.direction
            gi, gj = window.global_pair(pair.a, pair.b)
            truth = synthetic.relative_pose(seq.cam_from_world, gi, gj)
            scales = {
                "least_squares": fit_translation_scale(
                    points, pair.rays_j[usable].double(), rotation, direction
                ),
                "pixel_optimal": pixel_optimal_scale(
                    points, pair.uv_j[usable].double(), rotation, direction, camera
                ),
                "true": torch.tensor(float(np.linalg.norm(truth[:3, 3])), dtype=torch.float64),
            }
            for name, scale in scales.items():
                pose = torch.eye(4, dtype=torch.float64)
                pose[:3, :3], pose[:3, 3] = rotation, scale * direction
                loss, count = reprojection_loss(
                    depth_maps[window.frames[pair.a]].double(),
                    pose,
                    pair.uv_i,
                    pair.uv_j,
                    None,
                    camera,
                    problem.valid,
                    rays_i=(pair.rays_i, torch.ones(pair.uv_i.shape[0], dtype=torch.bool)),
                )
                if count:
                    errors[name].append(float(loss))
    return {name: float(np.mean(values)) for name, values in errors.items()}


def zero_adapter_depth(model, problem) -> torch.Tensor:
    from raytun3r_plugin.patching import apply
    from raytun3r_plugin.prediction import predict

    depth = torch.zeros(max(problem.inputs) + 1, problem.layout.height, problem.layout.width)
    with torch.no_grad(), apply(model, problem.layout.native_camera, None, strict=False):
        for frame, image in problem.inputs.items():
            depth[frame] = predict(model, image[None, None]).depth[0, 0]
    return depth


def main() -> None:
    model, description = default_network()
    spec, root = spec_for(model)
    energy = pe_energy(spec.describe(root).pos_embed)
    print(f"network: {description}; PE energy mean ||P||^2 = {energy:.1f}\n")
    scale_rows, price_rows, rank_rows = [], [], []
    for label, scene, seed in SEQUENCES:
        spec_camera = next(c for c in CAMERAS if c.label == label)
        camera = make_camera(spec_camera, 112)
        seq = synthetic.render_sequence(scene, camera, n_frames=24, seed=seed)
        cell = f"{label} {scene} {seed}"
        new = adapt_config(112, 300)
        old = adapt_config(112, 300, **PAPER)
        problem_new, problem_old = (
            prepare_problem(camera, seq.images, new),
            prepare_problem(camera, seq.images, old),
        )
        gt = torch.from_numpy(ground_truth_depth(seq, 24))
        at_truth = scale_errors(
            problem_new, seq, torch.where(gt > 0, gt, torch.full_like(gt, float("nan")))
        )
        at_zero = scale_errors(problem_new, seq, zero_adapter_depth(model, problem_new))
        unchecked = scale_errors(
            problem_old, seq, torch.where(gt > 0, gt, torch.full_like(gt, float("nan")))
        )
        scale_rows.append(
            {
                "sequence": cell,
                **{f"GT depth, {k}": v for k, v in at_truth.items()},
                **{f"zero adapter, {k}": v for k, v in at_zero.items() if k != "true"},
                **{f"GT depth, unchecked DIS, {k}": v for k, v in unchecked.items()},
            }
        )

        supervised = adapt(
            model, camera, seq.images, supervised_config(112, 100), depth=gt.numpy(), progress=False
        )
        quarter = copy.deepcopy(supervised)
        with torch.no_grad():
            for parameter in quarter.parameters():
                parameter.mul_(0.25)
        zero = Adapter.for_model(model)
        values = {}
        for objective, config, problem in (("paper", old, problem_old), ("new", new, problem_new)):
            for name, adapter in (("zero", zero), ("quarter", quarter), ("supervised", supervised)):
                values[(objective, name)] = objective_value(model, adapter, problem, config)
        sup_new, sup_old = values[("new", "supervised")], values[("paper", "supervised")]
        price_rows.append(
            {
                "sequence": cell,
                "paper L2+TV price": 2 * sup_old["l2"] + 20 * sup_old["tv"],
                "relative L2+TV price": 0.02 * sup_new["l2"] + 0.2 * sup_new["tv"],
                "data terms (new, zero adapter)": values[("new", "zero")]["reproj"]
                + new.weights.smooth * values[("new", "zero")]["smooth"],
                "data gain of the supervised fit (new)": (
                    values[("new", "zero")]["reproj"]
                    + new.weights.smooth * values[("new", "zero")]["smooth"]
                )
                - (sup_new["reproj"] + new.weights.smooth * sup_new["smooth"]),
            }
        )
        for objective in ("paper", "new"):
            rank_rows.append(
                {
                    "sequence": cell,
                    "objective": objective,
                    **{
                        name: values[(objective, name)]["loss"]
                        for name in ("zero", "quarter", "supervised")
                    },
                }
            )
        print(f"{cell}: done", flush=True)
    print(
        "\n1. Mean L1 reprojection error (px) of the matches, MAGSAC++ rotation and direction, by translation scale:\n"
    )
    print(format_table(scale_rows, list(scale_rows[0])))
    print(
        "\n2. Price of the supervised correction under each regulariser, next to the data terms:\n"
    )
    print(format_table(price_rows, list(price_rows[0])))
    print(
        "\n3. Objective value (lower is preferred) of the zero adapter, a quarter of the supervised correction and the supervised correction:\n"
    )
    print(format_table(rank_rows, list(rank_rows[0])))


if __name__ == "__main__":
    with quiet_upstream():
        main()
