"""Issue 37, measuring (deciding nothing): the pinhole-view teacher through two oracles.

Outdoors, and wherever the lens gate turns it on, much of a fit rests on the teacher: the same
network, unpatched, on pinhole views. Each oracle changes only the teacher's targets and fits the
default recipe as ``adapt()`` builds it for the network (the family's changes included), on
development sequences (seeds 80000+, never the benchmark's 90000+; frames 0-23 fitted, 24-35
scored at 112 px), with the zero adapter scored beside it:

* ``--oracle sky``: are the samples on sky what holds the outdoor fits back? The same fit with
  the teacher's samples on the renderer's sky mask dropped (outdoor wide-lens cells,
  ``--sequences`` per lens). docs/decisions.md, "The teacher's samples on sky".
* ``--oracle truth``: how much of the gap would the recipe close with a right teacher? The same
  fit with the teacher's value at each sample replaced by the ground-truth range at that pixel
  (samples on sky, which has none, dropped), the supervised fit beside it, and the teacher's own
  AbsRel on its samples (indoor and outdoor wide-lens cells, ``--sequences`` per cell).
  docs/decisions.md, "What limits the fit where it closes less than half".

    python experiments/teacher_oracle.py --oracle sky --network raytun3r-da3-tiny --out runs/sky.json
    python experiments/teacher_oracle.py --oracle truth --lenses "KB4 185" --out runs/truth_kb4.json
    PYTHONPATH=$PWD:$PWD/tests/stubs python experiments/teacher_oracle.py --weights W ...

One process of one thread; a sequence takes about 5 minutes here with ``sky`` and 10 with ``truth``
(two such processes side by side). A rerun skips the sequences its output already holds.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation import train
from raytun3r_plugin.apps.benchmark import (
    CAMERAS,
    DEVELOPMENT_SEED,
    SCENES,
    fit_and_score,
    make_camera,
    sequence_seed,
)
from raytun3r_plugin.apps.fits import adapt_config, supervised_config
from raytun3r_plugin.apps.sequence_methods import ground_truth_depth
from raytun3r_plugin.apps.trained_networks import network_from
from raytun3r_plugin.registry import quiet_upstream

SIZE, N_ADAPT, N_EVAL = 112, 24, 12
LENSES = ("KB4 185", "DS 195")


class _OracleTeacher:
    """``train.teacher_targets`` with the current sequence's sky samples dropped (``sky``), or
    with every sample's value replaced by the ground-truth range there (``truth``); the
    library's own targets while both are None."""

    def __init__(self) -> None:
        self.original = train.teacher_targets
        self.sky: torch.Tensor | None = None  # (N, H, W) bool
        self.truth: torch.Tensor | None = None  # (N, H, W) range, 0 on sky
        self.teacher_abs_rel: list[float] = []  # per frame and view, of the last truth call

    def __call__(self, model, problem, *args, **kwargs):
        targets = self.original(model, problem, *args, **kwargs)
        if self.sky is None and self.truth is None:
            return targets
        grid = tuple(next(iter(problem.inputs.values())).shape[-2:])
        for mask in (self.sky, self.truth):
            if mask is not None and grid != tuple(mask.shape[-2:]):
                # The samples are network-input pixels: the oracle must be on the same grid.
                raise SystemExit(f"the oracle is {tuple(mask.shape[-2:])}, the input {grid}")
        self.teacher_abs_rel = []
        changed = {}
        for index, frames in targets.items():
            window = problem.windows[index][0].frames
            changed[index] = []
            for k, (uv, value, view) in enumerate(frames):
                rows, cols = uv[:, 1].long(), uv[:, 0].long()
                if self.sky is not None:
                    keep = ~self.sky[int(window[k])][rows, cols]
                    changed[index].append((uv[keep], value[keep], view[keep]))
                    continue
                truth = self.truth[int(window[k])][rows, cols]
                keep = torch.isfinite(truth) & (truth > 0)
                self._score(value[keep], truth[keep], view[keep])
                changed[index].append((uv[keep], truth[keep], view[keep]))
        return changed

    def _score(self, value: torch.Tensor, truth: torch.Tensor, view: torch.Tensor) -> None:
        """The teacher's AbsRel on one frame's samples, per view, median-aligned to the truth."""
        for number in view.unique():
            taught, right = value[view == number], truth[view == number]
            if taught.numel():
                scale = torch.median(right / taught)
                self.teacher_abs_rel.append(float(((scale * taught - right).abs() / right).mean()))


