"""Fit an adapter for a camera from a short fisheye segment and save it as one shareable file.

    python examples/fit_adapter.py --out my_camera.safetensors [--frames FOLDER --camera CALIB [--mask PNG]]

Without --frames, a synthetic 190-degree fisheye segment is rendered, so the script runs anywhere.
"""

from __future__ import annotations

import argparse

import raytun3r_plugin as rt
from raytun3r_plugin import cameras, synthetic
from raytun3r_plugin.adaptation.config import AdaptConfig
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.apps.demo import default_network, demo_camera
from raytun3r_plugin.images import read_frames, read_mask


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--frames", help="image folder or video of the segment")
    parser.add_argument("--camera", help="calibration file of the frames")
    parser.add_argument(
        "--mask", help="scene mask of the frames (255 = scene, 0 = the vehicle's body or the mount)"
    )
    parser.add_argument("--backbone", help="backbone name (default: the built-in network)")
    parser.add_argument("--weights", help="local weight file of --backbone")
    parser.add_argument(
        "--size",
        type=int,
        default=None,
        help="network input long side (default: the backbone's own)",
    )
    parser.add_argument("--recipe", default="default", help="fit recipe (`raytun3r recipes`)")
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--n-frames", type=int, default=24)
    args = parser.parse_args()

    model = rt.load_backbone(args.backbone, args.weights) if args.backbone else default_network()[0]
    mask = None
    if args.frames:
        camera = cameras.load(args.camera)
        frames, _ = read_frames(args.frames, limit=args.n_frames)
        # Pixels that see the rig itself move with the camera: keep them out of the fit.
        mask = read_mask(args.mask, camera.width, camera.height) if args.mask else None
    else:
        camera = demo_camera(args.size or 112)
        frames = synthetic.render_sequence("indoor", camera, n_frames=args.n_frames, seed=7).images
    # Every backbone gets the same recipe (the library's default unless --recipe says otherwise);
    # the input size is the backbone's own unless --size is given.
    config = AdaptConfig.from_recipe(
        args.recipe, model=model, steps=args.steps, input_size=args.size, seed=0
    )
    adapter = adapt(model, camera, frames, config, out_path=args.out, progress=False, mask=mask)
    print(
        f"saved {args.out}: {adapter.num_parameters()['total']:,} parameters, recipe "
        f"{adapter.training_info['recipe']}; {adapter.training_info['verdict']['summary']}"
    )


if __name__ == "__main__":
    main()
