"""What adaptation does to the network's own rotation (issue 13), per benchmark cell.

Reads the per-sequence rows that ``benchmarks/fisheye_synthetic.py`` wrote (``results.json`` in
its ``--out`` folder) and prints, per camera and scene, the mean relative-rotation error of
vanilla, Center-PH, the zero adapter, the self-supervised fit and the supervised fit, vanilla's
error over the fit's (the paper's target: at least 2), and on how many sequences the fit is
below vanilla and below Center-PH. Nothing is re-run.

    python benchmarks/fisheye_synthetic.py --out runs/bench
    python experiments/rotation_effect.py runs/bench/results.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from raytun3r_plugin.apps.benchmark import rotation_effect
from raytun3r_plugin.apps.evaluation import format_table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", help="results.json of a benchmark run")
    args = parser.parse_args()
    data = json.loads(Path(args.results).read_text())
    rows = rotation_effect(data["sequences"])
    print(format_table(rows, list(rows[0])))


if __name__ == "__main__":
    main()
