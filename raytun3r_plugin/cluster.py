"""Independent tasks on a Ray cluster, or in this process: the one executor of the fleet and
dataset commands and of the benchmarks (docs/fleet.md).

A task is ``function(state, *arguments)``: ``state`` is what ``initializer(*initargs)`` returned
in the process that runs it, built once per worker process (the network, loaded once), and
``initargs`` travel once through Ray's object store, not once per task. ``function`` and
``initializer`` must be module-level functions (workers import them by name).

* :class:`ClusterSpec` ``address=None`` and one worker: everything runs here, in task order, with
  no Ray at all (the plain path).
* ``address=None`` and several workers: an embedded Ray cluster on this machine, started for the
  run and stopped after it, kept to the loopback interface and to a token of its own
  (:func:`connected`).
* ``address="auto"``, ``"HOST:PORT"`` or ``"ray://HOST:PORT"``: join that cluster (its own
  authentication settings come from the environment: ``RAY_AUTH_MODE``, ``RAY_AUTH_TOKEN``).

Each task asks for one GPU where the cluster has any (and ``threads`` CPUs), else for ``threads``
CPUs, and pins its intra-op threads to that count. A task whose worker process dies (SIGKILL,
out of memory, a lost node) is run again, up to ``max_retries`` times; a task that raises is not
retried: its error is returned as the outcome's ``error``, and the other tasks go on.
"""

from __future__ import annotations

import os
import secrets
import sys
import warnings
from collections.abc import Callable, Generator, Iterator, Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from typing import Any

from raytun3r_plugin.errors import (
    ClusterConnectionError,
    InputError,
    MissingDependencyError,
    TaskError,
)
from raytun3r_plugin.threads import torch_threads

__all__ = [
    "ClusterSpec",
    "TaskOutcome",
    "connected",
    "map_tasks",
    "node_of_this_process",
    "run_tasks",
]

#: The address every embedded cluster uses: Ray binds its servers to all interfaces unless its
#: node address is exactly this one.
LOOPBACK = "127.0.0.1"
#: Ray's switch that stops it from turning 127.0.0.1 into the machine's network address
#: (``ray._private.services.resolve_ip_for_localhost``); read when ``ray`` is imported.
RAY_LOCAL_ONLY_VARIABLE = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


@dataclass(frozen=True)
class ClusterSpec:
    """Where and how tasks run.

    address: None (this machine: in this process with one worker, else an embedded Ray
        cluster), ``"auto"`` (the cluster ``RAY_ADDRESS`` names, else the one ``ray start
        --head`` made here), ``"HOST:PORT"`` or ``"ray://HOST:PORT"`` (Ray Client).
    workers: tasks at once on the embedded cluster (its CPU count); ignored when joining.
    threads: CPU threads per task: its CPU request on Ray and ``torch.set_num_threads`` while
        it runs, in this process too. None: one on Ray; in this process, torch's setting as
        it is.
    gpus: one GPU per task; None: where the cluster has GPUs.
    max_retries: reruns of a task whose worker process died.
    """

    address: str | None = None
    workers: int = 1
    threads: int | None = None
    gpus: bool | None = None
    max_retries: int = 3

    def __post_init__(self) -> None:
        for name in ("workers", "threads"):
            value = getattr(self, name)
            if name == "threads" and value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise InputError(f"{name} must be a positive integer, got {value!r}")
        if self.max_retries < 0:
            raise InputError(f"max_retries must be at least 0, got {self.max_retries}")
        if self.address is not None and not self.address.strip():
            raise InputError("address must be 'auto', HOST:PORT or ray://HOST:PORT, got ''")

    @property
    def task_threads(self) -> int:
        """CPU threads a task asks for on Ray."""
        return 1 if self.threads is None else self.threads

    @property
    def in_process(self) -> bool:
        """True when the tasks run in this process, without Ray."""
        return self.address is None and self.workers == 1


@dataclass
class TaskOutcome:
    """What became of task ``index``: ``value`` (what ``function`` returned) or ``error``
    (``"ErrorType: message"``), and where it ran (``node``: Ray node id, or ``"local"``;
    ``pid``: the worker process)."""

    index: int
    value: Any = None
    error: str | None = None
    node: str = "local"
    pid: int = 0

    @property
    def ok(self) -> bool:
        return self.error is None


