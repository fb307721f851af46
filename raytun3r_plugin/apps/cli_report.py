"""``raytun3r report``: one HTML page from a fit's or a benchmark's output folder
(:mod:`raytun3r_plugin.apps.report`); the parser wiring is :mod:`raytun3r_plugin.apps.cli`."""

from __future__ import annotations

import argparse
from pathlib import Path

from raytun3r_plugin.errors import InputError


def _default_out(path: Path) -> Path:
    """``NAME.report.html`` beside an adapter file, ``report.html`` inside a folder."""
    if path.is_file():
        stem = (
            path.name[: -len(".safetensors")] if path.name.endswith(".safetensors") else path.stem
        )
        return path.with_name(f"{stem}.report.html")
    return path / "report.html"


def cmd_report(args: argparse.Namespace) -> int:
    from raytun3r_plugin.apps.report import DepthSource, report_kind, write_report

    source = Path(args.path)
    kind = report_kind(source)  # refuses a path with nothing to report before a model loads
    depth = None
    if args.frames or args.backbone:
        if not (args.frames and args.backbone):
            raise InputError("the depth picture needs both --frames and --backbone (and --weights)")
        if kind != "fit":
            raise InputError(f"{source}: --frames draws depth for one fit, not a {kind} folder")
        from raytun3r_plugin.apps.cli_adapt import _load_model
        from raytun3r_plugin.images import read_frames

        frames, _ = read_frames(args.frames, stride=args.stride, limit=args.max_frames)
        camera = None
        if args.camera:
            from raytun3r_plugin.cameras import load as load_camera

            camera = load_camera(args.camera)
        index = len(frames) // 2 if args.frame is None else args.frame
        depth = DepthSource(frames, _load_model(args.backbone, args.weights), index, camera)
    out = Path(args.out) if args.out else _default_out(source)
    write_report(source, out, depth)
    print(f"wrote {out}")
    if args.png:
        from raytun3r_plugin.apps.browser import render_page

        seen = render_page(out, args.png)
        problems = seen.errors + [f"image did not load: {src}" for src in seen.broken_images]
        if problems:
            raise InputError(f"{out}: the browser saw problems: " + "; ".join(problems))
        print(f"wrote {args.png} ({seen.size[0]}x{seen.size[1]} px, headless Chromium)")
    return 0


def add_report_command(sub) -> None:
    """Register ``raytun3r report`` on the sub-parsers ``sub``."""
    p = sub.add_parser(
        "report",
        help="one self-contained HTML page from a fit (adapter file or its folder) or a "
        "bench/demo output folder: metrics, verdict, loss curves, PE correction, depth",
    )
    p.add_argument("path", help="adapter .safetensors, its folder, or a bench/demo --out folder")
    p.add_argument(
        "--out", default=None, help="HTML file (default: NAME.report.html / DIR/report.html)"
    )
    p.add_argument(
        "--png", default=None, help="also render the page with headless Chromium to this PNG"
    )
    group = p.add_argument_group("depth before and after the fit (optional)")
    group.add_argument("--frames", default=None, help="image folder or video of the camera")
    group.add_argument("--frame", type=int, default=None, help="frame to show (default: middle)")
    group.add_argument("--stride", type=int, default=1, help="use every n-th frame")
    group.add_argument("--max-frames", type=int, default=None)
    group.add_argument("--backbone", default=None, help="the model the adapter was fitted for")
    group.add_argument("--weights", default=None, help="its local weight file or folder")
    group.add_argument(
        "--camera", default=None, help="camera file of the frames (default: the adapter's)"
    )
    p.set_defaults(func=cmd_report)
