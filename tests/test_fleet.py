"""``raytun3r fleet``: the manifest checked in full up front, tasks keyed by their inputs and
published atomically, reruns that skip finished tasks, failures that do not stop the others, and
the same task layer in this process and on one embedded Ray cluster shared by the module's tests
(``raytun3r_plugin.cluster``)."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal
import subprocess
import tempfile
import threading
from pathlib import Path

import pytest

from raytun3r_plugin.apps.fleet import file_digest
from raytun3r_plugin.errors import InputError
from tests.fleet_helpers import (
    descendants,
    render_segment,
    same_tensors,
    wait_for,
    write_manifest,
)

pytest.importorskip("depth_anything_3")
ROOT = Path(__file__).parent.parent
CAMERAS = {"car01": (84, 190.0, "kb4"), "car02": (84, 195.0, "ds")}


def _fleet_manifest(folder: Path, seed: int = 91011, changes: dict | None = None) -> Path:
    return write_manifest(
        folder,
        CAMERAS,
        [render_segment("car01-a", "car01", seed), render_segment("car02-a", "car02", 91012)],
        changes=changes,
    )


def _adapters(out: Path) -> dict[str, Path]:
    rows = list(csv.DictReader((out / "adapters.csv").open()))
    return {row["camera"]: out / row["adapter"] for row in rows}


@pytest.fixture(scope="module")
def in_process_run(tmp_path_factory):
    """The two-camera fleet fitted in this process (``--workers 1``: no Ray), on one thread
    (``--threads 1``) as the Ray runs below compare with: adapters are bit-identical only on
    the same thread count."""
    from raytun3r_plugin.apps.cli_fleet import run_fleet

    folder = tmp_path_factory.mktemp("fleet-plain")
    manifest = _fleet_manifest(folder / "in")
    report = run_fleet(manifest, folder / "out", "adapt", workers=1, threads=1, progress=False)
    return manifest, folder / "out", report


@pytest.fixture(scope="module")
def ray_cluster():
    """One embedded cluster (2 one-CPU workers) for the module: every command below joins it."""
    pytest.importorskip("ray")
    from raytun3r_plugin.cluster import ClusterSpec, connected

    with connected(ClusterSpec(workers=2)) as ray:
        yield ray


def test_a_bad_manifest_is_refused_with_every_problem_before_anything_runs(tmp_path):
    import yaml

    from raytun3r_plugin.apps.cli_fleet import run_fleet

    folder = tmp_path / "in"
    manifest = _fleet_manifest(folder)
    (folder / "car02.json").write_text('{"model": "kb4", "width": 84}')  # fields missing
    data = yaml.safe_load(manifest.read_text())
    data["backbone"] = "no-such-net"
    data["recipe_changes"]["no_such_field"] = 1
    data["segments"][0]["render"]["scene"] = "cave"
    data["segments"].append({"name": "car01-a", "camera": "car09", "frames": "missing-folder"})
    data["segments"].append(
        {
            "name": "car02-b",
            "camera": "car02",
            "render": data["segments"][1]["render"],
            "depth": True,
        }
    )
    manifest.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    with pytest.raises(InputError) as refused:
        run_fleet(manifest, out, "eval", workers=1, progress=False)
    message = str(refused.value)
    for problem in (
        "backbone: 'no-such-net' is not a backbone name",
        "recipe: AdaptConfig has no field 'no_such_field'",
        "cameras.car02.calibration:",
        "segments[0] (car01-a).render.scene: expected 'indoor' or 'outdoor', got 'cave'",
        "segments[2] (car01-a).camera: 'car09' is not one of cameras",
        "missing-folder does not exist",
        "segments: the name 'car01-a' is used more than once",
        "cameras.car02: give depth for all of its segments (a supervised fit) or for none",
        "eval: fleet eval needs an 'eval' section",
    ):
        assert problem in message, (problem, message)
    assert "nothing was run" in message
    assert not out.exists()


def test_in_process_fleet_fits_one_adapter_per_camera_and_a_rerun_skips_them(in_process_run):
    from raytun3r_plugin.adapter import Adapter
    from raytun3r_plugin.apps.cli_fleet import run_fleet
    from raytun3r_plugin.cameras import load

    manifest, out, report = in_process_run
    assert (report["tasks"], report["skipped"], report["ran"], report["failed"]) == (2, 0, 2, [])
    adapters = _adapters(out)
    assert sorted(adapters) == ["car01", "car02"]
    for camera, path in adapters.items():
        adapter = Adapter.load(path)  # a complete adapter for that camera's calibration
        assert adapter.camera == load(manifest.parent / f"{camera}.json")
        result = json.loads((path.parent / "result.json").read_text())
        assert (
            result["attempts"] == 1 and result["node"] == "local" and result["pid"] == os.getpid()
        )
    before = {p: p.stat().st_mtime_ns for p in adapters.values()}
    again = run_fleet(manifest, out, "adapt", workers=1, progress=False)
    assert (again["skipped"], again["ran"]) == (2, 0)
    assert {p: p.stat().st_mtime_ns for p in adapters.values()} == before
    assert (out / "adapters.csv").read_text().count("\n") == 3  # header + one row per camera


def test_a_changed_input_or_recipe_is_redone_and_nothing_else(in_process_run, tmp_path):
    from raytun3r_plugin.apps.cli_fleet import run_fleet
    from raytun3r_plugin.apps.fleet import plan_tasks
    from raytun3r_plugin.apps.fleet_manifest import read_manifest

    manifest, out, _ = in_process_run
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    changed = _fleet_manifest(tmp_path / "in", seed=91099)  # car01's segment renders anew
    keys = {t.name: t.key for t in plan_tasks(read_manifest(manifest), "adapt")}
    new = {t.name: t.key for t in plan_tasks(read_manifest(changed), "adapt")}
    assert new["car02"] == keys["car02"] and new["car01"] != keys["car01"]
    report = run_fleet(changed, copy, "adapt", workers=1, progress=False)
    assert (report["skipped"], report["ran"]) == (1, 1)
    # A changed calibration file or recipe changes every key it enters.
    (tmp_path / "in" / "car02.json").write_text(
        (tmp_path / "in" / "car02.json").read_text().replace("195.0", "196.0")
    )
    recipe = _fleet_manifest(tmp_path / "r", changes={"steps": 3, "n_windows": 2})
    assert {t.key for t in plan_tasks(read_manifest(changed), "adapt")}.isdisjoint(keys.values())
    assert {t.key for t in plan_tasks(read_manifest(recipe), "adapt")}.isdisjoint(keys.values())


def test_frame_folders_and_dataset_readers_are_segments_and_depth_makes_a_supervised_fit(
    tmp_path,
):
    """A frame folder through its calibration file, and a dataset read by its reader (its own
    camera) with ``depth: true``: fitted self-supervised and to the ground truth respectively."""
    import cv2
    import numpy as np

    from raytun3r_plugin import synthetic
    from raytun3r_plugin.apps.cli_fleet import run_fleet
    from raytun3r_plugin.cameras import load
    from raytun3r_plugin.datasets import write_sequence

    camera = tmp_path / "car01.json"
    write_manifest(tmp_path, {"car01": CAMERAS["car01"]}, [render_segment("x", "car01", 1)])
    seq = synthetic.render_sequence("indoor", load(camera), n_frames=6, seed=91013)
    (tmp_path / "frames").mkdir()
    for k in range(len(seq)):
        bgr = cv2.cvtColor((seq.image(k) * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(tmp_path / "frames" / f"{k:03d}.png"), bgr)
    write_sequence(
        synthetic.render_sequence("indoor", load(camera), 6, seed=91014), tmp_path / "ds"
    )
    dataset = {"path": "ds", "kind": "synthetic", "args": {}}
    manifest = write_manifest(
        tmp_path,
        {"car01": CAMERAS["car01"]},
        [
            {"name": "car01-a", "camera": "car01", "frames": "frames"},
            {"name": "room", "dataset": dataset, "depth": True},
        ],
    )
    report = run_fleet(manifest, tmp_path / "out", "adapt", workers=1, progress=False)
    assert report["failed"] == [] and report["ran"] == 2
    rows = {r["camera"]: r for r in csv.DictReader((tmp_path / "out" / "adapters.csv").open())}
    assert rows["car01"]["recipe"] == "default" and rows["room"]["recipe"] == "supervised"
    assert rows["room"]["frames"] == "6"
    # The dataset as an eval sequence: read by its reader, prepared at the input size, scored.
    evaluated = write_manifest(
        tmp_path / "eval",
        {},
        [{"name": "room", "dataset": {"path": str(tmp_path / "ds"), "kind": "synthetic"}}],
        eval_section={"adapt_frames": 3, "methods": ["vanilla", "no-adapter"]},
    )
    report = run_fleet(evaluated, tmp_path / "eval-out", "eval", workers=1, progress=False)
    assert report["failed"] == [], report["failed"]
    table = list(csv.DictReader((tmp_path / "eval-out" / "results.csv").open()))
    assert [(r["camera"], r["scene"], r["method"]) for r in table] == [
        ("room", "synthetic", "vanilla"),
        ("room", "synthetic", "raytun3r, no adapter"),
    ]
    assert all(0 < float(r["abs_rel"]) < 1 and float(r["coverage"]) > 0.9 for r in table)


def test_a_refused_calibration_fails_its_task_and_the_others_finish_on_ray(
    ray_cluster, in_process_run, tmp_path, capsys
):
    """On the embedded cluster: a frame folder that does not match its calibration fails its task
    with the error; the other task finishes, equal to this process's fit; exit status 1."""
    import cv2
    import numpy as np

    from raytun3r_plugin.apps.cli import main

    frames = tmp_path / "wrong-size"
    frames.mkdir()
    for k in range(6):
        cv2.imwrite(str(frames / f"{k:03d}.png"), np.full((64, 64, 3), 40 * k, np.uint8))
    wrong = {"name": "car02-b", "camera": "car02", "frames": "wrong-size"}
    manifest = write_manifest(tmp_path, CAMERAS, [render_segment("car01-a", "car01", 91011), wrong])
    # The built-in network's file named as a weights file: its bytes reach the workers through
    # the object store and are written once under the temporary folder, named by their digest.
    weights = tmp_path / "network.safetensors"
    shutil.copy(ROOT / "raytun3r_plugin" / "data" / "raytun3r-da3-tiny-v3.safetensors", weights)
    manifest.write_text(manifest.read_text() + "weights: network.safetensors\n")
    out = tmp_path / "out"
    assert main(["fleet", "adapt", str(manifest), "--out", str(out), "--no-progress"]) == 1
    captured = capsys.readouterr()
    assert "1 task(s) failed" in captured.err
    assert "car02: InputError: frames are 64x64 px but the camera is 84x84" in captured.err
    failures = json.loads((out / "failures.json").read_text())
    assert [f["task"] for f in failures] == ["car02"]
    adapters = _adapters(out)
    assert list(adapters) == ["car01"]
    _, plain, _ = in_process_run
    assert same_tensors(adapters["car01"], _adapters(plain)["car01"])  # Ray fits like in process
    shipped = (
        Path(tempfile.gettempdir()) / "raytun3r-weights" / f"{file_digest(weights)}.safetensors"
    )
    assert shipped.read_bytes() == weights.read_bytes()
    result = json.loads((adapters["car01"].parent / "result.json").read_text())
    assert result["node"] != "local" and result["pid"] != os.getpid()
    assert not [p for p in (out / "tasks").iterdir() if ".partial-" in p.name]


