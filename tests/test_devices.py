"""Models on another device than the CPU-built inputs (the CUDA path, checked here on PyTorch's
``meta`` device; the real GPU run is ``benchmarks/gpu_check.py``, docs/devices.md)."""

from __future__ import annotations

import pytest
import torch
from raytun3r_plugin.patches.da3_networks import build_tiny_network

from raytun3r_plugin import cameras
from raytun3r_plugin.baselines.multi_ph import (
    resample_to_view,
    view_depth_to_fisheye,
    view_rotation,
    virtual_pinhole,
)
from raytun3r_plugin.prediction import model_device, predict


class _Reached(Exception):
    """Raised by a forward pre-hook once the model's input has been seen."""


def test_predict_moves_cpu_images_to_the_models_device():
    model = build_tiny_network().to("meta")
    assert model_device(model) == torch.device("meta")
    seen = []

    def record(_module, args, kwargs):
        seen.append(args[0].device)
        raise _Reached

    model.register_forward_pre_hook(record, with_kwargs=True)
    with pytest.raises(_Reached):
        predict(model, torch.rand(2, 3, 28, 28))
    assert seen == [torch.device("meta")]


def test_model_device_of_a_module_without_tensors_is_the_cpu():
    assert model_device(torch.nn.Identity()) == torch.device("cpu")


@pytest.mark.parametrize("rotation", [None, view_rotation(30.0, 0.0)])
def test_view_resampling_and_depth_stay_on_the_input_device(rotation):
    camera = cameras.fisheye(56, 185.0, "kb4")
    view = virtual_pinhole(camera)
    images = torch.rand(2, 3, 56, 56)
    depth = torch.rand(2, 56, 56) + 1.0
    assert resample_to_view(images.to("meta"), camera, view, rotation).device.type == "meta"
    range_depth, inside = view_depth_to_fisheye(depth.to("meta"), camera, view, rotation)
    assert range_depth.device.type == "meta" and inside.device.type == "meta"
    # And on the CPU the values are what they were: the move is a no-op there.
    range_cpu, inside_cpu = view_depth_to_fisheye(depth, camera, view, rotation)
    assert bool(inside_cpu.any()) and bool((range_cpu[:, inside_cpu] > 0).all())
