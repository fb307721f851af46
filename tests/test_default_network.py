"""The shipped default network ``raytun3r-da3-tiny`` (issue 7): packaged weights, model card,
held-out sanity check and the training script's smoke run + resume."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.helpers import load_script, tiny_training_args

pytest.importorskip("depth_anything_3")

ROOT = Path(__file__).resolve().parents[1]
CARD = ROOT / "docs" / "model_card_raytun3r_da3_tiny.md"
NAME = "raytun3r-da3-tiny"


def _default():
    from raytun3r_plugin.patches import da3_default

    return da3_default


def _weights() -> Path:
    path = _default().data_dir() / _default().WEIGHTS_FILE
    if not path.is_file():
        pytest.fail(
            f"packaged weights {path} are missing (run scripts/train_default_network.py --export)"
        )
    return path


def test_builder_loads_packaged_weights_without_path():
    _weights()
    model = _default().BUILDERS[NAME]()
    assert model.raytun3r_name == NAME
    assert not model.training
    from raytun3r_plugin.patches.da3 import describe

    assert describe(model).name == NAME


def test_load_backbone_needs_no_path():
    _weights()
    from raytun3r_plugin import available_backbones, load_backbone

    if NAME not in available_backbones():
        pytest.skip("patches/da3.py does not merge da3_default.BUILDERS yet (the lead hooks it)")
    model = load_backbone(NAME)
    assert model.raytun3r_name == NAME and not model.training


def test_weight_file_small_and_sidecar_matches():
    path = _weights()
    assert path.stat().st_size <= 5 * 1000 * 1000  # the project keeps files in git under 5 MB
    kwargs = _default().build_kwargs()
    from safetensors import safe_open

    with safe_open(str(path), "pt") as fh:
        recorded = json.loads(fh.metadata()["build_kwargs"])
    assert {k: (tuple(v) if isinstance(v, list) else v) for k, v in recorded.items()} == kwargs


def test_missing_weights_raise_weights_error(tmp_path, monkeypatch):
    from raytun3r_plugin.errors import WeightsError

    module = _default()
    monkeypatch.setattr(module, "data_dir", lambda: tmp_path)
    with pytest.raises(WeightsError, match="missing"):
        module.build()


def test_model_card_numbers_match_metrics_sidecar():
    metrics_path = _default().data_dir() / _default().METRICS_FILE
    assert CARD.is_file(), "model card missing"
    assert metrics_path.is_file(), "metrics sidecar missing (run scripts/eval_default_network.py)"
    metrics = json.loads(metrics_path.read_text())
    text = CARD.read_text()
    block = text.split("<!-- metrics:begin -->", 1)[1].split("<!-- metrics:end -->", 1)[0]
    rows = [
        line
        for line in block.splitlines()
        if line.startswith("| ") and re.search(r"\d", line.split("|")[2])
    ]
    keys = [
        "abs_rel",
        "abs_rel_constant",
        "abs_rel_ratio",
        "delta_125",
        "delta_125_constant",
        "rotation_deg",
        "rotation_deg_no_rotation",
        "rotation_ratio",
        "translation_deg",
    ]
    assert len(rows) == len(metrics["results"]) == 3
    for row, name in zip(rows, ("pinhole", "kb4_120", "kb4_190"), strict=True):
        cells = [c.strip() for c in row.strip().strip("|").split("|")]
        for key, cell in zip(keys, cells[1:10], strict=True):
            assert float(cell) == pytest.approx(metrics["results"][name][key], abs=5e-5), (
                name,
                key,
            )
    # the pinhole headline numbers quoted in the card's summary
    p = metrics["results"]["pinhole"]
    assert f"{p['abs_rel_ratio']:.2f}" in text.split("<!-- metrics:begin -->")[0]
    assert f"{p['rotation_ratio']:.2f}" in text.split("<!-- metrics:begin -->")[0]


def test_beats_constant_depth_on_a_held_out_pinhole_frame():
    _weights()
    train = load_script("train_default_network")
    from raytun3r_plugin import predict
    from raytun3r_plugin.metrics import abs_rel
    from raytun3r_plugin.synthetic import render_sequence

    seed = 4242  # held out: training seeds start at train.TRAIN_SEED_BASE
    assert seed < train.TRAIN_SEED_BASE
    cam = train.pinhole_camera(112, 70.0)
    seq = render_sequence("indoor", cam, n_frames=3, seed=seed, flow_px=10.0, supersample=1)
    z = seq.meta["per_frame"]["z_depth"][[0, 2]]
    model = _default().BUILDERS[NAME]()
    images = torch.from_numpy(seq.images[[0, 2]]).permute(0, 3, 1, 2)[None]
    with torch.no_grad():
        depth = predict(model, images).depth[0].numpy()
    ok = z > 0
    ours = float(np.mean(abs_rel(depth, z, ok)))
    const = float(np.mean(abs_rel(np.ones_like(z), z, ok)))
    assert ours < const, (ours, const)


def test_training_smoke_run_resumes_exactly(tmp_path):
    train = load_script("train_default_network")
    common = tiny_training_args(**{"--n-seq": "1", "--n-frames": "2"})
    a, b = tmp_path / "a", tmp_path / "b"
    assert train.main(["--out", str(a), "--stop-after", "1", *common]) == 0
    assert json.loads((a / "checkpoint.json").read_text())["step"] == 1
    assert train.main(["--out", str(a), *common]) == 0  # resumes from step 1
    assert json.loads((a / "checkpoint.json").read_text())["step"] == 2
    b.mkdir()
    shutil.copy(a / "train_data.npz", b / "train_data.npz")  # same data, skip re-rendering
    assert train.main(["--out", str(b), *common]) == 0  # uninterrupted
    from safetensors.torch import load_file

    wa, wb = (
        load_file(str(a / "checkpoint.safetensors")),
        load_file(str(b / "checkpoint.safetensors")),
    )
    assert wa.keys() == wb.keys()
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    rows = (a / "log.csv").read_text().strip().splitlines()
    assert rows[0].startswith("step,") and len(rows) == 3


def test_quaternion_target_is_da3s_encoding_of_the_rotation():
    train = load_script("train_default_network")
    from depth_anything_3.model.utils.transform import quat_to_mat

    angles = torch.tensor(
        [[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [2.5, 0.4, -1.0]], dtype=torch.float64
    )

    def rot(a):
        cx, cy, cz = torch.cos(a)
        sx, sy, sz = torch.sin(a)
        rx = torch.tensor([[1, 0, 0], [0, cx, -sx], [0, sx, cx]], dtype=torch.float64)
        ry = torch.tensor([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]], dtype=torch.float64)
        rz = torch.tensor([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]], dtype=torch.float64)
        return rz @ ry @ rx

    rotations = torch.stack([rot(a) for a in angles])
    quat = train.quaternion_target(rotations)
    assert torch.allclose(quat.norm(dim=-1), torch.ones(3, dtype=torch.float64), atol=1e-9)
    assert (quat[:, 3] >= 0).all()  # real part last and non-negative: one encoding per rotation
    assert torch.allclose(quat_to_mat(quat), rotations, atol=1e-9)


def test_sincos_pe_init_has_the_requested_std_and_is_resolved_by_the_token_grid():
    train = load_script("train_default_network")
    table = train.sincos_table(37, 128, 0.5)
    assert table.shape == (37 * 37, 128)
    assert float(table.std()) == pytest.approx(0.5, rel=1e-4)
    # DA3 resizes the 37x37 table to the token grid (8x8 at 112 px): the map must survive that,
    # so neighbouring tokens of the 8x8 grid still differ.
    grid = table.reshape(1, 37, 37, 128).permute(0, 3, 1, 2)
    small = torch.nn.functional.interpolate(grid, size=(8, 8), mode="bicubic", align_corners=False)[
        0
    ]
    step = (small[:, :, 1:] - small[:, :, :-1]).norm(dim=0)
    assert float(step.min()) > 0.1 * float(small.norm(dim=0).mean())


def test_training_with_pe_init_and_quaternion_loss_starts_from_the_sincos_table(tmp_path):
    train = load_script("train_default_network")
    common = tiny_training_args(
        **{
            "--n-seq": "1",
            "--n-frames": "2",
            "--steps": "1",
            "--pe-std": "0.5",
            "--w-quat": "10",
            "--lr": "0",
        }
    )
    assert train.main(["--out", str(tmp_path), *common]) == 0
    from safetensors.torch import load_file

    weights = load_file(str(tmp_path / "checkpoint.safetensors"))
    key = next(k for k in weights if k.endswith("pretrained.pos_embed"))
    table = weights[key][0]
    assert torch.allclose(
        table[1:],
        train.sincos_table(int(round((table.shape[0] - 1) ** 0.5)), table.shape[1], 0.5),
        atol=1e-6,
    )
    header, row = (tmp_path / "log.csv").read_text().strip().splitlines()[:2]
    quat_loss = float(row.split(",")[header.split(",").index("quat")])
    assert quat_loss > 0


def test_fixed_batch_trains_on_the_first_batch_every_step(tmp_path, monkeypatch):
    train = load_script("train_default_network")
    requested = []
    original = train.make_batch

    def recording(data, seed, step, *args):
        requested.append(step)
        return original(data, seed, step, *args)

    monkeypatch.setattr(train, "make_batch", recording)
    common = tiny_training_args(**{"--n-seq": "1", "--steps": "3", "--ckpt-every": "3"})
    assert train.main(["--out", str(tmp_path / "fixed"), "--fixed-batch", *common]) == 0
    assert requested == [0, 0, 0]
    requested.clear()
    assert train.main(["--out", str(tmp_path / "normal"), *common]) == 0
    assert requested == [0, 1, 2]


def test_flow_targets_match_a_known_translation():
    train = load_script("train_default_network")
    H = W = 28
    depth = torch.full((1, 2, H, W), 2.0)
    depth[0, 0, :14, :14] = 0.0  # the first token has no depth: invalid
    poses = torch.eye(4, dtype=torch.float64).repeat(1, 2, 1, 1)
    poses[0, 1, 0, 3] = -0.2  # view 2 sees the scene 0.2 m to the left: points move left
    batch = {"depth": depth, "cam_from_world": poses, "fov": torch.tensor([90.0])}
    flow, ok = train.flow_targets(batch)
    assert flow.shape == (1, 2, 4, 2) and ok.shape == (1, 2, 4)
    f = (W / 2.0) / math.tan(math.radians(45.0))  # 14 px
    # u_b - u_a = f * t_x / z = 14 * -0.2 / 2 = -1.4 px, in units of half the width (14 px)
    assert torch.allclose(flow[0, 0, 1:, 0], torch.full((3,), -0.2 * f / 2.0 / (W / 2.0)))
    assert torch.allclose(flow[0, 1, :, 0], torch.full((4,), 0.2 * f / 2.0 / (W / 2.0)))
    assert torch.allclose(flow[..., 1], torch.zeros(1, 2, 4))
    assert not ok[0, 0, 0] and ok[0, 0, 1:].all() and ok[0, 1].all()


def test_flow_aux_pose_only_jitter_run_resumes_exactly_and_exports_no_aux_head(tmp_path):
    train = load_script("train_default_network")
    common = tiny_training_args(
        **{
            "--aux-flow": "1",
            "--aux-flow-kind": "both",
            "--aux-attn": "1",
            "--jitter-frac": "0.5",
            "--jitter-deg": "5",
            "--val-seqs": "1",
            "--rot-aug-deg": "3",
            "--rot-aug-frac": "1",
            "--w-tdir": "1",
        }
    )
    common.append("--pose-only")
    a, b = tmp_path / "a", tmp_path / "b"
    assert train.main(["--out", str(a), "--stop-after", "1", *common]) == 0
    assert train.main(["--out", str(a), *common, "--export", str(a / "net.safetensors")]) == 0
    b.mkdir()
    for name in ("train_data.npz", "val_data.npz"):
        shutil.copy(a / name, b / name)
    assert train.main(["--out", str(b), *common]) == 0
    from safetensors.torch import load_file

    for name in ("checkpoint.safetensors", "aux.safetensors"):
        wa, wb = load_file(str(a / name)), load_file(str(b / name))
        assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa), name
    exported = load_file(str(a / "net.safetensors"))
    aux_keys = load_file(str(a / "aux.safetensors")).keys()
    assert not any("mlps" in k or k.startswith("flowaux") for k in exported)
    assert aux_keys and not set(aux_keys) & set(exported)
    # the exported network is the plain builder's architecture: same keys as a run without aux
    c = tmp_path / "c"
    c.mkdir()
    shutil.copy(a / "train_data.npz", c / "train_data.npz")
    plain = tiny_training_args(**{"--jitter-frac": "0.5", "--jitter-deg": "5", "--steps": "1"})
    assert train.main(["--out", str(c), *plain, "--export", str(c / "net.safetensors")]) == 0
    assert exported.keys() == load_file(str(c / "net.safetensors")).keys()
    header, *rows = (a / "log.csv").read_text().strip().splitlines()
    cols = header.split(",")
    for col in ("flow", "attn", "tdir", "trans_deg", "val_rot_ratio", "val_trans_deg"):
        assert col in cols
    last = dict(zip(cols, rows[-1].split(","), strict=True))
    assert float(last["flow"]) > 0 and float(last["attn"]) > 0 and float(last["val_rot_ratio"]) > 0
    assert float(last["depth_si"]) == 0.0  # pose-only: no depth loss


def test_jitter_rotates_cameras_about_their_centres():
    train = load_script("train_default_network")
    plain = train.render_one(10_001, 28, 2)
    jit = train.render_one(10_001, 28, 2, jitter_deg=5.0)
    from raytun3r_plugin.synthetic.generate import camera_centres

    assert np.allclose(camera_centres(plain["poses"]), camera_centres(jit["poses"]), atol=1e-9)
    assert not np.allclose(plain["poses"][:, :3, :3], jit["poses"][:, :3, :3])
    assert train.jittered(10_001, 1.0) and not train.jittered(10_001, 0.0)


def test_rotate_views_is_an_exact_pinhole_rotation():
    train = load_script("train_default_network")
    from raytun3r_plugin.poses import rotations_from_rotvecs

    rng = np.random.default_rng(0)
    S, H, W = 2, 28, 28
    im = rng.uniform(size=(S, H, W, 3)).astype(np.float32)
    de = rng.uniform(1.0, 3.0, size=(S, H, W)).astype(np.float32)
    po = np.tile(np.eye(4), (S, 1, 1))
    same = train.rotate_views(im, de, po, 70.0, np.tile(np.eye(3), (S, 1, 1)))
    assert same is not None
    assert np.allclose(same[0], im, atol=1e-5) and np.allclose(same[1], de, atol=1e-5)
    assert same[3] == pytest.approx(70.0)
    # a turned camera: the new pose is R @ old, the zoom keeps every pixel inside (no border)
    rots = rotations_from_rotvecs(np.array([[0.0, 0.05, 0.0], [0.03, 0.0, 0.02]]))
    im2, de2, po2, fov2 = train.rotate_views(im, np.full_like(de, 2.0), po, 70.0, rots)
    assert np.allclose(po2[:, :3, :3], rots) and fov2 < 70.0
    assert (de2 > 0).all()
    # a fronto-parallel plane at z = 2 seen by a camera turned by R: z' = (R X)_z >= 0
    assert np.all(np.abs(de2 - 2.0) < 0.2)


def test_v3_is_a_second_built_in_of_the_same_architecture():
    """``raytun3r-da3-tiny-v3`` (issue 13) loads without a path, under its own name, and is not v2."""
    from raytun3r_plugin.patches.da3 import describe

    from raytun3r_plugin.weights import available_backbones, load_backbone

    module = _default()
    assert module.NAME_V3 in available_backbones()
    v2, v3 = load_backbone(NAME), load_backbone(module.NAME_V3)
    assert describe(v3).name == module.NAME_V3 and not v3.training
    assert module.build_kwargs(module.NAME_V3) == module.build_kwargs(NAME)
    assert v2.state_dict().keys() == v3.state_dict().keys()
    assert not torch.equal(v2.backbone.pretrained.pos_embed, v3.backbone.pretrained.pos_embed)
    size = (module.data_dir() / f"{module.NAME_V3}.safetensors").stat().st_size
    assert size < 10 * 2**20
    metrics = json.loads((module.data_dir() / f"{module.NAME_V3}.metrics.json").read_text())
    pinhole = metrics["results"]["pinhole"]
    # The rule fixed before the run (model card, "Versions"): what v3 was shipped on.
    assert metrics["network"] == module.NAME_V3
    assert pinhole["rotation_ratio"] <= 0.5 and pinhole["translation_deg"] < 90
    assert pinhole["abs_rel"] <= 0.185


def test_the_demo_and_benchmarks_fit_every_network_with_the_library_recipe():
    """v3 is the default network; every built-in network's fits take the library's ``default``
    recipe (hybrid pose source, pose weight 0.3, the lens-gated teacher at 10 on three views),
    and nothing is keyed by a network's name; v2's earlier fit is the ``targets`` recipe."""
    import inspect

    from raytun3r_plugin.adaptation.config import AdaptConfig
    from raytun3r_plugin.apps import demo
    from raytun3r_plugin.apps.demo import default_network
    from raytun3r_plugin.apps.fits import adapt_config
    from raytun3r_plugin.errors import InputError

    model, description = default_network()
    assert model.raytun3r_name == "raytun3r-da3-tiny-v3" and description.startswith(
        model.raytun3r_name
    )
    shipped = adapt_config(112, 10)
    assert shipped.recipe == "default"
    assert shipped.pose_source == "hybrid" and shipped.weights.pose == pytest.approx(0.3)
    assert shipped.weights.teacher == pytest.approx(10.0) and shipped.teacher_max_coverage == 0.5
    assert shipped.teacher_views == ("centre", "left", "right")
    assert shipped.teacher_view_weights == {"centre": 1.0, "left": 0.3, "right": 0.3}
    assert shipped.view_weights() == (1.0, 0.3, 0.3)
    assert shipped.to_dict()["teacher_view_weights"] == shipped.teacher_view_weights
    # The demo's fit is the library's own AdaptConfig() at its size and budget, resolved for the
    # model as adapt() resolves it; without a model, the recipe alone (its own step).
    library = AdaptConfig(input_size=112, steps=10, checkpoint_every=0)
    demo_fit = adapt_config(112, 10, model=model).resolved_for(model)
    assert demo_fit.identity() == library.resolved_for(model).identity()
    assert shipped.identity() == library.resolved_for(None).identity()
    assert adapt_config(112, 10, teacher_weight=0.0).weights.teacher == 0.0
    # Other views given without weights count equally (the recipe's weights name its views).
    centre = adapt_config(112, 10, teacher_views=["centre"])
    assert centre.teacher_views == ("centre",) and centre.teacher_view_weights is None
    only = adapt_config(112, 10, teacher_views=["centre"], teacher_view_weights={"centre": 2.0})
    assert only.view_weights() == (2.0,)
    with pytest.raises(InputError, match="teacher_view_weights"):
        adapt_config(112, 10, teacher_view_weights={"left": 1.0})
    # Nothing in a fit is keyed by a network's name.
    assert "network" not in inspect.signature(adapt_config).parameters
    assert not hasattr(demo, "NETWORK_FIT")
    v2_earlier = adapt_config(112, 10, recipe="targets")
    assert v2_earlier.pose_source == "targets" and v2_earlier.weights.teacher == 0.0
    v2, _ = default_network("raytun3r-da3-tiny")
    assert v2.raytun3r_name == "raytun3r-da3-tiny"
    differs = any(
        not torch.equal(a, b)
        for a, b in zip(model.state_dict().values(), v2.state_dict().values(), strict=True)
    )
    assert differs


def test_adapt_config_pose_weight_replaces_only_the_pose_term():
    """The benchmarks pass a pose weight through ``adapt_config``; the other weights stay the
    recipe's, and a pose weight next to explicit weights is refused rather than one of them
    being dropped."""
    from raytun3r_plugin.adaptation.config import DEFAULT_WEIGHTS
    from raytun3r_plugin.adaptation.losses import LossWeights
    from raytun3r_plugin.apps.fits import adapt_config
    from raytun3r_plugin.errors import InputError

    weights = adapt_config(112, 10, pose_source="model", pose_weight=3.0).weights.as_dict()
    assert weights == {**DEFAULT_WEIGHTS, "pose": 3.0}
    # Another pose source keeps the recipe's weights (the record lists the change).
    other = adapt_config(112, 10, pose_source="model")
    assert other.weights.as_dict() == DEFAULT_WEIGHTS
    assert other.recipe_record()["changes"]["pose_source"] == ["hybrid", "model"]
    explicit = LossWeights(**{**DEFAULT_WEIGHTS, "smooth": 5.0})
    assert adapt_config(112, 10, weights=explicit).weights == explicit
    with pytest.raises(InputError, match="pose_weight or weights"):
        adapt_config(112, 10, pose_weight=0.3, weights=LossWeights())


def test_the_rig_benchmark_fits_without_the_teacher_that_adapt_rig_refuses(monkeypatch):
    """benchmarks/rig.py fits with the rig recipe; adapt_rig has no teacher term yet and
    refuses one, so both rig fits leave it out (before, the script stopped at that refusal)."""
    rig_bench = load_script("rig", "benchmarks")
    seen = []

    class Stop(Exception):
        pass

    def record(model, camera, images, config, **kwargs):
        seen.append(config)
        raise Stop

    monkeypatch.setattr(rig_bench, "adapt", record)
    with pytest.raises(Stop):
        rig_bench.one_rig(None, rig_bench.RIG_SEED, 3)
    (config,) = seen
    assert config.weights.teacher == 0.0 and config.pose_source == "hybrid"
    assert config.weights.pose == pytest.approx(0.3)
