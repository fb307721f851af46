"""``scripts/train_default_network.py --arch vggt`` (issue 37): a small VGGT-architecture network
trained on the built-in networks' renders with their losses, mapped onto VGGT's conventions, and
loaded back for the benchmark by ``apps.trained_networks``."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.helpers import load_script, tiny_training_args

pytest.importorskip("depth_anything_3")
pytest.importorskip("vggt")  # the stub package (tests/conftest.py puts tests/stubs on the path)

ROOT = Path(__file__).resolve().parents[1]
SMOKE = [
    "--arch",
    "vggt",
    *tiny_training_args(**{"--n-seq": "1", "--n-frames": "2", "--pe-std": "0.5"}),
]


def _rotation(axis_angle) -> np.ndarray:
    """Rodrigues' formula."""
    angle = float(np.linalg.norm(axis_angle))
    k = np.asarray(axis_angle) / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _batch() -> dict:
    """Two samples of three views with known, distinct cam_from_world poses."""
    rng = np.random.default_rng(3)
    poses = np.tile(np.eye(4), (2, 3, 1, 1))
    for b in range(2):
        for s in range(3):
            poses[b, s, :3, :3] = _rotation(rng.normal(0, 0.2, 3))
            poses[b, s, :3, 3] = rng.normal(0, 1.0, 3)
    depth = torch.from_numpy(rng.uniform(1.0, 5.0, (2, 3, 28, 28))).float()
    return {
        "depth": depth,
        "cam_from_world": torch.from_numpy(poses),
        "fov": torch.tensor([60.0, 75.0], dtype=torch.float64),
    }


def test_vggt_pose_targets_are_camera_from_world_relative_to_the_first_view():
    losses = load_script("default_network_losses")
    batch = _batch()
    tg = losses.targets(batch, "vggt")
    poses = batch["cam_from_world"].numpy()
    scale = tg["scale"].numpy()
    for b in range(2):
        for s in range(3):
            # independent: camera s from camera 0 = T_s inv(T_0), translation in the depth scale
            expected = poses[b, s] @ np.linalg.inv(poses[b, 0])
            expected[:3, 3] /= scale[b]
            assert np.allclose(tg["pose"][b, s].numpy(), expected, atol=1e-5)
    da3 = losses.targets(batch)
    assert torch.equal(da3["pose"], da3["c2w"])  # DA3's encoding is world_from_cam


def test_vggt_pose_loss_vanishes_on_vggts_own_encoding_of_the_targets():
    from vggt.utils.pose_enc import extri_intri_to_pose_encoding

    losses = load_script("default_network_losses")
    tg = losses.targets(_batch(), "vggt")
    H = W = 28
    focal = tg["focal"][:, None].expand(2, 3)
    K = torch.zeros(2, 3, 3, 3)
    K[..., 0, 0] = K[..., 1, 1] = focal
    K[..., 0, 2], K[..., 1, 2], K[..., 2, 2] = W / 2, H / 2, 1.0
    encoding = extri_intri_to_pose_encoding(tg["pose"][..., :3, :], K, (H, W))
    weights = {"pose": 1.0, "quat": 1.0}
    ls = losses.pose_losses(encoding, tg, weights, zero=torch.zeros(()))
    assert float(ls["rot"]) < 1e-3 and float(ls["trans"]) < 1e-5 and float(ls["fov"]) < 1e-5
    assert float(ls["rot_deg"]) < 0.05 < float(ls["rot_gt_deg"])
    # the same numbers read as DA3's (world_from_cam) encoding are wrong: the mapping matters
    tg_da3 = {**tg, "pose": tg["c2w"], "arch": "da3"}
    assert float(losses.pose_losses(encoding, tg_da3, weights, torch.zeros(()))["trans"]) > 0.05


def test_vggt_smoke_run_resumes_exactly_and_exports_a_loadable_network(tmp_path):
    train = load_script("train_default_network")
    a, b = tmp_path / "a", tmp_path / "b"
    assert train.main(["--out", str(a), "--stop-after", "1", *SMOKE]) == 0
    assert train.main(["--out", str(a), *SMOKE, "--export", str(a / "net.safetensors")]) == 0
    b.mkdir()
    shutil.copy(a / "train_data.npz", b / "train_data.npz")
    assert train.main(["--out", str(b), *SMOKE]) == 0  # uninterrupted
    from safetensors.torch import load_file

    wa, wb = (
        load_file(str(a / "checkpoint.safetensors")),
        load_file(str(b / "checkpoint.safetensors")),
    )
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
    assert "aggregator.patch_embed.pos_embed" in wa and not any(
        k.startswith("backbone.") for k in wa
    )
    # the PE table started as the sin-cos map (not the stub's trunc-normal 0.02), and moved
    first = train.sincos_table(37, 32, 0.5)
    assert float((wa["aggregator.patch_embed.pos_embed"][0, 1:] - first).abs().max()) < 0.05
    record = json.loads((a / "net.json").read_text())
    assert record["arch"] == "vggt" and record["training"]["args"]["arch"] == "vggt"

    from raytun3r_plugin.apps.trained_networks import load_trained_network
    from raytun3r_plugin.registry import spec_for

    model, description = load_trained_network(a / "net.safetensors")
    assert "VGGT" in description and type(model).__name__ == "VGGT"
    from raytun3r_plugin.apps.trained_networks import network_from

    # The scripts' --weights beats --network; without it the built-in network is named.
    named = network_from("raytun3r-da3-tiny-v3", a / "net.safetensors")
    assert named[1] == description and type(named[0]).__name__ == "VGGT"
    built_in, said = network_from("raytun3r-da3-tiny-v3")
    assert said.startswith("raytun3r-da3-tiny-v3: ") and type(built_in).__name__ != "VGGT"
    assert spec_for(model)[0].family == "vggt"
    from raytun3r_plugin.registry import native_input_size

    assert native_input_size(model) == 28  # the size it was trained at, not VGGT-1B's 518
    trained = {k: v.float() for k, v in load_file(str(a / "net.safetensors")).items()}
    state = model.state_dict()
    assert all(torch.equal(state[k], trained[k]) for k in trained)
    images = torch.rand(1, 2, 3, 28, 28)
    with torch.no_grad():
        out = model(images)
    assert out["depth"].shape == (1, 2, 28, 28, 1) and out["pose_enc"].shape == (1, 2, 9)


