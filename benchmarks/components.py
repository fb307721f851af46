"""Effect of each parameter-free correction (no adapter), per component set; the paper's
component ablation (``--ablations``).

    python benchmarks/components.py                    # the demo's sequence
    python benchmarks/components.py --dev-sequences 5  # 5 development sequences per benchmark cell
    python benchmarks/components.py --ablations        # the ablation rows (docs/components.md)
    python benchmarks/components.py --ablations --refit  # ... plus one fit per learned row
    python benchmarks/components.py --ablations --refit --sequences 4  # means over 4 sequences
    python benchmarks/components.py --ablations --baselines  # ... plus Multi-PH, LoRA, tokens

Prints one row per component set: vanilla, each correction alone, and all of them. With
``--dev-sequences N`` the rows are means over N sequences of every (camera, scene) cell of the
benchmark, rendered from development seeds (80000 + 100 k + 10 camera + scene, never the
benchmark's 90000+), with on how many sequences each metric is lower than vanilla's.

``--ablations`` prints the rows of the paper's component table in its order (patch undistortion
alone, naive remap of the PE, radial PE only, radial + angular PE, RoPE only, full model) on the
demo's sequence: each with the zero adapter and, for rows with learned tables, with the adapter
fitted on frames 0-23 by the demo's configuration (all components on, then evaluated under the
row's switches); ``--refit`` adds, per learned row, an adapter fitted with only that row's
components on (as the paper's rows were trained); ``--baselines`` adds Multi-PH and LoRA and
calibration tokens fitted with the same objective, windows, optimiser and steps (the demo's
configuration with ``components=[]``, on the unpatched model). ``params``: the trainable
parameters a row uses.
"""

from __future__ import annotations

import argparse
import tempfile
import time

from raytun3r_plugin import synthetic
from raytun3r_plugin.adapter import COMPONENTS
from raytun3r_plugin.apps.benchmark import CAMERAS, SCENES, make_camera
from raytun3r_plugin.apps.demo import default_network, demo_camera
from raytun3r_plugin.apps.evaluation import format_table, headline, run_method, score
from raytun3r_plugin.registry import quiet_upstream

SETS = (
    ["patch_resample"],
    ["border_tokens"],
    ["grid"],
    ["patch_resample", "grid"],
    ["patch_resample", "border_tokens", "grid"],
)
METRICS = ("d_reproj_px", "abs_rel", "delta_1.25")
DEV_SEED = 80_000
#: The step of every fit here (the demo's when this was measured, on every lens).
LR = 1e-2
#: (label, components, has learned tables) of the paper's component ablation, in its order.
ABLATION_ROWS = (
    ("patch undistortion alone", ["patch_resample"], False),
    ("naive remap of PE", ["pe_naive_remap"], False),
    ("radial PE only", ["pe", "pe_radial_only"], True),
    ("radial + angular PE", ["pe"], True),
    ("RoPE only", ["rope"], True),
    ("full model", list(COMPONENTS), True),
)
ABLATION_METRICS = ("rot_deg", "trans_deg", "d_reproj_px", "abs_rel", "delta_1.25")


def score_sets(model, seq, held_out: list[int]) -> dict[str, dict[str, float]]:
    """{component set label: headline scores} on the held-out frames of one sequence."""
    scores = {
        "vanilla (unpatched)": headline(
            score(seq, run_method(model, seq, "vanilla", frames=held_out))
        )
    }
    for components in SETS:
        output = run_method(model, seq, "raytun3r", frames=held_out, components=components)
        scores[" + ".join(components)] = headline(score(seq, output))
    return scores


def _row_parameters(adapter, components: list[str]) -> int:
    """Trainable parameters of ``adapter`` that the switches ``components`` read."""
    counts = adapter.num_parameters()
    pe = counts["pe"] if "pe" in components else 0
    if "pe_radial_only" in components:
        pe = adapter.pe["radial"].numel()
    return pe + (counts["rope"] if "rope" in components else 0)


