"""``raytun3r fleet`` against real processes: a driver killed with SIGKILL and started again, and
a two-node Ray cluster on this machine's loopback (a head and a second ``ray start --address``)
joined with ``--address``. Each test stops only the processes it started."""

from __future__ import annotations

import csv
import json
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from tests.fleet_helpers import (
    fleet_command,
    kill_session,
    render_segment,
    session_processes,
    wait_for,
    write_manifest,
)

pytest.importorskip("depth_anything_3")
pytest.importorskip("ray")
ROOT = Path(__file__).parent.parent
CAMERAS = {
    "cam1": (84, 190.0, "kb4"),
    "cam2": (84, 195.0, "ds"),
    "cam3": (84, 185.0, "kb4"),
}


def _manifest(folder: Path) -> Path:
    return write_manifest(
        folder,
        CAMERAS,
        [render_segment(f"{name}-a", name, 91020 + k) for k, name in enumerate(CAMERAS)],
    )


@pytest.mark.slow  # two fleet runs and a Ray start-up: about 100 s here
def test_a_killed_driver_stops_its_ray_work_and_its_restart_skips_finished_tasks(tmp_path):
    manifest, out = _manifest(tmp_path / "in"), tmp_path / "out"
    driver = fleet_command(["adapt", str(manifest), "--out", str(out), "--workers", "2"])
    try:
        published = wait_for(
            lambda: list((out / "tasks").glob("*/result.json")) if (out / "tasks").is_dir() else [],
            240,
            "a first finished task",
        )
        os.kill(driver.pid, signal.SIGKILL)  # the driver alone: Ray's processes must follow it
        driver.wait()
        try:
            # The GCS, the raylet and the workers (mid-fit) end with it; Ray's two idle agents
            # end by themselves about a minute later (seen: 60-90 s), which kill_session cuts short.
            wait_for(lambda: not _working(session_processes(driver.pid)), 30, "Ray's processes")
        finally:
            kill_session(driver)  # whatever is left, so no test leaves processes behind
    except BaseException:
        kill_session(driver)
        raise
    finished_before = {p.parent.name for p in published}
    assert not (out / "adapters.csv").exists()  # the killed run never reached its table
    restart = subprocess.run(
        [sys.executable, "-m", "raytun3r_plugin.apps.cli", "fleet", "adapt", str(manifest)]
        + ["--out", str(out), "--workers", "1", "--no-progress"],
        env={**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert restart.returncode == 0, restart.stderr
    skipped = int(re.search(r"(\d+) already finished", restart.stdout).group(1))
    assert skipped >= len(finished_before) >= 1
    rows = list(csv.DictReader((out / "adapters.csv").open()))
    assert sorted(r["camera"] for r in rows) == sorted(CAMERAS)
    for name in finished_before:  # the finished tasks were not run again
        result = json.loads((out / "tasks" / name / "result.json").read_text())
        assert result["attempts"] == 1 and result["pid"] != 0
    assert not [p for p in (out / "tasks").iterdir() if ".partial-" in p.name]


#: Ray's per-node agents: idle, on loopback, and outliving a killed driver by about a minute.
AGENTS = ("ray::DashboardAgent", "ray::RuntimeEnvAgent")


def _working(pids: list[int]) -> list[str]:
    """The command lines of ``pids`` other than Ray's agents."""
    lines = []
    for pid in pids:
        try:
            line = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if not line.startswith(AGENTS):
            lines.append(line)
    return lines


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _ray_start(args: list[str], env: dict, wrapper: bool, log: Path) -> subprocess.Popen:
    """``ray start ... --block`` in a session of its own (stopped by :func:`kill_session`),
    returned once its node has joined (``ray start`` says so when the node is registered)."""
    command = (
        [sys.executable, str(ROOT / "tests" / "ray_start_loopback.py")]
        if wrapper
        else [shutil.which("ray") or "ray"]
    )
    with open(log, "w") as output:
        node = subprocess.Popen(
            [*command, "start", *args, "--block"],
            env=env,
            stdout=output,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    try:
        wait_for(lambda: "Ray runtime started" in log.read_text(), 120, f"ray start ({log.name})")
    except AssertionError:
        kill_session(node)
        raise AssertionError(log.read_text()[-2000:]) from None
    return node


def test_a_two_node_loopback_cluster_runs_tasks_on_both_nodes(tmp_path):
    """Head and second node on 127.0.0.1 with one CPU each and a token of their own; ``fleet
    adapt --address`` runs the three cameras' fits on both, and nothing listens beyond loopback."""
    temp = Path(tempfile.mkdtemp(prefix="r40-", dir="/tmp"))  # Ray's socket paths must be short
    port = _free_port()
    env = {
        **{k: v for k, v in os.environ.items() if k != "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"},
        "OMP_NUM_THREADS": "1",
        "PYTHONPATH": str(ROOT),
        "RAY_AUTH_MODE": "token",
        "RAY_AUTH_TOKEN": secrets.token_hex(32),
    }
    common = ["--node-ip-address", "127.0.0.1", "--num-cpus", "1", "--temp-dir", str(temp)]
    # Ports Ray would otherwise take at fixed numbers (Ray Client 10001, the agent's 52365),
    # which another Ray on this machine may hold.
    head = ["--head", "--port", str(port), "--include-dashboard", "false", *common]
    head += ["--ray-client-server-port", str(_free_port())]
    second = ["--address", f"127.0.0.1:{port}", *common]
    local_only = {**env, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
    nodes = []
    try:
        for args, node_env, wrapper, log in (
            (head, local_only, False, "head.log"),
            (second, env, True, "node.log"),
        ):
            args = [*args, "--dashboard-agent-listen-port", str(_free_port())]
            nodes.append(_ray_start(args, node_env, wrapper=wrapper, log=tmp_path / log))
        manifest, out = _manifest(tmp_path / "in"), tmp_path / "out"
        run = subprocess.run(
            [sys.executable, "-m", "raytun3r_plugin.apps.cli", "fleet", "adapt", str(manifest)]
            + ["--out", str(out), "--address", f"127.0.0.1:{port}", "--no-progress"],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert run.returncode == 0, run.stderr
        sockets = _sockets_of({pid for node in nodes for pid in session_processes(node.pid)})
    finally:
        for node in nodes:
            kill_session(node)
        shutil.rmtree(temp, ignore_errors=True)
    results = [json.loads(p.read_text()) for p in (out / "tasks").glob("*/result.json")]
    assert len(results) == 3
    assert len({r["node"] for r in results}) == 2, results  # both nodes ran tasks
    assert sockets and not [s for s in sockets if "127.0.0.1" not in s], sockets


def _sockets_of(pids: set[int]) -> list[str]:
    if shutil.which("ss") is None:
        pytest.skip("ss (iproute2) is not installed: scripts/install.sh installs it")
    listening = subprocess.run(["ss", "-ltnpH"], capture_output=True, text=True, check=True)
    return [
        line.split()[3]
        for line in listening.stdout.splitlines()
        if {int(p) for p in re.findall(r"pid=(\d+)", line)} & pids
    ]
