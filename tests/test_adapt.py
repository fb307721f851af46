"""Online adaptation (docs/conventions.md section 7, invariant 5) on the tiny real DA3 network.

The segment is the analytic textured room of ``test_losses.py`` seen by a 190-degree fisheye at
84x70 px; matches come from the default DIS matcher, targets from MAGSAC++.
"""

from __future__ import annotations

import json
import math

import pytest
import torch

from raytun3r_plugin import Adapter, apply, handle_of
from raytun3r_plugin.adaptation.checkpoint import artifact_paths, load_checkpoint, read_loss_log
from raytun3r_plugin.adaptation.config import (
    SELF_SUPERVISED_WEIGHTS,
    SUPERVISED_WEIGHTS,
    AdaptConfig,
)
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.errors import AlreadyAppliedError, InputError
from raytun3r_plugin.preprocess import RULE, RULE_VERSION, input_layout
from tests.helpers import fisheye
from tests.test_losses import room_sequence

pytest.importorskip("depth_anything_3")
from raytun3r_plugin.patches.da3_networks import build_tiny_network  # noqa: E402

TERMS = ("reproj", "smooth", "l2", "tv", "pose")
RECORDED_RULE = {"rule": RULE, "rule_version": RULE_VERSION}


@pytest.fixture(scope="module")
def camera():
    return fisheye(84, 70, 190.0)


@pytest.fixture(scope="module")
def frames(camera):
    images, _, _ = room_sequence(camera, 5, step=0.35, yaw=0.06)
    return images


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("adaptation-cache")


@pytest.fixture(autouse=True)
def _quiet_da3():
    """DA3 prints an INFO line on every 3-view forward; keep test output readable."""
    from depth_anything_3.utils.logger import logger

    level, logger.level = logger.level, 1
    yield
    logger.level = level


def config(cache_dir, **changes) -> AdaptConfig:
    # The mechanics of a fit, on the match terms alone: the teacher (default recipe), the
    # collapse guard and the parallax gate add forwards of their own; their tests switch them on.
    base = dict(
        steps=3,
        input_size=84,
        n_windows=3,
        checkpoint_every=2,
        cache_dir=str(cache_dir),
        matcher_options={"border_px": 2},
        seed=0,
        guard=False,
        min_parallax_px=0.0,
    )
    base.update(changes)
    return AdaptConfig.from_recipe("matches", **base)


def tables(adapter: Adapter) -> dict[str, torch.Tensor]:
    return {name: value.detach().clone() for name, value in adapter.state_dict().items()}