def test_a_worker_killed_mid_fit_is_retried_and_leaves_one_complete_result(
    ray_cluster, in_process_run, tmp_path
):
    """SIGKILL of the worker process while its task runs: Ray reruns the task, the retry
    publishes the only result folder, and the adapters equal an uninterrupted run's."""
    from raytun3r_plugin.apps.cli_fleet import run_fleet

    manifest = _fleet_manifest(tmp_path / "in")
    out = tmp_path / "out"
    report: dict = {}
    runner = threading.Thread(
        target=lambda: report.update(run_fleet(manifest, out, "adapt", progress=False))
    )
    runner.start()
    try:
        attempts = out / "attempts"
        mark = wait_for(
            lambda: next(iter(attempts.glob("car01-*/*")), None) if attempts.is_dir() else None,
            120,
            "car01's task to start",
        )
        staging = wait_for(
            lambda: next(iter((out / "tasks").glob(".car01-*.partial-*")), None), 60, "its staging"
        )
        os.kill(int(mark.name.rsplit("-", 1)[1]), signal.SIGKILL)
    finally:
        runner.join(timeout=300)
    assert not runner.is_alive()
    assert report["failed"] == [] and report["ran"] == 2
    adapters = _adapters(out)
    result = json.loads((adapters["car01"].parent / "result.json").read_text())
    assert result["attempts"] == 2 and result["pid"] != int(mark.name.rsplit("-", 1)[1])
    assert not staging.exists()
    folders = sorted(p.name for p in (out / "tasks").iterdir())
    assert len(folders) == 2 and not [f for f in folders if ".partial-" in f]
    _, plain, _ = in_process_run
    for camera, path in _adapters(plain).items():
        assert same_tensors(adapters[camera], path), camera
    assert _table_without_times(out) == _table_without_times(plain)


