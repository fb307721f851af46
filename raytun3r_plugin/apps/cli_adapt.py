"""``raytun3r adapt``, ``adapt-rig`` and ``recipes``: the fitting commands, their options and
the message a fit ends with. The parser that wires them is :mod:`raytun3r_plugin.apps.cli`."""

from __future__ import annotations

import argparse
import dataclasses
import sys

from raytun3r_plugin.apps.fits import recipe_text, settings_text
from raytun3r_plugin.errors import InputError


def _load_model(backbone: str, weights: str | None):
    from raytun3r_plugin.weights import load_backbone

    return load_backbone(backbone, weights)


def parse_named_numbers(text: str, names: tuple[str, ...], option: str) -> dict[str, float]:
    """``"a=1,b=0.3"`` (or the words of ``"a=1 b=0.3"``) -> ``{"a": 1.0, "b": 0.3}``.

    Raises:
        InputError: naming ``option`` and the part that is not ``NAME=NUMBER`` with a name of
            ``names``, or a name given twice.
    """
    numbers: dict[str, float] = {}
    expected = ",".join(f"{name}=X" for name in names)
    for part in text.replace(" ", ",").split(","):
        if not part:
            continue
        name, _, value = part.partition("=")
        name = name.strip()
        if name not in names or not value or name in numbers:
            raise InputError(f"{option}: expected {expected} (each at most once), got {part!r}")
        try:
            numbers[name] = float(value)
        except ValueError:
            raise InputError(f"{option}: {name} must be a number, got {value!r}") from None
    return numbers


def _adapt_settings(args: argparse.Namespace) -> dict:
    """The ``AdaptConfig`` fields the ``adapt`` and ``adapt-rig`` options change: only the
    options given, so everything else is the recipe's (``--recipe``)."""
    settings = {
        field: value
        for field, value in (
            ("steps", args.steps),
            ("input_size", args.size),
            ("n_windows", args.windows),
            ("matcher", args.matcher),
            ("seed", args.seed),
            ("pose_source", args.pose_source),
            ("cache_dir", args.cache_dir),
        )
        if value is not None
    }
    if args.pose_weight is not None:
        if getattr(args, "depth", None):
            raise InputError(
                "--pose-weight weighs the self-supervised pose term; a fit with --depth uses the "
                "depth loss alone, so leave one of the two out"
            )
        settings["weights"] = {"pose": float(args.pose_weight)}
    return settings


def parse_view_weights(words: list[str] | None) -> dict[str, float] | None:
    """``--teacher-view-weights centre=1 left=0.3 right=0.3`` as ``AdaptConfig.teacher_view_weights``."""
    from raytun3r_plugin.adaptation.config import TEACHER_VIEWS

    if words is None:
        return None
    return parse_named_numbers(" ".join(words), TEACHER_VIEWS, "--teacher-view-weights")


def _recipe_name(args: argparse.Namespace, supervised: bool) -> str:
    """``--recipe``, or what ``--depth`` and ``--teacher-only`` imply."""
    from raytun3r_plugin.adaptation.recipes import get_recipe

    if args.teacher_only:
        if args.recipe not in (None, "teacher-only"):
            raise InputError(
                f"--teacher-only is the recipe 'teacher-only': leave out --recipe {args.recipe}"
            )
        name = "teacher-only"
    else:
        name = args.recipe or ("supervised" if supervised else "default")
    recipe = get_recipe(name)
    if supervised and not recipe.supervised:
        raise InputError(
            f"--depth fits to ground-truth depth: use --recipe supervised (or leave --recipe "
            f"out), not {name!r}"
        )
    if recipe.needs_poses:
        raise InputError(
            f"the recipe {name!r} fits to ground-truth poses, which `raytun3r adapt` does not "
            "read: use adapt(model, camera, frames, poses=...) in Python"
        )
    if recipe.supervised and not supervised:
        raise InputError(f"the recipe {name!r} fits to ground-truth depth: give --depth")
    return name