def _sequences(args: argparse.Namespace):
    """(cell, camera spec, scene, seed) of the run, in order."""
    scenes = ("outdoor",) if args.oracle == "sky" else SCENES
    lenses = args.lenses or LENSES
    for k in range(args.sequences):
        for label in lenses:
            for scene in scenes:
                lens = [spec.label for spec in CAMERAS].index(label)
                seed = sequence_seed(lens, SCENES.index(scene), k, DEVELOPMENT_SEED)
                yield f"{label} {scene}", CAMERAS[lens], scene, seed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--oracle", choices=("sky", "truth"), required=True)
    parser.add_argument("--network", default="raytun3r-da3-tiny")
    parser.add_argument(
        "--weights",
        default=None,
        metavar="FILE",
        help="instead of --network, one exported by scripts/train_default_network.py (a VGGT "
        "one needs PYTHONPATH=tests/stubs)",
    )
    parser.add_argument("--lenses", nargs="+", choices=LENSES, default=None)
    parser.add_argument(
        "--sequences", type=int, default=None, help="per lens (sky: 5) or per cell (truth: 2)"
    )
    parser.add_argument("--out", help="results JSON (one row per sequence)")
    parser.add_argument(
        "--summarise",
        nargs="+",
        metavar="JSON",
        help="print the cells' means over these runs' outputs (e.g. one per lens) and fit nothing",
    )
    args = parser.parse_args()
    if args.summarise:
        _summary(
            [row for path in args.summarise for row in json.loads(Path(path).read_text())],
            args.oracle,
        )
        return
    if not args.out:
        parser.error("--out is needed unless --summarise")
    if args.sequences is None:
        args.sequences = 5 if args.oracle == "sky" else 2
    torch.set_num_threads(1)
    oracle = _OracleTeacher()
    train.teacher_targets = oracle
    try:
        _run(args, oracle)
    finally:
        train.teacher_targets = oracle.original  # the library as it was


def _run(args: argparse.Namespace, oracle: _OracleTeacher) -> None:
    """Fit and score every sequence not yet in ``args.out``, then print the cells' means."""
    out = Path(args.out)
    rows = json.loads(out.read_text()) if out.is_file() else []
    done = {row["seed"] for row in rows}
    model, description = network_from(args.network, args.weights)
    print(f"network: {description}")
    for cell, spec, scene, seed in _sequences(args):
        if seed in done:
            continue
        camera = make_camera(spec, SIZE)
        seq = synthetic.render_sequence(scene, camera, n_frames=N_ADAPT + N_EVAL, seed=seed)
        frames = list(range(N_ADAPT, N_ADAPT + N_EVAL))
        fit = (camera, seq.images[:N_ADAPT], adapt_config(SIZE, 300, seed=0, model=model), None)
        row = {"cell": cell, "seed": seed}
        row["zero"] = fit_and_score(model, seq, frames)["abs_rel"]
        row["default"] = fit_and_score(model, seq, frames, fit)["abs_rel"]
        if args.oracle == "sky":
            oracle.sky = torch.from_numpy(np.asarray(seq.meta["per_frame"]["sky"], bool))
            row["no_sky_teacher"] = fit_and_score(model, seq, frames, fit)["abs_rel"]
            oracle.sky = None
        else:
            oracle.truth = torch.from_numpy(ground_truth_depth(seq, N_ADAPT + N_EVAL))
            row["truth_teacher"] = fit_and_score(model, seq, frames, fit)["abs_rel"]
            oracle.truth = None
            row["teacher_abs_rel"] = float(np.mean(oracle.teacher_abs_rel))
            depth = ground_truth_depth(seq, N_ADAPT)
            sup = (camera, seq.images[:N_ADAPT], supervised_config(SIZE, 300), depth)
            row["supervised"] = fit_and_score(model, seq, frames, sup)["abs_rel"]
        rows.append(row)
        print(json.dumps(row), flush=True)
        out.write_text(json.dumps(rows, indent=1))
    _summary(rows, args.oracle)


def _summary(rows: list[dict], oracle: str) -> None:
    """Per cell: mean AbsRel of each fit; for ``truth`` also the gap each closes, pooled."""
    keys = (
        ("zero", "default", "no_sky_teacher")
        if oracle == "sky"
        else ("zero", "default", "truth_teacher", "supervised", "teacher_abs_rel")
    )
    cells = sorted({row["cell"] for row in rows})
    for cell in cells:
        part = [row for row in rows if row["cell"] == cell]
        means = {key: np.mean([row[key] for row in part]) for key in keys}
        line = f"{cell}, {len(part)} sequences: " + ", ".join(
            f"{key} {value:.4f}" for key, value in means.items()
        )
        if oracle == "sky":
            worse = sum(row["no_sky_teacher"] > row["default"] for row in part)
            change = 100 * (means["no_sky_teacher"] / means["default"] - 1)
            line += f" (without sky {change:+.1f} %, worse on {worse})"
        print(line)
    if oracle == "truth" and rows:
        for scope, part in (
            ("pooled", rows),
            *[(scene, [r for r in rows if r["cell"].endswith(scene)]) for scene in SCENES],
        ):
            if part:
                zero, sup = (np.mean([r[k] for r in part]) for k in ("zero", "supervised"))
                closed = {
                    key: (zero - np.mean([r[key] for r in part])) / (zero - sup)
                    for key in ("default", "truth_teacher")
                }
                print(
                    f"{scope}, {len(part)} sequences: gap closed with the real teacher "
                    f"{closed['default']:.3f}, with the right one {closed['truth_teacher']:.3f}; "
                    f"the teacher's own AbsRel {np.mean([r['teacher_abs_rel'] for r in part]):.4f}"
                )


if __name__ == "__main__":
    with quiet_upstream():
        main()
