"""The default recipe's rule on one network (docs/decisions.md, issues 37): read the per-sequence
rows of one or more benchmark runs (``results.json`` of ``benchmarks/fisheye_synthetic.py``) and
print what the rule checks, so the verdict is computed, not typed.

* (a) the pooled fraction of the AbsRel gap between the zero adapter and the supervised fit that
  the default recipe closes over the wide-lens sequences (means over the sequences), and per
  scene;
* (b) on how many wide-lens sequences the fit's AbsRel and d_reproj are both below the zero
  adapter's;
* (c) the worst AbsRel change against the zero adapter over every sequence run;
* per cell: AbsRel (zero / fitted / supervised, gap closed), d_reproj and rotation error
  (vanilla / zero adapter / fitted), and the slowest fit.

    python experiments/recipe_rule.py runs/dev_vggt_wide/results.json [runs/dev_vggt_narrow/results.json]
"""

from __future__ import annotations

import argparse
import collections
import json
import statistics

ZERO, FITTED, SUPERVISED = "raytun3r, no adapter", "raytun3r", "raytun3r, supervised"
WIDE = ("KB4 185", "DS 195")


def by_sequence(paths: list[str]) -> dict[tuple, dict[str, dict]]:
    """(camera, scene, seed) -> method -> row, over every file."""
    table: dict[tuple, dict[str, dict]] = collections.defaultdict(dict)
    for path in paths:
        with open(path) as handle:
            for row in json.load(handle)["sequences"]:
                table[(row["camera"], row["scene"], row["seed"])][row["method"]] = row
    return table


def mean(rows: list[dict], method: str, column: str) -> float:
    return statistics.mean(r[method][column] for r in rows)


def gap(rows: list[dict]) -> float:
    """Fraction of the mean-AbsRel gap (zero adapter -> supervised) the fit closes."""
    zero, fitted, sup = (mean(rows, m, "abs_rel") for m in (ZERO, FITTED, SUPERVISED))
    return (zero - fitted) / (zero - sup) if abs(zero - sup) > 1e-12 else float("nan")


def report(table: dict[tuple, dict[str, dict]], wide: tuple[str, ...] = WIDE) -> list[str]:
    lines = []
    wide_rows = [v for k, v in table.items() if k[0] in wide]
    if wide_rows:
        lines.append(f"(a) pooled wide-lens gap closed: {gap(wide_rows):.3f} over {len(wide_rows)}")
        for scene in ("indoor", "outdoor"):
            part = [v for k, v in table.items() if k[0] in wide and k[1] == scene]
            if part:
                lines.append(f"    {scene}: {gap(part):.3f} over {len(part)}")
        both = sum(
            v[FITTED]["abs_rel"] < v[ZERO]["abs_rel"]
            and v[FITTED]["d_reproj_px"] < v[ZERO]["d_reproj_px"]
            for v in wide_rows
        )
        lines.append(
            f"(b) wide-lens sequences below the zero adapter on both: {both}/{len(wide_rows)}"
        )
    change, key = max(
        (v[FITTED]["abs_rel"] / v[ZERO]["abs_rel"] - 1.0, k) for k, v in table.items()
    )
    lines.append(f"(c) worst AbsRel change vs the zero adapter: {100 * change:+.1f} % {key}")
    cells = collections.defaultdict(list)
    for k, v in table.items():
        cells[(k[0], k[1])].append(v)
    for (camera, scene), rows in sorted(cells.items()):
        lines.append(
            f"{camera} {scene} (n={len(rows)}): AbsRel vanilla {mean(rows, 'vanilla', 'abs_rel'):.3f} "
            f"zero {mean(rows, ZERO, 'abs_rel'):.3f} fitted {mean(rows, FITTED, 'abs_rel'):.3f} "
            f"supervised {mean(rows, SUPERVISED, 'abs_rel'):.3f} gap {gap(rows):.2f} | d_reproj "
            f"{mean(rows, ZERO, 'd_reproj_px'):.3f} -> {mean(rows, FITTED, 'd_reproj_px'):.3f} | "
            f"rot vanilla {mean(rows, 'vanilla', 'rot_deg'):.2f} zero {mean(rows, ZERO, 'rot_deg'):.2f} "
            f"fitted {mean(rows, FITTED, 'rot_deg'):.2f} | slowest fit "
            f"{max(r[FITTED]['adapt_s'] for r in rows):.0f} s"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="+", help="results.json files of benchmark runs")
    args = parser.parse_args()
    print("\n".join(report(by_sequence(args.results))))


if __name__ == "__main__":
    main()
