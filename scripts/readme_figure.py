"""The README's picture: depth on a 190-degree fisheye frame before and after raytun3r.

The demo's first sequence (render seed 1000, a synthetic room through the demo's 190-degree KB4
lens at 112 px) and the built-in network: an adapter is fitted with the default recipe on
frames 0-23, and frame 30 (not fitted) is shown as the fisheye image, its ground-truth range, the
unpatched network's depth and the adapted network's depth, each prediction scaled to the ground
truth by its median, on one colour scale. The title gives each one's AbsRel on that frame.

    python scripts/readme_figure.py [--out docs/images/depth_before_after.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    import cv2

    from raytun3r_plugin import metrics, synthetic
    from raytun3r_plugin.adaptation.train import adapt
    from raytun3r_plugin.apps.demo import DEFAULT_NETWORK, default_network, demo_camera
    from raytun3r_plugin.apps.evaluation import run_method
    from raytun3r_plugin.apps.fits import adapt_config
    from raytun3r_plugin.plots import heatmap
    from raytun3r_plugin.registry import quiet_upstream

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/images/depth_before_after.png")
    parser.add_argument("--frame", type=int, default=30)
    args = parser.parse_args()
    size = 112
    camera = demo_camera(size)
    seq = synthetic.render_sequence("indoor", camera, n_frames=36, seed=1000)
    model, _ = default_network(DEFAULT_NETWORK)
    with quiet_upstream():
        adapter = adapt(
            model,
            camera,
            seq.first_images(24),
            adapt_config(size, 300, seed=0, model=model),
            progress=False,
        )
        frames = [args.frame - 1, args.frame, args.frame + 1]
        outputs = {
            "vanilla": run_method(model, seq, "vanilla", frames=frames),
            "raytun3r": run_method(model, seq, "raytun3r", adapter=adapter, frames=frames),
        }
    truth = np.asarray(seq.depth[args.frame], np.float64)
    lens = camera.valid_mask().cpu().numpy().astype(bool) & (truth > 0)
    sky = seq.meta.get("per_frame", {}).get("sky")
    if sky is not None:
        lens &= ~np.asarray(sky[args.frame], bool)
    low, high = np.percentile(truth[lens], [2, 98])
    panels, scores = [], {}
    for name, output in outputs.items():
        depth = np.asarray(output.depth[args.frame], np.float64)
        keep = lens & (depth > 0)
        depth = depth * np.median(truth[keep]) / np.median(depth[keep])
        scores[name] = float(metrics.abs_rel(depth, truth, valid=keep, align="none"))
        title = "unpatched network" if name == "vanilla" else "raytun3r, adapted"
        panels.append(
            heatmap(
                depth, f"{title}: AbsRel {scores[name]:.3f}", "m", valid=keep, limits=(low, high)
            )
        )
    image = (np.asarray(seq.images[args.frame]) * 255).round().astype(np.uint8)[..., ::-1]
    ground = heatmap(truth, "ground-truth range", "m", valid=lens, limits=(low, high))
    height = ground.shape[0]
    frame = cv2.resize(image, (height - 44, height - 44), interpolation=cv2.INTER_NEAREST)
    frame = cv2.copyMakeBorder(frame, 34, 10, 8, 8, cv2.BORDER_CONSTANT, value=(255, 255, 255))
    cv2.putText(frame, "190-degree fisheye frame", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.45, 0, 1)
    row = [frame, ground, *panels]
    width = max(p.shape[0] for p in row)
    row = [
        cv2.copyMakeBorder(p, 0, width - p.shape[0], 0, 0, cv2.BORDER_CONSTANT, value=(255,) * 3)
        for p in row
    ]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), cv2.hconcat(row))
    print(
        f"wrote {out}: AbsRel on frame {args.frame}: "
        + ", ".join(f"{name} {value:.3f}" for name, value in scores.items())
    )


if __name__ == "__main__":
    main()
