"""``apps.workers.map_in_workers``: independent jobs in one-thread spawned worker processes."""

from __future__ import annotations

import os
import sys

import pytest

from raytun3r_plugin.apps.workers import map_in_workers
from raytun3r_plugin.errors import InputError


def _offset(value: int) -> dict:
    return {"offset": value}


def _job(state: dict, x: int) -> tuple:
    import torch

    if x < 0:
        raise InputError(f"job refused {x}")
    return x + state["offset"], os.getpid(), torch.get_num_threads()


def test_workers_return_every_job_with_its_index_state_and_one_thread():
    results = dict(
        map_in_workers(_job, [(x,) for x in range(5)], 2, initializer=_offset, initargs=(100,))
    )
    assert sorted(results) == [0, 1, 2, 3, 4]
    assert [results[i][0] for i in range(5)] == [100, 101, 102, 103, 104]
    assert all(pid != os.getpid() for _, pid, _ in results.values())
    assert {threads for _, _, threads in results.values()} == {1}


def test_a_failing_job_is_raised_in_the_caller_with_its_message():
    with pytest.raises(InputError, match="job refused -3"):
        list(map_in_workers(_job, [(1,), (-3,), (2,)], 2, initializer=_offset, initargs=(0,)))


def test_one_job_runs_in_this_process_in_order():
    results = list(map_in_workers(_job, [(2,), (1,)], 1, initializer=_offset, initargs=(10,)))
    assert [(index, value) for index, (value, _, _) in results] == [(0, 12), (1, 11)]
    assert {pid for _, (_, pid, _) in results} == {os.getpid()}


ORPHAN_SCRIPT = """
import os, sys, time
from raytun3r_plugin.apps.workers import map_in_workers

def job(state, folder):
    open(os.path.join(folder, str(os.getpid())), "w").close()
    time.sleep(120)

if __name__ == "__main__":
    for _ in map_in_workers(job, [(sys.argv[1],), (sys.argv[1],)], 2):
        pass
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_end_when_their_parent_is_killed(tmp_path):
    """A parent killed without cleanup (SIGKILL) leaves no worker running its job to the end."""
    import signal
    import subprocess
    import time

    script = tmp_path / "orphans.py"
    script.write_text(ORPHAN_SCRIPT)
    folder = tmp_path / "pids"
    folder.mkdir()
    parent = subprocess.Popen([sys.executable, str(script), str(folder)])
    try:
        deadline = time.monotonic() + 120
        while len(list(folder.iterdir())) < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
        workers = [int(path.name) for path in folder.iterdir()]
        assert len(workers) == 2
    finally:
        parent.send_signal(signal.SIGKILL)
        parent.wait()

    def alive(pid: int) -> bool:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        # A zombie waiting for its reaper has ended its job: look at its state.
        try:
            with open(f"/proc/{pid}/stat") as stat:
                return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
        except FileNotFoundError:
            return False

    deadline = time.monotonic() + 10
    while any(alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(alive(pid) for pid in workers)