def _import_ray():
    try:
        import ray
    except ImportError as error:
        raise MissingDependencyError(
            "running tasks on Ray needs the 'cluster' extra: pip install 'raytun3r[cluster]' "
            "(or run them in this process: --workers 1, jobs=1)"
        ) from error
    return ray


def _embedded_environment() -> None:
    """Token authentication on, with a token of this process's own, for the embedded cluster and
    the processes it starts. Set in this process's environment for its lifetime, so that every cluster this process
    starts and every process those start see the same token, which Ray reads once. A token the
    caller set (``RAY_AUTH_TOKEN``) is kept. Nothing is written to ``~/.ray``."""
    os.environ.setdefault("RAY_AUTH_TOKEN", secrets.token_hex(32))
    os.environ["RAY_AUTH_MODE"] = "token"
    if "ray" in sys.modules:
        # Ray reads its settings once; this is how ray.init itself re-reads them after turning
        # token mode on (ray._private.authentication.authentication_token_setup).
        from ray._raylet import Config  # type: ignore[attr-defined]

        Config.initialize("")


@contextmanager
def _local_only(ray) -> Iterator[None]:
    """Keep 127.0.0.1 as the node address while Ray starts: :data:`RAY_LOCAL_ONLY_VARIABLE` in
    the environment of the processes it starts then (they pass it on to theirs), and its module
    constant in this one (read when ``ray`` was imported). Both are restored afterwards, so a
    later ``ray start --address`` from this process is not refused."""
    from ray._private import ray_constants

    saved = ray_constants.ENABLE_RAY_CLUSTER, os.environ.get(RAY_LOCAL_ONLY_VARIABLE)
    ray_constants.ENABLE_RAY_CLUSTER = False
    os.environ[RAY_LOCAL_ONLY_VARIABLE] = "0"
    try:
        yield
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = saved[0]
        if saved[1] is None:
            os.environ.pop(RAY_LOCAL_ONLY_VARIABLE, None)
        else:
            os.environ[RAY_LOCAL_ONLY_VARIABLE] = saved[1]


@contextmanager
def connected(spec: ClusterSpec) -> Iterator[Any]:
    """Ray, connected as ``spec`` says, for the duration of the block; yields the ``ray`` module.

    A connection made before (``ray.init`` by the caller, or an outer :func:`connected`) is used
    as it is and left open. An embedded cluster listens on 127.0.0.1 only and requires the token
    of this process (``RAY_AUTH_MODE=token``, ``RAY_AUTH_TOKEN`` in its environment, never
    written to ``~/.ray``); it is stopped on leaving the block. Joining a cluster on 127.0.0.1
    keeps that address too; any other cluster's token comes from the caller's environment.
    """
    if spec.address is None and not _ray_connected():
        _embedded_environment()
    ray = _import_ray()
    if ray.is_initialized():
        yield ray
        return
    if spec.address is not None:
        address = _cluster_address(spec.address)
        host = address.split("://")[-1].rsplit(":", 1)[0]
        # A cluster on this machine's loopback (tests, a laptop): Ray would otherwise look for it
        # at the machine's network address (see RAY_LOCAL_ONLY_VARIABLE).
        local = _local_only(ray) if host in (LOOPBACK, "localhost") else nullcontext()
        with local:
            _join(ray, address)
        try:
            yield ray
        finally:
            ray.shutdown()
        return
    with _local_only(ray):
        ray.init(
            address="local",
            num_cpus=spec.workers * spec.task_threads,
            include_dashboard=False,
            _node_ip_address=LOOPBACK,
            log_to_driver=False,
            configure_logging=False,
        )
    try:
        yield ray
    finally:
        ray.shutdown()


#: Tries of a Ray Client connection whose server side failed to start (see :func:`_join`).
CLIENT_TRIES = 3