def _adapt_config(args: argparse.Namespace, settings: dict, supervised: bool, model=None):
    """The ``AdaptConfig`` of ``raytun3r adapt``: the recipe (``--recipe``; ``supervised`` with
    ``--depth``, ``teacher-only`` with ``--teacher-only``, else ``default``), with the changes
    ``model``'s backbone family declares for it, changed by the options given."""
    from raytun3r_plugin.adaptation.config import AdaptConfig

    teacher = {
        key: value
        for key, value in (
            ("teacher_views", tuple(args.teacher_views) if args.teacher_views else None),
            ("teacher_fov_deg", args.teacher_fov),
            ("teacher_view_weights", parse_view_weights(args.teacher_view_weights)),
        )
        if value is not None
    }
    if supervised and (args.teacher is not None or args.teacher_only or teacher):
        raise InputError(
            "--teacher, --teacher-only, --teacher-views, --teacher-view-weights and "
            "--teacher-fov add the pinhole-view "
            "teacher to a self-supervised fit; a fit with --depth uses the depth loss alone"
        )
    if args.teacher_only and (args.teacher is not None or "weights" in settings):
        raise InputError(
            "--teacher-only fits the teacher term alone: leave out --teacher and --pose-weight"
        )
    name = _recipe_name(args, supervised)
    unchanged = AdaptConfig.from_recipe(name, model=model)
    weight = unchanged.weights.teacher if args.teacher is None else args.teacher
    if teacher and not weight:
        raise InputError(
            f"--teacher-views, --teacher-view-weights and --teacher-fov change the teacher term, "
            f"which the recipe {name!r} leaves out: add --teacher WEIGHT"
        )
    changes = {**settings, **teacher}
    if args.teacher is not None:
        changes["weights"] = {**changes.get("weights", {}), "teacher": float(args.teacher)}
    return AdaptConfig.from_recipe(name, model=model, **changes)


def cmd_adapt(args: argparse.Namespace) -> int:
    from raytun3r_plugin.adaptation.check import check_frame_count
    from raytun3r_plugin.adaptation.checkpoint import artifact_paths
    from raytun3r_plugin.adaptation.train import adapt
    from raytun3r_plugin.cameras import load as load_camera
    from raytun3r_plugin.images import read_depth_maps, read_frames, read_mask

    settings = _adapt_settings(args)
    _adapt_config(args, settings, supervised=bool(args.depth))  # refuses bad options up front
    if args.depth and len(args.depth) != len(args.frames):
        raise InputError(
            f"--depth needs one folder per --frames segment: {len(args.frames)} segments, "
            f"{len(args.depth)} depth folders"
        )
    camera = load_camera(args.camera, camera=args.camera_id)
    segments, depths = [], []
    for k, source in enumerate(args.frames):
        frames, names = read_frames(source, stride=args.stride, limit=args.max_frames)
        segments.append(frames)
        if args.depth:
            depths.append(
                read_depth_maps(
                    args.depth[k], names, frames.shape[2], frames.shape[1], args.depth_png_scale
                )
            )
    height, width = segments[0].shape[1:3]
    mask = read_mask(args.mask, width, height) if args.mask else None
    depth = (depths if len(segments) > 1 else depths[0]) if depths else None
    model = _load_model(args.backbone, args.weights)
    held_out = check_frame_count(len(segments[-1]), args.check_frames)  # refuses a bad value
    config = _adapt_config(args, settings, supervised=bool(args.depth), model=model)
    # The check frames are the fit's own setting (adapt keeps them out and scores them).
    config = dataclasses.replace(config.resolved_for(model), check_frames=args.check_frames)
    recipe = config.recipe_record(model)
    print(
        f"fitting with {recipe_text(recipe, leave_out=('input_size',))}"
        + f"; input {config.input_size} px; "
        + (
            f"the last {held_out} frames held out for the check"
            if held_out
            else "no frames held out for a check (--check-frames)"
        ),
        file=sys.stderr,
    )
    adapter = adapt(
        model,
        camera,
        segments if len(segments) > 1 else segments[0],
        config,
        out_path=args.out,
        mask=mask,
        depth=depth,
        resume=not args.restart,
    )
    lines = [adapter.training_info["verdict"]["summary"]]
    if "check" in adapter.training_info:
        lines.append(_check_line(adapter.training_info["check"]))
    paths = artifact_paths(args.out)
    print(
        f"saved adapter to {args.out} ({adapter.num_parameters()['total']:,} parameters, recipe "
        f"'{recipe['name']}' v{recipe['version']}); losses: {paths['csv']}, {paths['curve']}"
    )
    print("\n".join(lines))
    return 0


