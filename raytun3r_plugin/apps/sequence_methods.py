"""The benchmark's methods on one sequence with ground truth (vanilla, Center-PH, Multi-PH, the
zero adapter, a fitted and a supervised adapter), each row with its scores, timing and
parameters: shared by ``raytun3r bench`` (:mod:`.benchmark`) and ``raytun3r fleet eval``
(:mod:`.fleet`), so both tables have the same columns and meaning."""

from __future__ import annotations

import math
import time
from pathlib import Path

from raytun3r_plugin.apps.evaluation import headline, run_method, score

ZERO_ADAPTER = "raytun3r, no adapter"
SUPERVISED = "raytun3r, supervised"


def ground_truth_depth(seq, frames: int):
    """Ground-truth range of the first ``frames`` frames as a user would pass it to ``adapt``:
    0 (no value) on the sky, which has no depth."""
    import numpy as np

    sky = seq.meta.get("per_frame", {}).get("sky")
    depth = np.asarray(seq.depth[:frames], dtype=np.float32).copy()
    if sky is not None:
        depth[np.asarray(sky[:frames], dtype=bool)] = 0.0
    return depth


def timed_row(model, seq, method: str, frames: list[int], adapter=None) -> dict:
    """:func:`headline` scores of ``method`` on ``frames`` plus ``ms_per_frame``: wall time of
    :func:`run_method` (the forward passes, with Multi-PH's resampling and fusion and the
    patch's apply/remove; not the scoring) per scored frame, in milliseconds."""
    start = time.perf_counter()
    output = run_method(model, seq, method, adapter=adapter, frames=frames)
    seconds = time.perf_counter() - start
    return {**headline(score(seq, output)), "ms_per_frame": 1000.0 * seconds / len(frames)}


#: The method keys of :func:`method_rows` (a fleet manifest's ``methods``) -> their row names.
METHOD_KEYS = {
    "vanilla": "vanilla",
    "center-ph": "center-ph",
    "multi-ph": "multi-ph",
    "no-adapter": ZERO_ADAPTER,
    "adapted": "raytun3r",
    "supervised": SUPERVISED,
}


def method_rows(
    model,
    seq,
    cell: dict,
    n_adapt: int,
    methods,
    *,
    fit=None,
    supervised_fit=None,
    adapter_path: Path | None = None,
    adapter=None,
    progress: bool = False,
) -> list[dict]:
    """The benchmark's rows of ``methods`` (keys of :data:`METHOD_KEYS`, rows in that order) on
    one sequence with ground truth: each scored on frames ``n_adapt`` onwards, the fits made on
    frames before. ``adapted`` fits ``fit`` (an ``AdaptConfig``) to ``adapter_path``, or uses
    ``adapter`` when one is given (its ``adapt_s`` is then NaN); ``supervised`` fits
    ``supervised_fit`` to the ground-truth depth, next to ``adapter_path``. Every row is ``cell``
    plus its ``method``, the :func:`timed_row` scores, ``adapt_s`` (s), ``params`` and
    ``x_vanilla`` (NaN without a vanilla row)."""
    from raytun3r_plugin.adaptation.train import adapt

    held_out = list(range(n_adapt, len(seq)))
    # One untimed window first: the first forward of a process pays one-off set-up costs that
    # would otherwise make vanilla, the time reference, look slow.
    run_method(model, seq, "vanilla", frames=held_out[:3])
    rows = []
    for key in (key for key in METHOD_KEYS if key in methods):
        name, fitted, seconds = METHOD_KEYS[key], None, math.nan
        if key == "adapted" and adapter is not None:
            fitted = adapter
        elif key in ("adapted", "supervised"):
            supervised = key == "supervised"
            path = None if adapter_path is None else Path(adapter_path)
            if path is not None and supervised:
                path = path.with_name(path.stem + "_supervised.safetensors")
            start = time.perf_counter()
            fitted = adapt(
                model,
                seq.camera,
                seq.first_images(n_adapt),
                supervised_fit if supervised else fit,
                out_path=path,
                resume=False,
                progress=progress,
                depth=ground_truth_depth(seq, n_adapt) if supervised else None,
            )
            seconds = time.perf_counter() - start
        method = "raytun3r" if key in ("no-adapter", "adapted", "supervised") else key
        rows.append(
            {
                **cell,
                "method": name,
                **timed_row(model, seq, method, held_out, adapter=fitted),
                "adapt_s": seconds,
                "params": 0 if fitted is None else fitted.num_parameters()["total"],
            }
        )
    reference = next((r["ms_per_frame"] for r in rows if r["method"] == "vanilla"), math.nan)
    for row in rows:
        row["x_vanilla"] = row["ms_per_frame"] / reference
    return rows
