"""``raytun3r analyze jacobian``: PE-Jacobian curves of a model, with and without its adapter.

Writes ``jacobian.csv`` (one row per radius bin: median and quartiles of sigma_1 and of the
area element for each curve, and the camera's analytic reference) and ``jacobian.png`` (the
medians against rho). The analysis itself is :mod:`raytun3r_plugin.analysis`.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

from torch import nn

from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.analysis import JacobianCurves, curves_table, pe_jacobian, reference_curves


def jacobian_report(
    model: nn.Module,
    adapter: Adapter | None,
    out: str | Path,
    *,
    size: int | None = None,
    bins: int = 20,
) -> dict[str, Any]:
    """Compute the curves of ``model`` (pretrained, and with ``adapter`` applied) and write them.

    Args:
        model: an unpatched registered backbone with an absolute PE table.
        adapter: an adapter for it (its camera sets the principal point and the reference), or
            None for the pretrained curve alone.
        out: folder for ``jacobian.csv`` and ``jacobian.png`` (created).
        size: square input side in pixels (default: 504 rounded to the patch size).

    Returns:
        ``{"csv", "png", "rows", "summary"}``; ``summary`` gives, per curve, sigma_1 and area at
        the outermost filled bin (1.0 = flat).
    """
    import raytun3r_plugin as rt
    from raytun3r_plugin.registry import spec_for

    spec, root = spec_for(model)
    patch = spec.describe(root).patch_size
    side = (size or 504) // patch * patch
    camera = adapter.camera if adapter is not None else None
    curves: dict[str, JacobianCurves] = {
        "pretrained": pe_jacobian(model, side, side, camera=camera, bins=bins)
    }
    reference = None
    if adapter is not None:
        with rt.apply(model, camera, adapter, strict=False):
            curves["adapted"] = pe_jacobian(model, side, side, camera=camera, bins=bins)
    if camera is not None:
        reference = reference_curves(camera, curves["pretrained"].rho, side, side)
    rows = curves_table(curves, reference)
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    csv_path = folder / "jacobian.csv"
    with csv_path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    png_path = folder / "jacobian.png"
    _picture(rows, list(curves), reference is not None, png_path, side)
    summary = {}
    for name in curves:
        filled = [row for row in rows if row["tokens"] and math.isfinite(row[f"{name}_sigma1"])]
        last = filled[-1] if filled else None
        summary[name] = (
            {"rho": last["rho"], "sigma1": last[f"{name}_sigma1"], "area": last[f"{name}_area"]}
            if last
            else {}
        )
    return {"csv": csv_path, "png": png_path, "rows": rows, "summary": summary}


def _picture(rows: list[dict], names: list[str], reference: bool, path: Path, side: int) -> None:
    """The two panels (sigma_1 and the area element over rho) side by side, 1280 px wide: with
    matplotlib (the ``viz`` extra), else with OpenCV's :func:`~raytun3r_plugin.plots.line_chart`."""
    from raytun3r_plugin.errors import MissingDependencyError
    from raytun3r_plugin.figures import curves_figure

    rho = [row["rho"] for row in rows]
    panels = []
    for quantity in ("sigma1", "area"):
        series = {name: [row[f"{name}_{quantity}"] for row in rows] for name in names}
        if reference:
            series["camera reference"] = [row[f"reference_{quantity}"] for row in rows]
        series["pinhole (flat)"] = [1.0] * len(rows)
        label = "sigma_1" if quantity == "sigma1" else "area element"
        panels.append((f"PE Jacobian {label} / centre, {side} px input", series))
    try:
        path.write_bytes(curves_figure(panels, rho, x_label="rho", size_px=(1280, 400)))
    except MissingDependencyError:
        import cv2
        import numpy as np

        from raytun3r_plugin.plots import line_chart

        drawn = [
            line_chart(series, title, x=rho, x_label="rho", size=(640, 400))
            for title, series in panels
        ]
        cv2.imwrite(str(path), np.concatenate(drawn, axis=1))
