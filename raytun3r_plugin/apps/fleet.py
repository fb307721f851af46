"""``raytun3r fleet adapt`` and ``fleet eval``: one task per camera (an adapter fitted on its
segments) or per sequence (the benchmark's methods scored on it), run by
:func:`raytun3r_plugin.cluster.run_tasks`, resumable and exact (docs/fleet.md).

Every task is keyed by a hash of what it reads and does (:func:`task_key`): the content of its
calibration file, segments (every file of a folder, video or dataset; a rendered segment's
settings), depth and adapter files, the weights file, the backbone, the input size, the resolved
recipe, the methods and the package version. It writes into a staging folder beside its final one
and renames it into place when done (``DIR/tasks/<name>-<key>``, ``result.json`` inside), so a
task killed at any moment leaves no half-written result, and a rerun skips exactly the tasks
whose folder exists. The tables (``DIR/adapters.*``, ``DIR/results.*``) are built from the task
folders of the current manifest only, so they are the same after one pass or several.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import secrets
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from raytun3r_plugin.apps.fleet_manifest import Manifest, Segment

#: Files and folders of DIR.
TASKS, ATTEMPTS, PARTIAL = "tasks", "attempts", ".partial-"
#: Columns of ``adapters.csv`` / ``adapters.md``.
ADAPT_COLUMNS = [
    "camera",
    "segments",
    "frames",
    "recipe",
    "verdict",
    "adapt_s",
    "params",
    "adapter",
]


@dataclass(frozen=True)
class FleetTask:
    """One task: ``record`` is everything its worker needs (plain data), ``key`` its hash."""

    kind: str
    name: str
    key: str
    record: dict

    @property
    def folder(self) -> str:
        return f"{self.name}-{self.key[:16]}"


def file_digest(path: str | os.PathLike) -> str:
    """SHA-256 of a file's content (hex)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def tree_digest(path: str | os.PathLike) -> str:
    """SHA-256 over a file's content, or over every file under a folder (relative name and
    content, in name order): a dataset or frame folder changes its key when any file does."""
    root = Path(path)
    if root.is_file():
        return file_digest(root)
    digest = hashlib.sha256()
    for file in sorted(p for p in root.rglob("*") if p.is_file()):
        digest.update(f"{file.relative_to(root).as_posix()}\0{file_digest(file)}\0".encode())
    return digest.hexdigest()


def _without_paths(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _without_paths(v) for k, v in value.items() if k != "path"}
    if isinstance(value, list):
        return [_without_paths(v) for v in value]
    return value


