"""``raytun3r fleet`` against real processes: a driver killed with SIGKILL and started again, and
a two-node Ray cluster on this machine's loopback (a head with its Ray Client server and a second
``ray start --address``, token authentication on) joined with ``--address HOST:PORT``,
``ray://HOST:PORT`` and ``auto``. Each test stops only the processes it started."""

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
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from raytun3r_plugin.cluster import RAY_LOCAL_ONLY_VARIABLE
from tests.fleet_helpers import (
    fleet_command,
    kill_session,
    render_segment,
    same_tensors,
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


@dataclass
class LoopbackCluster:
    """A head and a second node started with ``ray start`` on 127.0.0.1, one CPU each, with a
    token of their own (``env``: the environment of every process that joins it)."""

    port: int  # the head's GCS
    client_port: int  # the head's Ray Client server
    env: dict
    temp: Path  # Ray's temporary folder for both nodes (session folders, logs, sockets)
    nodes: list = field(default_factory=list)

    def logs(self) -> list[Path]:
        # session_latest is a link to the newest of them
        return sorted(p for p in self.temp.glob("session_*/logs") if not p.parent.is_symlink())

    def node_ids(self) -> set[str]:
        """The ids of the cluster's nodes, as their raylets logged them at start-up."""
        return {
            match
            for logs in self.logs()
            for log in logs.glob("raylet*.out")
            for match in re.findall(r"Setting node ID node_id=([0-9a-f]+)", log.read_text())
        }

    def processes(self) -> set[int]:
        return {pid for node in self.nodes for pid in session_processes(node.pid)}


@pytest.fixture(scope="module")
def loopback_cluster(tmp_path_factory):
    """The two-node cluster shared by the tests that join it. Stopped whatever happens: every
    process of the two ``ray start`` sessions is killed (not ``ray stop``, which stops every
    Ray on this machine, other tests' and other users' too) and its temporary folder removed."""
    temp = Path(tempfile.mkdtemp(prefix="r40-", dir="/tmp"))  # Ray's socket paths must be short
    folder = tmp_path_factory.mktemp("loopback-cluster")
    env = {
        **{
            k: v for k, v in os.environ.items() if k not in (RAY_LOCAL_ONLY_VARIABLE, "RAY_ADDRESS")
        },
        "OMP_NUM_THREADS": "1",
        "PYTHONPATH": str(ROOT),
        "RAY_AUTH_MODE": "token",
        "RAY_AUTH_TOKEN": secrets.token_hex(32),
    }
    cluster = LoopbackCluster(_free_port(), _free_port(), env, temp)
    common = ["--node-ip-address", "127.0.0.1", "--num-cpus", "1", "--temp-dir", str(temp)]
    # Ports Ray would otherwise take at fixed numbers (Ray Client 10001, the agent's 52365),
    # which another Ray on this machine may hold.
    head = ["--head", "--port", str(cluster.port), "--include-dashboard", "false", *common]
    head += ["--ray-client-server-port", str(cluster.client_port)]
    second = ["--address", f"127.0.0.1:{cluster.port}", *common]
    local_only = {**env, RAY_LOCAL_ONLY_VARIABLE: "0"}
    try:
        for args, node_env, wrapper, log in (
            (head, local_only, False, "head.log"),
            (second, env, True, "node.log"),
        ):
            args = [*args, "--dashboard-agent-listen-port", str(_free_port())]
            cluster.nodes.append(_ray_start(args, node_env, wrapper=wrapper, log=folder / log))
        yield cluster
    finally:
        for node in cluster.nodes:
            kill_session(node)
        # Ray's logs of both nodes stay with the test's folders, for a failure to be read.
        for logs in cluster.logs():
            shutil.copytree(logs, folder / "ray-logs" / logs.parent.name, dirs_exist_ok=True)
        shutil.rmtree(temp, ignore_errors=True)


@pytest.fixture(scope="module")
def in_process_run(tmp_path_factory):
    """The three cameras fitted in this process (``--workers 1``: no Ray), for comparison; on
    one thread (``--threads 1``), as a Ray task runs by default."""
    from raytun3r_plugin.apps.cli_fleet import run_fleet

    out = tmp_path_factory.mktemp("fleet-in-process") / "out"
    run_fleet(_manifest(out.parent / "in"), out, "adapt", workers=1, threads=1, progress=False)
    return out


def _adapt_on(cluster: LoopbackCluster, address: str, folder: Path, env: dict | None = None):
    """``raytun3r fleet adapt`` of the three cameras with ``--address address``; returns the
    output folder and the listening sockets of the cluster's processes just after the run."""
    manifest, out = _manifest(folder / "in"), folder / "out"
    run = subprocess.run(
        [sys.executable, "-m", "raytun3r_plugin.apps.cli", "fleet", "adapt", str(manifest)]
        + ["--out", str(out), "--address", address, "--no-progress"],
        env=cluster.env if env is None else env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    return out, _sockets_of(cluster.processes())


def _assert_same_fits(out: Path, reference: Path) -> None:
    """The same task folders, tables (but for the fit times) and bit-identical adapters."""
    names = sorted(p.name for p in (out / "tasks").iterdir())
    assert names == sorted(p.name for p in (reference / "tasks").iterdir())
    for name in names:
        assert same_tensors(
            out / "tasks" / name / "adapter.safetensors",
            reference / "tasks" / name / "adapter.safetensors",
        ), name

    def rows(folder: Path) -> list[dict]:
        table = csv.DictReader((folder / "adapters.csv").open())
        return sorted(({k: v for k, v in r.items() if k != "adapt_s"} for r in table), key=str)

    assert rows(out) == rows(reference)


def _results(out: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in (out / "tasks").glob("*/result.json")]


def test_a_two_node_loopback_cluster_runs_tasks_on_both_nodes(
    loopback_cluster, in_process_run, tmp_path
):
    """``fleet adapt --address 127.0.0.1:PORT`` (the head's GCS) runs the three cameras' fits on
    both nodes, fits as in this process, and nothing of the cluster listens beyond loopback."""
    out, sockets = _adapt_on(loopback_cluster, f"127.0.0.1:{loopback_cluster.port}", tmp_path)
    nodes = {r["node"] for r in _results(out)}
    assert len(_results(out)) == 3
    assert nodes == loopback_cluster.node_ids() and len(nodes) == 2  # both nodes ran tasks
    _assert_same_fits(out, in_process_run)
    assert sockets and not [s for s in sockets if "127.0.0.1" not in s], sockets


#: A Ray Client that connects once (one try, about 5 s) with the token of its environment, if
#: any; exit status 3 when refused, with the server's reason in its log on stderr.
CLIENT_PROBE = """
import logging, sys
from ray.util.client import ray as client
log = logging.getLogger("ray.util.client.worker")
log.setLevel(logging.DEBUG)
log.addHandler(logging.StreamHandler())
try:
    client.connect(sys.argv[1], connection_retries=1)
except ConnectionError:
    sys.exit(3)
"""


def test_ray_client_runs_the_fleet_on_the_cluster_it_names_and_refuses_a_client_without_token(
    loopback_cluster, in_process_run, tmp_path
):
    """``--address ray://127.0.0.1:PORT``: the driver works through the head's Ray Client server,
    the tasks run on the cluster's nodes and fit as in this process, and the client servers
    listen on loopback only. A client without the cluster's token is refused."""
    cluster = loopback_cluster

    def client_servers() -> list[Path]:
        # The proxy on client_port hands each client to a server process of its own, which
        # logs to ray_client_server_<its port>.out in the head's session.
        return [p for logs in cluster.logs() for p in logs.glob("ray_client_server_*.out")]

    assert not client_servers()
    out, sockets = _adapt_on(cluster, f"ray://127.0.0.1:{cluster.client_port}", tmp_path)
    # After the run, not beside it: the proxy starts a server per client from one port range,
    # and a refused client racing the fleet's driver for it failed the driver's start once in
    # a full-suite run.
    outsider = {k: v for k, v in cluster.env.items() if not k.startswith("RAY_AUTH_")}
    probe = subprocess.run(
        [sys.executable, "-c", CLIENT_PROBE, f"127.0.0.1:{cluster.client_port}"],
        env=outsider,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert probe.returncode == 3 and "Invalid or missing authentication token" in probe.stderr
    assert client_servers()  # the fleet's driver came through Ray Client
    assert len(_results(out)) == 3
    assert {r["node"] for r in _results(out)} <= cluster.node_ids()
    assert str(cluster.client_port) in [s.rsplit(":", 1)[1] for s in sockets], sockets
    assert not [s for s in sockets if "127.0.0.1" not in s], sockets
    _assert_same_fits(out, in_process_run)


def test_address_auto_is_the_cluster_ray_address_names(monkeypatch):
    """Resolved before ``ray.init``, so that a loopback cluster is joined on loopback."""
    from raytun3r_plugin.cluster import _cluster_address

    monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:6399")
    assert _cluster_address("auto") == "127.0.0.1:6399"
    assert _cluster_address("ray://10.0.0.7:10001") == "ray://10.0.0.7:10001"


class _RayThatFails:
    """``ray.init`` raising ``errors`` in turn, then connecting; records its calls."""

    def __init__(self, *errors: Exception):
        self.errors, self.inits, self.shutdowns = list(errors), 0, 0

    def init(self, **_):
        self.inits += 1
        if self.errors:
            raise self.errors.pop(0)

    def shutdown(self):
        self.shutdowns += 1


def test_a_ray_client_whose_server_failed_to_start_tries_again_then_says_why():
    """Ray Client's "Initialization failure from server" (the head's proxy lost the driver's
    server process) is tried again, warned about, and after the last try is a raytun3r error;
    a refused connection and a plain GCS address are not retried."""
    from raytun3r_plugin.cluster import CLIENT_TRIES, _join
    from raytun3r_plugin.errors import ClusterConnectionError

    lost = ConnectionAbortedError("Initialization failure from server: server failed")
    ray = _RayThatFails(lost, lost)
    with pytest.warns(RuntimeWarning, match="try 1 of 3") as warned:
        _join(ray, "ray://127.0.0.1:10001")
    assert (ray.inits, ray.shutdowns, len(warned)) == (3, 2, 2) and CLIENT_TRIES == 3

    ray = _RayThatFails(*[lost] * CLIENT_TRIES)
    with pytest.warns(RuntimeWarning), pytest.raises(ClusterConnectionError, match="3 times"):
        _join(ray, "ray://127.0.0.1:10001")
    assert ray.inits == CLIENT_TRIES

    ray = _RayThatFails(ConnectionError("Invalid or missing authentication token"))
    with pytest.raises(ConnectionError, match="token"):
        _join(ray, "ray://127.0.0.1:10001")
    assert ray.inits == 1
    ray = _RayThatFails(lost)
    with pytest.raises(ClusterConnectionError, match="127.0.0.1:6379"):
        _join(ray, "127.0.0.1:6379")
    assert ray.inits == 1


@pytest.mark.slow  # one more fleet run on the cluster: about 20 s here
def test_address_auto_joins_the_cluster_ray_address_names(
    loopback_cluster, in_process_run, tmp_path
):
    """``--address auto`` with ``RAY_ADDRESS=127.0.0.1:PORT`` (as ``ray start`` suggests): the
    tasks run on that cluster. Before the fix in ``raytun3r_plugin.cluster``, Ray looked for this
    loopback cluster at the machine's network address and waited for it forever."""
    cluster = loopback_cluster
    env = {**cluster.env, "RAY_ADDRESS": f"127.0.0.1:{cluster.port}"}
    out, _ = _adapt_on(cluster, "auto", tmp_path, env=env)
    assert len(_results(out)) == 3
    assert {r["node"] for r in _results(out)} <= cluster.node_ids()
    _assert_same_fits(out, in_process_run)


def _sockets_of(pids: set[int]) -> list[str]:
    if shutil.which("ss") is None:
        pytest.skip("ss (iproute2) is not installed: scripts/install.sh installs it")
    listening = subprocess.run(["ss", "-ltnpH"], capture_output=True, text=True, check=True)
    return [
        line.split()[3]
        for line in listening.stdout.splitlines()
        if {int(p) for p in re.findall(r"pid=(\d+)", line)} & pids
    ]
