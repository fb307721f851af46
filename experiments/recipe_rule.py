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

With ``--reference FILE ...`` the fits of an earlier run of the same sequences (a benchmark's
``results.json``, or the rows of ``experiments/patch_resample_map.py``, whose method
``--reference-method`` names) are compared with these, against this run's zero adapter and
supervised fit: per cell and pooled AbsRel, the gap each closes, the sequences each makes more
than 2 % worse than the zero adapter, and the rotation above the zero adapter's per cell.
"""

from __future__ import annotations

import argparse
import collections
import json
import statistics

from raytun3r_plugin.apps.benchmark import CAMERAS, NEW_LENSES

ZERO, FITTED, SUPERVISED = "raytun3r, no adapter", "raytun3r", "raytun3r, supervised"
#: The issue's wide lenses, 185 degrees and wider: the benchmark's and the new lens models.
WIDE = tuple(lens.label for lens in (*CAMERAS, *NEW_LENSES) if lens.fov_deg >= 185.0)


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


def reference_rows(paths: list[str], method: str) -> dict[tuple, dict]:
    """(camera, scene, seed) -> the row of ``method`` in benchmark results or in the rows of
    ``experiments/patch_resample_map.py`` (a list of per-sequence dicts keyed by method)."""
    rows: dict[tuple, dict] = {}
    for path in paths:
        with open(path) as handle:
            data = json.load(handle)
        if isinstance(data, dict):
            for row in data["sequences"]:
                if row["method"] == method:
                    rows[(row["camera"], row["scene"], row["seed"])] = row
        else:
            for row in data:
                rows[(row["camera"], row["scene"], row["seed"])] = row[method]
    return rows


def compare(
    table: dict[tuple, dict[str, dict]], reference: dict[tuple, dict], wide: tuple[str, ...] = WIDE
) -> list[str]:
    """This run's fits against ``reference``'s on the sequences both hold (see the module)."""
    keys = sorted(k for k in table if k in reference)
    missing = sorted(k for k in table if k not in reference)
    lines = [
        f"compared on {len(keys)} sequences" + (f"; no reference for {missing}" if missing else "")
    ]

    fits = {
        "reference": {k: reference[k] for k in keys},
        "this run": {k: table[k][FITTED] for k in keys},
    }

    def pooled(rows: list[tuple], source: str) -> tuple[float, float]:
        fitted = statistics.mean(fits[source][k]["abs_rel"] for k in rows)
        zero = statistics.mean(table[k][ZERO]["abs_rel"] for k in rows)
        sup = statistics.mean(table[k][SUPERVISED]["abs_rel"] for k in rows)
        return fitted, (zero - fitted) / (zero - sup)

    wide_keys = [k for k in keys if k[0] in wide]
    for source in fits if wide_keys else ():
        value, closed = pooled(wide_keys, source)
        lines.append(f"{source}: pooled wide-lens AbsRel {value:.4f}, gap closed {closed:.3f}")
    for source, fitted in fits.items():
        worse = [k for k in keys if fitted[k]["abs_rel"] > 1.02 * table[k][ZERO]["abs_rel"]]
        lines.append(
            f"{source}: {len(worse)} sequences worse than the zero adapter by > 2 %: {worse}"
        )
    cells = collections.defaultdict(list)
    for k in keys:
        cells[(k[0], k[1])].append(k)
    for (camera, scene), rows in sorted(cells.items()):
        ref, _ = pooled(rows, "reference")
        new, _ = pooled(rows, "this run")
        rot = statistics.mean(table[k][FITTED]["rot_deg"] for k in rows)
        zero_rot = statistics.mean(table[k][ZERO]["rot_deg"] for k in rows)
        lines.append(
            f"{camera} {scene} (n={len(rows)}): AbsRel reference {ref:.4f} this run {new:.4f} "
            f"({100 * (new / ref - 1):+.1f} %) | rotation this run {rot:.2f} zero adapter "
            f"{zero_rot:.2f} ({rot - zero_rot:+.2f}) reference "
            f"{statistics.mean(reference[k]['rot_deg'] for k in rows):.2f}"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="+", help="results.json files of benchmark runs")
    parser.add_argument(
        "--reference", nargs="+", default=None, help="an earlier run's fits of the same sequences"
    )
    parser.add_argument(
        "--reference-method",
        default=FITTED,
        help=f"the reference's method (default {FITTED!r}; for patch_resample_map.py rows, "
        "e.g. 'default recipe, central')",
    )
    args = parser.parse_args()
    table = by_sequence(args.results)
    print("\n".join(report(table)))
    if args.reference:
        print("\n".join(compare(table, reference_rows(args.reference, args.reference_method))))


if __name__ == "__main__":
    main()