def task_key(record: dict) -> str:
    """SHA-256 of a task's canonical JSON record (sorted keys) with the package version. File
    paths are left out (every file enters by its content digest), so moving the data or the
    manifest keeps the finished tasks."""
    from raytun3r_plugin import __version__

    view = _without_paths({**record, "raytun3r": __version__})
    text = json.dumps(view, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def _segment_record(segment: Segment) -> dict:
    record: dict[str, Any] = {"name": segment.name, "kind": segment.kind, "scene": segment.scene}
    if segment.kind == "render":
        record["source"] = dict(segment.source)
    elif segment.kind == "frames":
        record["source"] = {"path": segment.source}
        record["digest"] = tree_digest(segment.source)
    else:
        record["source"] = dict(segment.source)
        record["digest"] = tree_digest(segment.source["path"])
    if isinstance(segment.depth, str):
        record["depth"] = {"path": segment.depth, "digest": tree_digest(segment.depth)}
    else:
        record["depth"] = segment.depth
    return record


def _common_record(manifest: Manifest, camera: str) -> dict:
    entry = manifest.cameras[camera]
    calibration = None
    if entry.calibration is not None:
        calibration = {
            "path": str(entry.calibration),
            "camera_id": entry.camera_id,
            "digest": file_digest(entry.calibration),
        }
    weights = None
    if manifest.weights is not None:
        weights = {"path": str(manifest.weights), "digest": file_digest(manifest.weights)}
    return {
        "camera": camera,
        "calibration": calibration,
        "backbone": manifest.backbone,
        "weights": weights,
        "size": manifest.size,
        "recipe": manifest.recipe,
        "recipe_changes": manifest.recipe_changes,
    }


def plan_tasks(manifest: Manifest, kind: str) -> list[FleetTask]:
    """The tasks of ``fleet adapt`` (one per camera) or ``fleet eval`` (one per segment)."""
    tasks = []
    if kind == "adapt":
        for camera in manifest.cameras:
            segments = manifest.segments_of(camera)
            if not segments:
                continue
            record = {
                "kind": "adapt",
                **_common_record(manifest, camera),
                "segments": [_segment_record(s) for s in segments],
            }
            tasks.append(FleetTask("adapt", camera, task_key(record), record))
        return tasks
    for segment in manifest.segments:
        adapter = manifest.adapters.get(segment.camera)
        record = {
            "kind": "eval",
            **_common_record(manifest, segment.camera),
            "segments": [_segment_record(segment)],
            "adapt_frames": manifest.adapt_frames,
            "methods": list(manifest.methods),
            "adapter": None
            if adapter is None
            else {"path": str(adapter), "digest": file_digest(adapter)},
        }
        tasks.append(FleetTask("eval", segment.name, task_key(record), record))
    return tasks


# --- in the worker -------------------------------------------------------------------------


def load_network(backbone: str, weights: dict | None, blob: bytes | None):
    """The task state: the backbone with its weights, on the GPU Ray gave this task if any.

    ``blob``: the weights file's bytes, sent once through the object store (a worker on another
    machine need not see the driver's path); written once per machine to a file named by its
    digest in the temporary folder, then loaded like the file."""
    import tempfile

    import torch

    from raytun3r_plugin.atomic_files import atomic_write_bytes
    from raytun3r_plugin.weights import load_backbone

    path = None
    if weights is not None:
        path = Path(weights["path"])
        if blob is not None:
            path = (
                Path(tempfile.gettempdir())
                / "raytun3r-weights"
                / f"{weights['digest']}{path.suffix}"
            )
            if not path.is_file():
                atomic_write_bytes(path, blob)
    model = load_backbone(backbone, None if path is None else str(path))
    if torch.cuda.is_available():
        model = model.to("cuda")
    return model.eval()


def _camera_of(record: dict):
    from raytun3r_plugin.cameras import load as load_camera

    calibration = record["calibration"]
    return load_camera(calibration["path"], camera=calibration["camera_id"])


def _load_segment(segment: dict, camera, size: int):
    """(frames or Sequence, depth or None, camera) of one segment record."""
    from raytun3r_plugin.apps.sequence_methods import ground_truth_depth

    source, with_depth = segment["source"], segment["depth"]
    if segment["kind"] == "render":
        from raytun3r_plugin import synthetic
        from raytun3r_plugin.preprocess import InputLayout

        camera = InputLayout.for_camera(camera, size, 14).camera  # rendered at the input size
        seq = synthetic.render_sequence(
            source["scene"], camera, n_frames=source["frames"], seed=source["seed"]
        )
        return seq, (ground_truth_depth(seq, len(seq)) if with_depth else None), seq.camera
    if segment["kind"] == "frames":
        from raytun3r_plugin.images import read_depth_maps, read_frames

        frames, names = read_frames(source["path"])
        depth = None
        if isinstance(with_depth, dict):
            depth = read_depth_maps(with_depth["path"], names, frames.shape[2], frames.shape[1])
        return frames, depth, camera
    from raytun3r_plugin.apps.evaluation import fit_sequence
    from raytun3r_plugin.datasets import load_sequence

    seq = load_sequence(source["path"], kind=source["kind"], **source["args"])
    seq = fit_sequence(seq, size, max_frames=source["max_frames"])
    depth = None if not with_depth or seq.depth is None else seq.depth
    return seq, depth, seq.camera


def _config(record: dict, supervised: bool, model=None):
    """One camera's fit settings: its recipe with the backbone family's declared changes
    (``model``), then the manifest's."""
    from raytun3r_plugin.adaptation.train import AdaptConfig

    recipe = "supervised" if supervised else record["recipe"]
    changes = {**record["recipe_changes"], "input_size": record["size"], "checkpoint_every": 0}
    return AdaptConfig.from_recipe(recipe, model=model, **changes)


def _adapt(model, record: dict, staging: Path) -> dict:
    from raytun3r_plugin.adaptation.train import adapt
    from raytun3r_plugin.errors import InputError

    camera = _camera_of(record) if record["calibration"] else None
    frames, depths = [], []
    for segment in record["segments"]:
        images, depth, camera = _load_segment(segment, camera, record["size"])
        frames.append(images)
        depths.append(depth)
    if camera is None:  # read_manifest gives every camera a calibration or a dataset
        raise InputError(f"{record['camera']}: no calibration and no dataset camera")
    supervised = all(depth is not None for depth in depths)
    config = _config(record, supervised, model)
    started = time.perf_counter()
    adapter = adapt(
        model,
        camera,
        frames if len(frames) > 1 else frames[0],
        config,
        out_path=staging / "adapter.safetensors",
        resume=False,
        progress=False,
        depth=(depths if len(depths) > 1 else depths[0]) if supervised else None,
    )
    return {
        "camera": record["camera"],
        "segments": len(frames),
        "frames": sum(len(f) for f in frames),
        "recipe": config.recipe_record()["name"],
        "verdict": adapter.training_info["verdict"]["status"],
        "adapt_s": time.perf_counter() - started,
        "params": adapter.num_parameters()["total"],
    }


def _evaluate(model, record: dict, staging: Path) -> dict:
    from raytun3r_plugin.adapter import Adapter
    from raytun3r_plugin.apps.sequence_methods import method_rows
    from raytun3r_plugin.errors import InputError

    (segment,) = record["segments"]
    camera = _camera_of(record) if record["calibration"] else None
    seq, _, _ = _load_segment(segment, camera, record["size"])
    n_adapt = record["adapt_frames"]
    if len(seq) - n_adapt < 2 or seq.cam_from_world is None:
        raise InputError(
            f"{segment['name']}: {len(seq)} frames with poses={seq.cam_from_world is not None}; "
            f"scoring needs poses and at least 2 frames after the {n_adapt} fitted"
        )
    given = record["adapter"]
    rows = method_rows(
        model,
        seq,
        {"camera": record["camera"], "scene": segment["scene"], "seed": segment["name"]},
        n_adapt,
        record["methods"],
        fit=_config(record, False, model),
        supervised_fit=_config(record, True, model),
        adapter_path=staging / "adapter.safetensors",
        adapter=None if given is None else Adapter.load(given["path"]),
    )
    return {"rows": rows}


def run_fleet_task(model, record: dict, key: str, folder: str, out: str) -> dict:
    """Run one task and publish its folder ``out/tasks/<folder>`` atomically; returns its
    ``result.json`` record. A second attempt that finds the folder published keeps that one."""
    from raytun3r_plugin.atomic_files import atomic_write_text
    from raytun3r_plugin.cluster import node_of_this_process

    root = Path(out)
    node, pid = node_of_this_process(), os.getpid()
    marks = root / ATTEMPTS / folder
    marks.mkdir(parents=True, exist_ok=True)
    (marks / f"{node[:12]}-{pid}").write_text(f"{time.time()}\n")
    final = root / TASKS / folder
    if (final / "result.json").is_file():
        return json.loads((final / "result.json").read_text())
    staging = root / TASKS / f".{folder}{PARTIAL}{pid}-{secrets.token_hex(4)}"
    staging.mkdir(parents=True)
    try:
        work = _adapt if record["kind"] == "adapt" else _evaluate
        result = {
            **work(model, record, staging),
            "key": key,
            "node": node,
            "pid": pid,
            "attempts": len(list(marks.iterdir())),
        }
        atomic_write_text(staging / "result.json", json.dumps(result, indent=2, default=float))
        try:
            staging.rename(final)
        except OSError:  # published by another attempt in the meantime: that one stands
            if not (final / "result.json").is_file():
                raise
        return json.loads((final / "result.json").read_text())
    finally:
        shutil.rmtree(staging, ignore_errors=True)


# --- on the driver --------------------------------------------------------------------------


def remove_partial(out: Path) -> list[Path]:
    """Remove staging folders of attempts that died (no task is running before a run starts)."""
    removed = []
    tasks = out / TASKS
    if tasks.is_dir():
        for entry in tasks.iterdir():
            if PARTIAL in entry.name:
                shutil.rmtree(entry, ignore_errors=True)
                removed.append(entry)
    return removed


def finished(out: Path, task: FleetTask) -> dict | None:
    """The ``result.json`` of ``task`` under ``out``, or None when it has not finished."""
    path = out / TASKS / task.folder / "result.json"
    return json.loads(path.read_text()) if path.is_file() else None


def _write_table(out: Path, stem: str, rows: list[dict], columns: list[str], header: str) -> None:
    import csv
    import io

    from raytun3r_plugin.apps.evaluation import format_table
    from raytun3r_plugin.atomic_files import atomic_write_text

    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({c: _csv_cell(row.get(c, "")) for c in columns})
    atomic_write_text(out / f"{stem}.csv", buffer.getvalue())
    atomic_write_text(out / f"{stem}.md", header + "\n\n" + format_table(rows, columns) + "\n")


def _csv_cell(value: Any) -> Any:
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)
    return value