def _table_without_times(out: Path) -> list[dict]:
    rows = list(csv.DictReader((out / "adapters.csv").open()))
    return [{k: v for k, v in row.items() if k != "adapt_s"} for row in rows]


def test_ray_listens_on_loopback_only(ray_cluster):
    """Every socket a process of the embedded cluster listens on is bound to 127.0.0.1."""
    if shutil.which("ss") is None:
        pytest.skip("ss (iproute2) is not installed: scripts/install.sh installs it")
    ours = descendants(os.getpid()) | {os.getpid()}
    listening = subprocess.run(["ss", "-ltnpH"], capture_output=True, text=True, check=True)
    sockets = []
    for line in listening.stdout.splitlines():
        pids = {int(p) for p in re.findall(r"pid=(\d+)", line)}
        if pids & ours:
            sockets.append(line.split()[3])
    assert len(sockets) >= 3, listening.stdout  # the GCS, the raylet, the workers
    outside = [s for s in sockets if s.rsplit(":", 1)[0] not in ("127.0.0.1", "[::ffff:127.0.0.1]")]
    assert not outside, f"Ray listens beyond loopback: {outside}"


def test_the_example_fleet_runs_its_eval_with_the_benchmark_columns(ray_cluster, tmp_path):
    """examples/fleet.yaml as shipped: sequences x the six methods, one row per cell and method,
    and a rerun that runs nothing."""
    from raytun3r_plugin.apps.benchmark import COLUMNS, METHOD_KEYS
    from raytun3r_plugin.apps.cli_fleet import run_fleet

    out = tmp_path / "out"
    report = run_fleet(ROOT / "examples" / "fleet.yaml", out, "eval", progress=False)
    assert report["failed"] == [] and report["ran"] == 3
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert len(rows) == 3 * 6 and set(COLUMNS) <= set(rows[0])
    assert {r["method"] for r in rows} == set(METHOD_KEYS.values())
    sequences = json.loads((out / "results.json").read_text())["sequences"]
    for row in rows:  # a cell of one sequence: its mean is that sequence's value
        (match,) = [
            s for s in sequences if (s["camera"], s["method"]) == (row["camera"], row["method"])
        ]
        assert float(row["abs_rel"]) == pytest.approx(match["abs_rel"], rel=1e-12)
    again = run_fleet(ROOT / "examples" / "fleet.yaml", out, "eval", progress=False)
    assert (again["skipped"], again["ran"]) == (3, 0)
    assert list(csv.DictReader((out / "results.csv").open())) == rows


