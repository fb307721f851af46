"""Reading scene masks at the frames' size (fitting them to the network input: test_preprocess.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from raytun3r_plugin.errors import InputError
from raytun3r_plugin.images import read_mask


def test_read_mask_thresholds_and_checks_the_size(tmp_path):
    values = np.array([[0, 127, 128, 255]], np.uint8).repeat(3, axis=0)
    cv2.imwrite(str(tmp_path / "m.png"), values)
    assert read_mask(tmp_path / "m.png", 4, 3).tolist() == [[False, False, True, True]] * 3
    with pytest.raises(InputError, match="mask is 4x3 px, the frames are 5x3"):
        read_mask(tmp_path / "m.png", 5, 3)
    with pytest.raises(InputError, match="missing or unreadable"):
        read_mask(tmp_path / "none.png", 4, 3)
