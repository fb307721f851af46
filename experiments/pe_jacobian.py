"""PE-Jacobian curves of the built-in network: pretrained, self-supervised and supervised fits.

Reads the adapters a demo run wrote (``raytun3r demo --out DIR``: ``DIR/seq*/adapter.safetensors``
and ``adapter_supervised.safetensors``) and prints, per radius bin, the median over sequences of
sigma_1 / sigma_1(centre) for the pretrained PE, each fit, and the camera's analytic reference
(docs/analysis.md). 1.0 everywhere = a flat, pinhole-like PE.

    raytun3r demo --out demo_out && python experiments/pe_jacobian.py demo_out [--size 224] [--bins 5]
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import raytun3r_plugin as rt
from raytun3r_plugin.analysis import pe_jacobian, reference_curves
from raytun3r_plugin.weights import load_backbone


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("demo_out", type=Path)
    parser.add_argument("--backbone", default="raytun3r-da3-tiny")
    parser.add_argument("--size", type=int, default=224)
    parser.add_argument("--bins", type=int, default=5)
    args = parser.parse_args(argv)

    net = load_backbone(args.backbone)
    folders = sorted(args.demo_out.glob("seq*"))
    if not folders:
        raise SystemExit(f"{args.demo_out}: no seq*/ folders (run `raytun3r demo --out` first)")
    curves: dict[str, list] = {"pretrained": [], "self-supervised": [], "supervised": []}
    reference = None
    for folder in folders:
        for key, name in (("self-supervised", "adapter"), ("supervised", "adapter_supervised")):
            adapter = rt.Adapter.load(folder / f"{name}.safetensors")
            camera = adapter.camera
            with rt.apply(net, camera, adapter, strict=False):
                curves[key].append(
                    pe_jacobian(net, args.size, args.size, camera=camera, bins=args.bins)
                )
        curves["pretrained"].append(
            pe_jacobian(net, args.size, args.size, camera=camera, bins=args.bins)
        )
        reference = reference_curves(camera, curves["pretrained"][0].rho, args.size, args.size)
    rho = curves["pretrained"][0].rho
    print(
        f"sigma_1 / sigma_1(centre), {args.backbone}, {args.size} px input, median over "
        f"{len(folders)} sequences (adapters from {args.demo_out})"
    )
    header = ["rho", "tokens", *curves, "camera reference"]
    print(" | ".join(f"{h:>15}" for h in header))
    for k in range(rho.numel()):
        cells = [f"{float(rho[k]):15.2f}", f"{int(curves['pretrained'][0].count[k]):15d}"]
        for runs in curves.values():
            cells.append(f"{statistics.median(float(c.sigma1[k, 1]) for c in runs):15.3f}")
        cells.append(f"{float(reference['sigma1'][k]):15.3f}")
        print(" | ".join(cells))


if __name__ == "__main__":
    main()
