"""Apply a shared adapter file to a model in downstream code, then take it off again.

    python examples/apply_shared_adapter.py --adapter my_camera.safetensors [--backbone da3-small --weights model.safetensors]

The adapter file carries its camera; the frames here are synthetic renders through that camera.
"""

from __future__ import annotations

import argparse

import torch

import raytun3r_plugin as rt
from raytun3r_plugin import synthetic
from raytun3r_plugin.demo import default_network


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--adapter", required=True)
    parser.add_argument("--backbone", help="backbone name (default: the built-in network)")
    parser.add_argument("--weights", help="local weight file of --backbone")
    parser.add_argument("--size", type=int, default=112, help="network input long side (px)")
    args = parser.parse_args()

    model = rt.load_backbone(args.backbone, args.weights) if args.backbone else default_network()[0]
    adapter = rt.Adapter.load(args.adapter)  # validated: format, shapes, dtypes, finite values
    camera = adapter.camera.resized(args.size, round(args.size * adapter.camera.height / adapter.camera.width))
    frames = synthetic.render_sequence("indoor", camera, n_frames=3, seed=11).images
    images = torch.from_numpy(frames).permute(0, 3, 1, 2)  # (S, 3, H, W) in [0, 1]

    with rt.apply(model, adapter.camera, adapter) as handle:  # camera is rescaled to the input
        prediction = rt.predict(model, images)
        with handle.disabled():
            plain = rt.predict(model, images)
    change = (prediction.depth - plain.depth).abs().mean() / plain.depth.abs().mean()
    print(f"patched {handle.patched}")
    print(f"depth {tuple(prediction.depth.shape)}, cam_from_world {tuple(prediction.cam_from_world.shape)}")
    print(f"mean relative depth change from the adapter and corrections: {float(change):.3f}")
    print(f"model restored: {rt.handle_of(model) is None}")


if __name__ == "__main__":
    main()