def test_a_task_asks_for_one_gpu_exactly_where_the_cluster_has_gpus():
    """The resource request of every Ray task (raytun3r_plugin.cluster._resources): one GPU
    and its CPU threads where the cluster declares GPUs, CPU threads only elsewhere, and what
    the spec forces either way."""
    from types import SimpleNamespace

    from raytun3r_plugin.cluster import ClusterSpec, _resources

    with_gpus = SimpleNamespace(cluster_resources=lambda: {"CPU": 16.0, "GPU": 2.0})
    cpu_only = SimpleNamespace(cluster_resources=lambda: {"CPU": 16.0})
    spec = ClusterSpec(threads=3)
    assert _resources(with_gpus, spec) == {"num_cpus": 3, "num_gpus": 1}
    assert _resources(cpu_only, spec) == {"num_cpus": 3, "num_gpus": 0}
    assert _resources(with_gpus, ClusterSpec(threads=3, gpus=False))["num_gpus"] == 0
    assert _resources(cpu_only, ClusterSpec(gpus=True))["num_gpus"] == 1
    assert _resources(cpu_only, ClusterSpec()) == {"num_cpus": 1, "num_gpus": 0}  # threads None


def _threads_now(_state, _task):
    import torch

    return torch.get_num_threads()


def test_in_process_tasks_run_on_the_threads_asked_for_and_leave_the_callers_as_it_was():
    """``--workers 1 --threads N`` pins each task to N threads as a Ray task is pinned; without
    ``threads`` the caller's setting is used; either way it is the caller's again afterwards."""
    import torch

    from raytun3r_plugin.cluster import ClusterSpec, run_tasks
    from raytun3r_plugin.threads import torch_threads

    with torch_threads(2):
        ran = list(run_tasks(_threads_now, [(0,), (1,)], ClusterSpec(threads=1)))
        assert [o.value for o in ran] == [1, 1] and torch.get_num_threads() == 2
        ran = list(run_tasks(_threads_now, [(0,)], ClusterSpec()))
        assert [o.value for o in ran] == [2]