def build_tables(out: Path, kind: str, tasks: list[FleetTask], manifest: Manifest) -> list[dict]:
    """Write ``adapters.*`` or ``results.*`` (and ``results.json``) under ``out`` from the
    finished tasks of ``tasks``; returns the table's rows."""
    from raytun3r_plugin.apps.benchmark import COLUMNS, summarise
    from raytun3r_plugin.atomic_files import atomic_write_text

    results = [(task, finished(out, task)) for task in tasks]
    done = [(task, result) for task, result in results if result is not None]
    header = (
        f"Fleet {kind} of {manifest.path.name}: {len(done)} of {len(tasks)} tasks finished; "
        f"backbone {manifest.backbone}, input {manifest.size} px, recipe '{manifest.recipe}'"
        + (f" (changed: {manifest.recipe_changes})" if manifest.recipe_changes else "")
        + "."
    )
    if kind == "adapt":
        rows = [
            {**result, "adapter": f"{TASKS}/{task.folder}/adapter.safetensors"}
            for task, result in done
        ]
        _write_table(out, "adapters", rows, ADAPT_COLUMNS, header)
        return rows
    sequences = [row for _, result in done for row in result["rows"]]
    summary = summarise(sequences) if sequences else []
    columns = [*COLUMNS, "sequences", "lower_than_vanilla"]
    header += (
        f" Per (camera, scene, method): the mean over its sequences, each scored on its frames "
        f"from {manifest.adapt_frames} on (the benchmark's columns, docs/results.md)."
    )
    _write_table(out, "results", summary, columns, header)
    atomic_write_text(
        out / "results.json",
        json.dumps({"sequences": sequences, "summary": summary}, indent=2, default=float),
    )
    return summary
