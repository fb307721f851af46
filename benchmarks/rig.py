"""Issue 18: a two-camera fisheye rig in one forward, fitted per camera or jointly.

Each rig is a stereo pair rendered by ``synthetic.render_rig``: the benchmark's KB4 185 as the left
(reference) camera and its DS 195 as the right one, 0.1 m apart, 112 px, indoor, 36 instants. The
first 24 instants are for fitting and the last 12 are scored. Every method is scored on the same
rig forwards: windows of 3 instants x 2 cameras = 6 views through one patched model, each
camera's views scored against that camera's ground truth (``evaluation.score``: AbsRel
median-aligned per image without sky, d_reproj with ground-truth poses).

Methods:

* ``vanilla``: the unpatched network on the 6 views;
* ``rig, no adapter``: ``apply(model, [left, right])``, the parameter-free corrections;
* ``per-camera adapt``: ``adapt`` on each camera's frames alone, the two adapters applied as a rig;
* ``adapt_rig``: both adapters fitted together, both cameras' views in every forward;
* ``supervised per camera``: ``adapt(..., depth=...)`` per camera (the upper bound), applied as a rig.

The settings are a fit recipe's (``--recipe``, default ``rig``: the default recipe without the
teacher term, which ``adapt_rig`` does not have; 300 steps; the tables above that say v2 were
measured with v2's earlier settings, the ``targets`` recipe);
``min_parallax_px`` does not apply to ``adapt_rig``, which is why the scene is indoor, where the
gate keeps every window.

Decision rule, fixed before the first run: ``adapt_rig`` is the rig fitting path either way; the
README says joint fitting helps only if its AbsRel is below per-camera fitting on at least 5 of the
6 camera-sequences (3 rigs x 2 cameras), and reports the numbers whatever they are.
Development seeds 70000 + k indoors, 70100 + k outdoors (never the benchmark's 90000+).
``--scene outdoor --baseline 0.4 --cross-camera`` adds the opt-in cross-camera fit as a row.
Its rule, fixed before its first run (2 outdoor rigs): the cross-camera terms "help outdoors"
if that row's AbsRel is below the no-adapter row on at least 3 of the 4 camera-sequences; the
option stays opt-in either way until a held-out comparison exists.
``--held-out`` scores rigs no setting was chosen on (seeds 75000 + k indoors, 75100 + k outdoors).
Rule for the held-out outdoor comparison, fixed before it was run (``--held-out --scene outdoor
--baseline 0.4 --cross-camera``, 3 rigs, 6 camera-sequences): the README may say the cross-camera
terms help outdoors on unseen rigs if that row's AbsRel is below the no-adapter row on at least 5
of the 6 and its mean AbsRel is below both the no-adapter and the plain ``adapt_rig`` rows.

    python benchmarks/rig.py               # 3 rigs, about 15 minutes on one thread
    python benchmarks/rig.py --rigs 1 --steps 30
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from raytun3r_plugin import apply, predict, synthetic
from raytun3r_plugin.adaptation.recipes import recipe_names
from raytun3r_plugin.adaptation.rig import adapt_rig
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.apps.benchmark import CAMERAS, ZERO_ADAPTER, ground_truth_depth, make_camera
from raytun3r_plugin.apps.demo import BUILT_IN_NETWORKS, DEFAULT_NETWORK, default_network
from raytun3r_plugin.apps.evaluation import MethodOutput, frame_windows, score
from raytun3r_plugin.apps.fits import adapt_config, supervised_config
from raytun3r_plugin.registry import quiet_upstream

RIG_SEED = 70_000
RIG_HELD_OUT_SEED = 75_000
N_ADAPT, N_EVAL, SIZE = 24, 12, 112
METHODS = ("vanilla", ZERO_ADAPTER, "per-camera adapt", "adapt_rig", "supervised per camera")
CROSS = "adapt_rig + cross-camera"


def rig_outputs(model, rig, cameras, adapters, instants) -> dict[str, MethodOutput]:
    """Each camera's :class:`MethodOutput` from rig forwards of 3 instants (None: unpatched)."""
    names = rig.names
    depth = {name: np.zeros((len(rig), SIZE, SIZE), np.float32) for name in names}
    poses = {name: [] for name in names}
    handle = apply(model, cameras, adapters, strict=False) if cameras is not None else None
    start = time.perf_counter()
    try:
        with torch.no_grad():
            for group in frame_windows(instants, 3):
                views = torch.from_numpy(rig.views(group)).permute(0, 3, 1, 2)[None]
                prediction = predict(model, views)
                for offset, name in enumerate(names):
                    depth[name][group] = prediction.depth[0, offset :: len(names)].float().numpy()
                    poses[name].append(
                        (group, prediction.cam_from_world[0, offset :: len(names)].double().numpy())
                    )
    finally:
        if handle is not None:
            handle.remove()
    seconds = time.perf_counter() - start
    return {
        name: MethodOutput(depth=depth[name], window_poses=poses[name], seconds=seconds)
        for name in names
    }


