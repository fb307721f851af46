"""Small fleet manifests for the fleet tests: cameras written as calibration files, rendered
segments of a few frames, fits of a few steps (tests/test_adapt.py keeps fits cheap the same
way)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml

#: The fits of the test manifests: a few steps on 2 windows of the default recipe.
TINY_CHANGES = {"steps": 2, "n_windows": 2, "lr": 0.01}


def write_manifest(
    folder: Path,
    cameras: dict[str, tuple],
    segments: list[dict],
    changes: dict | None = None,
    eval_section: dict | None = None,
) -> Path:
    """``cameras``: name -> (size, fov_deg, model) written to ``folder/NAME.json``; returns the
    manifest's path (``folder/fleet.yaml``)."""
    from raytun3r_plugin.cameras import fisheye, save

    folder.mkdir(parents=True, exist_ok=True)
    for name, (size, fov, model) in cameras.items():
        save(fisheye(size, fov, model), folder / f"{name}.json")
    data = {
        "backbone": "raytun3r-da3-tiny-v3",
        "size": 84,
        "recipe": "default",
        "recipe_changes": dict(TINY_CHANGES if changes is None else changes),
        "cameras": {name: {"calibration": f"{name}.json"} for name in cameras},
        "segments": segments,
    }
    if eval_section is not None:
        data["eval"] = eval_section
    path = folder / "fleet.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def render_segment(name: str, camera: str, seed: int, frames: int = 6) -> dict:
    return {
        "name": name,
        "camera": camera,
        "render": {"scene": "indoor", "frames": frames, "seed": seed},
    }


def tensors_of(path: Path) -> dict:
    from safetensors.torch import load_file

    return load_file(str(path))


def same_tensors(a: Path, b: Path) -> bool:
    import torch

    left, right = tensors_of(a), tensors_of(b)
    return left.keys() == right.keys() and all(torch.equal(left[k], right[k]) for k in left)


def wait_for(condition, timeout_s: float, what: str, poll_s: float = 0.1):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(poll_s)
    raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")


def fleet_command(args: list[str]) -> subprocess.Popen:
    """``raytun3r fleet ...`` in a child process of its own session (its Ray processes with it),
    with this test run's source tree and one thread."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).parent.parent)}
    return subprocess.Popen(
        [sys.executable, "-m", "raytun3r_plugin.apps.cli", "fleet", *args, "--no-progress"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


def kill_session(process: subprocess.Popen) -> None:
    """SIGKILL a child started in a session of its own (:func:`fleet_command`, ``ray start``)
    and every process of that session: its process group, and the processes that left the group
    but not the session (Ray's workers each lead a group of their own)."""
    try:
        os.killpg(process.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    process.wait()
    for _ in range(50):  # a process may start one more before it dies: until none is left
        left = session_processes(process.pid)
        if not left:
            return
        for pid in left:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        time.sleep(0.1)


def session_processes(session: int) -> list[int]:
    """Live (not zombie) processes of the session ``session`` (Linux /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[0] != "Z" and int(fields[3]) == session:
            found.append(int(entry.name))
    return found


def descendants(pid: int) -> set[int]:
    """Every live process below ``pid`` (Linux /proc)."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[0] != "Z":
            children.setdefault(int(fields[1]), []).append(int(entry.name))
    found, todo = set(), [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            if child not in found:
                found.add(child)
                todo.append(child)
    return found
