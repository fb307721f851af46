"""``raytun3r report``: the HTML page of a fit and of a benchmark folder, checked in headless
Chromium (every image decoded, nothing logged as an error), and the smoothing its loss curves use."""

from __future__ import annotations

import json
import re
import shutil
import sys
import tempfile
from html import escape as html_escape
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("depth_anything_3")
pytest.importorskip("matplotlib")

from raytun3r_plugin.apps.cli import main  # noqa: E402
from raytun3r_plugin.apps.report import build_report, report_kind  # noqa: E402
from raytun3r_plugin.figures import smoothed, trend_change  # noqa: E402

NETWORK = "raytun3r-da3-tiny-v3"
SIZE = 112


@pytest.fixture(scope="module")
def fit(tmp_path_factory):
    """A short self-supervised fit of the built-in network on 8 synthetic fisheye frames (as
    ``raytun3r adapt`` writes it) and the frames as an image folder."""
    import cv2

    from raytun3r_plugin import synthetic
    from raytun3r_plugin.adaptation.train import adapt
    from raytun3r_plugin.apps.demo import default_network, demo_camera
    from raytun3r_plugin.apps.fits import adapt_config

    folder = tmp_path_factory.mktemp("report")
    camera = demo_camera(SIZE)
    seq = synthetic.render_sequence("indoor", camera, n_frames=8, seed=1000)
    frames = folder / "frames"
    frames.mkdir()
    for k, image in enumerate(seq.images):
        cv2.imwrite(str(frames / f"{k:03d}.png"), (image[..., ::-1] * 255).round().astype(np.uint8))
    model, _ = default_network(NETWORK)
    out = folder / "fit" / "adapter.safetensors"
    out.parent.mkdir()
    adapter = adapt(
        model,
        camera,
        seq.first_images(8),
        adapt_config(SIZE, 6, seed=0, n_windows=3),
        out_path=out,
        progress=False,
        resume=False,
    )
    return {"adapter": out, "frames": frames, "training": adapter.training_info, "folder": folder}


def _chromium():
    from raytun3r_plugin.apps.browser import find_chromium
    from raytun3r_plugin.errors import MissingDependencyError

    try:
        return find_chromium()
    except MissingDependencyError as error:  # scripts/install.sh installs it where it can
        pytest.skip(str(error))


def _self_contained(page: str) -> None:
    """Nothing the page would fetch: every image inline, no script, no link, no URL."""
    sources = re.findall(r'src="([^"]*)"', page)
    assert sources and all(s.startswith("data:image/png;base64,") for s in sources)
    assert "<script" not in page and "<link" not in page and "http" not in page


def _render(html, png):
    from raytun3r_plugin.apps.browser import render_page

    seen = render_page(html, png)
    assert seen.images and not seen.broken_images, seen.images
    assert seen.errors == []
    import cv2

    shot = cv2.imread(str(png))
    assert shot is not None and shot.shape[:2] == (seen.size[1], seen.size[0])
    return seen, shot