def _check_line(result: dict) -> str:
    """The held-out check in one line a user can act on."""
    if result.get("adapted_px") is None:
        return (
            f"check: not scored on the {result['frames']} held-out frames ({result.get('reason')})"
        )
    before, after = result["zero_adapter_px"], result["adapted_px"]
    change = result.get("change")
    trend = "" if change is None else f" ({100 * change:+.1f} %)"
    advice = (
        ""
        if after < before
        else "; the fit did not help on frames it did not see: try a longer or more varied "
        "segment (docs/recipes.md)"
    )
    return (
        f"check on the last {result['frames']} frames (not fitted): reprojection error "
        f"{before:.3f} px without the adapter -> {after:.3f} px with it{trend}{advice}"
    )


def cmd_adapt_rig(args: argparse.Namespace) -> int:
    from raytun3r_plugin.adaptation.config import AdaptConfig
    from raytun3r_plugin.adaptation.rig import adapt_rig, rig_artifact_paths
    from raytun3r_plugin.datasets.rig import load_eth3d_rig_set, load_tumvi_rig

    rig = (
        load_tumvi_rig(args.dataset) if args.format == "tumvi" else load_eth3d_rig_set(args.dataset)
    )
    instants = range(0, len(rig), args.stride)
    if args.max_frames is not None:
        instants = instants[: args.max_frames]
    rig = rig.subset(list(instants))
    model = _load_model(args.backbone, args.weights)
    config = AdaptConfig.from_recipe(args.recipe or "rig", model=model, **_adapt_settings(args))
    adapters = adapt_rig(
        model,
        rig,
        config,
        out_dir=args.out,
        resume=not args.restart,
        cross_camera=args.cross_camera,
    )
    paths = rig_artifact_paths(args.out, rig.names)
    for name in rig.names:
        verdict = adapters[name].training_info["verdict"]["summary"]
        print(f"{name}: saved {paths[f'adapter:{name}']}; {verdict}")
    print(f"losses: {paths['csv']}, {paths['curve']}")
    return 0


def _add_recipe_argument(parser: argparse.ArgumentParser, default: str) -> None:
    from raytun3r_plugin.adaptation.recipes import recipe_names

    parser.add_argument(
        "--recipe",
        default=None,
        choices=recipe_names(),
        metavar="NAME",
        help=f"the fit's settings by name: {', '.join(recipe_names())} (default: {default}; "
        "`raytun3r recipes` says what each does)",
    )


def cmd_recipes(args: argparse.Namespace) -> int:
    from raytun3r_plugin.adaptation.recipes import RECIPES, recipe_names

    for name in recipe_names():
        recipe = RECIPES[name]
        print(f"{name} (v{recipe.version}): {recipe.summary}")
        if args.verbose:
            from raytun3r_plugin.adaptation.config import RECIPE_LR, AdaptConfig

            settings = AdaptConfig.from_recipe(name).to_dict()
            left_to_backbone = {
                "input_size": "the backbone's own",
                "lr": f"the backbone family's step ({RECIPE_LR} unless the family declares one)",
            }
            for key in sorted(settings):
                if key != "recipe":
                    value = settings[key]
                    shown = (
                        left_to_backbone[key]
                        if value is None and key in left_to_backbone
                        else value
                    )
                    print(f"    {key}: {shown}")
            print(f"    chosen by: {recipe.evidence}")
    from raytun3r_plugin.registry import specs

    for family, spec in specs().items():
        for name, changes in spec.recipe_changes.items():
            print(f"backbone family {family!r} changes {name!r}: {settings_text(changes)}")
    return 0