def same_tables(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# --------------------------------------------------------------------------------------------
# Input layout
# --------------------------------------------------------------------------------------------


def test_input_layout_resizes_or_crops_consistently():
    layout = input_layout(fisheye(84, 70, 190.0), 84)
    assert (layout.width, layout.height, layout.crop) == (84, 70, None)
    wide = fisheye(1280, 720, 190.0)
    layout = input_layout(wide, 504)
    assert (layout.width, layout.height) == (504, 280)
    assert layout.crop == (0, 4, 1280, 711)  # 1280x720 -> 504x280 would stretch by 1.25%
    assert (layout.camera.width, layout.camera.height) == (504, 280)
    # A scene point lands on the same input pixel through the native camera + to_input_pixels.
    from raytun3r_plugin.adaptation.losses import to_input_pixels

    points = torch.tensor(
        [[0.3, -0.2, 1.0], [-1.0, 0.4, 0.5], [0.0, 0.0, 1.0]], dtype=torch.float64
    )
    native_uv, _ = wide.project(points)
    input_uv, _ = layout.camera.project(points)
    mapped = to_input_pixels(
        native_uv, layout.native_size, (layout.width, layout.height), layout.offset
    )
    torch.testing.assert_close(mapped, input_uv, atol=1e-6, rtol=0)


def test_config_validates_and_round_trips():
    # AdaptConfig() is the default recipe (docs/recipes.md).
    cfg = AdaptConfig()
    # The step and the input size are left to the backbone (resolved_for, tests/test_recipes.py).
    assert (cfg.steps, cfg.lr, cfg.clip, cfg.input_size, cfg.n_windows, cfg.pose_source) == (
        300,
        None,
        1.0,
        None,
        30,
        "hybrid",
    )
    assert cfg.weights.as_dict() == {**SELF_SUPERVISED_WEIGHTS, "pose": 0.3, "teacher": 10.0}
    assert cfg.recipe == "default" and cfg.teacher_views == ("centre", "left", "right")
    assert (cfg.scale, cfg.robust_px, cfg.pe_regulariser, cfg.guard) == (
        "pixel",
        1.0,
        "relative",
        True,
    )
    supervised = AdaptConfig.supervised(steps=5)
    assert (
        supervised.steps == 5
        and supervised.lr == 3e-2
        and supervised.weights.as_dict() == SUPERVISED_WEIGHTS
    )
    for field, value in (
        ("scale", "median"),
        ("robust_px", 0.0),
        ("pe_regulariser", "none"),
        ("guard_every", 0),
    ):
        with pytest.raises(InputError, match=field):
            AdaptConfig(**{field: value})
    again = AdaptConfig(**json.loads(json.dumps(cfg.to_dict())))
    assert again == cfg and again.identity() == cfg.identity()
    assert AdaptConfig(steps=10).identity() == cfg.identity()  # steps may change on resume
    with pytest.raises(InputError, match="pose_source"):
        AdaptConfig(pose_source="gt")
    for term, weight in (("pose", -0.3), ("tv", float("nan")), ("reproj", float("inf"))):
        with pytest.raises(InputError, match=f"weights.{term}"):
            AdaptConfig(weights={**SELF_SUPERVISED_WEIGHTS, term: weight})


# --------------------------------------------------------------------------------------------
# adapt(): files, frozen backbone, determinism, resume, Ctrl-C
# --------------------------------------------------------------------------------------------


def test_adapt_trains_only_the_adapter_and_restores_the_model(camera, frames, cache_dir, tmp_path):
    model = build_tiny_network()
    model.train()
    for index, parameter in enumerate(model.parameters()):
        parameter.requires_grad_(index % 3 != 0)  # a mix, to check the flags come back exactly
    flags = [p.requires_grad for p in model.parameters()]
    modes = [m.training for m in model.modules()]
    weights = {k: v.clone() for k, v in model.state_dict().items()}
    seen = []

    def spy(module, args):
        seen.append(
            (
                any(p.requires_grad for p in module.parameters()),
                any(m.training for m in module.modules()),
                handle_of(module) is not None,
            )
        )

    hook = model.register_forward_pre_hook(spy)
    try:
        adapter = adapt(
            model,
            camera,
            frames,
            config(cache_dir),
            out_path=tmp_path / "room.safetensors",
            progress=False,
        )
    finally:
        hook.remove()

    # During adaptation: frozen, eval mode, patched. Afterwards: everything as before.
    assert seen == [(False, False, True)] * 3
    assert handle_of(model) is None
    assert [p.requires_grad for p in model.parameters()] == flags
    assert [m.training for m in model.modules()] == modes
    assert all(torch.equal(weights[k], v) for k, v in model.state_dict().items())  # invariant 5
    assert all(p.grad is None for p in model.parameters())

    # The adapter moved, and every table received gradient.
    assert all(float(t.abs().max()) > 0 for t in tables(adapter).values())
    info = adapter.training_info
    assert (
        info["steps"] == 3
        and not info["interrupted"]
        and info["input"]
        == {
            "width": 84,
            "height": 70,
            "crop": None,
            **RECORDED_RULE,
            "long_side": 84,
            "patch": 14,
            "source": [84, 70],
        }
    )
    assert set(info["final_losses"]) == {"loss", *TERMS}
    assert info["config"]["steps"] == 3 and len(info["segment"]["windows"]) == 3

    # Files: the adapter (loadable, same tables), a per-step log with every term, a checkpoint.
    paths = artifact_paths(tmp_path / "room.safetensors")
    loaded = Adapter.load(paths["adapter"])
    assert same_tables(tables(loaded), tables(adapter)) and loaded.training_info["steps"] == 3
    log = read_loss_log(paths["adapter"])
    assert [r["step"] for r in log] == [0, 1, 2]
    for record in log:
        assert all(math.isfinite(record[name]) for name in ("loss", *TERMS))
        assert record["n_matches"] > 0 and record["n_pose"] > 0 and not record["skipped"]
    assert log[0]["l2"] == 0.0 and log[-1]["l2"] > 0.0  # zero adapter at step 0
    ckpt_tensors, ckpt_meta = load_checkpoint(paths["checkpoint"])
    assert ckpt_meta["step"] == "3" and "adam.pe.radial.exp_avg" in ckpt_tensors
    raw = paths["checkpoint"].read_bytes()
    assert raw[8:9] == b"{"  # safetensors: 8-byte header length, then JSON; no pickle anywhere

    # The adapter reproduces its training-time patch on the same model.
    with apply(model, camera, loaded):
        pass


def test_adapt_is_deterministic_and_resumes_exactly(camera, frames, cache_dir, tmp_path):
    model = build_tiny_network()
    full = adapt(model, camera, frames, config(cache_dir, steps=3), progress=False)
    # The same run in two halves (checkpoint + resume) gives bit-identical tables.
    out = tmp_path / "halves.safetensors"
    half = adapt(model, camera, frames, config(cache_dir, steps=2), out_path=out, progress=False)
    assert not same_tables(tables(half), tables(full))
    resumed = adapt(model, camera, frames, config(cache_dir, steps=3), out_path=out, progress=False)
    assert resumed.training_info["resumed_from"] == 2 and resumed.training_info["steps"] == 3
    assert same_tables(tables(resumed), tables(full))
    assert [r["step"] for r in read_loss_log(out)] == [0, 1, 2]
    # resume=False starts over; a checkpoint of another run is refused.
    from raytun3r_plugin.errors import AdapterError

    with pytest.raises(AdapterError, match="another run"):
        adapt(
            model, camera, frames, config(cache_dir, steps=5, lr=2e-3), out_path=out, progress=False
        )


def test_ctrl_c_saves_and_returns(camera, frames, cache_dir, tmp_path):
    model = build_tiny_network()
    calls = []

    def interrupt(module, args):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt

    hook = model.register_forward_pre_hook(interrupt)
    out = tmp_path / "stopped.safetensors"
    try:
        adapter = adapt(
            model, camera, frames, config(cache_dir, steps=3), out_path=out, progress=False
        )
    finally:
        hook.remove()
    assert adapter.training_info["interrupted"] and adapter.training_info["steps"] == 1
    assert handle_of(model) is None and all(p.requires_grad for p in model.parameters())
    assert Adapter.load(out).training_info["steps"] == 1
    assert load_checkpoint(artifact_paths(out)["checkpoint"])[1]["step"] == "1"
    assert len(read_loss_log(out)) == 1
    # Running again continues from the saved step.
    finished = adapt(
        model, camera, frames, config(cache_dir, steps=2), out_path=out, progress=False
    )
    assert finished.training_info["resumed_from"] == 1 and not finished.training_info["interrupted"]


def test_pose_from_targets_mode(camera, frames, cache_dir):
    model = build_tiny_network()
    adapter = adapt(
        model, camera, frames, config(cache_dir, steps=2, pose_source="targets"), progress=False
    )
    final = adapter.training_info["final_losses"]
    assert "pose" not in final and math.isfinite(final["reproj"]) and final["reproj"] > 0
    assert all(float(t.abs().max()) > 0 for t in tables(adapter).values())


def test_hybrid_and_both_modes_combine_the_reprojections_and_keep_the_pose_term(
    camera, frames, cache_dir, tmp_path
):
    # The first step's terms are taken at the zero adapter, so the four modes see one
    # prediction: hybrid's reprojection must be the targets mode's, its pose term the model
    # mode's (a mode that reprojected through the network's pose, or dropped the pose term,
    # would differ); "both" averages the two reprojections, so its term lies strictly between.
    first = {}
    for source in ("targets", "model", "hybrid", "both"):
        out = tmp_path / f"{source}.safetensors"
        adapt(
            build_tiny_network(),
            camera,
            frames,
            config(cache_dir, steps=1, pose_source=source),
            out_path=out,
            progress=False,
        )
        first[source] = read_loss_log(out)[0]
    assert "pose" not in first["targets"] and first["model"]["pose"] > 0
    assert first["hybrid"]["reproj"] == pytest.approx(first["targets"]["reproj"], rel=1e-5)
    assert first["hybrid"]["pose"] == pytest.approx(first["model"]["pose"], rel=1e-5)
    assert abs(first["model"]["reproj"] / first["targets"]["reproj"] - 1) > 1e-3
    low, high = sorted((first["model"]["reproj"], first["targets"]["reproj"]))
    assert low < first["both"]["reproj"] < high
    assert first["both"]["pose"] == pytest.approx(first["model"]["pose"], rel=1e-5)


def test_adapt_refuses_a_patched_model(camera, frames, cache_dir):
    model = build_tiny_network()
    with apply(model, camera), pytest.raises(AlreadyAppliedError):
        adapt(model, camera, frames, config(cache_dir), progress=False)


# --------------------------------------------------------------------------------------------
# Gradient reach: a student adapter recovers a teacher's tables through the patched hooks
# --------------------------------------------------------------------------------------------


class _Stop(Exception):
    pass


def _block_features(model, images: torch.Tensor, blocks: tuple[int, ...]) -> list[torch.Tensor]:
    """Outputs of the given ViT blocks for images (B, S, 3, H, W); the forward stops after the last."""
    from raytun3r_plugin.prediction import imagenet_normalise

    captured: dict[int, torch.Tensor] = {}
    handles = []
    for index in blocks:

        def hook(module, args, output, index=index):
            captured[index] = output
            if index == max(blocks):
                raise _Stop

        handles.append(model.backbone.pretrained.blocks[index].register_forward_hook(hook))
    try:
        model(imagenet_normalise(images))
    except _Stop:
        pass
    finally:
        for handle in handles:
            handle.remove()
    return [captured[index] for index in blocks]


def _gauge_free(adapter: Adapter) -> torch.Tensor:
    """PE tables without the one direction no input can see.

    A constant angular update c gives rho * c, which the radial table reproduces exactly as
    -c * rho_k: (radial - c rho_k, angular + c) yields the same correction on every grid. Project
    that direction out per channel, then flatten both tables.
    """
    radial, angular = adapter.pe["radial"].detach(), adapter.pe["angular"].detach()
    rho = torch.linspace(0, 1, radial.shape[0])[:, None]
    null = torch.cat(
        (-rho.expand_as(radial), torch.ones_like(angular)), dim=0
    )  # (n_r + n_theta, C)
    stacked = torch.cat((radial, angular), dim=0)
    coefficient = (stacked * null).sum(0) / (null * null).sum(0)
    return (stacked - coefficient * null).flatten()


def _pearson(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.corrcoef(torch.stack((a.flatten(), b.flatten())))[0, 1])


def test_gradients_reach_every_table_through_the_patched_hooks(camera):
    """Fit a fresh adapter to imitate a model patched with a known adapter (a teacher).

    Distillation target: outputs of ViT block 0 (sees the corrected absolute PE) and block 2 (the
    first frame-attention block with RoPE, sees the displaced RoPE positions) for fixed images.
    The 6x5 token grid samples only 9 distinct radii, so the tables are kept small (4 radial,
    4 angular, 6 RoPE bins): then every table direction except the gauge of ``_gauge_free`` is
    well conditioned (smallest nonzero singular value of the PE interpolation matrix 0.70; with 6
    radial bins it would be 0.05, with the default 20 only 14 of 28 directions are seen at all).
    """
    torch.manual_seed(0)
    model = build_tiny_network()
    for parameter in model.parameters():
        parameter.requires_grad_(False)
    sizes = dict(n_r=4, n_theta=4, n_r_rope=6)
    teacher = Adapter.for_model(model, camera, **sizes)
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        teacher.pe["radial"].copy_(torch.randn(4, 64, generator=generator) * 0.3)
        teacher.pe["angular"].copy_(torch.randn(4, 64, generator=generator) * 0.3)
        teacher.rope["radial"].copy_(torch.linspace(0, 1, 6) ** 2 * 0.8)
    images = torch.rand(1, 1, 3, 70, 84, generator=generator)
    blocks = (0, 2)
    with torch.no_grad(), apply(model, camera, teacher):
        targets = _block_features(model, images, blocks)

    student = Adapter.for_model(model, camera, **sizes)
    optimizer = torch.optim.Adam(student.parameters(), lr=0.05)
    scales = [target.var() for target in targets]
    with apply(model, camera, student):
        for _ in range(120):
            features = _block_features(model, images, blocks)
            loss = sum(
                ((f - t) ** 2).mean() / s for f, t, s in zip(features, targets, scales, strict=True)
            )
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    assert all(p.grad is None for p in model.parameters())
    pe_corr = _pearson(_gauge_free(student), _gauge_free(teacher))
    rope_corr = _pearson(student.rope["radial"].detach(), teacher.rope["radial"].detach())
    assert pe_corr >= 0.9, (
        f"PE tables: Pearson {pe_corr:.3f} (final loss {float(loss.detach()):.3g})"
    )
    assert rope_corr >= 0.9, (
        f"RoPE table: Pearson {rope_corr:.3f} (final loss {float(loss.detach()):.3g})"
    )


# --------------------------------------------------------------------------------------------
# User mask (a vehicle's body or a lens mount in view)
# --------------------------------------------------------------------------------------------


def body_mask(camera) -> torch.Tensor:
    """The bottom 30 % of the image is the vehicle: never the scene."""
    mask = torch.ones(camera.height, camera.width, dtype=torch.bool)
    mask[int(0.7 * camera.height) :] = False
    return mask


def test_mask_keeps_matches_and_losses_off_the_excluded_pixels(camera, frames, cache_dir):
    from raytun3r_plugin.adaptation.problem import prepare_problem

    mask = body_mask(camera)
    plain = prepare_problem(camera, frames, config(cache_dir))
    masked = prepare_problem(camera, frames, config(cache_dir), mask=mask)
    cut = (
        0.7 * camera.height * masked.layout.height / camera.height - 0.5
    )  # first excluded row, input px
    plain_rows = torch.cat(
        [torch.cat((p.uv_i[:, 1], p.uv_j[:, 1])) for _, pairs in plain.windows for p in pairs]
    )
    masked_rows = torch.cat(
        [torch.cat((p.uv_i[:, 1], p.uv_j[:, 1])) for _, pairs in masked.windows for p in pairs]
    )
    # Without the mask the body region is matched; with it, no match lands there.
    assert bool((plain_rows > cut + 1).any()) and not bool((masked_rows > cut + 1).any())
    assert masked.adaptation.cache_key != plain.adaptation.cache_key
    assert not bool(masked.valid[-1].any()) and bool(plain.valid[plain.valid.shape[0] // 2].any())
    assert torch.equal(masked.valid, masked.valid & plain.valid)
    assert (
        masked.mask is not None
        and tuple(masked.mask.shape) == (camera.height, camera.width)
        and plain.mask is None
    )


def test_adapt_patches_with_the_mask_and_records_it(camera, frames, cache_dir, monkeypatch):
    # Every patch a fit makes (the parallax gate's measurement and the fit itself) goes
    # through one helper, which applies the mask.
    import raytun3r_plugin.adaptation.evaluation as evaluation

    seen = []

    def recording_apply(*args, **kwargs):
        seen.append(kwargs.get("mask"))
        return apply(*args, **kwargs)

    monkeypatch.setattr(evaluation, "apply", recording_apply)
    mask = body_mask(camera)
    adapter = adapt(
        build_tiny_network(),
        camera,
        frames,
        config(cache_dir, steps=2),
        mask=mask.numpy(),
        progress=False,
    )
    expected = mask & camera.valid_mask().bool()
    assert seen and all(torch.equal(used, expected) for used in seen)
    recorded = adapter.training_info["segment"]["mask"]
    assert recorded["valid_fraction"] == pytest.approx(
        float((mask & camera.valid_mask().bool()).float().mean()), abs=1e-4
    )
    assert len(recorded["sha256"]) == 64


@pytest.mark.parametrize(
    ("make_mask", "message"),
    [
        (
            lambda camera: torch.ones(camera.height + 1, camera.width, dtype=torch.bool),
            "like the frames, got shape",
        ),
        (
            lambda camera: torch.zeros(camera.height, camera.width, dtype=torch.bool),
            "no pixel inside",
        ),
    ],
)
def test_bad_mask_is_refused_before_anything_is_written(
    camera, frames, cache_dir, tmp_path, make_mask, message
):
    model = build_tiny_network()
    before = {name: value.clone() for name, value in model.state_dict().items()}
    out = tmp_path / "run" / "adapter.safetensors"
    with pytest.raises(InputError, match=message):
        adapt(
            model,
            camera,
            frames,
            config(cache_dir),
            out_path=out,
            mask=make_mask(camera),
            progress=False,
        )
    assert not out.parent.exists() and handle_of(model) is None
    assert all(torch.equal(before[name], value) for name, value in model.state_dict().items())


def test_depth_parallax_is_the_reprojection_shift_per_log_depth():
    from raytun3r_plugin.adaptation.losses import depth_parallax_px
    from raytun3r_plugin.cameras import Pinhole

    camera = Pinhole(64, 64, {"fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 31.5})
    points = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 8.0]], dtype=torch.float64)
    sideways = torch.eye(4, dtype=torch.float64)
    sideways[0, 3] = 0.1  # 10 cm to the side: u = cx + f (x + b) / z
    step = 0.05
    expected = 50.0 * 0.1 / points[:, 2] * (1 - math.exp(-step)) / step
    assert torch.allclose(depth_parallax_px(points, sideways, camera, step), expected, rtol=1e-9)
    # Without translation a depth change moves nothing: such matches say nothing about depth.
    still = torch.eye(4, dtype=torch.float64)
    assert torch.equal(
        depth_parallax_px(points, still, camera), torch.zeros(2, dtype=torch.float64)
    )


def test_parallax_gate_keeps_moving_windows_and_stops_a_fit_without_signal(
    camera, frames, cache_dir
):
    model = build_tiny_network()
    ungated = adapt(model, camera, frames, config(cache_dir), progress=False)
    gated = adapt(model, camera, frames, config(cache_dir, min_parallax_px=0.3), progress=False)
    gate = gated.training_info["parallax_gate"]
    # This hand-held room moves enough everywhere: every window is kept, the fit is the same.
    assert gate["windows_dropped"] == 0 and gate["windows_kept"] == 3
    assert all(m is not None and m > 0.3 for m in gate["window_median_px"])
    assert same_tables(tables(gated), tables(ungated))
    assert "parallax_gate" not in ungated.training_info
    # A threshold no window reaches: no step, tables as they started, the verdict says why.
    weights = {k: v.clone() for k, v in model.state_dict().items()}
    stopped = adapt(model, camera, frames, config(cache_dir, min_parallax_px=1e6), progress=False)
    assert stopped.training_info["steps"] == 0
    assert stopped.training_info["parallax_gate"]["windows_kept"] == 0
    assert stopped.training_info["verdict"]["status"] == "no signal"
    assert "NO SIGNAL" in stopped.training_info["verdict"]["summary"]
    assert all(not v.abs().any() for v in tables(stopped).values())
    assert handle_of(model) is None
    assert all(torch.equal(weights[k], v) for k, v in model.state_dict().items())
    with pytest.raises(InputError, match="min_parallax_px"):
        AdaptConfig(min_parallax_px=-1.0)