def test_smoothed_trend_is_the_centred_mean_of_the_finite_values():
    rng = np.random.default_rng(0)
    values = rng.normal(size=40)
    values[[3, 17]] = np.nan
    for window in (1, 4, 5):
        got = smoothed(values, window)
        for k in range(values.size):
            lo, hi = max(0, k - (window - 1) // 2), min(values.size, k + window // 2 + 1)
            part = values[lo:hi][np.isfinite(values[lo:hi])]
            if part.size:
                assert got[k] == pytest.approx(part.mean())
            else:  # window 1 on a missing value
                assert np.isnan(got[k])
    steps = np.r_[np.full(6, 2.0), np.full(6, 1.0)]
    assert trend_change(steps, 6) == pytest.approx(-0.5)
    assert trend_change(steps, 7) is None  # fewer than two windows of values


def test_fit_report_renders_in_chromium_with_its_numbers(fit, tmp_path, capsys):
    _chromium()
    html, png = tmp_path / "fit.html", tmp_path / "fit.png"
    args = ["report", str(fit["adapter"]), "--out", str(html)]
    depth = ["--frames", str(fit["frames"]), "--frame", "4", "--backbone", NETWORK]
    assert main([*args, *depth]) == 0
    page = html.read_text(encoding="utf-8")
    _self_contained(page)
    training = fit["training"]
    assert html_escape(training["verdict"]["summary"]) in page
    # The final loss in the table is the mean of the log's last steps, computed here again.
    records = [json.loads(line) for line in fit["adapter"].with_name("adapter.log.jsonl").open()]
    over = training["final_losses_over_steps"]
    expected = np.mean([r["loss"] for r in records[-over:]])
    assert f'<td>final loss</td><td class="num">{expected:.4g}</td>' in page
    for heading in ("Depth before and after the fit", "Loss curves", "PE correction"):
        assert heading in page
    seen, shot = _render(html, png)
    assert len(seen.images) == 3  # depth, loss curves, PE correction
    assert shot.std() > 20  # a drawn page, not a blank one

    # A fit's folder works too, and without frames the page says how to get the depth picture.
    assert main(["report", str(fit["adapter"].parent)]) == 0
    folder_page = (fit["adapter"].parent / "report.html").read_text(encoding="utf-8")
    assert "Depth before and after is drawn when" in folder_page and folder_page.count("<img") == 2


def test_benchmark_report_has_the_table_charts_and_fits(fit, tmp_path):
    _chromium()
    bench = tmp_path / "bench"
    bench.mkdir()
    for suffix in (".safetensors", ".log.jsonl"):
        source = fit["adapter"].with_name("adapter" + suffix)
        shutil.copy(source, bench / f"KB4_190_indoor_90000{suffix}")
    methods = {"vanilla": (1.9, 0.31), "raytun3r, no adapter": (1.4, 0.22), "raytun3r": (1.1, 0.2)}
    summary = [
        {
            "camera": "KB4 190",
            "scene": scene,
            "method": method,
            "d_reproj_px": d,
            "abs_rel": a,
            "sequences": 1,
        }
        for scene in ("indoor", "outdoor")
        for method, (d, a) in methods.items()
    ]
    (bench / "results.json").write_text(json.dumps({"sequences": [], "summary": summary}))
    # --png renders the page in Chromium and fails the command on a broken image or an error.
    assert main(["report", str(bench), "--png", str(tmp_path / "bench.png")]) == 0
    page = (bench / "report.html").read_text(encoding="utf-8")
    _self_contained(page)
    rows = re.findall(r"<tr><td>KB4 190</td><td>(\w+)</td><td>([^<]+)</td>", page)
    assert rows == [(row["scene"], row["method"]) for row in summary]
    assert "<h3>d_reproj_px</h3>" in page and "<h3>abs_rel</h3>" in page
    assert "KB4_190_indoor_90000.safetensors" in page
    assert html_escape(fit["training"]["verdict"]["summary"]) in page
    assert page.count("<img") == 4  # two metric charts, the fit's PE correction and loss curves
    import cv2

    shot = cv2.imread(str(tmp_path / "bench.png"))
    assert shot is not None and shot.shape[1] == 1280 and shot.std() > 20

    # A demo folder (metrics.json, fits under seq*/) reads the same way.
    demo = tmp_path / "demo"
    shutil.copytree(
        bench, demo / "seq0", ignore=shutil.ignore_patterns("results.json", "report.html")
    )
    demo_rows = [{"method": m, "abs_rel": a, "d_reproj_px": d} for m, (d, a) in methods.items()]
    (demo / "metrics.json").write_text(json.dumps({"network": "tiny", "summary": demo_rows}))
    assert report_kind(demo) == "demo"
    demo_page = build_report(demo)
    assert re.findall(r"<tr><td>([^<]+)</td><td class=\"num\">", demo_page)[:3] == list(methods)
    assert "network: tiny" in demo_page and "Fits (1)" in demo_page


def test_report_refuses_what_it_cannot_draw_and_writes_nothing(fit, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["report", str(empty)]) == 2
    assert "nothing to report" in capsys.readouterr().err and not any(empty.iterdir())
    out = tmp_path / "x.html"
    assert (
        main(["report", str(fit["adapter"]), "--frames", str(fit["frames"]), "--out", str(out)])
        == 2
    )
    assert "--backbone" in capsys.readouterr().err and not out.exists()
    bench = tmp_path / "bench"
    bench.mkdir()
    (bench / "results.json").write_text(json.dumps({"summary": []}))
    assert main(["report", str(bench), "--frames", "f", "--backbone", NETWORK]) == 2
    assert "one fit" in capsys.readouterr().err
    assert main(["report", str(bench)]) == 2
    assert "no summary rows" in capsys.readouterr().err and not (bench / "report.html").exists()


def test_loss_picture_falls_back_to_opencv_without_matplotlib(fit, tmp_path, monkeypatch):
    import cv2

    from raytun3r_plugin.adaptation.checkpoint import (
        artifact_paths,
        read_loss_log,
        write_loss_artifacts,
    )

    records = read_loss_log(fit["adapter"])
    paths = artifact_paths(tmp_path / "a.safetensors")
    write_loss_artifacts(paths, records)
    drawn = cv2.imread(str(paths["curve"]))
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)  # import fails: no extra
    write_loss_artifacts(paths, records)
    fallback = cv2.imread(str(paths["curve"]))
    assert fallback.shape == (420, 720, 3)  # plots.line_chart's default size
    assert drawn is not None and drawn.shape != fallback.shape


def test_the_browser_check_sees_a_broken_image_and_a_console_error(tmp_path, monkeypatch):
    """The check the report tests rely on can fail: a page with one good and one undecodable
    image and a script that logs an error."""
    _chromium()
    from raytun3r_plugin.apps.browser import render_page
    from raytun3r_plugin.errors import MissingDependencyError

    good = "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8z8DwHwAFBQIAX8jx0gAAAABJRU5ErkJggg=="
    page = tmp_path / "bad.html"
    page.write_text(
        f'<html><body><img src="data:image/png;base64,{good}">'
        '<img src="data:image/png;base64,AAAA"><script>console.error("drawn wrong")</script>'
        "</body></html>"
    )
    profiles = set(Path(tempfile.gettempdir()).glob("raytun3r-chromium-*"))
    seen = render_page(page, None)
    assert [ok for _, ok in seen.images] == [True, False] and len(seen.broken_images) == 1
    assert seen.errors == ["console: drawn wrong"]
    # Every Chromium process is gone and its profile removed when render_page returns.
    assert set(Path(tempfile.gettempdir()).glob("raytun3r-chromium-*")) <= profiles
    assert not [
        p for p in Path("/proc").glob("[0-9]*/cmdline") if b"raytun3r-chromium-" in _read(p)
    ]
    monkeypatch.setenv("RAYTUN3R_CHROMIUM", str(tmp_path / "no-such-browser"))
    with pytest.raises(MissingDependencyError, match="cannot start Chromium"):
        render_page(page, None)


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError:  # the process ended meanwhile
        return b""