def _add_adapt_only_options(advanced: argparse._ArgumentGroup) -> None:
    """``adapt``'s advanced options beyond those ``adapt-rig`` shares: the depth PNG scale and
    the pinhole-view teacher's settings."""
    from raytun3r_plugin.adaptation.config import TEACHER_VIEWS

    advanced.add_argument(
        "--depth-png-scale",
        type=float,
        default=1000.0,
        help="16-bit depth PNG values per depth unit (1000 = millimetres)",
    )
    advanced.add_argument(
        "--teacher",
        type=float,
        default=None,
        metavar="WEIGHT",
        help="weight of the pinhole-view teacher term (default recipe: 10, on lenses wider "
        "than about 160 degrees): the unpatched model's depth on virtual pinhole views",
    )
    advanced.add_argument(
        "--teacher-only", action="store_true", help="the same as --recipe teacher-only"
    )
    advanced.add_argument(
        "--teacher-views",
        nargs="+",
        default=None,
        choices=TEACHER_VIEWS,
        help="the teacher's pinhole views (default recipe: centre left right)",
    )
    advanced.add_argument(
        "--teacher-view-weights",
        nargs="+",
        default=None,
        metavar="VIEW=WEIGHT",
        help="each teacher view's share of the term, one per view of --teacher-views, e.g. "
        "centre=1 left=0.3 right=0.3 (default: the recipe's for its views, else their mean)",
    )
    advanced.add_argument(
        "--teacher-fov", type=float, default=None, help="the teacher views' FOV, deg (default 110)"
    )


def _add_rig_command(sub) -> None:
    """Add ``adapt-rig`` to the subcommands ``sub``."""
    p = sub.add_parser(
        "adapt-rig",
        help="fit one adapter per camera of a multi-camera rig, all cameras in each forward (docs/rigs.md)",
    )
    _add_recipe_argument(p, "'rig', the default recipe without the teacher term")
    _add_model_arguments(p)
    p.add_argument("dataset", help="a TUM-VI sequence folder or an ETH3D rig scene")
    p.add_argument("--format", required=True, choices=("tumvi", "eth3d"))
    p.add_argument("--stride", type=int, default=1, help="use every n-th instant")
    p.add_argument("--max-frames", type=int, default=None, help="at most this many instants")
    p.add_argument(
        "--size",
        type=int,
        default=None,
        help="network input long side (default: the backbone's own)",
    )
    p.add_argument(
        "--cross-camera",
        action="store_true",
        help="add reprojection terms between the cameras at each instant (docs/rigs.md)",
    )
    p.add_argument("--out", required=True, help="output folder: <camera>.safetensors per camera")
    p.add_argument(
        "--restart",
        action="store_true",
        help="start over even if a checkpoint of another run is in --out (default: an "
        "interrupted run with the same settings resumes)",
    )
    _add_fit_arguments(p)
    p.set_defaults(func=cmd_adapt_rig)


