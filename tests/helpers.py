"""Small builders shared by the tests (not fixtures, so tests can call them with arguments)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import torch


def pinhole(width: int = 84, height: int = 70, focal: float = 60.0):
    from raytun3r_plugin.cameras import Pinhole

    return Pinhole(
        width, height, {"fx": focal, "fy": focal, "cx": (width - 1) / 2, "cy": (height - 1) / 2}
    )


def fisheye(width: int = 84, height: int = 70, fov_deg: float = 190.0, k1: float = 0.01):
    """An equidistant-like KB4 whose image circle (fov_deg) fits the shorter side."""
    from raytun3r_plugin.cameras import fisheye as build

    return build((width, height), fov_deg, "kb4", k=(k1, 0.0, 0.0, 0.0))


def small_kb4():
    """The 84 x 70 equidistant KB4 of 190 degrees the small fit tests render their rooms with."""
    from raytun3r_plugin.cameras import KannalaBrandt4

    return KannalaBrandt4(84, 70, [22.0, 22.0, 41.5, 34.5, 0.0, 0.0, 0.0, 0.0], max_fov_deg=190.0)


def small_fit_config(tmp_path, recipe: str, **changes):
    """A few-step fit of the tiny networks at 84 px on 2 windows, cached under ``tmp_path``,
    unguarded and without checkpoints: ``recipe``'s settings with ``changes`` on top."""
    from raytun3r_plugin.adaptation.config import AdaptConfig

    settings = {
        "steps": 4,
        "input_size": 84,
        "n_windows": 2,
        "checkpoint_every": 0,
        "cache_dir": str(tmp_path),
        "matcher_options": {"border_px": 2},
        "seed": 0,
        "guard": False,
        "teacher_views": ("centre",),
        **changes,
    }
    return AdaptConfig.from_recipe(recipe, **settings)


def outputs(model, images):
    from raytun3r_plugin import predict

    with torch.no_grad():
        prediction = predict(model, images)
    return {
        "depth": prediction.depth,
        "conf": prediction.confidence,
        "pose": prediction.cam_from_world,
    }


def max_relative_difference(a: dict, b: dict) -> float:
    worst = 0.0
    for key in a:
        scale = max(float(a[key].abs().max()), 1e-12)
        worst = max(worst, float((a[key] - b[key]).abs().max()) / scale)
    return worst


def randomise_(adapter, scale: float = 0.05, seed: int = 0):
    """Fill an adapter with a smooth, trained-looking nonzero correction."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in adapter.parameters():
            parameter.copy_(torch.randn(parameter.shape, generator=generator) * scale)
        if adapter.rope is not None:
            bins = adapter.rope["radial"].shape[0]
            adapter.rope["radial"].copy_(torch.linspace(0, 1, bins) ** 2 * 0.8)
    return adapter


def snapshot(model):
    """Everything remove() must restore: parameters/buffers and every module's attributes."""
    state = {k: v.clone() for k, v in model.state_dict().items()}
    attributes = {name: sorted(vars(module)) for name, module in model.named_modules()}
    return state, attributes


def assert_same_snapshot(model, snap):
    state, attributes = snap
    now_state, now_attributes = snapshot(model)
    assert now_state.keys() == state.keys()
    assert all(torch.equal(now_state[k], state[k]) for k in state)
    assert now_attributes == attributes


def fail_install_at(monkeypatch, call: int = 3) -> dict:
    """Make the ``call``-th replacement install raise; returns the call counter."""
    from raytun3r_plugin import patching

    calls = {"n": 0}
    real_install = patching._install

    def flaky_install(*args):
        calls["n"] += 1
        if calls["n"] == call:
            raise RuntimeError("injected failure")
        real_install(*args)

    monkeypatch.setattr(patching, "_install", flaky_install)
    return calls


def outputs_from_threads(models: dict, images, repeats: int = 1) -> dict:
    """Run ``outputs`` for every named model, each in its own thread at the same time."""
    import threading

    results = {}

    def run(name, model):
        for _ in range(repeats):
            results[name] = outputs(model, images)

    threads = [threading.Thread(target=run, args=item) for item in models.items()]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return results


REPO = Path(__file__).resolve().parents[1]


def load_script(name: str, folder: str = "scripts"):
    """``<folder>/<name>.py`` of the repository (``scripts``, ``benchmarks``, ``experiments``)
    as a module, its siblings importable while it loads."""
    where = REPO / folder
    spec = importlib.util.spec_from_file_location(name, where / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(where))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(where))
    return module


def tiny_training_args(**changes: str) -> list[str]:
    """Arguments of a seconds-long ``scripts/train_default_network.py --tiny`` run at 28 px;
    ``changes`` maps options (``"--steps"``) to other values or adds options."""
    args = {
        "--size": "28",
        "--n-seq": "2",
        "--n-frames": "3",
        "--max-gap": "1",
        "--batch": "1",
        "--steps": "2",
        "--warmup": "1",
        "--log-every": "1",
        "--ckpt-every": "1",
        "--threads": "1",
        **changes,
    }
    return ["--tiny", *[x for kv in args.items() for x in kv]]
