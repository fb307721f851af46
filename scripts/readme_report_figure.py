"""The README's picture of a report page: ``raytun3r report`` on a fit of the demo, rendered by
headless Chromium.

The demo's first sequence (render seed 1000: a synthetic room through the demo's 190-degree KB4
lens at 112 px) and the built-in network: an adapter is fitted as ``raytun3r demo`` fits it (the
default recipe at the demo's budget, :data:`~raytun3r_plugin.apps.demo.DEMO_STEPS` steps) on
frames 0-23, checked on frames 24-35 as
``raytun3r adapt --check-frames`` checks, and the page shows frame 30 (not fitted) before and
after. Needs the ``viz`` extra and Chromium.

    python scripts/readme_report_figure.py [--out docs/images/report.png] [--html report.html]
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path


def main() -> None:
    import torch

    from raytun3r_plugin import synthetic
    from raytun3r_plugin.adaptation.check import held_out_reprojection
    from raytun3r_plugin.adaptation.train import adapt
    from raytun3r_plugin.apps.browser import render_page
    from raytun3r_plugin.apps.demo import DEMO_STEPS, default_network, demo_camera
    from raytun3r_plugin.apps.fits import adapt_config
    from raytun3r_plugin.apps.report import DepthSource, write_report
    from raytun3r_plugin.registry import quiet_upstream

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/images/report.png")
    parser.add_argument("--html", default=None, help="also keep the HTML page here")
    parser.add_argument("--frame", type=int, default=30)
    parser.add_argument("--width", type=int, default=1100, help="page width in CSS px")
    args = parser.parse_args()
    torch.set_num_threads(1)
    size, n_adapt = 112, 24
    camera = demo_camera(size)
    seq = synthetic.render_sequence("indoor", camera, n_frames=36, seed=1000)
    model, _ = default_network()
    config = adapt_config(size, DEMO_STEPS, seed=0, model=model)
    out = Path(args.out).resolve()
    page = Path(args.html).resolve() if args.html else None
    home = Path.cwd()
    with tempfile.TemporaryDirectory() as scratch, quiet_upstream():
        os.chdir(scratch)  # the page names the fit as given: a short relative path
        fit = Path("demo_fit.safetensors")
        adapter = adapt(
            model, camera, seq.first_images(n_adapt), config, out_path=fit, progress=False
        )
        adapter.training_info["check"] = held_out_reprojection(
            model, camera, seq.images[n_adapt:], adapter, config
        )
        adapter.save(fit)
        page = page or Path(scratch) / "report.html"
        write_report(fit, page, DepthSource(seq.images, model, index=args.frame))
        out.parent.mkdir(parents=True, exist_ok=True)
        seen = render_page(page, out, width=args.width)
        os.chdir(home)
    problems = seen.errors + [f"image did not load: {src}" for src in seen.broken_images]
    if problems:
        raise SystemExit("the browser saw problems: " + "; ".join(problems))
    print(
        f"wrote {out} ({seen.size[0]}x{seen.size[1]} px); {adapter.training_info['verdict']['summary']}"
    )


if __name__ == "__main__":
    main()
