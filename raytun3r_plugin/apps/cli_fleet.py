"""``raytun3r fleet adapt`` and ``raytun3r fleet eval``: a manifest's tasks on Ray (embedded by
default, or a cluster with ``--address``), resumable (docs/fleet.md). The work of one task and the
tables are :mod:`raytun3r_plugin.apps.fleet`; the manifest, :mod:`.fleet_manifest`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from raytun3r_plugin.errors import InputError


def run_fleet(
    manifest_path: str | Path,
    out: str | Path,
    kind: str,
    *,
    address: str | None = None,
    workers: int | None = None,
    threads: int | None = None,
    gpus: bool | None = None,
    max_retries: int = 3,
    progress: bool = True,
) -> dict:
    """Check the manifest, run the tasks not yet finished under ``out`` and write the tables.

    Returns ``{"tasks", "skipped", "ran", "failed": [{"task", "error"}], "rows"}``. Raises
    :class:`InputError` (listing every problem) before any task starts when the manifest or a
    file it names is wrong.
    """
    from raytun3r_plugin.apps.fleet import (
        build_tables,
        finished,
        load_network,
        plan_tasks,
        remove_partial,
        run_fleet_task,
    )
    from raytun3r_plugin.apps.fleet_manifest import read_manifest
    from raytun3r_plugin.apps.workers import cpu_jobs
    from raytun3r_plugin.atomic_files import atomic_write_text
    from raytun3r_plugin.cluster import ClusterSpec, run_tasks

    if kind not in ("adapt", "eval"):
        raise InputError(f"fleet: expected 'adapt' or 'eval', got {kind!r}")
    manifest = read_manifest(manifest_path, for_eval=kind == "eval")
    out = Path(out)
    tasks = plan_tasks(manifest, kind)
    out.mkdir(parents=True, exist_ok=True)
    remove_partial(out)
    todo = [task for task in tasks if finished(out, task) is None]
    spec = ClusterSpec(
        address=address,
        workers=workers or cpu_jobs(len(todo)),
        threads=threads,
        gpus=gpus,
        max_retries=max_retries,
    )
    weights = tasks[0].record["weights"] if tasks else None
    # Through the object store once when the tasks run on Ray; read in place in this process.
    blob = None if weights is None or spec.in_process else Path(weights["path"]).read_bytes()
    failed = []
    for outcome in run_tasks(
        run_fleet_task,
        [(t.record, t.key, t.folder, str(out.resolve())) for t in todo],
        spec,
        initializer=load_network,
        initargs=(manifest.backbone, weights, blob),
        progress=f"fleet {kind}" if progress else None,
    ):
        if not outcome.ok:
            failed.append({"task": todo[outcome.index].name, "error": outcome.error})
    remove_partial(out)
    rows = build_tables(out, kind, tasks, manifest)
    atomic_write_text(out / "failures.json", json.dumps(failed, indent=2) + "\n")
    return {
        "tasks": len(tasks),
        "skipped": len(tasks) - len(todo),
        "ran": len(todo) - len(failed),
        "failed": failed,
        "rows": rows,
    }


def cmd_fleet(args: argparse.Namespace) -> int:
    report = run_fleet(
        args.manifest,
        args.out,
        args.fleet_command,
        address=args.address,
        workers=args.workers,
        threads=args.threads,
        gpus=args.gpus,
        max_retries=args.max_retries,
        progress=not args.no_progress,
    )
    table = "adapters" if args.fleet_command == "adapt" else "results"
    print(
        f"{report['tasks']} tasks: {report['skipped']} already finished (skipped), "
        f"{report['ran']} run now, {len(report['failed'])} failed; "
        f"tables: {Path(args.out) / table}.csv and .md"
    )
    print((Path(args.out) / f"{table}.md").read_text())
    if report["failed"]:
        print(f"raytun3r: {len(report['failed'])} task(s) failed:", file=sys.stderr)
        for failure in report["failed"]:
            print(f"  {failure['task']}: {failure['error']}", file=sys.stderr)
        return 1
    return 0


def _gpus(text: str) -> bool | None:
    choices = {"auto": None, "yes": True, "no": False}
    if text not in choices:
        raise argparse.ArgumentTypeError(f"expected auto, yes or no, got {text!r}")
    return choices[text]


def add_fleet_commands(sub) -> None:
    """Register ``raytun3r fleet adapt|eval`` on the top-level sub-parsers ``sub``."""
    fleet = sub.add_parser(
        "fleet",
        help="fit one adapter per camera, or score sequences x methods, as Ray tasks (docs/fleet.md)",
    )
    commands = fleet.add_subparsers(dest="fleet_command", required=True)
    for name, text in (
        ("adapt", "fit one adapter per camera of the manifest from its segments"),
        ("eval", "score every sequence of the manifest with its methods; table of cell means"),
    ):
        p = commands.add_parser(name, help=text)
        p.add_argument("manifest", help="fleet manifest (YAML; docs/fleet.md)")
        p.add_argument("--out", required=True, help="output folder; a rerun skips finished tasks")
        p.add_argument(
            "--address",
            default=None,
            help="join this Ray cluster: 'auto' (started here by `ray start`), HOST:PORT or "
            "ray://HOST:PORT; default: an embedded cluster on this machine (loopback only)",
        )
        p.add_argument(
            "--workers",
            type=int,
            default=None,
            help="tasks at once on the embedded cluster (default: one per CPU, at most one per "
            "task; 1 = in this process, without Ray)",
        )
        p.add_argument(
            "--threads",
            type=int,
            default=None,
            help="CPU threads per task (default: 1 on Ray; with --workers 1, torch's own)",
        )
        p.add_argument(
            "--gpus",
            type=_gpus,
            default=None,
            metavar="auto|yes|no",
            help="one GPU per task (default auto: where the cluster has GPUs)",
        )
        p.add_argument(
            "--max-retries",
            type=int,
            default=3,
            help="reruns of a task whose worker process died (default 3)",
        )
        p.add_argument("--no-progress", action="store_true", help="no progress bar")
        p.set_defaults(func=cmd_fleet)
