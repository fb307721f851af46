"""A held-out check that decides whether a fit is kept: does it remove the harm where a fit does
not carry to later frames, and what does it cost where the fit helps?

Per development sequence (``--held-out``: the benchmark's held-out seeds; frames 0-23 for
adaptation, 24-35 scored, as in the benchmark): the default recipe fitted on frames 0-19, its
held-out reprojection check on frames 20-23
(:func:`~raytun3r_plugin.adaptation.check.held_out_reprojection`, the check ``raytun3r adapt``
prints), and the gated result: the fit when the check's error is at least ``--margin`` lower
than the zero adapter's, else the zero tables. Rows are written in the benchmark's
``results.json`` form (methods ``raytun3r, no adapter``, ``raytun3r`` = gated,
``raytun3r, 20 frames`` = the fit whatever the check says), with the check under ``check``.

With ``--reference`` (a benchmark run's ``results.json`` over the same seeds), vanilla and the
supervised fit are taken from it, and :mod:`experiments.recipe_rule` prints the rule's numbers for
the gated fit and, beside them, for the reference's 24-frame fit.

    python experiments/check_gate.py [--network NAME | --weights FILE] [--cameras "KB4 120" ...]
        [--sequences 5] [--first-sequence 0] --out runs/check_gate.json
    python experiments/check_gate.py --analyse runs/check_gate.json --reference runs/x/results.json
        [--veto 0.02]

``--veto`` analyses the second form of the gate on the same rows: the fit is kept unless the
check's error rises by more than the veto (docs/decisions.md, same section).

The decision it serves: docs/decisions.md, "A held-out check that decides whether a fit is kept".
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.check import held_out_reprojection
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.apps.benchmark import (
    CAMERAS,
    DEVELOPMENT_SEED,
    HELD_OUT_SEED,
    SCENES,
    SEQUENCES_PER_CELL,
    cell_sequences,
    make_camera,
)
from raytun3r_plugin.apps.demo import DEFAULT_NETWORK
from raytun3r_plugin.apps.evaluation import headline, run_method, score
from raytun3r_plugin.apps.fits import adapt_config
from raytun3r_plugin.apps.trained_networks import network_from
from raytun3r_plugin.registry import quiet_upstream

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from experiments.recipe_rule import (  # noqa: E402
    FITTED,
    SUPERVISED,
    WIDE,
    ZERO,
    by_sequence,
    report,
)

SIZE, STEPS, N_FIT, N_CHECK, N_EVAL = 112, 300, 20, 4, 12
UNGATED = "raytun3r, 20 frames"


def one_sequence(model, spec, scene: str, seed: int, margin: float) -> list[dict]:
    """The zero adapter, the 20-frame fit and the gated fit on one sequence, scored on 24-35."""
    camera = make_camera(spec, SIZE)
    seq = synthetic.render_sequence(scene, camera, n_frames=N_FIT + N_CHECK + N_EVAL, seed=seed)
    scored = list(range(N_FIT + N_CHECK, len(seq)))
    config = adapt_config(SIZE, STEPS, seed=0)
    start = time.perf_counter()
    fitted = adapt(model, camera, seq.first_images(N_FIT), config, progress=False)
    seconds = time.perf_counter() - start
    check = held_out_reprojection(
        model, camera, seq.first_images(N_FIT + N_CHECK)[N_FIT:], fitted, config
    )
    kept = check.get("change") is not None and check["change"] <= -margin
    cell = {"camera": spec.label, "scene": scene, "seed": seed}

    def row(method: str, adapter, fit_s: float = float("nan")) -> dict:
        values = headline(score(seq, run_method(model, seq, "raytun3r", adapter, frames=scored)))
        return {**cell, "method": method, **values, "adapt_s": fit_s}

    zero = row(ZERO, None)
    ungated = row(UNGATED, fitted, seconds)
    gated = {**(ungated if kept else zero), "method": FITTED, "adapt_s": seconds}
    gated.update(check=check, kept=kept)
    return [zero, ungated, gated]


def vetoed(rows: dict[str, dict], veto: float) -> dict[str, dict]:
    """The sequence's rows with the second form of the gate: the fit is kept unless the check's
    error rises by more than ``veto`` (a check that could not be scored keeps it)."""
    check = rows[FITTED]["check"]
    change = check.get("change")
    kept = change is None or change <= veto
    chosen = rows[UNGATED] if kept else rows[ZERO]
    return {**rows, FITTED: {**chosen, "method": FITTED, "check": check, "kept": kept}}


def table_gap(table_path: str, rows: dict[tuple, dict[str, dict]]) -> list[str]:
    """The pooled wide-lens gap closed by ``rows``' fits against a benchmark table's zero-adapter
    and supervised cell means (docs/results.md's bench block), beside the table's own fit's."""
    lines = Path(table_path).read_text().splitlines()
    start = next(
        k for k, line in enumerate(lines) if line.startswith("| camera | scene | method |")
    )
    column = [c.strip() for c in lines[start].strip("|").split("|")].index("abs_rel")
    end = next((k for k in range(start, len(lines)) if not lines[k].startswith("|")), len(lines))
    means: dict[tuple[str, str, str], float] = {}
    for line in lines[start + 2 : end]:  # the first such table: the bench block's
        cells = [c.strip() for c in line.strip("|").split("|")]
        if line.startswith("| ") and len(cells) > column and cells[0] in WIDE:
            means[(cells[0], cells[1], cells[2])] = float(cells[column])
    cells = sorted({(k[0], k[1]) for k in rows if k[0] in WIDE})

    def pooled(method: str) -> float:
        return sum(means[(c, s, method)] for c, s in cells) / len(cells)

    def this_run(method: str) -> float:
        return sum(
            statistics.mean(r[method]["abs_rel"] for k, r in rows.items() if k[:2] == cell)
            for cell in cells
        ) / len(cells)

    zero, sup = pooled(ZERO), pooled(SUPERVISED)
    ours, ours_zero = this_run(FITTED), this_run(ZERO)
    return [
        f"table {table_path}: wide-lens cells {len(cells)}, zero adapter {zero:.4f} (this run "
        f"{ours_zero:.4f}), supervised {sup:.4f}",
        f"gap closed: this run's gated fit {(zero - ours) / (zero - sup):.3f}, the table's fit "
        f"{(zero - pooled(FITTED)) / (zero - sup):.3f}",
    ]


def analyse(
    paths: list[str], references: list[str], veto: float | None = None, table: str | None = None
) -> list[str]:
    """The rule's numbers for the gated fit and the 24-frame reference fit, over the sequences
    both hold; with ``veto``, for the second form of the gate (:func:`vetoed`)."""
    mine = dict(by_sequence(paths))
    if veto is not None:
        mine = {key: vetoed(rows, veto) for key, rows in mine.items()}
    reference = by_sequence(references)
    lines = []
    for key, rows in sorted(mine.items()):
        check = rows[FITTED]["check"]
        lines.append(
            f"{key}: check {check.get('zero_adapter_px')} -> {check.get('adapted_px')} px "
            f"({check.get('change')}), kept {rows[FITTED]['kept']}; AbsRel zero "
            f"{rows[ZERO]['abs_rel']:.3f} 20 frames {rows[UNGATED]['abs_rel']:.3f} gated "
            f"{rows[FITTED]['abs_rel']:.3f}"
            + (f" 24 frames {reference[key][FITTED]['abs_rel']:.3f}" if key in reference else "")
        )
    shared = [k for k in mine if k in reference]
    if shared:
        # recipe_rule's rows: vanilla and the supervised fit from the reference run.
        gated = {
            k: {**mine[k], "vanilla": reference[k]["vanilla"], SUPERVISED: reference[k][SUPERVISED]}
            for k in shared
        }
        lines += ["", "gated (fit on 20 frames, kept by the check):", *report(gated)]
        lines += ["", "reference (fit on 24 frames):", *report({k: reference[k] for k in shared})]
    else:
        kept = sum(rows[FITTED]["kept"] for rows in mine.values())
        worst = max(r[FITTED]["abs_rel"] / r[ZERO]["abs_rel"] - 1 for r in mine.values())
        lines += ["", f"kept {kept}/{len(mine)}; worst AbsRel change vs zero {100 * worst:+.1f} %"]
    if table:
        lines += table_gap(table, mine)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--network", default=DEFAULT_NETWORK)
    parser.add_argument("--weights", default=None, help="a network of train_default_network.py")
    parser.add_argument("--cameras", nargs="+", default=[c.label for c in CAMERAS])
    parser.add_argument("--sequences", type=int, default=SEQUENCES_PER_CELL)
    parser.add_argument("--first-sequence", type=int, default=0)
    parser.add_argument(
        "--held-out", action="store_true", help="the benchmark's held-out seeds (90000+)"
    )
    parser.add_argument("--margin", type=float, default=0.02, help="check drop needed to keep")
    parser.add_argument("--out", default="runs/check_gate.json")
    parser.add_argument("--analyse", nargs="+", default=None, help="check_gate JSON files")
    parser.add_argument("--reference", nargs="*", default=[], help="benchmark results.json")
    parser.add_argument(
        "--table", default=None, help="a bench table (docs/results.md) for the pooled gap"
    )
    parser.add_argument(
        "--veto",
        type=float,
        default=None,
        help="analyse the second form: keep the fit unless the check rises by more than this",
    )
    args = parser.parse_args()
    if args.analyse:
        print("\n".join(analyse(args.analyse, args.reference, args.veto, args.table)))
        return
    torch.set_num_threads(1)
    model, _ = network_from(args.network, args.weights)
    rows: list[dict] = []
    with quiet_upstream():
        cells = [f"{label} {scene}" for label in args.cameras for scene in SCENES]
        base = HELD_OUT_SEED if args.held_out else DEVELOPMENT_SEED
        for spec, scene, seed in cell_sequences(cells, args.sequences, base, args.first_sequence):
            rows += one_sequence(model, spec, scene, seed, args.margin)
            print(json.dumps(rows[-1]), flush=True)
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            Path(args.out).write_text(json.dumps({"sequences": rows}, indent=1))
    print("\n".join(analyse([args.out], [])))


if __name__ == "__main__":
    main()
