"""``raytun3r`` command line: adapt, recipes, infer, eval, inspect, weights, demo, bench, report,
fleet."""

from __future__ import annotations

import argparse
import sys

from raytun3r_plugin.apps.cli_adapt import (  # the fitting commands
    _add_frame_arguments,
    _add_model_arguments,
    _load_model,
    add_fit_commands,
    parse_named_numbers,
)
from raytun3r_plugin.apps.cli_deploy import add_deploy_command  # export a model graph
from raytun3r_plugin.apps.cli_fleet import add_fleet_commands
from raytun3r_plugin.apps.cli_report import add_report_command
from raytun3r_plugin.errors import InputError, Raytun3rError


def _default_long_side(adapter, model) -> int:
    """The input long side without ``--size``: the one the adapter was fitted at, else the
    backbone's own (:func:`~raytun3r_plugin.registry.native_input_size`)."""
    from raytun3r_plugin.registry import native_input_size

    recorded = ((adapter.training_info or {}).get("input") or {}) if adapter is not None else {}
    return int(recorded.get("long_side") or native_input_size(model))


def cmd_inspect(args: argparse.Namespace) -> int:
    from raytun3r_plugin.apps.adapter_report import describe_file, describe_record

    if args.json:
        import json

        print(json.dumps(describe_record(args.adapter), indent=2, sort_keys=True, default=str))
    else:
        print(describe_file(args.adapter))
    if args.picture:
        from raytun3r_plugin.adapter import Adapter
        from raytun3r_plugin.apps.adapter_report import write_pe_picture

        write_pe_picture(Adapter.load(args.adapter), args.picture)
        print(f"PE correction picture: {args.picture}")
    return 0


def cmd_analyze_jacobian(args: argparse.Namespace) -> int:
    from raytun3r_plugin.adapter import Adapter
    from raytun3r_plugin.apps.analysis import jacobian_report

    model = _load_model(args.backbone, args.weights)
    adapter = Adapter.load(args.adapter) if args.adapter else None
    report = jacobian_report(model, adapter, args.out, size=args.size, bins=args.bins)
    print("sigma_1 / sigma_1(centre) per radius bin (1.0 = flat, pinhole-like):")
    names = list(report["summary"])
    has_reference = "reference_sigma1" in report["rows"][0]
    print(
        "   rho  tokens  "
        + "  ".join(f"{n:>10}" for n in names)
        + ("   reference" if has_reference else "")
    )
    for row in report["rows"]:
        cells = "  ".join(f"{row[f'{n}_sigma1']:10.3f}" for n in names)
        reference = f"  {row['reference_sigma1']:10.3f}" if has_reference else ""
        print(f"  {row['rho']:4.2f}  {row['tokens']:6d}  {cells}{reference}")
    print(f"wrote {report['csv']} and {report['png']}")
    return 0


def cmd_weights(args: argparse.Namespace) -> int:
    """Say what a checkpoint is without building it (``raytun3r_plugin.weights.describe_checkpoint``)."""
    from raytun3r_plugin.weights import describe_checkpoint

    record = describe_checkpoint(args.path)
    if args.json:
        import json

        print(json.dumps(record, indent=2, sort_keys=True))
        return 0
    name = record["name"] or (
        f"one of {record['candidates']}" if record["candidates"] else "unknown"
    )
    if record["config_model_name"]:
        name += f"  (config.json: {record['config_model_name']})"
    dtypes = ", ".join(f"{dtype} ({count})" for dtype, count in record["dtypes"].items())
    rows = [
        ("file", record["file"]),
        ("family", record["family"] or "unknown (no registered backbone has these keys)"),
        ("name", name),
        ("shapes", record["detail"] or "-"),
        ("tensors", f"{record['tensors']} ({record['parameters']:,} values)"),
        ("dtype", dtypes),
        ("PE table", "x".join(map(str, record["pe_shape"])) if record["pe_shape"] else "-"),
    ]
    if record["ignored_entries"]:
        rows.append(("ignored", ", ".join(record["ignored_entries"])))
    rows.append(("load", record["load"] or "- (pass the name: see `raytun3r backbones`)"))
    print("\n".join(f"{key:<9} {value}" for key, value in rows))
    return 0


