"""What the command-line tests share: a random da3-small weight file, a camera file and a
synthetic sequence in a folder, and the options that point the commands at them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from raytun3r_plugin.patches.da3_networks import build_network

from raytun3r_plugin import cameras, synthetic
from tests.helpers import fisheye

SIZE = 84


def build_cli_setup(folder: Path) -> dict:
    """A random da3-small weight file, a camera file and a synthetic sequence folder."""
    import cv2
    from safetensors.torch import save_model

    torch.manual_seed(0)
    net = build_network("da3-small")
    with torch.no_grad():
        net.backbone.pretrained.pos_embed.normal_(0, 0.02)
    weights = folder / "model.safetensors"
    save_model(net, str(weights))
    camera = fisheye(SIZE, SIZE, 190.0)
    cameras.save(camera, folder / "camera.json")
    seq = synthetic.render_sequence("indoor", camera, n_frames=6, seed=5)
    frames = folder / "frames"
    frames.mkdir()
    for k, image in enumerate(seq.images):
        cv2.imwrite(str(frames / f"{k:04d}.png"), (image[..., ::-1] * 255).round().astype(np.uint8))
    synthetic.write_sequence(seq, folder / "sequence")
    depth = folder / "depth"
    depth.mkdir()
    for k, values in enumerate(seq.depth):
        if k % 2:  # half as .npy in depth units, half as 16-bit PNG in millimetres
            cv2.imwrite(str(depth / f"{k:04d}.png"), np.round(values * 1000).astype(np.uint16))
        else:
            np.save(depth / f"{k:04d}.npy", values)
    return {
        "depth": depth,
        "folder": folder,
        "weights": weights,
        "camera": folder / "camera.json",
        "frames": frames,
        "sequence": folder / "sequence",
        "net": net,
    }


def model_args(setup) -> list[str]:
    """``--backbone`` and ``--weights`` of the module's random da3-small file."""
    return ["--backbone", "da3-small", "--weights", str(setup["weights"])]


def frame_args(setup) -> list[str]:
    """``--frames`` and ``--size`` of the module's synthetic frame folder."""
    return ["--frames", str(setup["frames"]), "--size", str(SIZE)]
