"""Fit an adapter for a camera from a short fisheye segment and save it as one shareable file.

    python examples/fit_adapter.py --out my_camera.safetensors [--frames FOLDER --camera CALIB [--mask PNG]]

Without --frames, a synthetic 190-degree fisheye segment is rendered, so the script runs anywhere.
"""

from __future__ import annotations

import argparse

import raytun3r_plugin as rt
from raytun3r_plugin import cameras, synthetic
from raytun3r_plugin.adaptation.train import AdaptConfig, adapt
from raytun3r_plugin.apps.demo import adapt_config, default_network, demo_camera
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
    parser.add_argument("--size", type=int, default=112, help="network input long side (px)")
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
        camera = demo_camera(args.size)
        frames = synthetic.render_sequence("indoor", camera, n_frames=args.n_frames, seed=7).images
    # Your own backbone gets the library's defaults (the paper's objective); the built-in network
    # gets the settings it was benchmarked with (apps.demo.NETWORK_FIT).
    config = (
        AdaptConfig(steps=args.steps, input_size=args.size, seed=0)
        if args.backbone
        else adapt_config(
            args.size, args.steps, seed=0, checkpoint_every=AdaptConfig.checkpoint_every
        )
    )
    adapter = adapt(model, camera, frames, config, out_path=args.out, progress=False, mask=mask)
    print(
        f"saved {args.out}: {adapter.num_parameters()['total']:,} parameters, final losses {adapter.training_info.get('final_losses')}"
    )


if __name__ == "__main__":
    main()