def cmd_infer(args: argparse.Namespace) -> int:
    from raytun3r_plugin.adapter import Adapter
    from raytun3r_plugin.apps.cli_exports import export_options, write_infer_outputs
    from raytun3r_plugin.apps.inference import predict_with_camera
    from raytun3r_plugin.cameras import load as load_camera
    from raytun3r_plugin.images import read_frames, read_mask
    from raytun3r_plugin.preprocess import layout_for_inference

    options = export_options(args)  # the output options, checked before anything runs
    adapter = Adapter.load(args.adapter) if args.adapter else None
    if args.camera:
        camera = load_camera(args.camera, camera=args.camera_id)
    elif adapter is not None and adapter.camera is not None:
        camera = None  # the adapter's, its crop undone (preprocess.fitted_source_camera)
    else:
        raise InputError("infer needs --camera, or an --adapter that carries its camera")
    frames, names = read_frames(args.frames, stride=args.stride, limit=args.max_frames)
    model = _load_model(args.backbone, args.weights)
    # The layout adapt used (its rule and long side come from the adapter when --size is not
    # given; without an adapter, the backbone's own size); frames of another size than the
    # camera rescale the camera, a pure resize.
    layout = layout_for_inference(
        camera,
        (frames.shape[2], frames.shape[1]),
        adapter,
        long_side=args.size or _default_long_side(adapter, model),
        strict=not args.no_strict,
    )
    raw_mask = read_mask(args.mask, frames.shape[2], frames.shape[1]) if args.mask else None
    native_mask = None if raw_mask is None else layout.native_mask(raw_mask)
    images = layout.frames(frames)[None]
    # Patched with the (cropped) native camera, as adapt patched the model: the adapter's camera
    # check compares like with like, and the patch rescales it to the input as during the fit.
    prediction = predict_with_camera(
        model, layout.native_camera, adapter, images, strict=not args.no_strict, mask=native_mask
    )
    write_infer_outputs(args, options, prediction, images, layout, frames, names, raw_mask)
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from raytun3r_plugin.adapter import Adapter
    from raytun3r_plugin.apps.evaluation import (
        fit_sequence,
        format_table,
        headline,
        run_method,
        score,
    )
    from raytun3r_plugin.datasets import load_sequence

    # Every option is checked before the model and the sequence load: a typo costs no forward.
    methods, amounts, stride = _eval_options(args)
    model = _load_model(args.backbone, args.weights)
    adapter = Adapter.load(args.adapter) if args.adapter else None
    # Scored at the long side the adapter was fitted at unless --size says otherwise.
    long_side = args.size or _default_long_side(adapter, model)
    reader_options = {"camera": args.camera} if args.camera else {}
    seq = fit_sequence(
        load_sequence(args.dataset, kind=args.kind, **reader_options),
        long_side,
        max_frames=args.max_frames,
    )
    if seq.cam_from_world is None:
        raise InputError(f"{args.dataset}: the sequence has no ground-truth poses to score against")
    stride, stride_note = _pair_stride(seq, stride)
    rows = [
        {
            "method": method,
            **headline(score(seq, run_method(model, seq, method, adapter=adapter, stride=stride))),
        }
        for method in methods
    ]
    if amounts is not None:
        import dataclasses

        from raytun3r_plugin.cameras import perturbed

        rough = dataclasses.replace(seq, camera=perturbed(seq.camera, **amounts))
        label = ", ".join(f"{k} {v:+g}" for k, v in amounts.items())
        for method in methods:
            # Run with the rough camera, score against the true one (seq).
            output = run_method(model, rough, method, adapter=adapter, stride=stride)
            rows.append(
                {"method": f"{method} (calibration {label})", **headline(score(seq, output))}
            )
    print(
        f"{seq.name}: {len(seq)} frames at {seq.camera.width}x{seq.camera.height} px, camera {seq.camera!r}"
    )
    print(
        f"protocol: {stride_note}; relative poses of neighbouring views within each 3-view "
        "window, the "
        f"same pairs for every method; pairs whose ground-truth baseline is under 1 mm are "
        f"skipped and counted ({rows[0]['skipped_pairs']} of "
        f"{rows[0]['pairs'] + rows[0]['skipped_pairs']}); trans_deg is the signed direction "
        f"error (0-180), trans_folded_deg the folded one (0-90, VGGT-style)"
    )
    print(
        format_table(
            rows,
            [
                "method",
                "rot_deg",
                "trans_deg",
                "trans_folded_deg",
                "d_reproj_px",
                "abs_rel",
                "delta_1.25",
                "coverage",
            ],
        )
    )
    return 0


