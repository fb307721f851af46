"""Effect of each parameter-free correction (no adapter) on the demo's sequence and network.

    python benchmarks/components.py

Prints one row per component set: vanilla, each correction alone, and all of them.
"""

from __future__ import annotations

from raytun3r_plugin import synthetic
from raytun3r_plugin.demo import default_network, demo_camera
from raytun3r_plugin.evaluation import format_table, headline, run_method, score

SETS = (["patch_resample"], ["border_tokens"], ["grid"], ["patch_resample", "border_tokens", "grid"])


def main() -> None:
    model, description = default_network()
    seq = synthetic.render_sequence("indoor", demo_camera(112), n_frames=36, seed=1000)
    held_out = list(range(24, 36))
    rows = [{"components": "vanilla (unpatched)", **headline(score(seq, run_method(model, seq, "vanilla", frames=held_out)))}]
    for components in SETS:
        output = run_method(model, seq, "raytun3r", frames=held_out, components=components)
        rows.append({"components": " + ".join(components), **headline(score(seq, output))})
    print(f"network: {description}")
    print(format_table(rows, ["components", "d_reproj_px", "abs_rel", "delta_1.25"]))


if __name__ == "__main__":
    main()