def _join(ray, address: str) -> None:
    """``ray.init(address)``. Through Ray Client (``ray://``), a connection the head's client
    server accepted but could not start a per-client server for ("Initialization failure from
    server", ``ConnectionAbortedError``) is tried again, up to :data:`CLIENT_TRIES` times: on a
    busy head, Ray 2.60's proxy at times sees that server's process gone milliseconds after
    starting it, with nothing in its log (docs/fleet.md), and the next one starts. A refused
    token or an unreachable address is not retried."""
    tries = CLIENT_TRIES if address.startswith("ray://") else 1
    for attempt in range(1, tries + 1):
        try:
            ray.init(address=address, log_to_driver=False, configure_logging=False)
            return
        except ConnectionAbortedError as error:
            ray.shutdown()
            if attempt == tries:
                raise ClusterConnectionError(
                    f"{address}: the cluster's Ray Client server failed to start a server for "
                    f"this driver {tries} times; last reason: {error}"
                ) from error
            warnings.warn(
                f"{address}: Ray Client server failed to start (try {attempt} of {tries}); "
                "trying again",
                RuntimeWarning,
                stacklevel=2,
            )


def _cluster_address(address: str) -> str:
    """``address``, with ``"auto"`` replaced by the cluster it stands for, found as Ray finds it
    (``RAY_ADDRESS``; else the cluster the last ``ray start --head`` here recorded; else any Ray
    running here). Resolved before ``ray.init`` so that a cluster on loopback is seen to be one:
    given ``"auto"``, Ray looked for a loopback cluster at the machine's network address and
    waited for it forever."""
    if address != "auto":
        return address
    from ray._private.services import get_ray_address_from_environment

    try:
        return get_ray_address_from_environment("auto", None)
    except ConnectionError as error:  # no cluster found: the caller's address is wrong
        raise InputError(f"address 'auto': {error}") from error


def _ray_connected() -> bool:
    ray = sys.modules.get("ray")
    return ray is not None and ray.is_initialized()


def node_of_this_process() -> str:
    """The Ray node id of this process, or ``"local"`` outside a Ray worker."""
    if not _ray_connected():
        return "local"
    return sys.modules["ray"].get_runtime_context().get_node_id()


#: Per worker process: (key of the state's object, the state built from it).
_STATE: dict[str, Any] = {}


def _state_in_worker(key: str, initializer: Callable[..., Any] | None, boxed: list) -> Any:
    """The state for ``key``, built once per worker process; ``boxed`` holds the object ref of
    ``initargs`` in a list, so Ray hands the ref over instead of fetching it for every task."""
    if key not in _STATE:
        import ray

        _STATE.clear()  # one state at a time: a worker of a new run drops the last run's network
        initargs = ray.get(boxed[0])
        _STATE[key] = None if initializer is None else initializer(*initargs)
    return _STATE[key]


def _call_in_worker(
    function: Callable[..., Any],
    initializer: Callable[..., Any] | None,
    key: str,
    boxed: list,
    arguments: tuple,
    threads: int,
) -> tuple[Any, str | None, str, int]:
    """Run one task in a Ray worker: (value, error, node id, pid). A task's exception is returned
    as its error text, not raised: Ray would wrap it, and it must not be retried."""
    import torch

    from raytun3r_plugin.registry import quiet_upstream

    torch.set_num_threads(threads)
    node, pid = node_of_this_process(), os.getpid()
    try:
        with quiet_upstream():
            state = _state_in_worker(key, initializer, boxed)
            return function(state, *arguments), None, node, pid
    except Exception as error:  # every task error is reported, none stops the others
        return None, f"{type(error).__name__}: {error}", node, pid


def _run_in_process(
    function: Callable[..., Any],
    tasks: Sequence[tuple],
    initializer: Callable[..., Any] | None,
    initargs: tuple,
    threads: int | None,
) -> Iterator[TaskOutcome]:
    state = None if initializer is None else initializer(*initargs)
    for index, arguments in enumerate(tasks):
        try:
            # per task, not around the loop: the caller runs between tasks on its own setting
            with torch_threads(threads):
                value = function(state, *arguments)
        except Exception as error:  # reported per task, as on Ray
            yield TaskOutcome(index, error=f"{type(error).__name__}: {error}", pid=os.getpid())
            continue
        yield TaskOutcome(index, value=value, pid=os.getpid())


