"""How much each place raytun3r corrects can move a network's depth (its "leverage").

The adapter only works through the places it patches: a correction of the absolute PE, a
displacement of the RoPE positions, and the parameter-free corrections (patch resampling, border
tokens, head grid). A network that barely reads absolute position gives the learned tables
nothing to act on, whatever the adaptation does. This script measures, on one fisheye sequence,
the mean relative change of the predicted depth, |d - d_ref| / d_ref, when:

* the PE table is zeroed (unpatched network): how much the network relies on absolute PE;
* the adapter's PE tables are random with the std of the network's PE: a PE correction as
  large as the PE itself;
* the RoPE table displaces every token by one token outwards;
* the parameter-free corrections are switched on (zero adapter) against the unpatched network.

    python experiments/leverage.py [--weights W.safetensors ...] [--camera 1]

Each ``--weights`` file is a ``raytun3r-da3-tiny`` checkpoint; the default is the packaged one.
"""

from __future__ import annotations

import argparse

import torch

from raytun3r_plugin import apply, synthetic
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.apps.benchmark import CAMERAS, make_camera
from raytun3r_plugin.apps.evaluation import format_table
from raytun3r_plugin.prediction import predict
from raytun3r_plugin.registry import quiet_upstream
from raytun3r_plugin.weights import load_backbone


def relative_change(depth: torch.Tensor, reference: torch.Tensor) -> float:
    return float(((depth - reference).abs() / reference.clamp_min(1e-6)).mean())


def leverage(model, camera, images: torch.Tensor, seed: int = 0) -> dict[str, float]:
    """Mean relative depth change of each perturbation (see the module docstring)."""
    table = model.backbone.pretrained.pos_embed
    with torch.no_grad():
        vanilla = predict(model, images).depth
        saved = table.detach().clone()
        table.zero_()
        try:
            no_pe = predict(model, images).depth
        finally:
            table.copy_(saved)
        adapter = Adapter.for_model(model, camera)
        with apply(model, camera, adapter, strict=False):
            zero_adapter = predict(model, images).depth
        generator = torch.Generator().manual_seed(seed)
        pe_std = float(saved[0, 1:].std())
        for tensor in adapter.pe.values():
            tensor.copy_(torch.randn(tensor.shape, generator=generator) * pe_std)
        with apply(model, camera, adapter, strict=False):
            pe_corrected = predict(model, images).depth
        for tensor in adapter.pe.values():
            tensor.zero_()
        adapter.rope["radial"].fill_(1.0)
        with apply(model, camera, adapter, strict=False):
            rope_displaced = predict(model, images).depth
    return {
        "pe_std": pe_std,
        "zero_pe": relative_change(no_pe, vanilla),
        "pe_correction": relative_change(pe_corrected, zero_adapter),
        "rope_1_token": relative_change(rope_displaced, zero_adapter),
        "parameter_free": relative_change(zero_adapter, vanilla),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--weights",
        nargs="*",
        default=[None],
        help="raytun3r-da3-tiny weight files (default: packaged)",
    )
    parser.add_argument(
        "--camera",
        type=int,
        default=1,
        help="index into the benchmark cameras (0 KB4 120, 1 KB4 185, 2 DS 195)",
    )
    parser.add_argument("--seed", type=int, default=90_010)
    args = parser.parse_args()
    torch.manual_seed(0)
    camera = make_camera(CAMERAS[args.camera], 112)
    seq = synthetic.render_sequence("indoor", camera, n_frames=3, seed=args.seed)
    images = torch.from_numpy(seq.images).permute(0, 3, 1, 2)[None].float()
    rows = []
    for weights in args.weights:
        model = load_backbone("raytun3r-da3-tiny", weights)
        rows.append({"weights": weights or "packaged", **leverage(model, camera, images)})
    print(
        f"camera {CAMERAS[args.camera].label}, indoor seed {args.seed}, 3 views at 112 px; mean |d - d_ref| / d_ref"
    )
    print(
        format_table(
            rows,
            ["weights", "pe_std", "zero_pe", "pe_correction", "rope_1_token", "parameter_free"],
        )
    )


if __name__ == "__main__":
    with quiet_upstream():  # no per-forward INFO lines from the backbone's own logger
        main()
