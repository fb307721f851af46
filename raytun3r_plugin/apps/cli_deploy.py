"""``raytun3r export``: a graph of an adapted model for one fixed camera and input size.

Not to be confused with `raytun3r infer --export` (:mod:`raytun3r_plugin.exports`), which writes a model's
*predictions* (depth, poses, point clouds) to files. This command writes the *model*:
:func:`raytun3r_plugin.deploy.freeze` then :func:`raytun3r_plugin.deploy.export_onnx`
(docs/deployment.md).
"""

from __future__ import annotations

import argparse

from raytun3r_plugin.errors import InputError

FORMATS = ("onnx",)


def add_deploy_command(sub) -> None:
    """Add ``export`` to the subcommands ``sub``."""
    p = sub.add_parser(
        "export",
        help="write an adapted model for one camera and input size as an ONNX graph",
        description="Freeze the patched model for one camera and input size (every value that "
        "depends only on them becomes a constant) and write it as a graph that runs without "
        "raytun3r: input 'images' (1, views, 3, H, W) in [0, 1]; outputs 'depth', "
        "'confidence', 'cam_from_world'. See docs/deployment.md.",
    )
    p.add_argument("--backbone", required=True, help="model name (see `raytun3r backbones`)")
    p.add_argument("--weights", help="local weight file or model folder; never downloaded")
    p.add_argument("--adapter", help="adapter .safetensors (its camera is the camera)")
    p.add_argument(
        "--camera",
        help="calibration file, for parameter-free corrections without an adapter",
    )
    p.add_argument("--camera-id", default=None, help="which camera in the --camera file")
    p.add_argument(
        "--size",
        required=True,
        nargs=2,
        type=int,
        metavar=("H", "W"),
        help="network input height and width in pixels (multiples of the patch size)",
    )
    p.add_argument("--views", type=int, default=2, help="views S per forward (default 2)")
    p.add_argument("--format", choices=FORMATS, default="onnx")
    p.add_argument("--out", required=True, help="output file, e.g. cam0.onnx")
    p.add_argument(
        "--no-strict",
        action="store_true",
        help="apply an adapter fitted on other weights or another camera",
    )
    p.add_argument(
        "--check",
        action="store_true",
        help="run the written graph with ONNX Runtime and print its largest difference from "
        "the PyTorch model",
    )
    p.set_defaults(func=cmd_export_model)


def cmd_export_model(args: argparse.Namespace) -> int:
    import raytun3r_plugin as rt
    from raytun3r_plugin.deploy import export_onnx, freeze, run_onnx

    if args.views < 1:
        raise InputError(f"--views must be at least 1, got {args.views}")
    if args.adapter is None and args.camera is None:
        raise InputError("export needs --adapter (with its camera) or --camera")
    adapter = rt.Adapter.load(args.adapter) if args.adapter else None
    camera = None
    if args.camera:
        from raytun3r_plugin.cameras import load as load_camera

        camera = load_camera(args.camera, camera=args.camera_id)
    model = rt.load_backbone(args.backbone, args.weights)
    rt.apply(model, camera, adapter, strict=not args.no_strict)
    frozen = freeze(model, tuple(args.size), views=args.views)
    path = export_onnx(frozen, args.out)
    print(
        f"wrote {path}: images (1, {args.views}, 3, {args.size[0]}, {args.size[1]}) -> depth, confidence, cam_from_world"
    )
    if args.check:
        import torch

        images = torch.rand(frozen.shape, generator=torch.Generator().manual_seed(1))
        with torch.no_grad():
            expected = frozen(images)
        got = run_onnx(path, images)
        for name, want in zip(("depth", "confidence", "cam_from_world"), expected, strict=True):
            difference = float((got[name] - want).abs().max())
            print(f"  {name}: largest difference from PyTorch {difference:.3g}")
    return 0