def _eval_options(
    args: argparse.Namespace,
) -> tuple[list[str], dict[str, float] | None, int | None]:
    """``eval``'s methods, calibration perturbation and pair stride (None: auto), checked."""
    from raytun3r_plugin.apps.evaluation import METHODS

    methods = args.method.split(",")
    unknown = [method for method in methods if method not in METHODS]
    if unknown:
        raise InputError(
            f"--method: unknown {', '.join(map(repr, unknown))}; choose from {METHODS}"
        )
    amounts = _parse_amounts(args.perturb_calibration) if args.perturb_calibration else None
    if args.pair_stride == "auto":
        return methods, amounts, None
    try:
        return methods, amounts, int(args.pair_stride)
    except ValueError:
        raise InputError(
            f"--pair-stride must be 'auto' or an integer, got {args.pair_stride!r}"
        ) from None


def _pair_stride(seq, stride: int | None) -> tuple[int, str]:
    """The pair stride ``eval`` scores ``seq`` with (``stride``, or the automatic one for None)
    and the note that says how it was chosen."""
    from raytun3r_plugin.apps.evaluation import choose_pair_stride

    if stride is not None:
        return stride, f"pair stride {stride} (given)"
    chosen = choose_pair_stride(seq)
    return chosen["stride"], (
        f"pair stride {chosen['stride']} (auto: smallest with a median ground-truth baseline of "
        f"at least {chosen['rule']} = {chosen['threshold']:.3g}; it is "
        f"{chosen['median_baseline']:.3g})"
    )


def _parse_amounts(text: str) -> dict[str, float]:
    """``"focal=0.05,principal=0.01"`` -> ``{"focal": 0.05, "principal": 0.01}``."""
    return parse_named_numbers(text, ("focal", "principal", "distortion"), "--perturb-calibration")


def cmd_demo(args: argparse.Namespace) -> int:
    from raytun3r_plugin.apps.demo import run_demo

    return run_demo(args)


def cmd_bench(args: argparse.Namespace) -> int:
    from raytun3r_plugin.apps.benchmark import (
        CAMERAS,
        SEQUENCES_PER_CELL,
        check_baselines,
        run_benchmark,
    )
    from raytun3r_plugin.apps.demo import default_network

    # Checked before the network loads, so a typo fails at once.
    baselines = check_baselines(
        name.strip() for name in (args.baselines or "").split(",") if name.strip()
    )
    model, description = default_network()
    if args.quick:
        table = run_benchmark(
            model,
            args.out,
            size=84,
            n_adapt=6,
            n_eval=4,
            steps=3,
            sequences=1,
            cameras=CAMERAS[-1:],
            scenes=("indoor",),
            network=description,
            baselines=baselines,
            jobs=args.jobs,
            address=args.address,
        )
    else:
        table = run_benchmark(
            model,
            args.out,
            sequences=args.sequences or SEQUENCES_PER_CELL,
            network=description,
            progress=True,
            baselines=baselines,
            jobs=args.jobs,
            address=args.address,
        )
    print(table)
    return 0


#: How the input-size options round a size (their help text ends with it).
RULE = (
    "each side rounded to multiples of the patch size, centre-cropped only beyond a 1%% aspect "
    "change (raytun3r_plugin.preprocess)"
)


