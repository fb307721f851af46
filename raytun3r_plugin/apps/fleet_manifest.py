"""The fleet manifest (docs/fleet.md): what ``raytun3r fleet adapt`` and ``fleet eval`` run, read
and checked in full before any task starts.

A manifest is YAML; its paths are relative to the manifest's folder::

    backbone: raytun3r-da3-tiny-v3   # a name `raytun3r backbones` lists
    weights: null                    # weights file; null: the backbone's own (built-in) weights
    size: 84                         # network input long side, px
    recipe: default                  # fit recipe (`raytun3r recipes`)
    recipe_changes: {steps: 30}      # AdaptConfig fields the fits change
    cameras:
      car01: {calibration: cameras/car01.json}          # + camera_id for multi-camera files
    segments:
      - {name: car01-a, camera: car01, render: {scene: indoor, frames: 12, seed: 1}}
      - {name: car01-b, camera: car01, frames: data/car01-b}          # image folder or video
      - {name: room1, dataset: {path: data/tumvi/room1, kind: tumvi, args: {}}}
    eval:
      adapt_frames: 8                # frames fitted on; the rest of each sequence is scored
      methods: [vanilla, center-ph, multi-ph, no-adapter, adapted, supervised]
      adapters: {car01: runs/fleet/car01.safetensors}   # optional: 'adapted' uses this file

A segment may add ``depth``: a folder of per-frame depth maps (``frames`` segments) or ``true``
(the ground truth of ``render`` and ``dataset`` segments); a camera whose segments all have depth
is fitted to it (the ``supervised`` recipe). A ``dataset`` segment without ``camera`` is a camera
of its own, named like the segment, calibrated by its dataset.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from raytun3r_plugin.errors import InputError

TOP_KEYS = {
    "backbone",
    "weights",
    "size",
    "recipe",
    "recipe_changes",
    "cameras",
    "segments",
    "eval",
}
EVAL_KEYS = {"adapt_frames", "methods", "adapters"}
SEGMENT_SOURCES = ("render", "frames", "dataset")
SEGMENT_KEYS = {"name", "camera", "scene", "depth", *SEGMENT_SOURCES}
RENDER_KEYS = {"scene", "frames", "seed"}
DATASET_KEYS = {"path", "kind", "args", "max_frames"}
DEFAULT_METHODS = ("vanilla", "center-ph", "multi-ph", "no-adapter", "adapted", "supervised")


@dataclass(frozen=True)
class CameraEntry:
    """A camera of the fleet: its calibration file (None: calibrated by its dataset segment)."""

    name: str
    calibration: Path | None
    camera_id: str | int | None = None


@dataclass(frozen=True)
class Segment:
    """One segment: ``source`` is ``render`` (a dict), ``frames`` (a path) or ``dataset`` (a
    dict with an absolute ``path``); ``depth`` a folder, True (ground truth) or None."""

    name: str
    camera: str
    kind: str
    source: Any
    scene: str
    depth: Any = None


@dataclass
class Manifest:
    """A checked manifest (:func:`read_manifest`)."""

    path: Path
    backbone: str
    weights: Path | None
    size: int
    recipe: str
    recipe_changes: dict
    cameras: dict[str, CameraEntry]
    segments: list[Segment]
    adapt_frames: int | None = None
    methods: tuple[str, ...] = DEFAULT_METHODS
    adapters: dict[str, Path] = field(default_factory=dict)

    def segments_of(self, camera: str) -> list[Segment]:
        return [segment for segment in self.segments if segment.camera == camera]


class _Problems(list):
    def add(self, where: str, problem: str) -> None:
        self.append(f"{where}: {problem}")


def _file(base: Path, value: Any, where: str, problems: _Problems, *, folder_ok=False) -> Path:
    if not isinstance(value, str) or not value:
        problems.add(where, f"expected a path, got {value!r}")
        return base
    path = (base / value).resolve()
    if not path.exists():
        problems.add(where, f"{path} does not exist")
    elif path.is_dir() and not folder_ok:
        problems.add(where, f"{path} is a folder, expected a file")
    return path


def _positive(value: Any, where: str, problems: _Problems, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        problems.add(where, f"expected an integer of at least {minimum}, got {value!r}")
        return minimum
    return value


def _unknown(data: dict, allowed: set, where: str, problems: _Problems) -> None:
    extra = sorted(str(key) for key in data if key not in allowed)
    if extra:
        problems.add(where, f"unknown key(s) {extra}; expected {sorted(allowed)}")


def _camera(base: Path, name: str, data: Any, problems: _Problems) -> CameraEntry:
    from raytun3r_plugin.cameras import load as load_camera
    from raytun3r_plugin.errors import Raytun3rError

    where = f"cameras.{name}"
    if not isinstance(data, dict) or "calibration" not in data:
        problems.add(where, "expected a mapping with 'calibration' (and optionally 'camera_id')")
        return CameraEntry(name, None)
    _unknown(data, {"calibration", "camera_id"}, where, problems)
    path = _file(base, data["calibration"], f"{where}.calibration", problems)
    if path.is_file():
        try:
            load_camera(path, camera=data.get("camera_id"))
        except Raytun3rError as error:
            problems.add(f"{where}.calibration", str(error))
    return CameraEntry(name, path, data.get("camera_id"))


def _render(data: Any, where: str, problems: _Problems) -> dict:
    if not isinstance(data, dict):
        problems.add(where, "expected a mapping {scene, frames, seed}")
        return {}
    _unknown(data, RENDER_KEYS, where, problems)
    if data.get("scene") not in ("indoor", "outdoor"):
        problems.add(f"{where}.scene", f"expected 'indoor' or 'outdoor', got {data.get('scene')!r}")
    frames = _positive(data.get("frames"), f"{where}.frames", problems, minimum=2)
    seed = _positive(data.get("seed", 0), f"{where}.seed", problems, minimum=0)
    return {"scene": data.get("scene"), "frames": frames, "seed": seed}


def _dataset(base: Path, data: Any, where: str, problems: _Problems) -> dict:
    from raytun3r_plugin.datasets import KINDS

    if not isinstance(data, dict) or "path" not in data:
        problems.add(where, "expected a mapping {path, kind, args, max_frames}")
        return {}
    _unknown(data, DATASET_KEYS, where, problems)
    path = _file(base, data["path"], f"{where}.path", problems, folder_ok=True)
    kind = data.get("kind")
    if kind is not None and kind not in KINDS:
        problems.add(f"{where}.kind", f"expected one of {list(KINDS)}, got {kind!r}")
    args = data.get("args") or {}
    if not isinstance(args, dict):
        problems.add(f"{where}.args", f"expected a mapping of reader arguments, got {args!r}")
        args = {}
    max_frames = data.get("max_frames")
    if max_frames is not None:
        max_frames = _positive(max_frames, f"{where}.max_frames", problems, minimum=2)
    return {"path": str(path), "kind": kind, "args": args, "max_frames": max_frames}


def _segment(base: Path, index: int, data: Any, cameras: dict, problems: _Problems) -> Segment:
    where = f"segments[{index}]"
    if not isinstance(data, dict):
        problems.add(where, f"expected a mapping, got {data!r}")
        return Segment(f"#{index}", "", "render", {}, "")
    name = str(data.get("name", f"segment{index}"))
    where = f"segments[{index}] ({name})"
    _unknown(data, SEGMENT_KEYS, where, problems)
    kinds = [kind for kind in SEGMENT_SOURCES if kind in data]
    if len(kinds) != 1:
        problems.add(where, f"give exactly one of {list(SEGMENT_SOURCES)}, got {kinds}")
        return Segment(name, "", "render", {}, "")
    kind = kinds[0]
    camera = data.get("camera")
    if camera is None and kind == "dataset":
        camera = name  # calibrated by its dataset
        cameras.setdefault(name, CameraEntry(name, None))
    elif camera not in cameras:
        problems.add(f"{where}.camera", f"{camera!r} is not one of cameras {sorted(cameras)}")
    if kind == "render":
        source: Any = _render(data["render"], f"{where}.render", problems)
        scene = source.get("scene") or "render"
    elif kind == "frames":
        source = str(_file(base, data["frames"], f"{where}.frames", problems, folder_ok=True))
        scene = "frames"
    else:
        source = _dataset(base, data["dataset"], f"{where}.dataset", problems)
        scene = source.get("kind") or "dataset"
    depth = data.get("depth")
    if depth is not None:
        if kind == "frames":
            depth = str(_file(base, depth, f"{where}.depth", problems, folder_ok=True))
        elif depth is not True:
            problems.add(f"{where}.depth", "a render or dataset segment takes depth: true")
    return Segment(name, str(camera), kind, source, str(data.get("scene", scene)), depth or None)


def _check_recipe(recipe: Any, changes: Any, size: int, problems: _Problems) -> None:
    from raytun3r_plugin.adaptation.train import AdaptConfig
    from raytun3r_plugin.errors import Raytun3rError

    if not isinstance(changes, dict):
        problems.add("recipe_changes", f"expected a mapping of AdaptConfig fields, got {changes!r}")
        return
    try:
        AdaptConfig.from_recipe(str(recipe), **{**changes, "input_size": size})
    except (Raytun3rError, TypeError) as error:
        problems.add("recipe", str(error))


def _check_eval(base: Path, data: Any, manifest: Manifest, problems: _Problems) -> None:
    if data is None:
        return
    if not isinstance(data, dict):
        problems.add("eval", f"expected a mapping {sorted(EVAL_KEYS)}, got {data!r}")
        return
    _unknown(data, EVAL_KEYS, "eval", problems)
    count = len(problems)
    adapt_frames = _positive(data.get("adapt_frames"), "eval.adapt_frames", problems)
    manifest.adapt_frames = adapt_frames if len(problems) == count else None
    methods = data.get("methods", list(DEFAULT_METHODS))
    unknown = [m for m in methods if m not in DEFAULT_METHODS] if isinstance(methods, list) else 0
    if not isinstance(methods, list) or unknown or not methods:
        problems.add("eval.methods", f"expected a list of {list(DEFAULT_METHODS)}, got {methods!r}")
    else:
        manifest.methods = tuple(methods)
    for camera, value in (data.get("adapters") or {}).items():
        if camera not in manifest.cameras:
            problems.add(
                f"eval.adapters.{camera}", f"not one of cameras {sorted(manifest.cameras)}"
            )
        manifest.adapters[str(camera)] = _file(base, value, f"eval.adapters.{camera}", problems)


def _load_yaml(path: Path) -> dict:
    import yaml

    if not path.is_file():
        raise InputError(f"{path}: no such manifest file")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise InputError(f"{path}: not valid YAML ({error})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def read_manifest(path: str | Path, *, for_eval: bool = False) -> Manifest:
    """Read and check the manifest at ``path``; with ``for_eval`` also what ``fleet eval``
    needs (an ``eval`` section; segments with ground truth, long enough to score).

    Raises:
        InputError: listing every problem found (missing files, unknown keys and names,
            calibration files their reader refuses, bad recipe changes), one per line.
    """
    from raytun3r_plugin.adaptation.recipes import recipe_names
    from raytun3r_plugin.weights import available_backbones

    path = Path(path).resolve()
    data = _load_yaml(path)
    base, problems = path.parent, _Problems()
    _unknown(data, TOP_KEYS, "manifest", problems)
    backbone = data.get("backbone")
    if backbone not in available_backbones():
        problems.add("backbone", f"{backbone!r} is not a backbone name (`raytun3r backbones`)")
    weights = data.get("weights")
    weights = None if weights is None else _file(base, weights, "weights", problems)
    size = _positive(data.get("size"), "size", problems, minimum=14)
    recipe = data.get("recipe", "default")
    if recipe not in recipe_names():
        problems.add("recipe", f"{recipe!r} is not one of {recipe_names()}")
    else:
        _check_recipe(recipe, data.get("recipe_changes") or {}, size, problems)
    cameras_data = data.get("cameras") or {}
    if not isinstance(cameras_data, dict):
        problems.add("cameras", "expected a mapping NAME -> {calibration: FILE}")
        cameras_data = {}
    cameras = {str(n): _camera(base, str(n), d, problems) for n, d in cameras_data.items()}
    segments_data = data.get("segments") or []
    if not isinstance(segments_data, list) or not segments_data:
        problems.add("segments", "expected a non-empty list of segments")
        segments_data = []
    segments = [_segment(base, k, d, cameras, problems) for k, d in enumerate(segments_data)]
    names = [segment.name for segment in segments]
    for name in sorted({n for n in names if names.count(n) > 1}):
        problems.add("segments", f"the name {name!r} is used more than once")
    manifest = Manifest(
        path, str(backbone), weights, size, str(recipe), dict(data.get("recipe_changes") or {}),
        cameras, segments,
    )  # fmt: skip
    for name, entry in cameras.items():
        used = manifest.segments_of(name)
        if entry.calibration is not None and not used:
            problems.add(f"cameras.{name}", "no segment uses this camera")
        if len({segment.depth is None for segment in used}) > 1:
            problems.add(
                f"cameras.{name}",
                "give depth for all of its segments (a supervised fit) or for none",
            )
    if for_eval:
        if data.get("eval") is None:
            problems.add("eval", "fleet eval needs an 'eval' section (adapt_frames, methods)")
        _check_eval(base, data.get("eval"), manifest, problems)
        _check_eval_segments(manifest, problems)
    if problems:
        raise InputError(
            f"{path}: {len(problems)} problem(s), nothing was run:\n  " + "\n  ".join(problems)
        )
    return manifest


def _check_eval_segments(manifest: Manifest, problems: _Problems) -> None:
    for segment in manifest.segments:
        where = f"segments ({segment.name})"
        if segment.kind == "frames":
            problems.add(where, "has no ground truth to score: use a render or dataset segment")
        frames = segment.source.get("frames") if segment.kind == "render" else None
        if frames is not None and manifest.adapt_frames is not None:
            if frames - manifest.adapt_frames < 2:
                problems.add(
                    where,
                    f"{frames} frames leave fewer than 2 to score after "
                    f"eval.adapt_frames {manifest.adapt_frames}",
                )