def one_rig(
    model,
    seed: int,
    steps: int,
    scene: str = "indoor",
    baseline: float = 0.1,
    cross_camera: bool = False,
    recipe: str = "rig",
) -> list[dict]:
    cameras = {
        "left": make_camera(CAMERAS[1], SIZE),  # KB4 185
        "right": make_camera(CAMERAS[2], SIZE),  # DS 195
    }
    rig = synthetic.render_rig(
        scene,
        cameras,
        synthetic.stereo_extrinsics(baseline),
        n_frames=N_ADAPT + N_EVAL,
        seed=seed,
    )
    fit, held_out = rig.subset(range(N_ADAPT)), list(range(N_ADAPT, N_ADAPT + N_EVAL))
    names, lenses = rig.names, rig.cameras
    # adapt_rig has no teacher term yet (it refuses one), so neither rig fit takes it: the
    # per-camera fits and the joint one differ only in how they fit, like with like.
    config = adapt_config(SIZE, steps, seed=0, recipe=recipe, teacher_weight=0.0, model=model)
    fitted: dict[str, list | None] = {"vanilla": None, ZERO_ADAPTER: [None, None]}
    seconds: dict[str, float] = {"vanilla": 0.0, ZERO_ADAPTER: 0.0}
    began = time.perf_counter()
    fitted["per-camera adapt"] = [
        adapt(model, seq.camera, seq.images[:N_ADAPT], config, progress=False)
        for seq in rig.sequences.values()
    ]
    seconds["per-camera adapt"] = time.perf_counter() - began
    began = time.perf_counter()
    joint = adapt_rig(model, fit, config, progress=False)
    fitted["adapt_rig"] = [joint[name] for name in names]
    seconds["adapt_rig"] = time.perf_counter() - began
    methods = METHODS
    if cross_camera:
        began = time.perf_counter()
        crossed = adapt_rig(model, fit, config, progress=False, cross_camera=True)
        fitted[CROSS] = [crossed[name] for name in names]
        seconds[CROSS] = time.perf_counter() - began
        methods = (*METHODS[:4], CROSS, METHODS[4])
    began = time.perf_counter()
    fitted["supervised per camera"] = [
        adapt(
            model,
            seq.camera,
            seq.images[:N_ADAPT],
            supervised_config(SIZE, steps, seed=0, pose_source=config.pose_source),
            depth=ground_truth_depth(seq, N_ADAPT),
            progress=False,
        )
        for seq in rig.sequences.values()
    ]
    seconds["supervised per camera"] = time.perf_counter() - began
    rows = []
    for method in methods:
        adapters = fitted[method]
        outputs = rig_outputs(model, rig, None if adapters is None else lenses, adapters, held_out)
        for name in names:
            summary = score(rig.sequences[name], outputs[name])
            rows.append(
                {
                    "seed": seed,
                    "camera": name,
                    "method": method,
                    "abs_rel": float(summary["abs_rel"]["mean"]),
                    "d_reproj_px": float(summary["d_reproj"]["mean"]),
                    "fit_s": seconds[method],
                }
            )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rigs", type=int, default=3)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--scene", default="indoor", choices=("indoor", "outdoor"))
    parser.add_argument("--baseline", type=float, default=0.1, help="stereo baseline (m)")
    parser.add_argument(
        "--cross-camera", action="store_true", help="add an adapt_rig(cross_camera=True) row"
    )
    parser.add_argument(
        "--held-out",
        action="store_true",
        help=f"held-out rigs (seeds {RIG_HELD_OUT_SEED}+) instead of the development ones ({RIG_SEED}+)",
    )
    parser.add_argument("--network", default=DEFAULT_NETWORK, choices=BUILT_IN_NETWORKS)
    parser.add_argument(
        "--recipe",
        default="rig",
        choices=recipe_names(),
        help="fit recipe of the rig fits (its teacher term left out)",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    model, description = default_network(args.network)
    fitting = adapt_config(SIZE, args.steps, recipe=args.recipe, teacher_weight=0.0, model=model)
    base = RIG_HELD_OUT_SEED if args.held_out else RIG_SEED
    print(
        f"network: {description}; recipe '{args.recipe}', pose source '{fitting.pose_source}', "
        f"pose weight {fitting.weights.pose:g}; {args.rigs} "
        f"{'held-out' if args.held_out else 'development'} stereo rigs (left KB4 185, right DS 195, "
        f"{args.baseline:g} m), {args.scene}, {SIZE} px, fitted on {N_ADAPT} instants, scored on {N_EVAL}, {args.steps} steps\n"
    )
    rows = []
    with quiet_upstream():
        for k in range(args.rigs):
            seed = base + (100 if args.scene == "outdoor" else 0) + k
            rows += one_rig(
                model, seed, args.steps, args.scene, args.baseline, args.cross_camera, args.recipe
            )
    print("| method | camera | AbsRel (mean over rigs) | d_reproj px | fit s (both cameras) |")
    print("|---|---|---|---|---|")
    for method in (*METHODS[:4], CROSS, METHODS[4]) if args.cross_camera else METHODS:
        for camera in ("left", "right"):
            cell = [r for r in rows if r["method"] == method and r["camera"] == camera]
            print(
                f"| {method} | {camera} | {np.mean([r['abs_rel'] for r in cell]):.3f} | "
                f"{np.mean([r['d_reproj_px'] for r in cell]):.3f} | "
                f"{np.mean([r['fit_s'] for r in cell]):.0f} |"
            )
    joint = {(r["seed"], r["camera"]): r["abs_rel"] for r in rows if r["method"] == "adapt_rig"}
    alone = {
        (r["seed"], r["camera"]): r["abs_rel"] for r in rows if r["method"] == "per-camera adapt"
    }
    wins = sum(joint[key] < alone[key] for key in joint)
    print(
        f"\nadapt_rig below per-camera adapt on AbsRel: {wins} of {len(joint)} camera-sequences "
        f"(the rule: joint fitting helps if at least {len(joint) - 1 if len(joint) > 1 else 1})"
    )
    print("\nper camera-sequence AbsRel:")
    for key in sorted(joint):
        cells = {r["method"]: r["abs_rel"] for r in rows if (r["seed"], r["camera"]) == key}
        print(f"  seed {key[0]} {key[1]}: " + ", ".join(f"{m} {v:.3f}" for m, v in cells.items()))


if __name__ == "__main__":
    main()