def _add_fit_arguments(parser: argparse.ArgumentParser) -> argparse._ArgumentGroup:
    """The objective's settings ``adapt`` and ``adapt-rig`` share (read by :func:`_adapt_settings`),
    under an "advanced" heading: each changes the recipe, and the adapter records it."""
    from raytun3r_plugin.adaptation.config import POSE_SOURCES

    group = parser.add_argument_group(
        "advanced: change the recipe (each option given is recorded in the adapter file)"
    )
    group.add_argument("--steps", type=int, default=None, help="optimisation steps (recipe: 300)")
    group.add_argument("--windows", type=int, default=None, help="3-frame windows (recipe: 30)")
    group.add_argument("--matcher", default=None, help="dis | sift | a registered matcher")
    group.add_argument("--pose-source", default=None, choices=POSE_SOURCES)
    group.add_argument("--pose-weight", type=float, default=None, help="weight of the pose term")
    group.add_argument(
        "--cache-dir", default=None, help="keep matches and pose targets here for a rerun"
    )
    group.add_argument("--seed", type=int, default=None)
    return group


def _add_model_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--backbone", required=True, help="model name, e.g. da3-small (see `raytun3r backbones`)"
    )
    parser.add_argument(
        "--weights",
        help="local weight file (.safetensors, .pt) or model folder (config.json + weights); never downloaded",
    )


def _add_frame_arguments(
    parser: argparse.ArgumentParser, size_help: str, several: bool = False
) -> None:
    if several:
        parser.add_argument(
            "--frames",
            required=True,
            nargs="+",
            help="image folder (sorted by name) or video file; several are segments of the "
            "camera, fitted together into one adapter",
        )
    else:
        parser.add_argument(
            "--frames", required=True, help="image folder (sorted by name) or video file"
        )
    parser.add_argument("--stride", type=int, default=1, help="use every n-th frame")
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--size", type=int, default=None, help=size_help)
    parser.add_argument(
        "--mask",
        default=None,
        help="scene mask image at the frames' size: 255 = scene, 0 = excluded (vehicle body, mount)",
    )


def add_fit_commands(sub, rule: str) -> None:
    """Add ``adapt``, ``recipes`` and ``adapt-rig`` to the subcommands ``sub`` (``rule``: the
    input-size rule every ``--size`` help names)."""
    p = sub.add_parser(
        "adapt",
        help="fit an adapter for a camera on a short fisheye segment (the 'default' recipe; "
        "from ground-truth depth with --depth)",
        description="Fit an adapter for a camera on a short segment of its footage. Without "
        "options beyond the model, frames, camera and output it uses the 'default' recipe, "
        "keeps the last fifth of the segment out of the fit and reports the reprojection error "
        "there before and after (docs/recipes.md).",
    )
    _add_recipe_argument(p, "'default'; 'supervised' with --depth")
    _add_model_arguments(p)
    _add_frame_arguments(
        p,
        "network input long side in pixels (default: the backbone's own, e.g. 504 for DA3, 112 "
        f"for the built-in networks; recorded in the adapter); {rule}",
        several=True,
    )
    p.add_argument(
        "--camera",
        required=True,
        help="calibration file (Kalibr, basalt, COLMAP, KITTI-360, raytun3r JSON)",
    )
    p.add_argument("--camera-id", default=None, help="which camera in the file")
    p.add_argument(
        "--depth",
        default=None,
        nargs="+",
        help="folder of ground-truth depth per frame (NAME.npy, or 16-bit NAME.png): supervised "
        "fit; one folder per --frames segment, in the same order",
    )
    p.add_argument(
        "--check-frames",
        default="auto",
        help="frames at the end of the segment kept out of the fit and scored before and after "
        "(auto: a fifth of the segment when it has 15 frames or more; 0: fit on every frame)",
    )
    p.add_argument("--out", required=True, help="output adapter .safetensors")
    p.add_argument(
        "--restart",
        action="store_true",
        help="start over even if a checkpoint of another run is next to --out (default: an "
        "interrupted run with the same settings resumes)",
    )
    _add_adapt_only_options(_add_fit_arguments(p))
    p.set_defaults(func=cmd_adapt)

    p = sub.add_parser("recipes", help="list the fit recipes and what each does")
    p.add_argument(
        "-v", "--verbose", action="store_true", help="every setting, and where it was chosen"
    )
    p.set_defaults(func=cmd_recipes)

    _add_rig_command(sub)
