"""``raytun3r report``: one self-contained HTML page from a fit's or a benchmark's output folder.

What it reads (nothing is recomputed except the optional depth pictures):

* a fit: the adapter file (``adapt`` writes ``NAME.safetensors``) with its training record and,
  beside it, the per-step loss log ``NAME.log.jsonl``. The page shows the fit's verdict, a table
  of its numbers (final losses, held-out check, PE correction size, ...), the loss curves
  (:func:`raytun3r_plugin.figures.loss_figure`), the PE correction over the image and, when
  frames and the model are given, the depth of one frame before and after the fit beside it;
* a benchmark (``raytun3r bench``: ``results.json``) or a demo (``raytun3r demo``:
  ``metrics.json``): the summary table, bar charts of its main metrics and every fit in the
  folder (verdicts in a table, the curves of the first few).

Pictures are PNGs embedded as ``data:`` URIs, the style sheet is inline and there is no script:
the file can be mailed or attached to an issue and opens anywhere. Drawing needs matplotlib (the
``viz`` extra).
"""

from __future__ import annotations

import base64
import datetime
import html
import json
import math
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from raytun3r_plugin.apps.evaluation import METRIC_COLUMNS
from raytun3r_plugin.errors import InputError

__all__ = ["DepthSource", "build_report", "find_fits", "report_kind", "write_report"]

#: Metrics of benchmark and demo tables drawn as bar charts (those present are drawn).
BAR_METRICS = ("d_reproj_px", "abs_rel", "rot_deg")
#: Fits of a benchmark or demo folder whose loss curves are drawn (all are listed in the table).
CURVES_PER_FOLDER = 3

_STYLE = """
body { font-family: system-ui, -apple-system, 'Segoe UI', sans-serif; margin: 24px auto;
       max-width: 1180px; padding: 0 16px; color: #1d1d1f; line-height: 1.4; }
h1 { font-size: 1.5em; margin-bottom: 0.2em; } h2 { font-size: 1.2em; margin-top: 1.6em; }
h3 { font-size: 1.0em; }
.meta { color: #555; font-size: 0.9em; }
.verdict { padding: 10px 14px; border-radius: 6px; border-left: 6px solid; }
.status-ok { background: #eef8ee; border-color: #2e8b2e; }
.status-warn { background: #fff6e0; border-color: #d89000; }
.status-bad { background: #fdecec; border-color: #c62828; }
table { border-collapse: collapse; font-size: 0.88em; margin: 8px 0; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
th { background: #f2f2f2; }
img { max-width: 100%; height: auto; display: block; margin: 6px 0; }
figcaption, .note { color: #555; font-size: 0.85em; }
.pair { display: flex; gap: 28px; align-items: flex-start; flex-wrap: wrap; }
.pair > div { flex: 1 1 420px; }
"""


@dataclass
class DepthSource:
    """What the depth-before-and-after picture needs: ``frames`` (N, H, W, 3) float32 RGB in
    [0, 1] as :func:`raytun3r_plugin.images.read_frames` reads them, the ``model`` the adapter
    was fitted for, the ``index`` of the frame to show, and the ``camera`` of the frames (None:
    the adapter's)."""

    frames: np.ndarray
    model: Any
    index: int = 0
    camera: Any = None


def _esc(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _number(value: Any) -> str:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return _esc(value)
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.4g}"
    return f"{value:,}"


