"""The adapter reader is strict and bounded for any bytes (property-based, hypothesis).

For any file, ``Adapter.load`` returns a valid adapter or raises ``AdapterError`` naming the
file, within a second; an adapter it accepts has finite tables inside the documented limits and
can be applied to a network without breaking its forward.
"""

from __future__ import annotations

import json
import math
import struct
import time

import pytest
import torch

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import raytun3r_plugin as rt  # noqa: E402
from raytun3r_plugin.adapter import TABLE_LIMITS, normalise_components  # noqa: E402
from raytun3r_plugin.errors import AdapterError  # noqa: E402
from tests.adapter_generators import adapter_bytes, mutate, valid_adapter  # noqa: E402


def _load_or_refuse(path):
    started = time.perf_counter()
    try:
        adapter = rt.Adapter.load(path)
    except AdapterError as error:
        assert str(path) in str(error)
        assert len(str(error)) < 2000, "error messages quote values briefly"
        adapter = None
    assert time.perf_counter() - started < 1.0
    return adapter


@settings(max_examples=40)
@given(rng=st.randoms(use_true_random=False))
def test_valid_files_round_trip(rng, tmp_path_factory):
    adapter = valid_adapter(rng)
    path = tmp_path_factory.mktemp("valid") / "a.safetensors"
    path.write_bytes(adapter_bytes(adapter))
    loaded = rt.Adapter.load(path)
    assert loaded.same_as(adapter)
    assert loaded.training_info == adapter.training_info
    assert loaded.components == adapter.components


@settings(max_examples=400)
@given(rng=st.randoms(use_true_random=False))
def test_any_mutation_loads_a_valid_adapter_or_raises_adapter_error(rng, tmp_path_factory):
    path = tmp_path_factory.mktemp("mutated") / "a.safetensors"
    path.write_bytes(mutate(rng, adapter_bytes(valid_adapter(rng))))
    adapter = _load_or_refuse(path)
    if adapter is None:
        return
    for name, value in adapter.state_dict().items():
        assert bool(torch.isfinite(value).all())
        assert float(value.abs().max()) <= TABLE_LIMITS[name]
    assert all(isinstance(flag, bool) for flag in adapter.components.values())
    # Whatever a file says, what loads is a consistent component set (no excluded pair).
    assert normalise_components(adapter.components) == adapter.components
    if adapter.camera is not None:
        rays, valid = adapter.camera.unproject(adapter.camera.pixel_grid())
        assert bool(torch.isfinite(rays[valid]).all())


def _header(data: bytes) -> tuple[dict, bytes]:
    (size,) = struct.unpack("<Q", data[:8])
    return json.loads(data[8 : 8 + size]), data[8 + size :]


def _with_header(text: str, body: bytes) -> bytes:
    raw = text.encode()
    return struct.pack("<Q", len(raw)) + raw + body


@pytest.fixture
def saved(tmp_path):
    import random

    adapter = valid_adapter(random.Random(3))
    path = tmp_path / "a.safetensors"
    path.write_bytes(adapter_bytes(adapter))
    return adapter, path


def test_a_duplicate_tensor_key_is_refused(saved):
    # The safetensors library keeps the last of two entries of one name; a shared file that
    # says two things about one table is corrupt.
    _adapter, path = saved
    header, body = _header(path.read_bytes())
    entry = json.dumps({"pe.radial": header["pe.radial"]})[1:-1]
    path.write_bytes(_with_header(json.dumps(header)[:-1] + ", " + entry + "}", body))
    with pytest.raises(AdapterError, match="duplicate key 'pe.radial'"):
        rt.Adapter.load(path)


@pytest.mark.parametrize(("value", "accepted"), [(99.0, True), (101.0, False), (1e30, False)])
def test_table_values_over_the_limit_are_refused(saved, value, accepted):
    adapter, path = saved
    with torch.no_grad():
        adapter.pe["radial"][0, 0] = value
    path.write_bytes(adapter_bytes(adapter))
    if accepted:
        assert float(rt.Adapter.load(path).pe["radial"][0, 0].detach()) == value
    else:
        with pytest.raises(AdapterError, match="over the limit 100"):
            rt.Adapter.load(path)


def test_a_lying_header_length_is_refused(saved):
    _adapter, path = saved
    data = path.read_bytes()
    path.write_bytes(struct.pack("<Q", 2**63) + data[8:])
    with pytest.raises(AdapterError, match="not a readable safetensors file"):
        rt.Adapter.load(path)


def test_a_file_over_the_size_limit_is_refused_before_it_is_read(saved, monkeypatch):
    from raytun3r_plugin import adapter as adapter_module

    _adapter, path = saved
    monkeypatch.setattr(adapter_module, "MAX_FILE_BYTES", path.stat().st_size - 1)
    with pytest.raises(AdapterError, match="more than the"):
        rt.Adapter.load(path)


def test_constructor_refuses_bools_and_sizes_over_the_limits():
    with pytest.raises(AdapterError, match="n_r must be an integer in \\[2, 1024\\]"):
        rt.Adapter("da3-small", 64, n_r=True)
    with pytest.raises(AdapterError, match="embed_dim must be an integer in \\[1, 8192\\]"):
        rt.Adapter("da3-small", 10**6)
    with pytest.raises(AdapterError, match="component 'pe' must be True or False, got 'no'"):
        rt.Adapter("da3-small", 64, components={"pe": "no"})


pytest.importorskip("depth_anything_3")


def test_strict_apply_refuses_a_camera_that_differs_only_in_its_field_of_view():
    from raytun3r_plugin.patches.da3_networks import build_tiny_network

    from raytun3r_plugin.cameras import fisheye

    net = build_tiny_network(seed=0)
    fitted = fisheye((84, 70), 190.0, "kb4")
    other = type(fitted)(fitted.width, fitted.height, fitted.params, max_fov_deg=170.0)
    adapter = rt.Adapter.for_model(net, fitted)
    with pytest.raises(AdapterError, match="adapter was fitted on"):
        rt.apply(net, other, adapter)
    with rt.apply(net, other, adapter, strict=False):
        pass
    with rt.apply(net, fitted, adapter):
        pass


_NET: list = []


def _tiny_net():
    from raytun3r_plugin.patches.da3_networks import build_tiny_network

    if not _NET:
        _NET.append(build_tiny_network(seed=0))
    return _NET[0]


@settings(max_examples=8)
@given(rng=st.randoms(use_true_random=False))
def test_an_accepted_mutated_adapter_never_breaks_a_patched_forward(rng, tmp_path_factory):
    net = _tiny_net()
    template = rt.Adapter.for_model(net, valid_adapter(rng).camera)
    with torch.no_grad():
        for parameter in template.parameters():
            parameter.copy_(torch.randn(parameter.shape) * 0.05)
    path = tmp_path_factory.mktemp("forward") / "a.safetensors"
    adapter = None
    for _ in range(20):  # draw mutations until one is accepted (most are refused)
        path.write_bytes(mutate(rng, adapter_bytes(template)))
        adapter = _load_or_refuse(path)
        if adapter is not None and adapter.camera is not None:
            break
    else:
        return
    images = torch.rand(2, 3, 56, 56)
    before = {k: v.clone() for k, v in net.state_dict().items()}
    try:
        handle = rt.apply(net, adapter.camera.resized(56, 56), adapter, strict=False)
    except AdapterError:  # an adapter for another backbone or size: refused, model untouched
        assert rt.handle_of(net) is None
    else:
        with handle, torch.no_grad():
            depth = rt.predict(net, images).depth
        assert bool(torch.isfinite(depth).all())
        assert not math.isnan(float(depth.mean()))
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())
