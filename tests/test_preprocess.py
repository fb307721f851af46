"""The one input-preparation object (raytun3r_plugin.preprocess): its rule, camera, pixels, masks."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from raytun3r_plugin.errors import AdapterError, InputError, Raytun3rError
from raytun3r_plugin.geometry import ASPECT_TOLERANCE
from raytun3r_plugin.preprocess import (
    RULE,
    RULE_VERSION,
    InputLayout,
    fitted_source_camera,
    input_layout,
    layout_for_inference,
)
from tests.helpers import fisheye

# (native W, H, long side) -> (input w, h, crop): the rule of the module docstring, worked by hand.
CASES = [
    (1400, 1400, 504, (504, 504, None)),  # KITTI-360
    (752, 480, 504, (504, 322, None)),  # 504 x 321.7: rounded to 23 patches, 0.1% stretch
    (1280, 1024, 504, (504, 406, None)),  # issue 17: 403.2 -> 406 is a 0.7% stretch, no crop
    (1280, 720, 504, (504, 280, (0, 4, 1280, 711))),  # 283.5 -> 280 would stretch 1.25%: crop
    (160, 128, 84, (84, 70, (3, 0, 154, 128))),  # 1280x1024-shaped at a small size: crop
    (128, 160, 112, (84, 112, (4, 0, 120, 160))),
    (160, 121, 112, (112, 84, None)),  # 84.7 -> 84: 0.8% stretch
    (112, 112, 112, (112, 112, None)),  # the benchmark
    (84, 84, 84, (84, 84, None)),
    (10, 10, 5, (14, 14, None)),  # never below one patch
]


@pytest.mark.parametrize(("width", "height", "long_side", "expected"), CASES)
def test_rule_sizes_and_crops(width, height, long_side, expected):
    camera = fisheye(width, height, 190.0)
    layout = InputLayout.for_camera(camera, long_side)
    assert (layout.width, layout.height, layout.crop) == expected
    assert layout.width % 14 == 0 and layout.height % 14 == 0
    assert (
        layout.source_size == (width, height)
        and layout.long_side == long_side
        and layout.patch == 14
    )
    # What is left after the crop is a pure resize: the aspect ratio changes by at most 1%.
    native_w, native_h = layout.native_size
    assert (
        abs(layout.width / layout.height - native_w / native_h) / (native_w / native_h)
        <= ASPECT_TOLERANCE
    )
    assert input_layout(camera, long_side) == layout


@pytest.mark.parametrize(("width", "height", "long_side", "expected"), CASES[2:6])
def test_cameras_are_the_stated_crop_then_a_pure_resize(width, height, long_side, expected):
    camera = fisheye(width, height, 190.0)
    layout = InputLayout.for_camera(camera, long_side)
    native = camera if layout.crop is None else camera.cropped(*layout.crop)
    assert layout.native_camera.to_dict() == native.to_dict()
    assert layout.camera.to_dict() == native.resized(layout.width, layout.height).to_dict()
    assert layout.offset == ((0, 0) if layout.crop is None else layout.crop[:2])


@pytest.mark.parametrize(
    ("width", "height", "long_side"),
    [(1280, 1024, 504), (1280, 720, 504), (160, 128, 84), (128, 160, 112)],
)
def test_native_pixels_map_to_the_input_pixels_of_the_input_camera(width, height, long_side):
    camera = fisheye(width, height, 190.0)
    layout = InputLayout.for_camera(camera, long_side)
    points = torch.tensor(
        [[0.3, -0.2, 1.0], [-1.0, 0.4, 0.5], [0.0, 0.0, 1.0], [0.7, 0.6, 0.2]], dtype=torch.float64
    )
    native_uv, _ = camera.project(points)
    input_uv, _ = layout.camera.project(points)
    torch.testing.assert_close(layout.to_input_pixels(native_uv), input_uv, atol=1e-6, rtol=0)


def test_frames_are_cropped_then_resized_bilinear_antialiased():
    camera = fisheye(160, 128, 190.0)
    layout = InputLayout.for_camera(camera, 84)
    frames = np.random.default_rng(0).random((2, 128, 160, 3), dtype=np.float32)
    frames[:, :, :3] = 5.0  # columns the crop (x0 = 3) removes: must not reach the input
    out = layout.frames(frames)
    assert out.shape == (2, 3, 70, 84) and out.dtype == torch.float32 and out.is_contiguous()
    x0, y0, w, h = layout.crop
    expected = F.interpolate(
        torch.from_numpy(frames).permute(0, 3, 1, 2)[..., y0 : y0 + h, x0 : x0 + w],
        size=(70, 84),
        mode="bilinear",
        align_corners=False,
        antialias=True,
    )
    assert torch.equal(out, expected.clamp(0, 1))
    assert float(out.max()) <= 1.0
    assert torch.equal(layout.frames(torch.from_numpy(frames)), out)  # tensors take the same path


def test_frames_at_the_input_size_pass_through_bit_identically():
    # The benchmark's cameras (square, a multiple of 14, used at their size): no resampling at all.
    for size in (84, 112):
        layout = InputLayout.for_camera(fisheye(size, size, 190.0), size)
        frames = np.random.default_rng(size).random((3, size, size, 3), dtype=np.float32)
        assert torch.equal(layout.frames(frames), torch.from_numpy(frames).permute(0, 3, 1, 2))
        assert (
            layout.camera is layout.native_camera
            or layout.camera.to_dict() == layout.native_camera.to_dict()
        )


def test_masks_follow_the_frames_nearest_neighbour():
    camera = fisheye(160, 128, 190.0)
    layout = InputLayout.for_camera(camera, 84)
    mask = np.zeros((128, 160), bool)
    mask[30:80, 90:] = True  # a block off-centre
    native = layout.native_mask(mask)
    assert native.shape == (128, 154) and native.dtype == torch.bool
    assert torch.equal(native, torch.from_numpy(mask[:, 3:157]))
    fitted = layout.mask(mask)
    assert fitted.shape == (70, 84) and fitted.dtype == torch.bool
    # Where the resized frame of the same mask is clearly inside or outside the block, they agree.
    frame = layout.frames(np.repeat(mask[None, ..., None].astype(np.float32), 3, axis=-1))[
        0, 0
    ].numpy()
    clear = (frame > 0.9) | (frame < 0.1)
    assert clear.mean() > 0.8 and np.array_equal(fitted.numpy()[clear], frame[clear] > 0.5)
    stacked = layout.mask(np.stack([mask, ~mask]))
    assert (
        stacked.shape == (2, 70, 84)
        and torch.equal(stacked[0], fitted)
        and torch.equal(stacked[1], layout.mask(~mask))
    )


def test_depth_maps_keep_their_values_and_holes():
    camera = fisheye(160, 128, 190.0)
    layout = InputLayout.for_camera(camera, 84)
    depth = np.random.default_rng(1).uniform(1, 5, (2, 128, 160)).astype(np.float32)
    depth[:, ::3] = 0.0  # sparse: 0 = no value
    out = layout.depth(depth)
    assert out.shape == (2, 70, 84) and out.dtype == torch.float32
    assert set(np.unique(out.numpy())) <= set(np.unique(depth))  # nothing blended
    assert (out == 0).any()


def test_wrong_sizes_are_input_errors():
    layout = InputLayout.for_camera(fisheye(160, 128, 190.0), 84)
    with pytest.raises(InputError, match="frames are 128x160 px but the camera describes 160x128"):
        layout.frames(np.zeros((1, 160, 128, 3), np.float32))
    with pytest.raises(InputError, match=r"\(N, H, W, 3\)"):
        layout.frames(np.zeros((128, 160, 3), np.float32))
    with pytest.raises(InputError, match="mask is"):
        layout.mask(np.zeros((127, 160), bool))
    with pytest.raises(InputError, match="depth maps are"):
        layout.depth(np.zeros((1, 128, 161), np.float32))
    with pytest.raises(InputError, match="long side"):
        InputLayout.for_camera(fisheye(160, 128, 190.0), 0)
    assert issubclass(InputError, Raytun3rError)


class _Adapter:
    """What layout_for_inference reads from an adapter: its camera, patch size and record."""

    def __init__(self, camera, record, patch_size=14):
        self.camera, self.patch_size, self.training_info = camera, patch_size, {"input": record}


@pytest.mark.parametrize(
    ("width", "height", "long_side"), [(160, 128, 84), (128, 160, 112), (1280, 1024, 504)]
)
def test_the_record_reproduces_the_fitted_layout(width, height, long_side):
    camera = fisheye(width, height, 190.0)
    layout = InputLayout.for_camera(camera, long_side)
    record = layout.record()
    assert record == {
        "rule": RULE,
        "rule_version": RULE_VERSION,
        "long_side": long_side,
        "patch": 14,
        "source": [width, height],
        "width": layout.width,
        "height": layout.height,
        "crop": list(layout.crop) if layout.crop else None,
    }
    adapter = _Adapter(layout.native_camera, record)
    # The adapter's camera with its crop undone is the calibration itself.
    assert fitted_source_camera(adapter).to_dict() == camera.to_dict()
    for given in (camera, None):  # the calibration, or the adapter's own camera
        again = layout_for_inference(given, (width, height), adapter)
        assert again == layout


def test_inference_rescales_the_camera_to_frames_of_another_size():
    camera = fisheye(160, 120, 190.0)
    layout = layout_for_inference(camera, (320, 240), long_side=112)
    assert layout.source_size == (320, 240) and (layout.width, layout.height, layout.crop) == (
        112,
        84,
        None,
    )
    assert layout.native_camera.to_dict() == camera.resized(320, 240).to_dict()
    with pytest.raises(InputError, match="only a pure resize"):
        layout_for_inference(camera, (160, 100), long_side=112)


def test_inference_refuses_another_rule():
    camera = fisheye(160, 128, 190.0)
    record = {**InputLayout.for_camera(camera, 84).record(), "rule_version": RULE_VERSION + 1}
    with pytest.raises(AdapterError, match="prepared by rule"):
        layout_for_inference(camera, (160, 128), _Adapter(camera, record))
    assert (
        layout_for_inference(camera, (160, 128), _Adapter(camera, record), strict=False).long_side
        == 84
    )
    # An adapter without a record (older files, or none at all): the long side given, else 504.
    assert layout_for_inference(camera, (160, 128), _Adapter(camera, {})).long_side == 504
    assert layout_for_inference(camera, (160, 128), None, long_side=112).long_side == 112
