"""Independent jobs of ``raytun3r demo`` in one-thread worker processes.

Kept for the demo only; everything else that loops over independent tasks (``raytun3r bench``,
``raytun3r fleet``, the experiments) runs them with :mod:`raytun3r_plugin.cluster` (Ray). The
demo is the first command a user runs, on the core install: Ray is an optional extra, and its
start-up (``ray.init``, 6-12 s here) would add a fifth to a demo that takes about a minute on
two cores (benchmarks/fleet_scaling.py measures the start-up; docs/fleet.md).

The built-in network is small (112 px, a few hundred tokens per frame): its operators are too
short for a second intra-op thread to pay much, while a second process scoring another sequence
uses the core fully (docs/results.md, "The demo", has the timings). Only the applications use this; the
library's ``adapt`` never starts processes behind its caller's back.

* Workers start with ``spawn``, not ``fork``: a forked child of a process whose OpenMP pool has
  already run can hang.
* Each worker runs one intra-op thread and holds upstream logging back for its whole life, as
  the command line does in its own process.
* Ctrl-C reaches only the parent (the workers ignore SIGINT); leaving :func:`map_in_workers`
  terminates the pool, so nothing keeps fitting after the command has stopped.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from typing import Any

#: Per worker process: the context holding upstream logging back (kept referenced: a collected
#: generator context would exit) and what the caller's initializer returned.
_CONTEXT = None
_STATE: Any = None


def cpu_jobs(count: int) -> int:
    """Worker processes for ``count`` independent jobs: one per CPU this process may run on, at
    most one per job, at least one."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    return max(1, min(count, cpus))


def _start(initializer: Callable[..., Any] | None, initargs: tuple) -> None:
    import contextlib
    import signal

    import torch

    from raytun3r_plugin.registry import quiet_upstream

    global _CONTEXT, _STATE
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops the pool
    _exit_with_parent()
    torch.set_num_threads(1)
    _CONTEXT = contextlib.ExitStack()
    _CONTEXT.enter_context(quiet_upstream())
    _STATE = None if initializer is None else initializer(*initargs)


def _exit_with_parent(poll_s: float = 0.5) -> None:
    """End this worker once its parent is gone. A parent killed by SIGTERM or SIGKILL never
    terminates its pool, and its workers would otherwise run their jobs to the end on CPUs that
    the next run needs (seen: two orphans halving a benchmark's speed for 9 minutes)."""
    import os
    import threading
    import time

    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        os._exit(1)

    threading.Thread(target=watch, name="raytun3r-exit-with-parent", daemon=True).start()


def _call(job: tuple[int, Callable[..., Any], tuple]) -> tuple[int, Any]:
    index, function, args = job
    return index, function(_STATE, *args)


def map_in_workers(
    function: Callable[..., Any],
    tasks: Iterable[tuple],
    jobs: int,
    *,
    initializer: Callable[..., Any] | None = None,
    initargs: tuple = (),
) -> Iterator[tuple[int, Any]]:
    """``(index, function(state, *task))`` for every task, in the order they finish.

    ``state`` is what ``initializer(*initargs)`` returned in that worker (the network, loaded or
    unpickled once per process); ``function`` and ``initializer`` must be module-level functions
    (spawned workers import them). With ``jobs == 1`` everything runs in this process, with its
    threads, in task order. A job's exception is raised here and stops the rest."""
    tasks = list(tasks)
    if jobs <= 1:
        state = None if initializer is None else initializer(*initargs)
        for index, task in enumerate(tasks):
            yield index, function(state, *task)
        return
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    with context.Pool(
        min(jobs, len(tasks)), initializer=_start, initargs=(initializer, initargs)
    ) as pool:
        yield from pool.imap_unordered(
            _call, [(index, function, task) for index, task in enumerate(tasks)]
        )