def build_parser() -> argparse.ArgumentParser:
    """The ``raytun3r`` parser: each subcommand's options are added by its own function."""
    parser = argparse.ArgumentParser(
        prog="raytun3r",
        description="Run frozen pinhole-trained 3D foundation models on fisheye cameras.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    _add_inspect(sub)
    _add_infer(sub, RULE)
    add_fit_commands(sub, RULE)
    add_fleet_commands(sub)
    add_deploy_command(sub)
    _add_eval(sub, RULE)
    _add_demo(sub)
    _add_bench(sub)
    _add_weights(sub)
    _add_analyze(sub)
    add_report_command(sub)
    _add_backbones(sub)
    return parser


def _add_inspect(sub: argparse._SubParsersAction) -> None:
    """``raytun3r inspect``: an adapter file's metadata, camera and parameter count."""
    p = sub.add_parser(
        "inspect", help="print an adapter file's metadata, camera and parameter count"
    )
    p.add_argument("adapter")
    p.add_argument(
        "--json",
        action="store_true",
        help="print the whole metadata record (training included) as JSON",
    )
    p.add_argument(
        "--picture",
        default=None,
        help="write the PE correction's size over the image (PNG) to this path",
    )
    p.set_defaults(func=cmd_inspect)


def _add_infer(sub: argparse._SubParsersAction, rule: str) -> None:
    """``raytun3r infer``: apply an adapter and write depth, poses, points and exports."""
    p = sub.add_parser(
        "infer",
        help="apply an adapter and write depth (.npy, .png), poses (TUM), a point cloud (.ply) "
        "and exports (COLMAP, nerfstudio, GLB, Rerun)",
    )
    _add_model_arguments(p)
    _add_frame_arguments(
        p,
        "network input long side in pixels (default: the adapter's, else the backbone's own); "
        f"{rule}",
    )
    p.add_argument(
        "--camera", help="calibration file (Kalibr, basalt, COLMAP, KITTI-360, raytun3r JSON)"
    )
    p.add_argument(
        "--camera-id", default=None, help="which camera in the file (cam1, index, COLMAP id)"
    )
    p.add_argument(
        "--adapter", help="adapter .safetensors (optional: parameter-free corrections only)"
    )
    p.add_argument(
        "--no-strict",
        action="store_true",
        help="apply an adapter fitted on other weights or another camera",
    )
    p.add_argument("--out", required=True)
    from raytun3r_plugin.apps.cli_exports import add_output_arguments

    add_output_arguments(p)
    p.set_defaults(func=cmd_infer)


def _add_eval(sub: argparse._SubParsersAction, rule: str) -> None:
    """``raytun3r eval``: methods on a dataset sequence, one metrics table."""
    p = sub.add_parser(
        "eval", help="run a method on a dataset sequence and print the metrics table"
    )
    _add_model_arguments(p)
    p.add_argument(
        "--dataset",
        required=True,
        help="sequence folder or file (synthetic, colmap, scannetpp, tumvi, kitti360, "
        "eth3d_rig, adt, fiord)",
    )
    p.add_argument("--kind", default=None, help="reader to use (default: detect)")
    p.add_argument(
        "--camera",
        default=None,
        help="passed to the reader as camera=: the calibration file of a FIORD scene (required "
        "there), the camera name of an ETH3D rig",
    )
    p.add_argument(
        "--method",
        default="vanilla,center-ph,raytun3r",
        help="comma-separated: vanilla, center-ph, multi-ph, raytun3r",
    )
    p.add_argument("--adapter", default=None)
    p.add_argument(
        "--size",
        type=int,
        default=None,
        help="network input long side in pixels (default: the adapter's, else the backbone's "
        f"own); {rule}",
    )
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument(
        "--pair-stride",
        default="auto",
        help="frames between the two views of a scored pair: an integer, or 'auto' (the "
        "smallest stride whose median ground-truth baseline is 3%% of the median depth, or "
        "5 cm without depth)",
    )
    p.add_argument(
        "--perturb-calibration",
        default=None,
        metavar="focal=F,principal=P,distortion=D",
        help="also run every method with a camera whose focal lengths change by F (relative), "
        "principal point by P (fraction of the image size) and distortion parameters by D "
        "(relative), and report both rows; scoring always uses the true camera",
    )
    p.set_defaults(func=cmd_eval)


def _add_demo(sub: argparse._SubParsersAction) -> None:
    """``raytun3r demo``: the main job on the built-in default network."""
    p = sub.add_parser(
        "demo",
        help="the main job on a built-in default: synthetic fisheye, adapt, metrics before/after",
    )
    p.add_argument("--out", default="runs/demo")
    p.add_argument(
        "--steps", type=int, default=None, help="adaptation steps (default: the demo's budget)"
    )
    p.add_argument("--size", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--sequences", type=int, default=None, help="sequences to score (default 4)")
    p.add_argument(
        "--jobs",
        type=int,
        default=None,
        help="worker processes, one thread each (default: one per CPU, at most one per sequence; 1 = in this process)",
    )
    p.set_defaults(func=cmd_demo)


def _add_bench(sub: argparse._SubParsersAction) -> None:
    """``raytun3r bench``: the synthetic fisheye benchmark."""
    p = sub.add_parser(
        "bench",
        help="the synthetic fisheye benchmark (vanilla vs Center-PH vs Multi-PH vs raytun3r)",
    )
    p.add_argument("--out", default="runs/bench")
    p.add_argument(
        "--sequences",
        type=int,
        default=None,
        help="held-out sequences per camera and scene (default 5)",
    )
    p.add_argument("--quick", action="store_true")
    p.add_argument(
        "--baselines",
        default="",
        metavar="lora,caltok",
        help="also fit and score these baselines per sequence (comma-separated: lora = LoRA r=8, "
        "caltok = calibration tokens t=4), on the adaptation frames and objective of raytun3r's "
        "fit; each adds a fit per sequence",
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="sequences scored at once, as Ray tasks of one thread each on an embedded cluster "
        "(default 1: in this process, and the timing columns are one process's; more makes the "
        "run shorter and the timings one thread's beside the others; docs/fleet.md)",
    )
    p.add_argument(
        "--address",
        default=None,
        help="score the sequences on this Ray cluster instead ('auto', HOST:PORT, ray://HOST:PORT)",
    )
    p.set_defaults(func=cmd_bench)


def _add_weights(sub: argparse._SubParsersAction) -> None:
    """``raytun3r weights``: what a checkpoint is and how to load it."""
    p = sub.add_parser(
        "weights",
        help="say what a checkpoint (file or folder) is, without building it, and how to load it",
    )
    p.add_argument("path", help="weight file, model folder or hub snapshot folder")
    p.add_argument("--json", action="store_true", help="print the record as JSON")
    p.set_defaults(func=cmd_weights)


def _add_analyze(sub: argparse._SubParsersAction) -> None:
    """``raytun3r analyze``: analyses of a model."""
    p = sub.add_parser("analyze", help="analyses of a model (docs/analysis.md)")
    analyses = p.add_subparsers(dest="analysis", required=True)
    p = analyses.add_parser(
        "jacobian",
        help="PE-Jacobian curves per radius (pretrained, and with an adapter), CSV and picture",
    )
    _add_model_arguments(p)
    p.add_argument("--adapter", default=None, help="adapter file; its camera sets the reference")
    p.add_argument("--size", type=int, default=None, help="square input side in px (default 504)")
    p.add_argument("--bins", type=int, default=20, help="radius bins over rho in [0, 1]")
    p.add_argument("--out", default="jacobian", help="folder for jacobian.csv and jacobian.png")
    p.set_defaults(func=cmd_analyze_jacobian)


def _add_backbones(sub: argparse._SubParsersAction) -> None:
    """``raytun3r backbones``: the names ``load_backbone`` accepts."""
    p = sub.add_parser("backbones", help="list the backbone names load_backbone accepts")
    p.set_defaults(
        func=lambda args: print("\n".join(__import__("raytun3r_plugin").available_backbones())) or 0
    )


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        from raytun3r_plugin.registry import quiet_upstream

        with quiet_upstream():
            return int(args.func(args) or 0)
    except Raytun3rError as error:
        print(f"raytun3r: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("raytun3r: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
