"""Apply a shared adapter file to a model in downstream code, then take it off again.

    python examples/apply_shared_adapter.py --adapter my_camera.safetensors [--backbone da3-small --weights model.safetensors]

The adapter file carries its camera and the input rule it was fitted with; the frames here are
synthetic renders through that camera, prepared for the network by the same rule
(``raytun3r_plugin.preprocess.InputLayout``).
"""

from __future__ import annotations

import argparse

import raytun3r_plugin as rt
from raytun3r_plugin import synthetic
from raytun3r_plugin.apps.demo import default_network
from raytun3r_plugin.preprocess import fitted_source_camera, input_layout


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--adapter", required=True)
    parser.add_argument("--backbone", help="backbone name (default: the built-in network)")
    parser.add_argument("--weights", help="local weight file of --backbone")
    parser.add_argument("--size", type=int, default=112, help="network input long side (px)")
    args = parser.parse_args()

    model = rt.load_backbone(args.backbone, args.weights) if args.backbone else default_network()[0]
    adapter = rt.Adapter.load(args.adapter)  # validated: format, shapes, dtypes, finite values
    # Native frames (here rendered through the camera the adapter was fitted on), prepared for
    # the network exactly as adaptation prepared its frames: same rule, same crop, same resize.
    camera = fitted_source_camera(adapter)
    frames = synthetic.render_sequence("indoor", camera, n_frames=3, seed=11).images  # (S, H, W, 3)
    layout = input_layout(camera, args.size, adapter.patch_size)
    images = layout.frames(frames)  # (S, 3, h, w) in [0, 1]

    with rt.apply(
        model, layout.native_camera, adapter
    ) as handle:  # camera is rescaled to the input
        prediction = rt.predict(model, images)
        with handle.disabled():
            plain = rt.predict(model, images)
    change = (prediction.depth - plain.depth).abs().mean() / plain.depth.abs().mean()
    print(f"patched {handle.patched}")
    print(
        f"depth {tuple(prediction.depth.shape)}, cam_from_world {tuple(prediction.cam_from_world.shape)}"
    )
    print(f"mean relative depth change from the adapter and corrections: {float(change):.3f}")
    print(f"model restored: {rt.handle_of(model) is None}")


if __name__ == "__main__":
    main()
