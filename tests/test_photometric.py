"""Issue 12, outdoors: the optional dense photometric term (``LossWeights.photo``).

On a rendered street pair with its true depth and pose, the term and its translation scale
behave as the fit relies on: true depth costs less than a flattened depth, the searched scale
finds the true translation length, a pixel warped out of view costs ``OUTSIDE_COST``, the
gradient reaches the depth; and in the trainer the term is off by default (configuration
identities unchanged), validated, and keeps the windows that the parallax gate would drop.
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from raytun3r_plugin.patches.da3_networks import build_tiny_network

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.config import AdaptConfig
from raytun3r_plugin.adaptation.losses import (
    LossWeights,
)
from raytun3r_plugin.adaptation.photometric import (
    OUTSIDE_COST,
    blurred_gray,
    photometric_loss,
    photometric_optimal_scale,
)
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.cameras import KannalaBrandt4
from raytun3r_plugin.errors import InputError
from tests.helpers import small_kb4


@pytest.fixture(scope="module")
def street():
    """Two consecutive frames of the outdoor scene (KB4, 190 degrees, 96 x 80 px, a median
    motion of 1 px): grey images, true range depth of frame 0, the lens's valid region, and the
    true ``cam_1_from_cam_0``."""
    camera = KannalaBrandt4(96, 80, [26.0, 26.0, 47.5, 39.5, 0.0, 0.0, 0.0, 0.0], max_fov_deg=190.0)
    seq = synthetic.render_sequence("outdoor", camera, n_frames=2, seed=3, flow_px=1.0)
    images = torch.from_numpy(seq.images).permute(0, 3, 1, 2).double()
    depth = torch.from_numpy(seq.depth[0]).double()
    valid = camera.valid_mask().bool()
    pose = torch.as_tensor(synthetic.relative_pose(seq.cam_from_world, 0, 1)).double()
    rows, cols = torch.nonzero(valid & (depth > 0), as_tuple=True)
    pixels = torch.stack((cols, rows), dim=-1)
    rays, ok = camera.unproject(pixels.double())
    return {
        "camera": camera,
        "gray": blurred_gray(images, 1.0),
        "depth": depth,
        "valid": valid,
        "rotation": pose[:3, :3],
        "translation": pose[:3, 3],
        "pixels": pixels[ok],
        "rays": rays[ok],
    }


def _loss(street, depth, valid=None):
    t = street["translation"]
    return photometric_loss(
        depth,
        street["rays"],
        street["pixels"],
        street["gray"][0],
        street["gray"][1],
        street["rotation"],
        t / t.norm(),
        street["camera"],
        street["valid"] if valid is None else valid,
    )


def test_blur_keeps_a_flat_image_and_sigma_zero_is_the_channel_mean():
    generator = torch.Generator().manual_seed(0)
    images = torch.rand(2, 3, 9, 11, generator=generator, dtype=torch.float64)
    assert torch.allclose(blurred_gray(images, 0.0), images.mean(dim=1))
    flat = torch.full((1, 3, 9, 11), 0.4, dtype=torch.float64)
    assert torch.allclose(blurred_gray(flat, 2.0), flat[:, 0])
    blurred = blurred_gray(images, 1.5)
    assert blurred.shape == (2, 9, 11)
    assert blurred.std() < images.mean(dim=1).std()


def test_true_depth_costs_less_than_a_flattened_depth(street):
    true, count = _loss(street, street["depth"])
    assert count == street["pixels"].shape[0]
    # The same depths pulled towards their median (in log): the near road reads too far, the
    # houses too near. A global rescaling costs nothing: the translation length is searched.
    log = street["depth"].clamp_min(1e-3).log()
    median = log[street["depth"] > 0].median()
    costs = []
    for keep in (0.75, 0.5):
        flattened = torch.where(street["depth"] > 0, torch.exp(keep * log + (1 - keep) * median), 0)
        costs.append(float(_loss(street, flattened)[0]))
    assert float(true) < 0.95 * costs[0] and costs[0] < costs[1]
    rescaled, _ = _loss(street, 3.0 * street["depth"])
    assert float(rescaled) == pytest.approx(float(true), rel=0.05)


def test_the_searched_scale_is_the_true_translation_length(street):
    t = street["translation"]
    pixels = street["pixels"]
    points = street["rays"] * street["depth"][pixels[:, 1], pixels[:, 0], None]
    scale = photometric_optimal_scale(
        points,
        street["gray"][0][pixels[:, 1], pixels[:, 0]],
        street["gray"][1],
        street["rotation"],
        t / t.norm(),
        street["camera"],
        street["valid"],
    )
    assert not scale.requires_grad
    assert float(scale) == pytest.approx(float(t.norm()), rel=0.15)


def test_a_pixel_warped_out_of_view_costs_outside_cost(street):
    # A frame j with no valid pixel: every warped pixel is outside.
    loss, count = _loss(street, street["depth"], torch.zeros_like(street["valid"]))
    assert count > 0 and float(loss) == pytest.approx(OUTSIDE_COST)


def test_the_gradient_reaches_the_depth(street):
    depth = street["depth"].clone().requires_grad_(True)
    loss, _ = _loss(street, depth)
    loss.backward()
    assert torch.isfinite(depth.grad).all() and depth.grad.abs().sum() > 0


def test_photo_is_off_by_default_and_leaves_the_configuration_identity_alone():
    default = AdaptConfig.from_recipe("matches")
    assert AdaptConfig().weights.photo == 0 and default.weights.photo == 0
    assert "photo" not in default.to_dict()["weights"]
    assert "photo_sigma" not in default.to_dict() and "photo_pixels" not in default.to_dict()
    on = dataclasses.replace(default, weights=dataclasses.replace(default.weights, photo=10.0))
    saved = on.to_dict()
    assert saved["weights"]["photo"] == 10.0
    assert saved["photo_sigma"] == 1.0 and saved["photo_pixels"] == 4096
    assert AdaptConfig(**saved).weights.photo == 10.0 and AdaptConfig(**saved) == on
    assert LossWeights().as_dict() == {
        k: v for k, v in dataclasses.asdict(LossWeights()).items() if k not in ("photo", "teacher")
    }


@pytest.mark.parametrize(
    "change", [{"photo_sigma": -1.0}, {"photo_sigma": math.nan}, {"photo_pixels": 0}]
)
def test_bad_photometric_settings_are_refused(change):
    with pytest.raises(InputError, match=next(iter(change))):
        AdaptConfig(**change)


def _tiny_fit(tmp_path, **changes):
    """(camera, frames, config) of a two-step fit of the tiny DA3 network on a 5-frame room."""
    camera = small_kb4()
    frames = synthetic.render_sequence("indoor", camera, n_frames=5, seed=7).images
    config = AdaptConfig.from_recipe(
        "matches",
        steps=2,
        input_size=84,
        n_windows=2,
        checkpoint_every=0,
        cache_dir=str(tmp_path),
        matcher_options={"border_px": 2},
        seed=0,
        guard=False,
        photo_pixels=256,
        **changes,
    )
    return camera, frames, config


def test_with_the_term_on_the_gate_keeps_every_window_and_the_fit_steps(tmp_path):
    """A threshold no window reaches stops the match-only fit ("no signal"); with the
    photometric term the same windows are kept, recorded, and fitted."""
    from depth_anything_3.utils.logger import logger

    camera, frames, base = _tiny_fit(tmp_path, min_parallax_px=1e6)
    photo = dataclasses.replace(base, weights=dataclasses.replace(base.weights, photo=100.0))
    level, logger.level = logger.level, 1
    try:
        stopped = adapt(build_tiny_network(), camera, frames, base, progress=False)
        fitted = adapt(
            build_tiny_network(), camera, frames, photo, progress=False, out_path=tmp_path / "a"
        )
    finally:
        logger.level = level
    assert stopped.training_info["verdict"]["status"] == "no signal"
    gate = fitted.training_info["parallax_gate"]
    assert gate["windows_kept"] == 2 and gate["windows_dropped"] == 0
    assert fitted.training_info["steps"] == 2
    assert fitted.training_info["config"]["weights"]["photo"] == 100.0
    header = (tmp_path / "a.losses.csv").read_text().splitlines()[0]
    assert "photo" in header


def test_the_photometric_scale_is_recorded_and_scales_the_reprojection(tmp_path):
    """``scale="photometric"`` keeps its blur and pixel count in the configuration, and a fit
    with it steps and measures its windows' parallax at that scale."""
    from depth_anything_3.utils.logger import logger

    from raytun3r_plugin.adaptation.parallax import window_parallax
    from raytun3r_plugin.adaptation.problem import prepare_problem
    from raytun3r_plugin.adapter import Adapter

    saved = AdaptConfig(scale="photometric").to_dict()
    assert saved["scale"] == "photometric" and saved["photo_pixels"] == 4096
    assert "photo" not in saved["weights"]
    camera, frames, config = _tiny_fit(tmp_path, scale="photometric")
    level, logger.level = logger.level, 1
    try:
        model = build_tiny_network()
        problem = prepare_problem(camera, frames, config)
        photometric = window_parallax(model, Adapter.for_model(model), problem, config)
        pixel = window_parallax(
            model, Adapter.for_model(model), problem, dataclasses.replace(config, scale="pixel")
        )
        fitted = adapt(model, camera, frames, config, progress=False)
    finally:
        logger.level = level
    assert all(math.isfinite(m) and m > 0 for m in photometric)
    assert photometric != pixel
    assert fitted.training_info["steps"] == 2
    assert fitted.training_info["config"]["scale"] == "photometric"
