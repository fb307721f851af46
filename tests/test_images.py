"""Frames and scene masks fitted to the network input: one geometry for both."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from raytun3r_plugin.errors import InputError
from raytun3r_plugin.images import fit_mask_to_network, fit_to_network, read_mask
from tests.helpers import fisheye


@pytest.mark.parametrize(("width", "height", "long_side"), [(130, 90, 84), (90, 130, 98), (84, 84, 84)])
def test_mask_follows_the_frames_through_resize_and_crop(width, height, long_side):
    mask = np.zeros((height, width), bool)
    mask[int(0.2 * height) : int(0.6 * height), int(0.5 * width) :] = True  # a block off-centre
    image = np.repeat(mask[..., None].astype(np.float32), 3, axis=-1)[None]
    tensor, camera = fit_to_network(image, fisheye(width, height, 180.0), long_side)
    fitted = fit_mask_to_network(mask, long_side)
    assert tuple(fitted.shape) == tuple(tensor.shape[-2:]) == (camera.height, camera.width)
    # Where the resized frame is clearly inside or outside the block, the mask agrees.
    frame = tensor[0, 0, 0].numpy()
    clear = (frame > 0.9) | (frame < 0.1)
    assert clear.mean() > 0.8 and np.array_equal(fitted.numpy()[clear], frame[clear] > 0.5)


def test_read_mask_thresholds_and_checks_the_size(tmp_path):
    values = np.array([[0, 127, 128, 255]], np.uint8).repeat(3, axis=0)
    cv2.imwrite(str(tmp_path / "m.png"), values)
    assert read_mask(tmp_path / "m.png", 4, 3).tolist() == [[False, False, True, True]] * 3
    with pytest.raises(InputError, match="mask is 4x3 px, the frames are 5x3"):
        read_mask(tmp_path / "m.png", 5, 3)
    with pytest.raises(InputError, match="missing or unreadable"):
        read_mask(tmp_path / "none.png", 4, 3)