def _img(png: bytes, alt: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<img src="data:image/png;base64,{data}" alt="{_esc(alt)}">'


def _table(rows: Iterable[Mapping[str, Any]], columns: list[str]) -> str:
    head = "".join(f"<th>{_esc(c)}</th>" for c in columns)
    body = []
    for row in rows:
        cells = []
        for column in columns:
            value = row.get(column, "")
            numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
            cells.append(
                f'<td class="num">{_number(value)}</td>' if numeric else f"<td>{_esc(value)}</td>"
            )
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def find_fits(folder: Path) -> list[Path]:
    """Adapter files under ``folder`` (recursively, sorted), checkpoints left out."""
    return sorted(
        p
        for p in folder.rglob("*.safetensors")
        if not p.name.endswith(".ckpt.safetensors") and p.is_file()
    )


def report_kind(path: str | os.PathLike) -> str:
    """``"fit"`` (an adapter file, or a folder holding exactly one), ``"benchmark"`` (a folder
    with ``results.json``), ``"demo"`` (a folder with ``metrics.json``) or ``"fits"`` (a folder
    of several adapter files).

    Raises:
        InputError: the path does not exist or holds none of these.
    """
    p = Path(path)
    if p.is_file():
        if p.name.endswith(".safetensors") and not p.name.endswith(".ckpt.safetensors"):
            return "fit"
        raise InputError(f"{p}: not an adapter file (.safetensors) or an output folder")
    if not p.is_dir():
        raise InputError(f"{p}: no such file or folder")
    if (p / "results.json").is_file():
        return "benchmark"
    if (p / "metrics.json").is_file():
        return "demo"
    fits = find_fits(p)
    if len(fits) == 1:
        return "fit"
    if fits:
        return "fits"
    raise InputError(
        f"{p}: nothing to report (no adapter .safetensors, results.json of `raytun3r bench` "
        "or metrics.json of `raytun3r demo`)"
    )


def _verdict_class(status: str) -> str:
    return {"ok": "status-ok", "warn": "status-warn"}.get(status, "status-bad")


def _fit_rows(adapter, records: list[dict]) -> list[dict]:
    """The fit's numbers as (quantity, value, note) rows."""
    info = adapter.training_info or {}
    rows: list[dict] = []

    def add(quantity: str, value: Any, note: str = "") -> None:
        rows.append({"quantity": quantity, "value": value, "note": note})

    steps = info.get("steps", len(records))
    add(
        "steps",
        steps,
        f"of {info['requested_steps']} requested" if "requested_steps" in info else "",
    )
    if "wall_time_s" in info:
        add("wall time (s)", float(info["wall_time_s"]))
    over = info.get("final_losses_over_steps")
    from raytun3r_plugin.adaptation.config import TERMS

    losses = info.get("final_losses") or {}
    order = {name: k for k, name in enumerate(("loss", *TERMS))}
    for name, value in sorted(losses.items(), key=lambda item: order.get(item[0], len(order))):
        add(f"final {name}", float(value), f"mean of the last {over} steps" if over else "")
    verdict = info.get("verdict") or {}
    for key, label in (
        ("first_pass_loss", "loss, first pass over the windows"),
        ("last_pass_loss", "loss, last pass over the windows"),
        ("pe_correction_relative_rms", "PE correction / PE rms"),
        ("rope_max_token", "largest RoPE shift (token)"),
        ("skipped_steps", "skipped steps"),
    ):
        if verdict.get(key) is not None:
            add(label, verdict[key])
    check = info.get("check") or {}
    if check.get("adapted_px") is not None:
        note = f"{check.get('frames')} held-out frames, not fitted"
        add("held-out reprojection, no adapter (px)", float(check["zero_adapter_px"]), note)
        add("held-out reprojection, adapted (px)", float(check["adapted_px"]), note)
    teacher = info.get("teacher") or {}
    if "used" in teacher:
        add(
            "pinhole-view teacher",
            "used" if teacher["used"] else "left out",
            f"largest view covers {float(teacher.get('coverage', 0)):.0%} of the lens",
        )
    gate = info.get("parallax_gate") or {}
    if "windows_kept" in gate:
        add(
            "windows kept by the parallax gate",
            gate["windows_kept"],
            f"{gate.get('windows_dropped', 0)} dropped",
        )
    recipe = info.get("recipe") or {}
    if recipe.get("name"):
        changes = ", ".join(
            f"{k} {old} -> {new}" for k, (old, new) in (recipe.get("changes") or {}).items()
        )
        add("recipe", f"{recipe['name']} v{recipe.get('version')}", changes or "as the recipe is")
    add("trainable parameters", adapter.num_parameters()["total"])
    return rows


def _loss_series(records: list[dict]) -> dict[str, list[float]]:
    from raytun3r_plugin.adaptation.config import TERMS

    names = ["loss", *(t for t in TERMS if records and t in records[0])]
    return {
        name: [float(r.get(name, math.nan)) for r in records]
        for name in names
        if any(float(r.get(name, 0.0) or 0.0) > 0 for r in records)
    }


def _fit_section(path: Path, depth: DepthSource | None, heading: str = "h2") -> str:
    from raytun3r_plugin.adaptation.checkpoint import artifact_paths, read_loss_log, trend_window
    from raytun3r_plugin.adapter import Adapter
    from raytun3r_plugin.figures import field_figure, loss_figure

    adapter = Adapter.load(path)
    info = adapter.training_info or {}
    log = artifact_paths(path)["log"]
    records = read_loss_log(log) if log.is_file() else []
    verdict = info.get("verdict") or {}
    parts = [f"<{heading}>Fit: {_esc(path.name)}</{heading}>"]
    camera = (
        f"{adapter.camera!r}, field of view {adapter.camera.fov_deg:.0f} deg"
        if adapter.camera
        else "none"
    )
    parts.append(
        f'<p class="meta">backbone {_esc(adapter.backbone)}; camera {_esc(camera)}; '
        f"{_esc(info.get('method', 'not fitted'))}</p>"
    )
    if verdict.get("summary"):
        parts.append(
            f'<div class="verdict {_verdict_class(str(verdict.get("status")))}"><b>Verdict:</b> '
            f"{_esc(verdict['summary'])}</div>"
        )
    else:
        parts.append(
            '<div class="verdict status-warn">No verdict recorded (not fitted by raytun3r adapt).</div>'
        )
    if depth is not None:
        parts.append("<h3>Depth before and after the fit</h3>" + _depth_html(adapter, depth))
    if records:
        window = trend_window(records)
        parts.append(
            "<h3>Loss curves</h3>"
            + _img(loss_figure(_loss_series(records), window), f"loss curves of {path.name}")
            + f"<figcaption>Each term on its own scale: grey, the value of every step (each step "
            f"sees one window); blue, the mean over {window} steps (one pass through the "
            "windows). The title gives the change of the last pass against the one before: a "
            "fit has settled when these are small.</figcaption>"
        )
    else:
        parts.append(f'<p class="note">No loss log ({_esc(log.name)}) beside the adapter.</p>')
    numbers = "<h3>Numbers</h3>" + _table(
        _fit_rows(adapter, records), ["quantity", "value", "note"]
    )
    pe = ""
    if adapter.camera is not None:
        from raytun3r_plugin.apps.adapter_report import pe_correction_field

        values, lens, title = pe_correction_field(adapter)
        pe = (
            "<h3>PE correction</h3>"
            + _img(field_figure(values, title, "PE units", valid=lens), "PE correction")
            + "<figcaption>Size of the positional-embedding correction the adapter adds per "
            "token (grey: outside the lens). Zero everywhere is the identity adapter.</figcaption>"
        )
    # The table and the PE picture side by side, before the wide pictures.
    parts.insert(3, f'<div class="pair"><div>{numbers}</div><div>{pe}</div></div>')
    return "\n".join(parts)


def depth_before_after(
    adapter, source: DepthSource
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Depth of frame ``source.index`` with the patch but no adapter (before the fit) and with
    the fitted adapter (after), on the network input the adapter was fitted at; the frame is run
    with its neighbours (up to three views), as the fit saw windows.

    Returns ``(frame (h, w, 3), before (h, w), after (h, w), valid (h, w) bool)``: ``before``
    scaled to ``after`` by the ratio of their medians over the valid pixels, as predictions are
    known up to scale.
    """
    import torch

    from raytun3r_plugin.apps.inference import predict_with_camera
    from raytun3r_plugin.preprocess import layout_for_inference

    frames = source.frames
    if not 0 <= source.index < len(frames):
        raise InputError(f"frame index {source.index} is outside the {len(frames)} frames")
    layout = layout_for_inference(source.camera, (frames.shape[2], frames.shape[1]), adapter)
    first = max(0, min(source.index - 1, len(frames) - 3))
    window = list(range(first, min(len(frames), first + 3)))
    images = layout.frames(torch.as_tensor(frames[window]))[None]
    depths = [
        predict_with_camera(source.model, layout.native_camera, fitted, images)
        .depth[0, window.index(source.index)]
        .float()
        .cpu()
        .numpy()
        for fitted in (None, adapter)
    ]
    valid = layout.camera.valid_mask().cpu().numpy().astype(bool)
    valid &= np.isfinite(depths[0]) & np.isfinite(depths[1]) & (depths[0] > 0) & (depths[1] > 0)
    before, after = depths
    if valid.any():
        before = before * float(np.median(after[valid]) / np.median(before[valid]))
    frame = images[0, window.index(source.index)].permute(1, 2, 0).cpu().numpy()
    return frame, before, after, valid


def _depth_html(adapter, source: DepthSource) -> str:
    from raytun3r_plugin.figures import depth_figure

    frame, before, after, valid = depth_before_after(adapter, source)
    picture = depth_figure(
        frame,
        {"before the fit (no adapter)": before, "after the fit": after},
        valid=valid,
        unit="depth (network units)",
        frame_title=f"input frame {source.index}",
    )
    change = np.abs(after - before)[valid] / np.maximum(after[valid], 1e-12)
    return (
        _img(picture, "depth before and after the fit")
        + f"<figcaption>The network's depth at its input size ({frame.shape[1]}x{frame.shape[0]} "
        "px), on one colour scale; 'before' is scaled to 'after' by their medians (depth is known "
        f"up to scale). Median relative change: {float(np.median(change)) if change.size else 0:.2%}."
        "</figcaption>"
    )


def _folder_section(folder: Path, kind: str) -> str:
    """The summary table and bar charts of a benchmark or demo folder."""
    from raytun3r_plugin.figures import metric_bars

    name = "results.json" if kind == "benchmark" else "metrics.json"
    data = json.loads((folder / name).read_text(encoding="utf-8"))
    summary = data.get("summary") or []
    if not isinstance(summary, list) or not summary:
        raise InputError(f"{folder / name}: no summary rows")
    preferred = [
        *METRIC_COLUMNS,
        "params",
        "gap_closed",
        "lower_than_vanilla",
        "lower_than_no_adapter",
    ]
    columns = [c for c in preferred if any(c in row for row in summary)]
    parts = ["<h2>Metrics</h2>"]
    if data.get("network"):
        parts.append(f'<p class="meta">network: {_esc(data["network"])}</p>')
    parts.append(_table(summary, columns))
    parts.append(
        "<p class=\"note\">Means over each cell's sequences; see the run's results.md / the "
        "command's printout for every column's definition.</p>"
    )
    for metric in BAR_METRICS:
        if not any(isinstance(row.get(metric), (int, float)) for row in summary):
            continue
        values: dict[str, dict[str, float]] = {}
        for row in summary:
            cell = " ".join(str(row[k]) for k in ("camera", "scene") if k in row) or "all"
            if isinstance(row.get(metric), (int, float)):
                values.setdefault(cell, {})[str(row["method"])] = float(row[metric])
        parts.append(f"<h3>{_esc(metric)}</h3>" + _img(metric_bars(values, metric), metric))
    return "\n".join(parts)


def _fits_section(fits: list[Path]) -> str:
    from raytun3r_plugin.adapter import Adapter
    from raytun3r_plugin.errors import AdapterError

    rows, drawn = [], []
    for path in fits:
        try:
            info = Adapter.load(path).training_info or {}
        except AdapterError as error:  # another safetensors file in the folder
            rows.append({"fit": str(path.name), "status": "not an adapter", "verdict": str(error)})
            continue
        drawn.append(path)
        verdict = info.get("verdict") or {}
        rows.append(
            {
                "fit": str(path.name),
                "status": verdict.get("status", "-"),
                "steps": info.get("steps", "-"),
                "verdict": verdict.get("summary", "-"),
            }
        )
    parts = [f"<h2>Fits ({len(fits)})</h2>", _table(rows, ["fit", "status", "steps", "verdict"])]
    for path in drawn[:CURVES_PER_FOLDER]:
        parts.append(_fit_section(path, None, heading="h3"))
    if len(drawn) > CURVES_PER_FOLDER:
        parts.append(
            f'<p class="note">Curves of the first {CURVES_PER_FOLDER} fits shown; '
            "`raytun3r report FILE.safetensors` draws any one of them.</p>"
        )
    return "\n".join(parts)


def build_report(path: str | os.PathLike, depth: DepthSource | None = None) -> str:
    """The HTML page for ``path`` (see :func:`report_kind`), as a string.

    ``depth``: frames and model for the depth-before-and-after picture of a fit (left out
    without it, and the page says how to get it).

    Raises:
        InputError: nothing to report at ``path``, or ``depth`` given for a folder of several
            fits.
        MissingDependencyError: matplotlib (the ``viz`` extra) is not installed.
    """
    from raytun3r_plugin import __version__

    p = Path(path)
    kind = report_kind(p)
    if depth is not None and kind != "fit":
        raise InputError(f"{p}: depth before and after is drawn for one fit, not a {kind} folder")
    body = []
    if kind == "fit":
        fit = p if p.is_file() else find_fits(p)[0]
        title = f"raytun3r fit report: {fit.name}"
        body.append(_fit_section(fit, depth))
        if depth is None:
            body.append(
                '<p class="note">Depth before and after is drawn when the frames and the model '
                "are given: <code>raytun3r report ADAPTER --frames DIR --backbone NAME "
                "[--weights FILE]</code>.</p>"
            )
    else:
        title = f"raytun3r {kind} report: {p.name}"
        if kind in ("benchmark", "demo"):
            body.append(_folder_section(p, kind))
        fits = find_fits(p)
        if fits:
            body.append(_fits_section(fits))
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{_esc(title)}</title><style>{_STYLE}</style></head><body>"
        f"<h1>{_esc(title)}</h1>"
        f'<p class="meta">{_esc(p)}; written {stamp} by raytun3r {_esc(__version__)}</p>\n'
        + "\n".join(body)
        + "\n</body></html>\n"
    )


def write_report(
    path: str | os.PathLike, out: str | os.PathLike, depth: DepthSource | None = None
) -> Path:
    """Build the page for ``path`` (:func:`build_report`) and write it to ``out`` atomically;
    returns ``out``. Nothing is written when building fails."""
    from raytun3r_plugin.atomic_files import atomic_write_text

    return atomic_write_text(out, build_report(path, depth))
