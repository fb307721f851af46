"""``apps.workers.map_in_workers``: independent jobs in one-thread spawned worker processes."""

from __future__ import annotations

import os

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