def baseline_rows(model, seq, held_out: list[int], n_adapt: int, cache: str) -> list[dict]:
    """Multi-PH, and LoRA and calibration tokens fitted like raytun3r's tables (the demo's
    configuration, ``components=[]``: the unpatched model), scored on ``held_out``."""
    from raytun3r_plugin.apps.benchmark import fitted_baseline
    from raytun3r_plugin.apps.demo import DEMO_STEPS
    from raytun3r_plugin.apps.fits import adapt_config

    rows = [
        {
            "configuration": "Multi-PH (5 pinhole views)",
            "components": "-",
            "adapter": "-",
            "params": 0,
            **headline(score(seq, run_method(model, seq, "multi-ph", frames=held_out))),
        }
    ]
    config = adapt_config(
        seq.camera.width,
        DEMO_STEPS,
        lr=LR,
        seed=0,
        cache_dir=cache,
        components=[],
        model=model,
    )
    for label, name in (
        ("LoRA (r = 8, alpha = 16)", "lora"),
        ("calibration tokens (t = 4)", "caltok"),
    ):
        with fitted_baseline(model, seq.camera, seq.images[:n_adapt], name, config) as (tuned, _):
            output = run_method(model, seq, "vanilla", frames=held_out)
        rows.append(
            {
                "configuration": label,
                "components": "-",
                "adapter": "fitted (same objective)",
                "params": tuned.num_parameters(),
                **headline(score(seq, output)),
            }
        )
    return rows


def ablation_rows(model, seed: int, refit: bool, baselines: bool = False) -> list[dict]:
    """The ``--ablations`` rows on one demo sequence (frames 0-23 fitted, 24-35 scored)."""
    from raytun3r_plugin.adaptation.train import adapt
    from raytun3r_plugin.apps.demo import DEMO_STEPS
    from raytun3r_plugin.apps.fits import adapt_config

    size, n_adapt = 112, 24
    seq = synthetic.render_sequence("indoor", demo_camera(size), n_frames=36, seed=seed)
    held_out = list(range(n_adapt, len(seq)))

    def scored(adapter, components) -> dict[str, float]:
        output = run_method(
            model, seq, "raytun3r", adapter=adapter, frames=held_out, components=components
        )
        return headline(score(seq, output))

    rows = [
        {
            "configuration": "vanilla (unpatched)",
            "components": "-",
            "adapter": "-",
            "params": 0,
            **headline(score(seq, run_method(model, seq, "vanilla", frames=held_out))),
        }
    ]
    with tempfile.TemporaryDirectory() as cache:

        def fit(components):
            began = time.perf_counter()
            config = adapt_config(
                size,
                DEMO_STEPS,
                lr=LR,
                seed=0,
                cache_dir=cache,
                components=components,
                model=model,
            )
            adapter = adapt(model, seq.camera, seq.images[:n_adapt], config, progress=False)
            print(
                f"  seed {seed}: fitted {components or 'all components'} in "
                f"{time.perf_counter() - began:.0f} s",
                flush=True,
            )
            return adapter

        demo_fit = fit(None)
        for label, components, learned in ABLATION_ROWS:
            names = " + ".join(components) if components != list(COMPONENTS) else "all five"
            base = {"configuration": label, "components": names}
            rows.append({**base, "adapter": "none", "params": 0, **scored(None, components)})
            if learned:
                rows.append(
                    {
                        **base,
                        "adapter": "demo fit (all on)",
                        "params": _row_parameters(demo_fit, components),
                        **scored(demo_fit, components),
                    }
                )
                if refit and components != list(COMPONENTS):
                    refitted = fit(components)
                    rows.append(
                        {
                            **base,
                            "adapter": "fitted for the row",
                            "params": _row_parameters(refitted, components),
                            **scored(refitted, components),
                        }
                    )
        if baselines:
            rows += baseline_rows(model, seq, held_out, n_adapt, cache)
    return rows