def _resources(ray, spec: ClusterSpec) -> dict[str, float]:
    gpus = spec.gpus
    if gpus is None:
        gpus = ray.cluster_resources().get("GPU", 0) > 0
    return {"num_cpus": spec.task_threads, "num_gpus": 1 if gpus else 0}


def run_tasks(
    function: Callable[..., Any],
    tasks: Sequence[tuple],
    spec: ClusterSpec | None = None,
    *,
    initializer: Callable[..., Any] | None = None,
    initargs: tuple = (),
    progress: str | None = None,
) -> Generator[TaskOutcome, None, None]:
    """One :class:`TaskOutcome` per task, in the order they finish (task order in process).

    ``function(state, *task)`` runs every task, ``state = initializer(*initargs)`` once per
    worker process. ``progress``: a label for a progress bar over the tasks on stderr (None:
    none). Worker deaths beyond ``spec.max_retries`` end as an outcome with an error; the
    iteration itself raises only for the driver's own problems (Ray missing, no cluster at
    ``spec.address``).
    """
    spec = spec or ClusterSpec()
    tasks = list(tasks)
    bar = None
    if progress is not None and tasks:
        from tqdm import tqdm

        bar = tqdm(total=len(tasks), desc=progress, unit="task", file=sys.stderr)
    try:
        if spec.in_process:
            outcomes = _run_in_process(function, tasks, initializer, initargs, spec.threads)
        else:
            outcomes = _run_on_ray(function, tasks, spec, initializer, initargs)
        for outcome in outcomes:
            if bar is not None:
                bar.update(1)
            yield outcome
    finally:
        if bar is not None:
            bar.close()


def _run_on_ray(
    function: Callable[..., Any],
    tasks: list[tuple],
    spec: ClusterSpec,
    initializer: Callable[..., Any] | None,
    initargs: tuple,
) -> Iterator[TaskOutcome]:
    if not tasks:
        return
    with connected(spec) as ray:
        boxed = [ray.put(initargs)]  # once, into the object store
        key = boxed[0].hex()
        remote = ray.remote(_call_in_worker).options(
            max_retries=spec.max_retries, retry_exceptions=False, **_resources(ray, spec)
        )
        pending = {
            remote.remote(
                function, initializer, key, boxed, tuple(arguments), spec.task_threads
            ): index
            for index, arguments in enumerate(tasks)
        }
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for reference in done:
                    index = pending.pop(reference)
                    try:
                        value, error, node, pid = ray.get(reference)
                    except ray.exceptions.RayError as failure:  # its worker died too often
                        first_line = str(failure).strip().splitlines()[0] if str(failure) else ""
                        yield TaskOutcome(index, error=f"{type(failure).__name__}: {first_line}")
                        continue
                    yield TaskOutcome(index, value=value, error=error, node=node, pid=pid)
        finally:
            for reference in pending:  # the driver stopped early: nothing keeps running
                ray.cancel(reference, force=True)


def map_tasks(
    function: Callable[..., Any],
    tasks: Sequence[tuple],
    spec: ClusterSpec | None = None,
    *,
    initializer: Callable[..., Any] | None = None,
    initargs: tuple = (),
) -> Iterator[tuple[int, Any]]:
    """``(index, function(state, *task))`` for every task, in the order they finish, for loops
    that need every result (the benchmark, the experiments): the first task that fails stops
    the rest. In this process (one worker) its exception is raised as it is; from Ray, as
    :class:`TaskError` naming its index and error."""
    spec = spec or ClusterSpec()
    if spec.in_process:
        state = None if initializer is None else initializer(*initargs)
        for index, arguments in enumerate(tasks):
            yield index, function(state, *arguments)
        return
    outcomes = run_tasks(function, tasks, spec, initializer=initializer, initargs=initargs)
    try:
        for outcome in outcomes:
            if not outcome.ok:
                raise TaskError(f"task {outcome.index} failed: {outcome.error}")
            yield outcome.index, outcome.value
    finally:
        outcomes.close()  # on Ray: cancels the tasks still pending