def test_vggt_arch_refuses_the_da3_only_auxiliaries(tmp_path):
    train = load_script("train_default_network")
    with pytest.raises(SystemExit, match="not available with --arch vggt"):
        train.main(["--out", str(tmp_path / "x"), *SMOKE, "--aux-flow", "1"])
    assert not (tmp_path / "x").exists()


def test_vggt_arch_without_the_stub_names_pythonpath(monkeypatch):
    vggt = load_script("default_network_vggt")
    monkeypatch.setitem(sys.modules, "vggt", None)  # import vggt now raises ImportError
    monkeypatch.setitem(sys.modules, "vggt.models.vggt", None)
    with pytest.raises(SystemExit, match="PYTHONPATH=tests/stubs"):
        vggt.require_vggt()


def test_load_trained_network_refuses_a_file_without_its_record(tmp_path):
    from raytun3r_plugin.apps.trained_networks import load_trained_network
    from raytun3r_plugin.errors import WeightsError

    weights = tmp_path / "net.safetensors"
    weights.write_bytes(b"")
    with pytest.raises(WeightsError, match="build record"):
        load_trained_network(weights)
    weights.with_suffix(".json").write_text(json.dumps({"arch": "pi3", "build_kwargs": {}}))
    with pytest.raises(WeightsError, match="unknown arch 'pi3'"):
        load_trained_network(weights)


def test_the_benchmark_fits_and_scores_a_trained_vggt_network(tmp_path):
    """The synthetic benchmark runs end to end on an exported VGGT (the path of
    ``benchmarks/fisheye_synthetic.py --weights``): every row, a fitted adapter, its gap."""
    train = load_script("train_default_network")
    out = tmp_path / "run"
    assert train.main(["--out", str(out), *SMOKE, "--export", str(out / "net.safetensors")]) == 0
    from raytun3r_plugin.apps.benchmark import (
        CAMERAS,
        DEVELOPMENT_SEED,
        run_benchmark,
        sequence_seed,
    )
    from raytun3r_plugin.apps.trained_networks import load_trained_network

    model, description = load_trained_network(out / "net.safetensors")
    from raytun3r_plugin.errors import InputError

    with pytest.raises(InputError, match="first_sequence"):
        run_benchmark(model, tmp_path / "refused", first_sequence=-1)
    assert not (tmp_path / "refused").exists()
    table = run_benchmark(
        model,
        tmp_path / "bench",
        size=56,
        n_adapt=4,
        n_eval=3,
        steps=2,
        sequences=1,
        first_sequence=1,
        cameras=CAMERAS[-1:],
        scenes=("indoor",),
        network=description,
        base_seed=DEVELOPMENT_SEED,
    )
    assert "small VGGT-architecture network" in table
    rows = json.loads((tmp_path / "bench" / "results.json").read_text())["sequences"]
    # the second sequence of the DS 195 indoor cell: the seed it has in a full run
    assert {row["seed"] for row in rows} == {sequence_seed(2, 0, 1, DEVELOPMENT_SEED)}
    methods = {row["method"] for row in rows}
    assert {"vanilla", "raytun3r, no adapter", "raytun3r", "raytun3r, supervised"} <= methods
    fitted = next(row for row in rows if row["method"] == "raytun3r")
    assert fitted["params"] > 0 and np.isfinite(fitted["abs_rel"])


def test_benchmark_script_refuses_weights_with_a_network_and_unknown_cameras(
    tmp_path, monkeypatch, capsys
):
    bench = load_script("fisheye_synthetic", "benchmarks")
    for extra, message in (
        (["--weights", "x.safetensors", "--network", "raytun3r-da3-tiny"], "no --network"),
        (["--cameras", "KB4 999"], "unknown ['KB4 999']"),
    ):
        monkeypatch.setattr(sys, "argv", ["fisheye_synthetic.py", "--out", str(tmp_path), *extra])
        with pytest.raises(SystemExit) as stopped:
            bench.main()
        assert stopped.value.code == 2 and message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # refused before anything ran