def ablation_table(model, refit: bool, sequences: int, baselines: bool = False) -> str:
    """Means of :func:`ablation_rows` over the demo's sequences (seeds 1000, 1001, ...), with on
    how many of them a row's d_reproj and AbsRel are below vanilla's."""
    per_sequence = [ablation_rows(model, 1000 + k, refit, baselines) for k in range(sequences)]
    rows = []
    for index, first in enumerate(per_sequence[0]):
        row = {key: first[key] for key in ("configuration", "components", "adapter", "params")}
        for key in ABLATION_METRICS:
            row[key] = sum(s[index][key] for s in per_sequence) / len(per_sequence)
        if index and sequences > 1:
            row["lower_than_vanilla"] = ", ".join(
                f"{key} {sum(s[index][key] < s[0][key] for s in per_sequence)}/{sequences}"
                for key in ("d_reproj_px", "abs_rel")
            )
        rows.append(row)
    columns = ["configuration", "components", "adapter", "params", *ABLATION_METRICS]
    return format_table(rows, columns + (["lower_than_vanilla"] if sequences > 1 else []))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--dev-sequences",
        type=int,
        default=0,
        help="sequences per benchmark cell (0: the demo's sequence)",
    )
    parser.add_argument(
        "--ablations",
        action="store_true",
        help="the paper's component-ablation rows on the demo's sequence (docs/components.md)",
    )
    parser.add_argument(
        "--sequences",
        type=int,
        default=1,
        help="with --ablations: demo sequences to average over (seeds 1000, 1001, ...)",
    )
    parser.add_argument(
        "--refit",
        action="store_true",
        help="with --ablations: also fit one adapter per learned row with only its components",
    )
    parser.add_argument(
        "--baselines",
        action="store_true",
        help="with --ablations: also Multi-PH, and LoRA and calibration tokens fitted alike",
    )
    args = parser.parse_args()
    model, description = default_network()
    print(f"network: {description}")
    if args.ablations:
        began = time.perf_counter()
        table = ablation_table(model, args.refit, args.sequences, args.baselines)
        seeds = f"seed{'s' if args.sequences > 1 else ''} 1000-{999 + args.sequences}"
        print(
            f"{args.sequences} demo sequence(s) (indoor, KB4 190 deg, 112 px, {seeds}): frames "
            f"0-23 fitted (demo configuration), 24-35 scored; means; "
            f"{time.perf_counter() - began:.0f} s"
        )
        print(table)
        return
    if not args.dev_sequences:
        seq = synthetic.render_sequence("indoor", demo_camera(112), n_frames=36, seed=1000)
        scores = score_sets(model, seq, list(range(24, 36)))
        print(
            format_table(
                [{"components": label, **row} for label, row in scores.items()],
                ["components", *METRICS],
            )
        )
        return
    per_sequence = []
    for camera_index, spec in enumerate(CAMERAS):
        camera = make_camera(spec, 112)
        for scene_index, scene in enumerate(SCENES):
            for k in range(args.dev_sequences):
                seed = DEV_SEED + 100 * k + 10 * camera_index + scene_index
                seq = synthetic.render_sequence(scene, camera, n_frames=36, seed=seed)
                per_sequence.append(score_sets(model, seq, list(range(24, 36))))
    rows = []
    for label in per_sequence[0]:
        row = {"components": label}
        for key in METRICS:
            row[key] = sum(s[label][key] for s in per_sequence) / len(per_sequence)
        if label != "vanilla (unpatched)":
            lower = {
                key: sum(s[label][key] < s["vanilla (unpatched)"][key] for s in per_sequence)
                for key in ("d_reproj_px", "abs_rel")
            }
            row["lower_than_vanilla"] = ", ".join(
                f"{key} {n}/{len(per_sequence)}" for key, n in lower.items()
            )
        rows.append(row)
    print(
        f"{len(per_sequence)} development sequences ({args.dev_sequences} per camera and scene), 112 px, frames 24-35 scored; means:"
    )
    print(format_table(rows, ["components", *METRICS, "lower_than_vanilla"]))


if __name__ == "__main__":
    with quiet_upstream():  # no per-forward INFO lines from the backbone's own logger
        main()
