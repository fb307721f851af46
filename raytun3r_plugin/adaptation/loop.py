"""The optimisation loop every fit shares: :func:`~raytun3r_plugin.adaptation.train.adapt` (one
camera) and :func:`~raytun3r_plugin.adaptation.rig.adapt_rig` (every camera of a rig).

A fit differs in how it prepares its problem and in what one step does; everything around the
step is here, once: the model frozen and put back, the RNG forked and seeded, the patch applied
for the run and removed after (even on an error), the per-step JSON log (truncated on a fresh
run, cut back to the restored step on a resumed one), progress, the collapse guard, periodic
checkpoints and Ctrl-C (the last completed step is kept and the caller saves it).
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import nn

from raytun3r_plugin.adaptation.checkpoint import _rewrite_log
from raytun3r_plugin.adaptation.evaluation import frozen_backbone
from raytun3r_plugin.adaptation.guard import _CollapseGuard

__all__ = ["LoopOutcome", "run_fit_loop"]


class _Progress:
    """A tqdm bar on a terminal; off a terminal (a log file, a pipe, a notebook's captured
    stream) one line to stderr every :attr:`every_s` seconds and at the end, so a log holds
    lines, not one carriage-return line of thousands of characters."""

    every_s = 5.0

    def __init__(self, total: int, initial: int, enabled: bool, label: str = "adapt") -> None:
        self.enabled = enabled
        self.total = total
        self.label = label
        self.bar = None
        self.last = time.monotonic()
        if enabled and _is_terminal(sys.stderr):
            try:
                from tqdm.auto import tqdm

                self.bar = tqdm(
                    total=total, initial=initial, desc=label, unit="step", dynamic_ncols=True
                )
            except ImportError:
                self.bar = None

    def update(self, step: int, loss: float) -> None:
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix(loss=f"{loss:.4g}", refresh=False)
            return
        now = time.monotonic()
        if now - self.last >= self.every_s or step + 1 == self.total:
            self.last = now
            print(
                f"{self.label}: step {step + 1}/{self.total} loss {loss:.4g}",
                file=sys.stderr,
                flush=True,
            )

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _is_terminal(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


@dataclasses.dataclass
class LoopOutcome:
    """What a run of the loop did.

    Attributes:
        completed: steps done, counting those restored from a checkpoint.
        interrupted: the run was stopped by Ctrl-C (``KeyboardInterrupt``) after ``completed``.
        history: the records of the steps this call ran (not the restored ones).
        seconds: wall time of the loop, in seconds.
    """

    completed: int
    interrupted: bool
    history: list[dict[str, Any]]
    seconds: float


def run_fit_loop(
    model: nn.Module,
    patch: Callable[[], Any],
    step: Callable[[int], dict[str, Any]],
    *,
    steps: int,
    start: int = 0,
    seed: int = 0,
    log_path: Path | None = None,
    progress: bool = True,
    label: str = "adapt",
    guard: _CollapseGuard | None = None,
    guarded: nn.Module | None = None,
    guard_every: int = 0,
    checkpoint: Callable[[int], None] | None = None,
    checkpoint_every: int = 0,
) -> LoopOutcome:
    """Run steps ``start .. steps - 1`` of a fit on ``model``.

    Args:
        model: the backbone; frozen for the run (``requires_grad`` off, eval mode) and put back
            afterwards, whatever happens.
        patch: applies the fit's patch to ``model`` and returns its handle (removed after the
            run, even on an error).
        step: ``step(k)`` runs optimisation step ``k`` on the patched model and returns its log
            record (a JSON-serialisable dict with a ``"loss"``).
        steps: the step to stop before. ``start >= steps`` runs no step (a run with nothing to
            fit passes ``steps=start``).
        start: the first step (a resumed run's restored step).
        seed: the torch RNG seed of the run (the global RNG is forked, so the caller's is
            untouched).
        log_path: the per-step JSON-lines log; truncated when ``start`` is 0, else cut back to
            the records before ``start``. None: no log file.
        progress: show progress (:class:`_Progress`) under ``label``.
        guard: the collapse guard, checked at ``start`` (its reference), every ``guard_every``
            steps and at the last step; a failed check restores the last healthy parameters of
            ``guarded`` and stops the run.
        checkpoint: ``checkpoint(completed)`` writes a resumable checkpoint; called every
            ``checkpoint_every`` completed steps before the last (the caller writes the final
            one with its files).

    Returns:
        :class:`LoopOutcome`.
    """
    if log_path is not None:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        if start == 0:
            log_path.write_text("", encoding="utf-8")
        else:
            _rewrite_log(log_path, start)
    history: list[dict[str, Any]] = []
    completed, interrupted, began = start, False, time.perf_counter()
    bar = _Progress(steps, start, progress, label)
    log = open(log_path, "a", encoding="utf-8") if log_path is not None else None  # noqa: SIM115
    try:
        with frozen_backbone(model), torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            handle = patch()
            # The guard keeps and restores what is fitted (``guarded``).
            watch = None if guard is None or guarded is None else (guard, guarded)
            try:
                if watch is not None:
                    watch[0].check(model, watch[1], start)
                for k in range(start, steps):
                    record = step(k)
                    completed = k + 1
                    history.append(record)
                    if log is not None:
                        log.write(json.dumps(record) + "\n")
                        log.flush()
                    bar.update(k, record["loss"])
                    if (
                        watch is not None
                        and (completed % guard_every == 0 or completed == steps)
                        and not watch[0].check(model, watch[1], completed)
                    ):
                        break
                    if (
                        checkpoint is not None
                        and checkpoint_every
                        and completed % checkpoint_every == 0
                        and completed < steps
                    ):
                        checkpoint(completed)
            except KeyboardInterrupt:
                interrupted = True
            finally:
                handle.remove()
    finally:
        bar.close()
        if log is not None:
            log.close()
    return LoopOutcome(completed, interrupted, history, time.perf_counter() - began)
